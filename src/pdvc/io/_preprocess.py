"""From counts to line integrals: flat/dark normalisation and friends.

``p = -log((I - D) / (F - D))`` with ``D`` the mean dark and ``F`` the flat
of that view (``DESIGN.md`` §1: projections are float32 line integrals).

Flats of one view
-----------------
Flats taken at the same moment (same ``flat_positions`` value) form a group
and are averaged. With ``flat_interpolation="linear"`` and two or more
groups at known positions, the flat of view ``k`` (position ``k`` on the
time line) is the linear interpolation between the groups on either side,
and the first/last group before/after them (no extrapolation): this follows
a beam or detector that drifts during the scan. Otherwise (``"mean"``,
positions unknown, or one group) every flat is averaged into one.

Clipping
--------
A transmission below ``clip_min`` (zero or negative after dark subtraction:
dead pixels, noise in opaque regions, a dark larger than the signal) has no
logarithm; it is set to ``clip_min``, so ``p <= -log(clip_min)``, and every
such pixel is counted in the :class:`PreprocessReport`.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from ..errors import InputTypeError, ShapeError
from ..geometry import VectorGeometry
from ._projections import DataError, RawScan

__all__ = [
    "PreprocessReport",
    "normalize",
    "flats_from_columns",
    "beam_hardening",
    "detector_roi",
]

log = logging.getLogger("pdvc.io")

_INTERPOLATIONS = ("linear", "mean")


@dataclass(frozen=True)
class PreprocessReport:
    """What :func:`normalize` did.

    Attributes
    ----------
    is_raw : bool
        False when the data were already line integrals and were only copied.
    flat_interpolation : str
        What was asked: ``"linear"`` or ``"mean"``.
    flat_method : str
        What was done: ``"linear"`` (interpolated between flat groups),
        ``"mean"`` (all flats averaged) or ``"none"`` (not raw).
    n_flats, n_darks : int
        Frames used (0 when none).
    flat_group_positions : tuple of float
        Positions (view units) of the flat groups that were interpolated;
        empty unless ``flat_method == "linear"``.
    clip_min : float
        Smallest transmission kept.
    n_clipped : int
        Pixels whose transmission was below ``clip_min`` and set to it.
    n_nonpositive : int
        Of those, the ones whose transmission was zero or negative.
    clipped_fraction : float
        ``n_clipped`` over the number of pixels of all views.
    clipped_views : tuple of int
        Views holding at least one clipped pixel.
    clipped_counts : tuple of int
        Clipped pixels in each of ``clipped_views``.
    """

    is_raw: bool
    flat_interpolation: str
    flat_method: str
    n_flats: int
    n_darks: int
    flat_group_positions: tuple[float, ...]
    clip_min: float
    n_clipped: int
    n_nonpositive: int
    clipped_fraction: float
    clipped_views: tuple[int, ...]
    clipped_counts: tuple[int, ...]

    def summary(self) -> str:
        """One line for logs and reports."""
        if not self.is_raw:
            return "data were line integrals already: copied unchanged"
        dark = f"{self.n_darks} darks" if self.n_darks else "no darks"
        return (
            f"{self.n_flats} flats ({self.flat_method}), {dark}; {self.n_clipped} pixels clipped "
            f"({self.clipped_fraction:.3g} of all) in {len(self.clipped_views)} views"
        )


def _flat_groups(raw: RawScan, method: str) -> tuple[list[np.ndarray], np.ndarray | None]:
    """Indices of the flats in each group and the group positions (None: one group, no interpolation)."""
    n = raw.flats.shape[0]
    if method == "mean" or raw.flat_positions is None:
        return [np.arange(n)], None
    positions, inverse = np.unique(raw.flat_positions, return_inverse=True)
    if positions.size < 2:
        return [np.arange(n)], None
    return [np.nonzero(inverse == g)[0] for g in range(positions.size)], positions


class _GroupMeans:
    """Mean flat minus mean dark of each group, computed on demand, the last few kept."""

    def __init__(self, flats: np.ndarray, groups: list[np.ndarray], dark: np.ndarray | float, keep: int = 2):
        self.flats, self.groups, self.dark, self.keep = flats, groups, dark, keep
        self.cache: dict[int, np.ndarray] = {}

    def __call__(self, g: int) -> np.ndarray:
        if g not in self.cache:
            if len(self.cache) >= self.keep:
                self.cache.pop(next(iter(self.cache)))
            idx = self.groups[g]
            mean = self.flats[idx[0]].astype(np.float64) if idx.size == 1 else self.flats[idx].mean(0, dtype=np.float64)
            self.cache[g] = mean - self.dark
        return self.cache[g]


def _check_flats(means: _GroupMeans, n_groups: int, has_darks: bool) -> None:
    """Every group's flat minus dark must be positive at every pixel."""
    bad = None
    for g in range(n_groups):
        b = means(g) <= 0
        bad = b if bad is None else (bad | b)
    n_bad = int(np.count_nonzero(bad))
    if n_bad:
        r, c = np.unravel_index(int(np.argmax(bad)), bad.shape)
        what = "flats minus mean dark (darks >= flats)" if has_darks else "flats"
        raise DataError(
            f"{what} must be > 0 at every detector pixel; {n_bad} of {bad.size} pixels are <= 0 "
            f"(first at row {r}, col {c}). Crop to a detector ROI that excludes them (detector_roi) "
            f"or mask them as bad pixels"
        )


