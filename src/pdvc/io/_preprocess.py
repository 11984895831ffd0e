"""From counts to line integrals: flat/dark normalisation and friends.

``p = -log((I - D) / (F - D))`` with ``D`` the mean dark and ``F`` the flat
of that view (``DESIGN.md`` §1: projections are float32 line integrals).
Transmission data (``RawScan.kind == "transmission"``, ``I/I0`` already)
give ``p = -log(T)`` (divided by the flat first when there are flats).

Bad pixels
----------
:func:`fill_bad_pixels` replaces masked detector pixels by linear
interpolation along their row between the nearest good pixels on either
side (the nearest one at the ends of a row): the standard dead-pixel
correction. A dead column becomes the mean of its two neighbours.
:func:`pdvc.io.read_projections` applies it (``bad_pixels=``,
``dead_columns=``) before anything else.

Air level
---------
The rays that miss the sample should read 0 in line integrals. When the flat
field does not match the projections (wrong or drifting flats, data given as
``I/I0`` with a reference that is not the open beam), they read
``-log(a)``, ``a`` the ratio of the beam seen in the projections to the
flat. :func:`estimate_air` measures it and :func:`subtract_air` removes it.
The model: a flat mismatch is a factor ``b_k · A(c)`` on the intensity (a
beam intensity per view, a detector profile), so in line integrals it adds
``o_k + P(c)``, a per-view offset plus a column profile shared by all views.
A beam whose profile drifts across the detector also tilts the air from one
view to the next: each view has a tilt ``g_k x`` of its own as well, zero on
average over the views (what they share belongs to ``P``).
``P`` is a low-order polynomial (degree 2 by default, zero mean over the
columns) in the column index, fitted jointly to the air pixels of every
view: a column never in air at one view is in air at others, and the
columns that the sample always covers (the middle of a centred sample) are
bridged smoothly instead of guessed view by view. Air pixels are found
iteratively: the lowest decile of each view (once a first profile, the lower
envelope of the columns, is taken out) to start, then the pixels
within ``[-5 s, +3 s]`` of the current model (``s`` the robust spread of
the air residuals: their noise), refitting ``o_k``, ``g_k`` and ``P``
until the selection stops changing. A view without air (fewer than 0.5 %
of its pixels) takes the offset interpolated between its neighbours.
A profile along the rows shared by the views (a beam that falls off toward
the detector's top and bottom) is fitted too, a degree-2 polynomial, where
it stands out of the noise and spans 0.02 or more (``row_profile``; the
in-memory :func:`subtract_air` and the calibration subtract it, the chunked
reader does not).

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
import threading
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
    "bad_pixel_mask",
    "fill_bad_pixels",
    "AirEstimate",
    "estimate_air",
    "subtract_air",
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
    kind : str
        What the data were: ``"counts"``, ``"transmission"`` or ``"line_integrals"``.
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
    kind: str = "counts"

    def summary(self) -> str:
        """One line for logs and reports."""
        if not self.is_raw:
            return "data were line integrals already: copied unchanged"
        clipped = (
            f"{self.n_clipped} pixels clipped ({self.clipped_fraction:.3g} of all) in {len(self.clipped_views)} views"
        )
        if self.kind == "transmission":
            flats = f"divided by {self.n_flats} flats ({self.flat_method})" if self.n_flats else "no flats"
            return f"transmission I/I0: -log taken, {flats}; {clipped}"
        dark = f"{self.n_darks} darks" if self.n_darks else "no darks"
        return f"{self.n_flats} flats ({self.flat_method}), {dark}; {clipped}"


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
        self.lock = threading.Lock()

    def __call__(self, g: int) -> np.ndarray:
        with self.lock:  # the chunked reader normalises chunks in threads
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
        If ``raw.kind == "transmission"`` the data are ``I/I0`` already:
        ``-log(data)`` (``-log(data / flat)`` when there are flats, e.g. from
        :func:`flats_from_columns`); darks do not apply to them.
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
        Raw counts without flats; flats not above the darks at some pixel;
        transmission data with darks.
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
    norm = Normalizer(raw, flat_interpolation=flat_interpolation, clip_min=clip_min)
    out = norm(raw.data)
    return out, norm.report()


class Normalizer:
    """:func:`normalize` a chunk of views at a time (the chunked reader's path; ``normalize`` is one chunk).

    Parameters
    ----------
    raw : RawScan or pdvc.io._projections.ProjectionSource
        What the values are (``kind``, ``is_raw``), the flats, darks and flat
        positions; the projections are passed to each call.
    flat_interpolation, clip_min
        As :func:`normalize`.

    Calling it with ``(data, start)`` (views ``start .. start + len(data) - 1``)
    returns their line integrals (float32, new array) and counts what was
    clipped; :meth:`report` is the :class:`PreprocessReport` of every view
    normalised so far. The flat of view ``k`` follows the flat groups and
    their positions on the time line of the whole scan (``k`` is the global
    view index), so chunks give what one call on the whole scan gives.

    Raises
    ------
    DataError
        As :func:`normalize` (raw counts without flats, flats not above the
        darks, transmission with darks), when it is made.
    """

    def __init__(self, raw, *, flat_interpolation: str = "linear", clip_min: float = 1e-6):
        if flat_interpolation not in _INTERPOLATIONS:
            raise DataError(f"flat_interpolation must be one of {_INTERPOLATIONS}, got {flat_interpolation!r}")
        if not (isinstance(clip_min, (int, float, np.floating)) and 0 < clip_min < 1):
            raise DataError(f"clip_min must be a number in (0, 1), got {clip_min!r}")
        self.flat_interpolation = flat_interpolation
        self.clip_min = clip_min = float(clip_min)
        self.kind = getattr(raw, "kind", "counts" if raw.is_raw else "line_integrals")
        self.is_raw = bool(raw.is_raw)
        self.flats_given = raw.flats is not None
        self.n_flats = 0 if raw.flats is None else int(raw.flats.shape[0])
        self.n_darks = 0 if raw.darks is None else int(raw.darks.shape[0])
        self.clipped_views, self.clipped_counts = [], []
        self.n_clipped = self.n_nonpos = self.n_pixels = 0
        self.positions = None
        if not self.is_raw:
            return
        transmission = self.kind == "transmission"
        if transmission and raw.darks is not None:
            raise DataError(
                "transmission data (I/I0) are dark- and flat-corrected already: darks do not apply; "
                "remove them, or set is_raw=True if the values are counts"
            )
        if raw.flats is None and not transmission:
            raise DataError("raw counts need flats; pass flats= or set is_raw=False (or use flats_from_columns)")
        self.dark = raw.darks.mean(0, dtype=np.float64) if raw.darks is not None else 0.0
        if raw.flats is None:  # transmission without flats: a unit flat
            groups, self.positions = [np.arange(1)], None
            self.means = _GroupMeans(np.ones((1,) + tuple(raw.det_shape), dtype=np.float32), groups, 0.0)
        else:
            groups, self.positions = _flat_groups(raw, flat_interpolation)
            self.means = _GroupMeans(raw.flats, groups, self.dark)
            _check_flats(self.means, len(groups), raw.darks is not None)

    def flat(self, k: int):
        """Flat minus mean dark of view ``k`` (float64 image)."""
        positions, means = self.positions, self.means
        if positions is None:
            return means(0)
        j = int(np.searchsorted(positions, k, side="right"))  # positions[j-1] <= k < positions[j]
        if j == 0:
            return means(0)
        if j == positions.size:
            return means(positions.size - 1)
        w = (k - positions[j - 1]) / (positions[j] - positions[j - 1])
        return (1.0 - w) * means(j - 1) + w * means(j)

    def __call__(self, data, start: int = 0, *, count: bool = True) -> np.ndarray:
        """Line integrals of views ``start ..`` (``data`` not modified); ``count=False``: no clip counts kept."""
        out, clipped = self.apply(data, start)
        if count:
            self.record(clipped, np.size(data))
        return out

    def apply(self, data, start: int = 0) -> tuple[np.ndarray, list]:
        """Line integrals of views ``start ..`` and what was clipped, ``[(view, n_clipped, n_nonpositive)]``.

        Changes nothing in ``self`` (threads may call it on different chunks); :meth:`record` the clipping
        in view order for :meth:`report`.
        """
        data = np.asarray(data)
        if not self.is_raw:
            return np.array(data, dtype=np.float32, copy=True), []
        clip_min = self.clip_min
        out = np.empty(data.shape, dtype=np.float32)
        clipped = []
        for i in range(data.shape[0]):
            k = start + i
            t = np.subtract(data[i], self.dark, dtype=np.float64)  # (I - D) / (F - D), in place: no temporaries
            np.divide(t, self.flat(k), out=t)
            low = t < clip_min
            n_low = int(np.count_nonzero(low))
            if n_low:
                clipped.append((k, n_low, int(np.count_nonzero(t <= 0))))
                t[low] = clip_min
            np.log(t, out=t)
            np.negative(t, out=out[i], casting="same_kind")
        return out, clipped

    def record(self, clipped: list, n_pixels: int) -> None:
        """Count the clipping :meth:`apply` returned for ``n_pixels`` more pixels (call in view order)."""
        self.n_pixels += int(n_pixels)
        for k, n_low, n_nonpos in clipped:
            self.n_nonpos += n_nonpos
            self.n_clipped += n_low
            self.clipped_views.append(k)
            self.clipped_counts.append(n_low)

    def report(self) -> PreprocessReport:
        """What was done to the views normalised so far (and logged, as :func:`normalize` does)."""
        if not self.is_raw:
            report = PreprocessReport(False, self.flat_interpolation, "none", 0, 0, (), self.clip_min, 0, 0, 0.0, (), (),
                                      self.kind)
            log.info("normalize: %s", report.summary())
            return report
        positions = self.positions
        report = PreprocessReport(
            is_raw=True,
            flat_interpolation=self.flat_interpolation,
            flat_method="none" if not self.flats_given else ("mean" if positions is None else "linear"),
            n_flats=self.n_flats,
            n_darks=self.n_darks,
            flat_group_positions=() if positions is None else tuple(float(p) for p in positions),
            clip_min=self.clip_min,
            n_clipped=self.n_clipped,
            n_nonpositive=self.n_nonpos,
            clipped_fraction=self.n_clipped / max(self.n_pixels, 1),
            clipped_views=tuple(self.clipped_views),
            clipped_counts=tuple(self.clipped_counts),
            kind=self.kind,
        )
        if self.flat_interpolation == "linear" and positions is None and self.flats_given:
            log.info("normalize: flat positions unknown or a single group; flats averaged")
        if self.n_clipped:
            log.warning(
                "normalize: %d transmissions below clip_min=%g set to it (%d <= 0) in %d views, first view %d",
                self.n_clipped, self.clip_min, self.n_nonpos, len(self.clipped_views), self.clipped_views[0],
            )
        log.info("normalize: %s", report.summary())
        return report


def _column_indices(value, n_cols: int, name: str) -> np.ndarray:
    """Sorted unique column indices (negative ones count from the end), checked against ``n_cols``."""
    try:
        idx = np.asarray(value, dtype=np.int64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise InputTypeError(f"{name} must be a sequence of column indices, got {value!r}") from exc
    if np.any((idx < -n_cols) | (idx >= n_cols)):
        raise ShapeError(f"{name} must lie inside the detector's {n_cols} columns, got {value!r}")
    return np.unique(idx % n_cols)


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
        Counts or transmission (``is_raw`` True). Its darks, if any, are
        kept and subtracted by :func:`normalize` from both data and flats.
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
        raise DataError(
            "flats_from_columns needs raw counts or transmission (raw.is_raw True); these are line integrals"
        )
    idx = open_beam_columns(raw.det_shape[1], columns)
    per_view = open_beam_means(raw.data, idx)  # (n_views, n_rows)
    flats = np.broadcast_to(per_view[:, :, None], raw.data.shape)
    if raw.flats is not None:
        log.info("flats_from_columns: the %d existing flats are replaced", raw.flats.shape[0])
    meta = dict(raw.metadata)
    meta["flats_source"] = f"open-beam columns {idx.min()}..{idx.max()} ({idx.size} columns), one flat per view"
    log.info("flats_from_columns: %s", meta["flats_source"])
    return dataclasses.replace(
        raw, flats=flats, flat_positions=np.arange(raw.n_views, dtype=np.float64), metadata=meta
    )


def open_beam_means(data, columns: np.ndarray) -> np.ndarray:
    """Mean of each view's rows over the open-beam ``columns``: ``(n, n_rows)`` float32 (see flats_from_columns)."""
    return np.asarray(data)[:, :, columns].mean(axis=2, dtype=np.float64).astype(np.float32)


def open_beam_columns(n_cols: int, columns) -> np.ndarray:
    """The column indices ``columns`` (slice or sequence) selects, checked as :func:`flats_from_columns` does."""
    if isinstance(columns, slice):
        idx = np.arange(n_cols)[columns]
    else:
        idx = _column_indices(columns, n_cols, "columns")
    if idx.size == 0:
        raise DataError(f"columns must select at least one of the detector's {n_cols} columns, got {columns!r}")
    return idx


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
    c = _bh_coefficients(coeffs)
    arr = np.asarray(p)
    if not np.issubdtype(arr.dtype, np.number) or arr.size == 0:
        raise InputTypeError(f"p must be a non-empty numeric array, got dtype {arr.dtype} and size {arr.size}")
    _check_bh(c, float(np.min(arr)), float(np.max(arr)))
    return _apply_bh(arr, c)


def _bh_coefficients(coeffs) -> np.ndarray:
    c = np.asarray(coeffs, dtype=np.float64)
    if c.ndim != 1 or c.size == 0 or not np.all(np.isfinite(c)):
        raise DataError(f"coeffs must be a non-empty sequence of finite numbers (c_1, c_2, ...), got {coeffs!r}")
    return c


def _check_bh(c: np.ndarray, lo: float, hi: float) -> None:
    """The beam-hardening polynomial must increase over the range ``[lo, hi]`` of the line integrals."""
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


def _apply_bh(arr: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``sum_i c_i arr**i`` (float32), unchecked."""
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
    r, c = roi_ranges(geom.det_shape, rows, cols)
    out = np.array(arr[:, r[0] : r[1], c[0] : c[1]], dtype=np.float32, copy=True)
    return out, geom.cropped(r, c)


def roi_ranges(det_shape, rows=None, cols=None) -> tuple[tuple[int, int], tuple[int, int]]:
    """``((r0, r1), (c0, c1))``: the detector window :func:`detector_roi` crops, checked the same way."""
    return _range(rows, int(det_shape[0]), "rows"), _range(cols, int(det_shape[1]), "cols")


# --------------------------------------------------------------------------- bad pixels


def bad_pixel_mask(det_shape, mask=None, dead_columns=None) -> tuple[np.ndarray, str]:
    """A boolean ``(n_rows, n_cols)`` mask of bad detector pixels, and a description of where it came from.

    Parameters
    ----------
    det_shape : (n_rows, n_cols)
        The detector, as the views are laid out (after ``sinogram=True``).
    mask : str, os.PathLike or array, optional
        A detector-shaped boolean or numeric image, nonzero (True, 1) = bad;
        ``(n_cols,)`` is accepted for a one-row detector. A path is read as
        TIFF (``.tif``/``.tiff``) or ``.npy``.
    dead_columns : sequence of int, optional
        Columns bad as a whole (negative indices count from the end).

    Raises
    ------
    ShapeError
        A mask of another shape, or a column outside the detector.
    DataError
        A mask holding NaN/Inf.
    """
    import os

    from ._projections import _read_array_file

    n_rows, n_cols = (int(v) for v in det_shape)
    out = np.zeros((n_rows, n_cols), dtype=bool)
    desc = []
    if mask is not None:
        if isinstance(mask, (str, os.PathLike)):
            arr, src = _read_array_file(mask, "mask")
            desc.append(f"mask {src}")
        else:
            arr = np.asarray(mask)
            desc.append("mask array")
        if arr.dtype != np.bool_ and (
            not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating)
        ):
            raise InputTypeError(f"mask must be a boolean or numeric image, got dtype {arr.dtype}")
        arr = np.asarray(arr)
        if arr.ndim == 3 and arr.shape[0] == 1:
            arr = arr[0]
        if arr.ndim == 1 and n_rows == 1:
            arr = arr[None, :]
        if arr.shape != (n_rows, n_cols):
            extra = f" or ({n_cols},) for a one-row detector" if n_rows == 1 else ""
            raise ShapeError(
                f"mask must be a detector-shaped image ({n_rows}, {n_cols}){extra} (the views' rows and columns), "
                f"got shape {arr.shape}"
            )
        if arr.dtype != np.bool_ and not np.all(np.isfinite(arr)):
            raise DataError("mask must be finite (0/1 or boolean; nonzero = bad pixel)")
        out |= arr.astype(bool)
    if dead_columns is not None:
        cols = _column_indices(dead_columns, n_cols, "dead_columns")
        out[:, cols] = True
        desc.append(f"dead columns {[int(c) for c in cols]}")
    return out, ", ".join(desc) if desc else "none"


def fill_bad_pixels(frames, mask) -> np.ndarray:
    """Replace bad detector pixels by linear interpolation along their row from the nearest good pixels.

    Parameters
    ----------
    frames : (n, n_rows, n_cols) array
        Projections, flats or darks; not modified.
    mask : (n_rows, n_cols) bool array
        True at bad pixels (the same in every frame), see :func:`bad_pixel_mask`.

    Returns
    -------
    (n, n_rows, n_cols) float32 array
        A copy in which pixel ``(r, c)`` of the mask is
        ``(1 - w) · f[r, a] + w · f[r, b]``, ``a < c < b`` the nearest good
        columns of row ``r`` and ``w = (c - a) / (b - a)``; beyond the last
        good pixel of a row, that pixel's value. A dead column between two
        good ones becomes their mean. Whatever the masked pixels held (NaN
        included) is not used.

    Raises
    ------
    ShapeError
        ``mask`` not ``(n_rows, n_cols)``.
    DataError
        A detector row that is bad in every column (nothing to interpolate
        from along it).
    """
    arr = np.asarray(frames)
    if arr.ndim != 3:
        raise ShapeError(f"frames must have shape (n, n_rows, n_cols), got {arr.shape}")
    m = np.asarray(mask, dtype=bool)
    if m.shape != arr.shape[1:]:
        raise ShapeError(f"mask must have the detector shape {arr.shape[1:]}, got {m.shape}")
    out = np.array(arr, dtype=np.float32, copy=True)
    if not m.any():
        return out
    full = np.flatnonzero(m.all(axis=1))
    if full.size:
        raise DataError(
            f"detector row{'s' if full.size > 1 else ''} {[int(r) for r in full[:10]]} are bad in every column: "
            "nothing to interpolate from along the row; crop them away ([preprocess] roi_rows) instead"
        )
    rr, cc, left, right, weight = [], [], [], [], []
    for r in np.flatnonzero(m.any(axis=1)):
        good = np.flatnonzero(~m[r])
        bad = np.flatnonzero(m[r])
        j = np.searchsorted(good, bad)  # good[j-1] < c < good[j]
        a = good[np.clip(j - 1, 0, good.size - 1)]
        b = good[np.clip(j, 0, good.size - 1)]
        w = np.where(b != a, (bad - a) / np.maximum(b - a, 1), 0.0)
        rr.append(np.full(bad.size, r))
        cc.append(bad)
        left.append(a)
        right.append(b)
        weight.append(w)
    rr, cc, left, right = (np.concatenate(v) for v in (rr, cc, left, right))
    w = np.concatenate(weight).astype(np.float32)
    out[:, rr, cc] = (1.0 - w) * out[:, rr, left] + w * out[:, rr, right]
    return out


# --------------------------------------------------------------------------- air level

AIR_TOLERANCE = 0.02
"""Air levels (line integrals) within this of 0 are not reported as a problem (2 % in transmission)."""

AIR_COLUMN_TOLERANCE = 0.05
"""A fitted column profile of the air varying by more than this (peak to peak) is reported as a problem."""


def _robust_std(x: np.ndarray, max_size: int = 500_000) -> float:
    x = np.asarray(x).reshape(-1)
    if x.size > max_size:
        x = x[:: x.size // max_size + 1]
    x = x[np.isfinite(x)]
    if x.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


#: :func:`estimate_air`'s first column profile is the lower envelope of this quantile of each column (over views and
#: rows): a column that sees air in at least this fraction of its pixels reads about the air there
ENVELOPE_QUANTILE = 0.05
#: ... in at most this many blocks of consecutive views (of 8 views at least)
ENVELOPE_BLOCKS = 8


#: a view's tilt of the air is fitted where the columns of its air pixels spread by at least this variance in ``x``
#: (-1 .. 1 over the detector; 1/3 for air in every column, 0.6 for air at both sides of a rod half as wide)
TILT_MIN_SPREAD = 0.05


def _beyond_noise(weighted_squares: np.ndarray, noise_std: float) -> bool:
    """Whether terms of variance ``noise_std**2`` each (their squares times their counts, ``weighted_squares``) vary
    beyond their noise: their χ² per term above ``1 + 3 sqrt(2 / m)`` for ``m`` terms, 3 terms at least."""
    m = int(np.size(weighted_squares))
    if m < 3:
        return False
    return float(np.mean(weighted_squares)) / max(float(noise_std), 1e-12) ** 2 >= 1.0 + 3.0 * np.sqrt(2.0 / m)


def _view_lines(sel, R, x, good, noise_std: float, *, tilt: bool = True):
    """Per-view least squares of the selected ``R`` on ``(1, x)``: offsets ``o`` (views without air ``good``
    interpolated from their neighbours) and tilts ``g``, zero on average over the views that have one (0 where the
    air's columns spread by less than ``TILT_MIN_SPREAD`` in ``x``, or with ``tilt=False``).

    The tilts are kept only where they vary from view to view beyond their noise: their χ² about 0 (each tilt over
    its standard deviation ``noise_std / sqrt(n var)``), per view, above ``1 + 3 sqrt(2 / m)`` for ``m`` views.
    Tilts that are noise alone would add their noise to every pixel of the background subtracted."""
    w = sel.sum(axis=1).astype(np.float64)  # (nv, nc) selected pixels per view and column
    y = np.where(sel, R, 0.0).sum(axis=1)
    n = np.maximum(w.sum(axis=1), 1.0)
    mx, my = (w @ x) / n, y.sum(axis=1) / n
    var = (w @ (x * x)) / n - mx**2
    g = np.zeros(n.size)
    fit = good & (var >= TILT_MIN_SPREAD) if tilt else np.zeros(n.size, dtype=bool)
    if fit.any():
        g[fit] = ((y @ x) / n - mx * my)[fit] / var[fit]
        g[fit] -= np.average(g[fit], weights=n[fit])
        if not _beyond_noise(g[fit] ** 2 * n[fit] * var[fit], noise_std):
            g[:] = 0.0
        elif not fit.all():
            # a view whose air lies on one side takes its neighbours' tilt, so that the next selection can reach
            # the other side (where a flat's tilt changes, the first one saw one side of some views only)
            g = np.interp(np.arange(g.size), np.flatnonzero(fit), g[fit])
    o = np.where(good, my - g * mx, np.nan)
    return np.interp(np.arange(o.size), np.flatnonzero(good), o[good]), g


#: degree of the air's profile along the rows (fitted where it stands out of the noise)
ROW_DEGREE = 2


def _row_profile(sel, R, Vr, noise_std: float):
    """The air's profile along the rows examined, ``(Vr @ c, c)``, zero on average over the air pixels: least
    squares of the selected ``R``'s row means on ``Vr``, kept only where those means vary beyond their noise (their
    χ² per row about the fit's mean above ``1 + 3 sqrt(2 / m)``, ``m`` rows with air) and the profile spans
    ``AIR_TOLERANCE`` or more; zeros otherwise."""
    m_rows = Vr.shape[0]
    n = sel.sum(axis=(0, 2)).astype(np.float64)
    ok = n > 0
    zero = np.zeros(m_rows), np.zeros(Vr.shape[1])
    if ok.sum() < max(3, Vr.shape[1] + 1):
        return zero
    mean = np.where(ok, np.where(sel, R, 0.0).sum(axis=(0, 2)) / np.maximum(n, 1.0), 0.0)
    mu = float(np.average(mean[ok], weights=n[ok]))
    if not _beyond_noise(n[ok] * (mean[ok] - mu) ** 2, noise_std):
        return zero
    c = np.linalg.lstsq(Vr[ok] * np.sqrt(n[ok])[:, None], (mean[ok] - mu) * np.sqrt(n[ok]), rcond=None)[0]
    c[0] -= float(np.average(Vr[ok] @ c, weights=n[ok]))
    if float(np.ptp(Vr @ c)) < AIR_TOLERANCE:
        return zero  # the rows' means of a sample's data hold structure of their own at 1e-4..1e-3: not a flat's
    return Vr @ c, c


def _runs(mask: np.ndarray, length: int) -> np.ndarray:
    """``mask`` (1-D) without its runs of True shorter than ``length``: a binary opening by a segment that long."""
    from scipy import ndimage

    return ndimage.binary_opening(mask, structure=np.ones(length, dtype=bool))


def _lower_envelope(q: np.ndarray, V: np.ndarray, noise_std: float, max_iter: int = 10) -> np.ndarray:
    """The polynomial ``V @ c`` through the lower envelope of ``q`` (one value per column, ``V``'s rows).

    Material only adds to the air. The columns within 2 noise std of the lower convex hull of ``(column, q)`` are
    fitted first, then those within 2 noise std above the fit, until they stop changing; only runs of at least 3
    such columns count (a hull always ends at both end columns, where a sample may stand); zeros when fewer than
    twice the polynomial's terms are left. (A least-squares start through every column followed a sample's bump
    with its curvature and kept it.)
    """
    n = q.size
    x = np.arange(n, dtype=np.float64)
    ok = np.isfinite(q)
    if ok.sum() < 2 * V.shape[1]:
        return np.zeros(n)
    hx, hq = [], []
    for xi, qi in zip(x[ok], q[ok]):  # Andrew's monotone chain, lower half
        while len(hx) >= 2 and (hx[-1] - hx[-2]) * (qi - hq[-2]) - (hq[-1] - hq[-2]) * (xi - hx[-2]) <= 0:
            hx.pop()
            hq.pop()
        hx.append(xi)
        hq.append(qi)
    tol = 2.0 * max(float(noise_std), 1e-12)
    keep = _runs(ok & (q - np.interp(x, hx, hq) <= tol), 3)
    fit = np.zeros(n)
    for _ in range(max_iter):
        if keep.sum() < 2 * V.shape[1]:
            return np.zeros(n)
        fit = V @ np.linalg.lstsq(V[keep], q[keep], rcond=None)[0]
        new = _runs(ok & (q - fit <= tol), 3)
        if np.array_equal(new, keep):
            break
        keep = new
    return fit


def _noise_std(s: np.ndarray) -> float:
    """Pixel noise std from neighbour differences along the rows (robust: edges are a minority)."""
    if s.shape[-1] < 2:
        return 0.0
    return _robust_std(np.diff(s, axis=-1)) / np.sqrt(2.0)


@dataclass(frozen=True, eq=False)
class AirEstimate:
    """The air level of line integrals: what the rays that miss the sample read (0 when the flats match).

    Attributes
    ----------
    found : bool
        False when (almost) no pixel looked like air (sample wider than
        the field of view): the other figures are then NaN and meaningless.
    level : float
        Median over the views of the per-view air level (line integral;
        ``exp(-level)`` is the transmission of air).
    per_view : (n_views,) float64 array
        Air level of each view (mean over the columns of the fitted model).
    profile : (n_cols,) float64 array
        Measured air level of each column: median over the views of its air
        pixels, corrected by the per-view offsets, plus ``level``; NaN in
        columns that are never in air.
    fitted : (n_cols,) float64 array
        The fitted column profile ``level + P(c)``.
    coefficients : tuple of float
        ``P(c) = sum_i a_i x**i - mean``, ``x = 2 c / (n_cols - 1) - 1``:
        ``(a_0, a_1, ...)``, lowest order first (``a_0`` absorbed by the
        offsets).
    degree : int
        Degree of ``P``.
    noise_std : float
        Noise std of the air pixels (robust spread of their residuals to
        the fitted background).
    level_std : float
        Uncertainty of ``level`` (robust spread of ``per_view`` over the
        square root of the number of views with air).
    air_fraction : float
        Fraction of the examined pixels taken as air.
    n_air_columns : int
        Columns with air in at least some views (finite ``profile``).
    views_without_air : tuple of int
        Views with too little air (offset interpolated from neighbours).
    per_view_tilt : (n_views,) float64 array or None
        ``g_k``: each view's tilt of the air across the columns, per unit of
        ``x`` (-1 .. 1 over the detector), zero on average over the views;
        0 where a view's air spans too few columns to tell. None: no tilts.
    row_profile : (n_rows,) float64 array or None
        The air's profile along the detector rows (a degree-2 fit to the
        rows examined, zero on average over their air pixels, evaluated at
        every row; ``level + P(c) + row_profile`` is the air), where it stands
        out of the noise: a beam that falls off toward the top and bottom.
        None: flat along the rows. Not part of :meth:`background`.
    """

    found: bool
    level: float
    per_view: np.ndarray
    profile: np.ndarray
    fitted: np.ndarray
    coefficients: tuple
    degree: int
    noise_std: float
    level_std: float
    air_fraction: float
    n_air_columns: int
    views_without_air: tuple
    per_view_tilt: "np.ndarray | None" = None
    row_profile: "np.ndarray | None" = None

    @property
    def transmission(self) -> float:
        """``exp(-level)``: the transmission the air reads."""
        return float(np.exp(-self.level))

    @property
    def column_range(self) -> tuple[float, float]:
        """Smallest and largest measured per-column air level (NaN when none)."""
        f = self.profile[np.isfinite(self.profile)]
        return (float(f.min()), float(f.max())) if f.size else (float("nan"), float("nan"))

    @property
    def fitted_range(self) -> tuple[float, float]:
        """Smallest and largest value of the fitted column profile."""
        return float(self.fitted.min()), float(self.fitted.max())

    @property
    def significant(self) -> bool:
        """Whether the air is measurably off 0: the level beyond ``max(AIR_TOLERANCE, 3 level_std)``,
        or the fitted column profile varying by more than ``AIR_COLUMN_TOLERANCE``."""
        if not self.found:
            return False
        lo, hi = self.fitted_range
        rows = 0.0 if self.row_profile is None else float(np.ptp(self.row_profile))
        return (abs(self.level) > max(AIR_TOLERANCE, 3.0 * self.level_std) or (hi - lo) > AIR_COLUMN_TOLERANCE
                or rows > AIR_COLUMN_TOLERANCE)

    def background(self) -> np.ndarray:
        """The fitted air of every view and column, ``(n_views, n_cols)`` float64: ``o_k + g_k x + P(c)``."""
        out = self.per_view[:, None] + (self.fitted - self.level)[None, :]
        if self.per_view_tilt is not None and self.fitted.size > 1:
            out = out + self.per_view_tilt[:, None] * np.linspace(-1.0, 1.0, self.fitted.size)[None, :]
        return out

    def summary(self) -> str:
        """One line for logs, notes and reports."""
        if not self.found:
            return "air level: no air found (the sample covers the detector): not estimated"
        lo, hi = self.column_range
        flo, fhi = self.fitted_range
        return (
            f"air level {self.level:.4g} in the line integrals (transmission {self.transmission:.3f}), median over "
            f"{self.per_view.size} views (view to view spread {_robust_std(self.per_view):.2g}); across columns "
            f"{lo:.4g} .. {hi:.4g} measured in {self.n_air_columns} of {self.profile.size} columns "
            f"(degree-{self.degree} fit {flo:.4g} .. {fhi:.4g}); "
            + (f"a tilt across the columns that changes from view to view (RMS "
               f"{np.sqrt(np.mean(self.per_view_tilt ** 2)):.2g} from the middle column to an end); "
               if self.per_view_tilt is not None and np.any(self.per_view_tilt) else "")
            + (f"along the rows {self.row_profile.min() + self.level:.4g} .. {self.row_profile.max() + self.level:.4g}; "
               if self.row_profile is not None else "")
            + f"noise std {self.noise_std:.2g}; {100 * self.air_fraction:.0f}% of the pixels are air"
        )

    def problem(self) -> str | None:
        """What ``pdvc inspect`` reports when the air is off 0, or None."""
        if not self.significant:
            return None
        lo, hi = self.fitted_range
        return (
            f"air level in the line integrals is {self.level:.2f} (transmission {self.transmission:.2f}), "
            f"{lo:.2f} .. {hi:.2f} across the columns: the flat field does not match; "
            f'set [preprocess] air = "auto" to normalise it (the calibration subtracts it anyway: [calibration] air = "auto")'
        )


def estimate_air(p, *, degree: int = 2, max_rows: int = 16, max_iter: int = 20,
                 max_pixels: int = 1_000_000) -> AirEstimate:
    """Estimate the air level of line integrals: per view, per column, and overall.

    Parameters
    ----------
    p : (n_views, n_rows, n_cols) array
        Line integrals (after ``-log``); finite. Not modified.
    degree : int, >= 0
        Degree of the column profile ``P`` (module docstring). 2 follows a
        smooth flat-field mismatch across the detector; 0 assumes none.
    max_rows, max_pixels : int
        At most this many rows, evenly spaced, are examined, and fewer when
        needed to keep ``n_views x rows x n_cols`` under ``max_pixels`` (the
        estimate is a median over many pixels; this bounds the cost).
    max_iter : int
        Passes of the select-and-fit loop at most (it usually stops after
        3-8, when the selection no longer changes).

    Returns
    -------
    AirEstimate
        ``level``, ``per_view``, ``profile``, ``fitted``, ... (see there).

    Notes
    -----
    The model is ``p[k, r, c] = o_k + g_k x + P(c) + sample + noise`` with
    the sample >= 0 (``g_k`` zero unless the views' tilts vary beyond their
    noise); air pixels are those within ``[-5 s, +3 s]`` of the model (``s``
    the robust spread of the air residuals: their noise), found iteratively
    from the lowest decile of each view once the lower envelope of the
    columns is taken out. Dead pixels and zingers fall outside the window;
    the level is a median. See the module docstring for why a per-view
    offset and tilt plus a column profile.
    """
    arr = np.asarray(p)
    if arr.ndim != 3 or min(arr.shape) < 1:
        raise ShapeError(f"p must have shape (n_views, n_rows, n_cols), got {arr.shape}")
    degree = int(degree)
    if degree < 0:
        raise DataError(f"degree must be >= 0, got {degree}")
    nv, nr, nc = arr.shape
    rows = air_rows(arr.shape, max_rows=max_rows, max_pixels=max_pixels)
    S = np.asarray(arr[:, rows, :], dtype=np.float64)
    if not np.all(np.isfinite(S)):
        raise DataError("p must be finite to estimate the air level")
    per_view_px = S[0].size
    x = np.linspace(-1.0, 1.0, nc) if nc > 1 else np.zeros(1)
    deg = min(degree, nc - 1)
    V = np.vander(x, deg + 1, increasing=True)  # (nc, deg + 1)

    # the first selection: the lowest decile of each view once a first column profile is taken out, the lower
    # envelope of the columns over a block of consecutive views. Without it, a flat field that tilts across the
    # detector (issue #10's synchrotron scan: 8 % of transmission from one side to the other, 0.16 in line integrals
    # against a noise of 0.004) put every view's lowest decile in the last 9 of 56 columns, the degree-2 fit through
    # them ran off elsewhere and the selection emptied: no air found. Blocks, since a flat that drifts across the
    # detector tilts the air differently over the scan (one envelope for all views kept each view's selection on the
    # side its tilt lowers, and the tilt out of sight)
    noise0 = _noise_std(S)
    D = np.empty_like(S)
    for blk in np.array_split(np.arange(nv), max(1, min(ENVELOPE_BLOCKS, nv // 8))):
        q = np.quantile(S[blk], ENVELOPE_QUANTILE, axis=(0, 1))
        D[blk] = S[blk] - _lower_envelope(q, V, noise0)
    # ... and the lower envelope of the rows examined, the same way: a beam that falls off toward the detector's top
    # and bottom (a flat field that does not match along the rows) would put every view's decile in its lowest rows
    yr = 2.0 * rows / max(nr - 1, 1) - 1.0 if nr > 1 else np.zeros(rows.size)
    degr = min(ROW_DEGREE, rows.size - 1)
    Vr = np.vander(yr, degr + 1, increasing=True)
    D -= _lower_envelope(np.quantile(D, ENVELOPE_QUANTILE, axis=(0, 2)), Vr, noise0)[None, :, None]
    sel = D <= np.quantile(D.reshape(nv, -1), 0.1, axis=1)[:, None, None]
    Rr = np.zeros(rows.size)  # the air's profile along the rows examined (zero mean; 0 unless it stands out)
    rcoef = np.zeros(degr + 1)
    P = np.zeros(nc)
    coef = np.zeros(deg + 1)
    o = np.zeros(nv)
    g = np.zeros(nv)
    X = x[None, None, :]
    s_noise = noise0  # the air residuals' spread from the first pass on
    good = np.ones(nv, dtype=bool)
    min_px = max(3, int(np.ceil(0.005 * per_view_px)))
    for _ in range(max_iter):
        nsel = sel.reshape(nv, -1).sum(axis=1)
        good = nsel >= min_px
        if not good.any():
            break
        # per-view offsets and tilts: least squares of the selected residuals on (1, x), the tilts' mean over the
        # views left to P (the window already trims outliers)
        o, g = _view_lines(sel, S - P - Rr[None, :, None], x, good, s_noise, tilt=deg >= 1)
        # column profile: least squares of (p - o_k - g_k x) on the polynomial, over the selected pixels
        w = sel.sum(axis=(0, 1)).astype(np.float64)
        ysum = np.where(sel, S - o[:, None, None] - g[:, None, None] * X - Rr[None, :, None], 0.0).sum(axis=(0, 1))
        if np.count_nonzero(w) > deg:
            coef = np.linalg.lstsq(V.T @ (w[:, None] * V), V.T @ ysum, rcond=None)[0]
            P = V @ coef
            P -= P.mean()
        Rr, rcoef = _row_profile(sel, S - o[:, None, None] - g[:, None, None] * X - P, Vr, s_noise)
        res = S - o[:, None, None] - g[:, None, None] * X - P - Rr[None, :, None]
        s = max(_robust_std(res[sel], 200_000), 1e-6 * (1.0 + abs(float(np.median(o)))))
        s_noise = s
        new = (res > -5.0 * s) & (res < 3.0 * s)
        changed = np.count_nonzero(new != sel)
        sel = new
        if changed <= 1e-4 * sel.size:
            break

    good = sel.reshape(nv, -1).sum(axis=1) >= min_px  # of the last selection (a view may have lost its air in it)
    found = bool(good.any()) and sel.mean() >= 0.001
    if not found:
        nan = np.full(nc, np.nan)
        return AirEstimate(False, float("nan"), np.full(nv, np.nan), nan, nan.copy(), tuple(float(c) for c in coef),
                           deg, _noise_std(S), float("nan"), float(sel.mean()), 0, tuple(range(nv)))
    # final offsets as medians (robust), then the measured per-column profile
    R = np.where(sel, S - P - g[:, None, None] * X - Rr[None, :, None], np.nan).reshape(nv, -1)
    med = np.full(nv, np.nan)
    med[good] = np.nanmedian(R[good], axis=1)
    o = np.interp(np.arange(nv), np.flatnonzero(good), med[good])
    level = float(np.median(o[good]))
    Y = np.where(sel, S - o[:, None, None] - g[:, None, None] * X - Rr[None, :, None], np.nan).transpose(2, 0, 1).reshape(nc, -1)
    cnt = sel.sum(axis=(0, 1))
    profile = np.full(nc, np.nan)
    ok = cnt >= 3
    if ok.any():
        profile[ok] = np.nanmedian(Y[ok], axis=1) + level
    level_std = _robust_std(o[good]) / np.sqrt(max(int(good.sum()), 1))
    return AirEstimate(
        found=True,
        level=level,
        per_view=o,
        profile=profile,
        fitted=level + P,
        coefficients=tuple(float(c) for c in coef),
        degree=deg,
        noise_std=float(s),
        level_std=float(level_std),
        air_fraction=float(sel.mean()),
        n_air_columns=int(ok.sum()),
        views_without_air=tuple(int(k) for k in np.flatnonzero(~good)),
        per_view_tilt=g,
        row_profile=(np.vander(np.linspace(-1.0, 1.0, nr) if nr > 1 else np.zeros(1), degr + 1, increasing=True) @ rcoef
                     if np.any(rcoef) else None),
    )


def air_rows(shape, *, max_rows: int = 16, max_pixels: int = 1_000_000) -> np.ndarray:
    """The detector rows :func:`estimate_air` examines in line integrals of ``shape`` (n_views, n_rows, n_cols).

    ``estimate_air`` of those rows alone (same ``max_rows``, ``max_pixels``)
    is ``estimate_air`` of the whole stack: the chunked reader keeps only them.
    """
    nv, nr, nc = (int(v) for v in shape)
    n_rows_used = max(1, min(nr, int(max_rows), int(max_pixels) // max(nv * nc, 1)))
    return np.unique(np.linspace(0, nr - 1, n_rows_used).round().astype(np.int64))


def subtract_background(arr, background, start: int = 0) -> np.ndarray:
    """``arr[i] - background[start + i]`` row-broadcast, one view at a time (float32, new array)."""
    out = np.empty(np.shape(arr), dtype=np.float32)
    for i in range(out.shape[0]):  # one view at a time: no float64 copy of the stack
        out[i] = arr[i] - background[start + i][None, :]
    return out


def subtract_air(p, estimate: AirEstimate | None = None, **kwargs) -> tuple[np.ndarray, AirEstimate]:
    """Subtract the air background ``o_k + P(c)`` so that the rays missing the sample read 0.

    Parameters
    ----------
    p : (n_views, n_rows, n_cols) array
        Line integrals; not modified.
    estimate : AirEstimate, optional
        From :func:`estimate_air` on these ``p``; computed (with ``kwargs``)
        when not given.

    Returns
    -------
    p_corrected : (n_views, n_rows, n_cols) float32 array
        ``p - o_k - P(c)``, the same background for every row of view ``k``.
    estimate : AirEstimate
        What was subtracted (``level``, ``per_view``, ``fitted``). When no air
        was found nothing is subtracted (a copy is returned).

    Raises
    ------
    ShapeError
        ``estimate`` made for another number of views or columns.
    """
    arr = np.asarray(p)
    if estimate is None:
        estimate = estimate_air(arr, **kwargs)
    if not isinstance(estimate, AirEstimate):
        raise InputTypeError(f"estimate must be an AirEstimate (see estimate_air), got {type(estimate).__name__}")
    if arr.ndim != 3 or estimate.per_view.shape != (arr.shape[0],) or estimate.fitted.shape != (arr.shape[2],):
        raise ShapeError(
            f"estimate is for {estimate.per_view.size} views of {estimate.fitted.size} columns, "
            f"p has shape {arr.shape}"
        )
    if not estimate.found:
        log.warning("subtract_air: no air found; nothing subtracted")
        return np.array(arr, dtype=np.float32, copy=True), estimate
    out = subtract_background(arr, estimate.background())
    if estimate.row_profile is not None and estimate.row_profile.size == out.shape[1]:
        out -= estimate.row_profile.astype(np.float32)[None, :, None]
    log.info("subtract_air: %s", estimate.summary())
    return out, estimate