def normalize(
    raw: RawScan, *, flat_interpolation: str = "linear", clip_min: float = 1e-6
) -> tuple[np.ndarray, PreprocessReport]:
    """Line integrals from raw counts: ``-log((data - dark) / (flat - dark))``.

    Parameters
    ----------
    raw : RawScan
        Counts with flats (and optionally darks). If ``raw.is_raw`` is False
        the data are line integrals already and come back as a float32 copy.
    flat_interpolation : {"linear", "mean"}
        ``"linear"``: with flats in two or more groups at known
        ``raw.flat_positions`` (view units), view ``k`` uses the flat
        interpolated linearly at position ``k`` between the surrounding
        groups (the nearest group outside their span). ``"mean"``: the mean
        of all flats. Flats of one group are always averaged.
    clip_min : float, 0 < clip_min < 1
        Transmissions below it (zero, negative) are set to it and counted,
        so every value is at most ``-log(clip_min)``.

    Returns
    -------
    p : (n_views, n_rows, n_cols) float32 array
        Line integrals (dimensionless). New array; ``raw`` is not modified.
    report : PreprocessReport

    Raises
    ------
    DataError
        Raw counts without flats; flats not above the darks at some pixel.
    InputTypeError
        ``raw`` not a :class:`RawScan`.

    Examples
    --------
    >>> raw = read_projections("tooth.h5")          # doctest: +SKIP
    >>> p, rep = normalize(raw)                     # doctest: +SKIP
    >>> rep.n_clipped                               # doctest: +SKIP
    0
    """
    if not isinstance(raw, RawScan):
        raise InputTypeError(f"raw must be a RawScan (see read_projections), got {type(raw).__name__}")
    if flat_interpolation not in _INTERPOLATIONS:
        raise DataError(f"flat_interpolation must be one of {_INTERPOLATIONS}, got {flat_interpolation!r}")
    if not (isinstance(clip_min, (int, float, np.floating)) and 0 < clip_min < 1):
        raise DataError(f"clip_min must be a number in (0, 1), got {clip_min!r}")
    clip_min = float(clip_min)
    if not raw.is_raw:
        report = PreprocessReport(False, flat_interpolation, "none", 0, 0, (), clip_min, 0, 0, 0.0, (), ())
        log.info("normalize: %s", report.summary())
        return np.array(raw.data, dtype=np.float32, copy=True), report
    if raw.flats is None:
        raise DataError("raw counts need flats; pass flats= or set is_raw=False (or use flats_from_columns)")

    dark = raw.darks.mean(0, dtype=np.float64) if raw.darks is not None else 0.0
    groups, positions = _flat_groups(raw, flat_interpolation)
    means = _GroupMeans(raw.flats, groups, dark)
    _check_flats(means, len(groups), raw.darks is not None)

    n_views = raw.n_views
    out = np.empty(raw.data.shape, dtype=np.float32)
    clipped_views, clipped_counts = [], []
    n_clipped = n_nonpos = 0
    for k in range(n_views):
        if positions is None:
            flat = means(0)
        else:
            j = int(np.searchsorted(positions, k, side="right"))  # positions[j-1] <= k < positions[j]
            if j == 0:
                flat = means(0)
            elif j == positions.size:
                flat = means(positions.size - 1)
            else:
                w = (k - positions[j - 1]) / (positions[j] - positions[j - 1])
                flat = (1.0 - w) * means(j - 1) + w * means(j)
        t = (raw.data[k] - dark) / flat
        low = t < clip_min
        n_low = int(np.count_nonzero(low))
        if n_low:
            n_nonpos += int(np.count_nonzero(t <= 0))
            t[low] = clip_min
            n_clipped += n_low
            clipped_views.append(k)
            clipped_counts.append(n_low)
        out[k] = -np.log(t)

    report = PreprocessReport(
        is_raw=True,
        flat_interpolation=flat_interpolation,
        flat_method="mean" if positions is None else "linear",
        n_flats=int(raw.flats.shape[0]),
        n_darks=0 if raw.darks is None else int(raw.darks.shape[0]),
        flat_group_positions=() if positions is None else tuple(float(p) for p in positions),
        clip_min=clip_min,
        n_clipped=n_clipped,
        n_nonpositive=n_nonpos,
        clipped_fraction=n_clipped / raw.data.size,
        clipped_views=tuple(clipped_views),
        clipped_counts=tuple(clipped_counts),
    )
    if flat_interpolation == "linear" and positions is None:
        log.info("normalize: flat positions unknown or a single group; flats averaged")
    if n_clipped:
        log.warning(
            "normalize: %d transmissions below clip_min=%g set to it (%d <= 0) in %d views, first view %d",
            n_clipped, clip_min, n_nonpos, len(clipped_views), clipped_views[0],
        )
    log.info("normalize: %s", report.summary())
    return out, report


def flats_from_columns(raw: RawScan, columns=slice(0, 30)) -> RawScan:
    """A per-view flat from open-beam detector columns, for scans without flats.

    For each view and row the flat is the mean of the data over ``columns``
    (which the sample must never cover), the same for every column of that
    row. The result holds one flat per view at position ``k``, so
    :func:`normalize` uses view ``k``'s own flat: this also removes beam
    intensity fluctuations from view to view.

    Parameters
    ----------
    raw : RawScan
        Counts (``is_raw`` True). Its darks, if any, are kept and subtracted
        by :func:`normalize` from both data and flats.
    columns : slice or sequence of int
        Open-beam detector columns. Default ``slice(0, 30)``.

    Returns
    -------
    RawScan
        A new scan with ``flats`` of shape ``(n_views, n_rows, n_cols)`` (a
        read-only broadcast view: no memory per column) and
        ``flat_positions = arange(n_views)``; existing flats are replaced.

    Raises
    ------
    DataError
        ``raw`` holds line integrals, or ``columns`` selects no column.
    ShapeError
        ``columns`` outside the detector.
    """
    if not isinstance(raw, RawScan):
        raise InputTypeError(f"raw must be a RawScan, got {type(raw).__name__}")
    if not raw.is_raw:
        raise DataError("flats_from_columns needs raw counts (raw.is_raw True); these are line integrals")
    n_cols = raw.det_shape[1]
    if isinstance(columns, slice):
        idx = np.arange(n_cols)[columns]
    else:
        try:
            idx = np.asarray(columns, dtype=np.int64).reshape(-1)
        except (TypeError, ValueError) as exc:
            raise InputTypeError(f"columns must be a slice or a sequence of ints, got {columns!r}") from exc
        if np.any((idx < -n_cols) | (idx >= n_cols)):
            raise ShapeError(f"columns must lie inside the detector's {n_cols} columns, got {columns!r}")
        idx = np.unique(idx % n_cols)
    if idx.size == 0:
        raise DataError(f"columns must select at least one of the detector's {n_cols} columns, got {columns!r}")
    per_view = raw.data[:, :, idx].mean(axis=2, dtype=np.float64).astype(np.float32)  # (n_views, n_rows)
    flats = np.broadcast_to(per_view[:, :, None], raw.data.shape)
    if raw.flats is not None:
        log.info("flats_from_columns: the %d existing flats are replaced", raw.flats.shape[0])
    meta = dict(raw.metadata)
    meta["flats_source"] = f"open-beam columns {idx.min()}..{idx.max()} ({idx.size} columns), one flat per view"
    log.info("flats_from_columns: %s", meta["flats_source"])
    return dataclasses.replace(
        raw, flats=flats, flat_positions=np.arange(raw.n_views, dtype=np.float64), metadata=meta
    )


def beam_hardening(p, coeffs) -> np.ndarray:
    """Polynomial beam-hardening correction ``p' = sum_i c_i p**i``, ``i = 1 .. len(coeffs)``.

    Parameters
    ----------
    p : (n_views, n_rows, n_cols) array
        Line integrals; not modified. Any shape is accepted.
    coeffs : sequence of float
        ``(c_1, c_2, ..., c_m)``: the coefficient of ``p``, ``p**2``, ...
        (no constant term, so ``p = 0`` stays 0). Third order is typical,
        e.g. ``(1.0, 0.05, 0.01)``.

    Returns
    -------
    (same shape as p) float32 array

    Raises
    ------
    DataError
        Coefficients not finite, empty, or giving a correction that is not
        increasing over the range of ``p`` (it would swap line integrals).
    """
    c = np.asarray(coeffs, dtype=np.float64)
    if c.ndim != 1 or c.size == 0 or not np.all(np.isfinite(c)):
        raise DataError(f"coeffs must be a non-empty sequence of finite numbers (c_1, c_2, ...), got {coeffs!r}")
    arr = np.asarray(p)
    if not np.issubdtype(arr.dtype, np.number) or arr.size == 0:
        raise InputTypeError(f"p must be a non-empty numeric array, got dtype {arr.dtype} and size {arr.size}")
    lo, hi = float(np.min(arr)), float(np.max(arr))
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise DataError("p must be finite to apply a beam-hardening correction")
    # derivative sum_i i c_i p**(i-1): positive at both ends and no real root inside [lo, hi]
    deriv = np.arange(1, c.size + 1) * c  # coefficients of p**0, p**1, ...
    poly = np.polynomial.Polynomial(deriv)
    bad_at = [x for x in (lo, hi) if poly(x) <= 0]
    if deriv.size > 1:
        roots = poly.roots()
        real = roots[np.abs(roots.imag) <= 1e-12 * max(1.0, np.max(np.abs(roots)))].real
        bad_at += [float(r) for r in real if lo <= r <= hi]
    if bad_at:
        raise DataError(
            f"coeffs {tuple(c.tolist())} do not give an increasing correction over the range of p "
            f"[{lo:.4g}, {hi:.4g}]: its derivative is <= 0 at p = {min(bad_at):.4g}"
        )
    acc = np.zeros(arr.shape, dtype=np.float64)
    x = arr.astype(np.float64)
    for ci in c[::-1]:  # Horner: ((c_m p + c_{m-1}) p + ...) p
        acc = (acc + ci) * x
    return acc.astype(np.float32)


def _range(sel, n: int, name: str) -> tuple[int, int]:
    if sel is None:
        return 0, n
    if isinstance(sel, slice):
        if sel.step not in (None, 1):
            raise ShapeError(f"{name} must be a contiguous range (step 1), got {sel!r}")
        start, stop, _ = sel.indices(n)
    else:
        try:
            start, stop = (int(v) for v in sel)
        except (TypeError, ValueError) as exc:
            raise InputTypeError(f"{name} must be None, a slice or (start, stop), got {sel!r}") from exc
        if not (0 <= start <= n and 0 <= stop <= n):
            raise ShapeError(f"{name} must lie inside 0..{n}, got ({start}, {stop})")
    if stop <= start:
        raise ShapeError(f"{name} selects no detector {name[:-1]}: {sel!r} gives [{start}, {stop}) of {n}")
    return start, stop


def detector_roi(p, geom: VectorGeometry, rows=None, cols=None) -> tuple[np.ndarray, VectorGeometry]:
    """Crop projections to a detector window and give the matching geometry.

    Parameters
    ----------
    p : (n_views, n_rows, n_cols) array
        Projections; not modified.
    geom : VectorGeometry
        Their geometry (``geom.det_shape == (n_rows, n_cols)``).
    rows, cols : slice or (start, stop), optional
        Half-open detector ranges ``[start, stop)``; None keeps all. Slices
        may use negative indices; steps must be 1.

    Returns
    -------
    p_roi : (n_views, stop_r - start_r, stop_c - start_c) float32 array
        A copy.
    geom_roi : VectorGeometry
        ``geom.cropped(rows, cols)``: same pixels, detector centre moved to
        the window's centre.

    Raises
    ------
    ShapeError
        ``p`` does not match ``geom``, or an empty / out-of-range window.
    """
    if not isinstance(geom, VectorGeometry):
        raise InputTypeError(f"geom must be a VectorGeometry, got {type(geom).__name__}")
    arr = np.asarray(p)
    expected = (geom.n_views,) + tuple(geom.det_shape)
    if arr.shape != expected:
        raise ShapeError(f"p must have shape (n_views, n_rows, n_cols) = {expected} to match geom, got {arr.shape}")
    r = _range(rows, geom.det_shape[0], "rows")
    c = _range(cols, geom.det_shape[1], "cols")
    out = np.array(arr[:, r[0] : r[1], c[0] : c[1]], dtype=np.float32, copy=True)
    return out, geom.cropped(r, c)
