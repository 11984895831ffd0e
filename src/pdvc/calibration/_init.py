"""Coarse initialisation: the centre-of-rotation offset from opposite views.

The P-DVC engine linearises the projections about the current geometry, so
it converges from a fraction of the size of the sample's features, not from
the tens of pixels by which the rotation axis of a lab scanner may be off
its nominal column. The paper's suggestion (Jailin et al. 2018, §4) is to
start from a cross-correlation; here the classic one of opposite views:

in parallel beam, the view at ``θ + π`` is the mirror image of the view at
``θ`` about the projected rotation axis. If the axis projects to column
``c_ax``, the horizontally mirrored partner ``b'(j) = p_{θ+π}(n_cols - 1 - j)``
is the view ``p_θ`` shifted by twice the offset,
``b'(j) = p_θ(j + 2 (c_ax - (n_cols - 1)/2))``, which a cross-correlation
finds to a small fraction of a pixel.

Offset convention (shared with :class:`pdvc.calibration.MotionSummary`):
``offset_px = c_ax - (n_cols - 1)/2``, positive toward larger column
indices (the detector's ``u``, the lab ``+x``). It corresponds to a
constant lab translation of the sample by ``offset_px · |u| / M`` along
lab ``x`` (``M`` the magnification of the nominal axis, 1 in parallel
beam), which :func:`offset_poses` writes as per-view sample-frame poses.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..correlation import lab_frames
from ..errors import InputTypeError, PdvcError, ShapeError
from ..geometry import Poses, VectorGeometry

__all__ = [
    "InitError", "AxisLeanEstimate", "AxisOffsetEstimate", "AxisRollEstimate", "MirrorComparison", "compare_axes",
    "compare_offsets", "estimate_axis_lean", "estimate_axis_offset", "estimate_axis_roll", "offset_poses",
]

log = logging.getLogger(__name__)

_MAD_TO_SIGMA = 1.4826


class InitError(PdvcError, ValueError):
    """The coarse initialisation found no usable data or no reliable estimate."""


@dataclass(frozen=True, eq=False)
class AxisOffsetEstimate:
    """Centre-of-rotation offset found by correlating opposite views.

    Attributes
    ----------
    offset_px : float, pixels
        Column of the projected rotation axis minus the detector centre
        column ``(n_cols - 1)/2``; positive toward larger column indices.
        Median over the pairs.
    translation : float, length
        The same offset as a lab-frame translation of the sample along lab
        ``x`` (the detector's ``u``): ``offset_px · pixel_size /
        magnification``. A constant lab translation ``(translation, 0, 0)``
        (:func:`pdvc.simulate.lab_motion_to_poses`, or :func:`offset_poses`)
        moves the nominal axis onto the detected one.
    spread_px : float, pixels
        Robust spread of the per-pair offsets, 1.4826 x their median
        absolute deviation (0 when there is a single pair).
    n_pairs : int
    pairs : (n_pairs, 2) int64
        View indices ``(i, j)``, ``θ_j ≈ θ_i + π``.
    pair_offsets_px : (n_pairs,) float64, pixels
    pair_correlation : (n_pairs,) float64
        Normalised cross-correlation of each pair at its best shift (1 for
        a perfect mirror image).
    magnification : float
        Source-to-detector over source-to-axis distance (mean over views;
        1 for parallel beam).
    pixel_size : float, length
        Detector column pitch ``|u|`` (mean over views).
    rows : (n_rows_used,) int64
        Detector rows that were correlated.
    mismatch_slope : float, pixels per radian
        A 180° scan (pairs of views near opposite): how the pairs' offsets change
        with their mismatch ``δ = θ_j − θ_i − π`` (the line extrapolated to
        ``δ = 0``); 0 where the pairs are opposite.
    """

    offset_px: float
    translation: float
    spread_px: float
    n_pairs: int
    pairs: np.ndarray
    pair_offsets_px: np.ndarray
    pair_correlation: np.ndarray
    magnification: float
    pixel_size: float
    rows: np.ndarray
    mismatch_slope: float = 0.0

    @property
    def lab_translation(self) -> np.ndarray:
        """``(translation, 0, 0)``: the constant lab-frame translation of the sample, length."""
        return np.array([self.translation, 0.0, 0.0])


def _read_only(a, dtype=np.float64) -> np.ndarray:
    arr = np.array(a, dtype=dtype)
    arr.setflags(write=False)
    return arr


def _scan_angles(geom: VectorGeometry) -> np.ndarray:
    """Azimuth of each view's lab ``x`` (detector ``u``) in the sample frame, radians in [0, 2π).

    Exactly the scan angle θ of :func:`pdvc.geometry.circular_cone` and
    :func:`pdvc.geometry.parallel`.
    """
    F = lab_frames(geom)
    return np.mod(np.arctan2(F[:, 1, 0], F[:, 0, 0]), 2 * np.pi)


def _magnification(geom: VectorGeometry) -> np.ndarray:
    """Per-view magnification of the nominal axis (the volume-frame origin)."""
    if geom.kind != "cone":
        return np.ones(geom.n_views)
    N = geom.det_normal
    src = geom.src
    sdd = np.einsum("ij,ij->i", geom.det_center - src, N)
    sod = np.einsum("ij,ij->i", -src, N)
    return sdd / sod


def _from_opposite(d: np.ndarray) -> np.ndarray:
    """Angle differences ``θ_j − θ_i`` as ``θ_j − θ_i − π`` wrapped to [−π, π): how far view ``j`` is from opposite
    view ``i``."""
    return np.asarray(d) % (2 * np.pi) - np.pi


def _mismatch(theta: np.ndarray, i: int) -> np.ndarray:
    """``θ_j − θ_i − π`` for every view ``j``, wrapped to [−π, π): how far each view is from opposite view ``i``."""
    return _from_opposite(theta - theta[i])


#: a scan where fewer views than this have an opposite view is a short scan (docs/method.md §6)
SHORT_SCAN_OPPOSITE_FRACTION = 0.5


def opposite_fraction(geom: VectorGeometry) -> float:
    """The fraction of the views that have an opposite view (within half an angular step): 1 for a full turn,
    about 0 for a parallel scan over [0°, 180°)."""
    pairs, _ = _opposite_pairs(_scan_angles(geom), None)
    return 2.0 * pairs.shape[0] / geom.n_views


def distinct_directions(geom: VectorGeometry) -> int:
    """How many distinct projection directions the views hold.

    In parallel beam, view θ + 180° holds the line integrals of view θ,
    mirrored: a pair whose angles coincide within a tenth of the angular
    step counts once (a full turn of an even number of evenly spaced views
    has half as many directions as views; an odd number interleaves them).
    A cone-beam view is its own direction.
    """
    if geom.kind != "parallel":
        return int(geom.n_views)
    theta = _scan_angles(geom)
    step = _opposite_pairs(theta, None)[1]
    return int(geom.n_views - _opposite_pairs(theta, 0.1 * step)[0].shape[0])


def _opposite_pairs(theta: np.ndarray, max_mismatch: float | None) -> tuple[np.ndarray, float]:
    """Unordered pairs ``(i, j)``, ``i < j``, with ``θ_j`` nearest to ``θ_i + π`` within the tolerance."""
    n = theta.size
    srt = np.sort(theta)
    gaps = np.diff(np.concatenate([srt, srt[:1] + 2 * np.pi]))
    gaps = gaps[gaps > 1e-9]
    step = float(np.median(gaps)) if gaps.size else 0.0
    tol = 0.5 * step if max_mismatch is None else float(max_mismatch)
    tol *= 1 + 1e-9  # a partner exactly half a step away counts
    pairs = set()
    for i in range(n):
        d = np.abs(_mismatch(theta, i))
        d[i] = np.inf
        j = int(np.argmin(d))
        if d[j] <= tol:
            pairs.add((min(i, j), max(i, j)))
    return np.array(sorted(pairs), dtype=np.int64).reshape(-1, 2), step


def _near_opposite_pairs(theta: np.ndarray, step: float, reach: float = 2.5) -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``(i, j)``, ``i < j``, with ``θ_j`` within ``reach`` steps of ``θ_i + π``, and their mismatches.

    The mismatch ``δ = θ_j − θ_i − π`` (:func:`_mismatch`) is signed: a
    180° scan without its end point pairs view 0 with the last view at
    ``δ = −step`` and with the one before at ``−2 step``. One view at a
    time (memory in the number of views, not its square).
    """
    pairs, delta = [], []
    for i in range(theta.size - 1):
        d = _mismatch(theta, i)[i + 1:]
        for j in np.nonzero(np.abs(d) <= reach * step * (1 + 1e-9))[0]:
            pairs.append((i, i + 1 + j))
            delta.append(d[j])
    return np.array(pairs, dtype=np.int64).reshape(-1, 2), np.array(delta, dtype=np.float64)


def _pairs(theta: np.ndarray, max_mismatch: float | None = None) -> tuple[np.ndarray, np.ndarray | None, float]:
    """The pairs :func:`estimate_axis_offset` correlates, their mismatches (None where they are opposite) and the
    angular step: opposite views, else (``max_mismatch`` unset) the views up to 2.5 steps from opposite where they
    hold two different mismatches to extrapolate from.

    "Else" is fewer than two opposite pairs: a 180° scan with its end point has one (its first and last views), too
    few for anything that needs a spread over pairs (a standard error, a slope common to every pair); its views near
    opposite hold that pair and five more (1 and 2 steps from opposite), as those of a 180° scan without its end point
    do."""
    pairs, step = _opposite_pairs(theta, max_mismatch)
    if pairs.shape[0] < 2 and max_mismatch is None and step > 0:
        near, delta = _near_opposite_pairs(theta, step)
        if np.unique(np.round(delta / step)).size >= 2:
            return near, delta, step
    return pairs, None, step


def pairs_phrase(geom: VectorGeometry, n_pairs: int) -> str:
    """How the log and ``pdvc inspect`` name the ``n_pairs`` pairs an estimate from opposite views used: opposite, or
    (fewer than two opposite on the scan: a 180° scan) near opposite."""
    near = _pairs(_scan_angles(geom))[1] is not None
    return (f"{n_pairs} pairs of views near opposite (up to 2.5 steps from 180°)" if near
            else f"{n_pairs} opposite view pairs")


def _mirrored(projections, i: int, j: int, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """View ``i``'s rows and view ``j``'s mirrored (float64)."""
    return (np.asarray(projections[i], np.float64)[rows], np.asarray(projections[j], np.float64)[rows][:, ::-1])


def _prepare(img: np.ndarray) -> np.ndarray:
    """Rows minus the straight line through their end values: zero at both ends, so zero padding adds no step."""
    x = np.linspace(0.0, 1.0, img.shape[1])
    return img - (img[:, :1] * (1.0 - x) + img[:, -1:] * x)


def _vertex(y: np.ndarray, j: int) -> float:
    """Where the parabola through ``y[j - 1 : j + 2]`` peaks, relative to ``j`` (0 at an end or without a peak)."""
    if not 0 < j < y.size - 1:
        return 0.0
    y0, y1, y2 = y[j - 1], y[j], y[j + 1]
    den = y0 - 2 * y1 + y2
    return float(0.5 * (y0 - y2) / den) if den < 0 else 0.0


def _shift_by_correlation(a: np.ndarray, b: np.ndarray, *, upsample: int, max_shift: float) -> tuple[float, float]:
    """Shift ``s`` (columns) with ``b(j) ≈ a(j + s)``, summed over rows; and the normalised peak.

    Zero-padded FFT cross-correlation, then the band-limited (DFT)
    interpolation of the correlation on a grid of ``1/upsample`` pixel
    around the integer peak, then a parabola through the best grid point
    and its neighbours.
    """
    n = a.shape[1]
    size = 1 << int(np.ceil(np.log2(2 * n)))
    A = np.fft.rfft(a, size, axis=1)
    B = np.fft.rfft(b, size, axis=1)
    X = np.sum(A * np.conj(B), axis=0)
    corr = np.fft.irfft(X, size)
    lags = np.fft.fftfreq(size, 1.0 / size)  # 0, 1, ..., -1
    allowed = np.abs(lags) <= max_shift
    i = int(np.argmax(np.where(allowed, corr, -np.inf)))
    s0 = float(lags[i])
    k = np.arange(X.size)
    weight = np.where((k == 0) | ((size % 2 == 0) & (k == size // 2)), 1.0, 2.0)
    grid = s0 + np.arange(-upsample, upsample + 1) / upsample
    fine = (np.exp(2j * np.pi * np.outer(grid, k) / size) @ (weight * X)).real / size
    j = int(np.argmax(fine))
    shift = float(grid[j] + _vertex(fine, j) / upsample)
    norm = float(np.sqrt(np.sum(a * a) * np.sum(b * b)))
    ncc = float(fine[j] / norm) if norm > 0 else 0.0
    if abs(shift) >= max_shift - 1.0:
        shift = np.copysign(np.inf, shift)  # the peak sits at the search limit: no estimate
    return shift, ncc


#: _shift_over_overlap compares at most this many bands of consecutive rows (each their rows' mean)
OVERLAP_BANDS = 16


def _bands(x: np.ndarray, n_bands: int = OVERLAP_BANDS) -> np.ndarray:
    """At most ``n_bands`` rows: bands of consecutive rows averaged (the columns' structure kept, the cost
    bounded)."""
    if x.shape[0] <= n_bands:
        return x
    edges = np.linspace(0, x.shape[0], n_bands + 1).round().astype(int)
    return np.add.reduceat(x, edges[:-1], axis=0) / np.diff(edges)[:, None]


def _window(shifts: np.ndarray, n: int) -> tuple[int, int]:
    """The columns ``lo:hi`` of a row of ``n`` where every shift of ``shifts`` (columns) keeps the shifted row inside,
    ``OVERLAP_EDGE`` from its smoothed ends."""
    lo = max(0, int(np.ceil(-np.min(shifts)))) + OVERLAP_EDGE
    hi = min(n, n - int(np.ceil(np.max(shifts)))) - OVERLAP_EDGE
    return lo, hi


def _t(d: np.ndarray) -> float:
    """The mean of the samples ``d`` over its standard error (inf where they all agree and are positive)."""
    se = float(np.std(d, ddof=1) / np.sqrt(d.size))
    return float(np.mean(d) / se) if se > 0 else (np.inf if np.mean(d) > 0 else 0.0)


#: the rows compared over their overlap are smoothed along the columns by a Gaussian of this standard deviation, pixels,
#: before any shift: a cubic spline at a fraction of a pixel averages the noise it interpolates (its variance 0.5-0.6
#: of the noise's at half a pixel, 1 at a whole one), which pulls the mean squared difference toward fractional
#: shifts wherever the noise dominates it: a cylinder wider than the field at i0 = 2e3 (its views smooth domes) came
#: out 0.21-0.23 px off an axis at 0 or 0.5 px, and the comparison preferred 0.25 px to the true 0 by 18-20 standard
#: errors. Smoothed, both agree within 0.02 px and the comparison prefers the truth (docs/method.md §5.43)
OVERLAP_SMOOTH_PX = 1.0
#: columns at each end of a smoothed row that the smoothing took past the row's end, left out of every comparison
OVERLAP_EDGE = 3


def _smoothed(x: np.ndarray, axes=(1,)) -> np.ndarray:
    """Rows smoothed by ``OVERLAP_SMOOTH_PX`` along ``axes`` (the columns; rows too with ``(0, 1)``)."""
    from scipy import ndimage

    for ax in axes:
        x = ndimage.gaussian_filter1d(x, OVERLAP_SMOOTH_PX, axis=ax, mode="nearest")
    return x


def _msd(a: np.ndarray, b: np.ndarray, shifts, lo: int, hi: int, per_row: bool = False) -> np.ndarray:
    """Mean squared difference of ``b(j)`` and ``a(j + s)`` (a cubic spline) over the columns ``lo:hi``, per shift
    (and per row: ``(n_shifts, n_rows)``)."""
    from scipy import ndimage

    return np.array([np.mean((b[:, lo:hi] - ndimage.shift(a, (0.0, -s), order=3, mode="nearest")[:, lo:hi]) ** 2,
                             axis=1 if per_row else None) for s in shifts])


def _shift_over_overlap(a: np.ndarray, b: np.ndarray, *, upsample: int, max_shift: float,
                        smooth: bool = True) -> tuple[float, float]:
    """Shift ``s`` (columns) with ``b(j) ≈ a(j + s)``, from the mean squared difference over the columns both rows
    hold; and the (mean-removed) correlation coefficient there.

    For rows whose ends hold material (a region-of-interest scan): zero padding would add a step at each end and
    :func:`_prepare`'s straight line differs between the two rows (their ends lie at different places of the
    sample), both of which pull the estimate toward the shift that lines up the detector's edges. Here nothing is
    padded or detrended: the mean squared difference over the overlap at every whole shift (FFT, each shift
    normalised by its own overlap, at least half the row), then on a fixed window of columns at ``1/upsample``
    pixel around the best one (``a`` interpolated by a cubic spline), then a parabola. With ``smooth``, both rows are
    smoothed along the columns first (:data:`OVERLAP_SMOOTH_PX`); the window is kept :data:`OVERLAP_EDGE` columns from
    their ends.
    """
    from scipy import ndimage

    a, b = (_smoothed(_bands(a)), _smoothed(_bands(b))) if smooth else (_bands(a), _bands(b))
    nr, n = a.shape
    size = 1 << int(np.ceil(np.log2(2 * n)))
    ones = np.ones_like(a)

    def xcorr(x, y):  # sum over rows and j of y(j) x(j + s), for every whole s
        return np.fft.irfft(np.sum(np.fft.rfft(x, size, axis=1) * np.conj(np.fft.rfft(y, size, axis=1)), axis=0), size)

    count = xcorr(ones, ones) / nr
    ssd = xcorr(a * a, ones) + xcorr(ones, b * b) - 2.0 * xcorr(a, b)
    lags = np.fft.fftfreq(size, 1.0 / size)
    allowed = (np.abs(lags) <= max_shift) & (count >= 0.5 * n - 0.5)
    i = int(np.argmin(np.where(allowed, ssd / np.maximum(count, 1.0), np.inf)))
    s0 = float(lags[i])
    grid = s0 + np.arange(-upsample, upsample + 1) / upsample
    lo, hi = _window(grid, n)
    if hi - lo < 2:
        return np.copysign(np.inf, s0), 0.0

    msd = _msd(a, b, grid, lo, hi)
    j = int(np.argmin(msd))
    shift = float(grid[j] + _vertex(-msd, j) / upsample)
    x = ndimage.shift(a, (0.0, -shift), order=3, mode="nearest")[:, lo:hi].ravel()
    y = b[:, lo:hi].ravel()
    x, y = x - x.mean(), y - y.mean()
    norm = float(np.sqrt(np.sum(x * x) * np.sum(y * y)))
    ncc = float(np.sum(x * y) / norm) if norm > 0 else 0.0
    if abs(s0) >= max_shift - 1.0:
        shift = np.copysign(np.inf, s0)  # the best whole shift sits at the search limit: no estimate
    return shift, ncc


def _rows(rows, geom: VectorGeometry) -> np.ndarray:
    nr = geom.det_shape[0]
    if rows is None:
        if geom.kind == "cone":
            m = max(1, nr // 4)
            r0 = (nr - m) // 2
            return np.arange(r0, r0 + m)
        return np.arange(nr)
    if isinstance(rows, slice):
        idx = np.arange(nr)[rows]
    else:
        idx = np.atleast_1d(np.asarray(rows))
        if idx.dtype.kind not in "iu" or idx.ndim != 1:
            raise ShapeError(f"rows must be a slice or a 1D sequence of row indices (ints), got {rows!r}")
    if idx.size == 0 or np.any(idx < -nr) or np.any(idx >= nr):
        raise ShapeError(f"rows must select at least one of the {nr} detector rows, got {rows!r}")
    return np.mod(idx, nr).astype(np.int64)


def estimate_axis_offset(
    projections,
    geom: VectorGeometry,
    *,
    rows=None,
    upsample: int = 10,
    max_mismatch: float | None = None,
    max_offset: float | None = None,
    max_spread: float = 2.0,
    min_correlation: float = 0.5,
    overlap: bool = False,
    smooth: bool = True,
) -> AxisOffsetEstimate:
    """Centre-of-rotation offset by cross-correlating each view with its mirrored opposite.

    Every view ``i`` is paired with the view ``j`` whose angle is nearest
    to ``θ_i + π``, if it lies within ``max_mismatch`` (default half the
    median angular step; otherwise view ``i`` is skipped); each unordered
    pair is used once. ``p_j`` is mirrored horizontally and the column
    shift ``s`` that best aligns it with ``p_i`` is found by FFT
    cross-correlation refined to ``1/upsample`` pixel and a parabola; the
    pair's offset is ``s / 2``. The estimate is the median over pairs.

    This works for 360° scans (one pair per two views), 180° scans and
    irregular angle lists. A 180° scan **without** its end point (``n``
    views over ``[0, π)``, the usual synchrotron list) has no opposite view
    within half a step, one with its end point only one pair (0 and 180°):
    then (``max_mismatch`` unset) the views up to 2.5 steps from opposite are
    paired (view 0 with the last views), each pair's offset is biased by
    how far the sample turned between them (its projected motion over the
    mismatch ``δ``), and the offset is the straight line through the
    pairs' offsets against ``δ``, taken at ``δ = 0``.
    In **cone beam**, the opposite view is only approximately a mirror
    image (conjugate rays lie at ``θ + π + 2γ``, and depth changes the
    magnification), so by default only the central quarter of the rows (the
    mid-plane, where the cone angle is smallest) is correlated: the result
    is a **coarse** estimate, good to a pixel or so at small cone angles,
    for the P-DVC engine to refine, not a calibration.

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) array
        Line integrals (``-log`` of the flat/dark-normalised intensity);
        read only (e.g. a memory map: only the paired views are read).
    geom : VectorGeometry
        Nominal geometry (cone or parallel); its scan angle at view k is
        the azimuth of the detector's ``u`` (exact for
        :func:`pdvc.geometry.circular_cone` / :func:`pdvc.geometry.parallel`).
    rows : slice or sequence of int, optional
        Detector rows to correlate (summed). Default all rows in parallel
        beam, the central quarter (at least one) in cone beam.
    upsample : int, >= 1
        Sub-pixel grid of the correlation peak, ``1/upsample`` pixel.
    max_mismatch : float, radians, optional
        Largest ``|θ_j - θ_i - π|`` accepted for a pair.
    max_offset : float, pixels, optional
        Largest ``|offset_px|`` searched; default ``n_cols / 4``.
    max_spread : float, pixels
        The estimate is refused (:class:`InitError`) if the per-pair
        offsets spread more than this (1.4826 x MAD).
    min_correlation : float
        Refused if the median normalised peak correlation of the pairs is
        below this (the opposite views do not look alike).
    overlap : bool
        Compare each pair over the columns both views hold only (their mean
        squared difference), without the zero padding and the straight line
        through each row's ends that the default correlation takes out:
        for rows whose ends hold material (a region-of-interest scan, the
        sample wider than the field of view), where that line differs
        between the two views and pulls the estimate toward the detector's
        centre (a rod of ``bench_accuracy.py --quick --roi 1.0``: -0.20 px
        found for an axis at +1.28 px). Both rows are smoothed along the
        columns first (``OVERLAP_SMOOTH_PX``: a spline's fractional shifts
        average the noise, which biased views at the noise toward them) and
        their ``OVERLAP_EDGE`` end columns left out. Its correlation is the
        mean-removed one over the overlap.
    smooth : bool
        With ``overlap``: smooth both rows first (default). The smoothing
        also weakens a fine structure against a pattern fixed on the
        detector: a granular sample wider than the field under issue #10's
        flat field came out at -6.7 px for +1.4 px smoothed, +1.39 px
        without (the pipeline compares both, ``docs/method.md`` §5.43).

    Returns
    -------
    AxisOffsetEstimate

    Raises
    ------
    InitError
        No pair of opposite views, or an unreliable estimate (peaks at the
        search limit, spread above ``max_spread``, weak correlation,
        projections without signal).

    Examples
    --------
    >>> import numpy as np
    >>> from pdvc.geometry import parallel
    >>> from pdvc.simulate import shepp_logan_3d, project_analytic
    >>> angles = np.linspace(0, np.pi, 181)
    >>> geom = parallel(angles, det_shape=(4, 128), pixel=0.0125)
    >>> moved = geom.apply_poses(*offset_poses(geom, 12.5))
    >>> est = estimate_axis_offset(project_analytic(shepp_logan_3d(0.6), moved, supersampling=2), geom)
    >>> abs(est.offset_px - 12.5) < 0.1
    True
    """
    if not isinstance(geom, VectorGeometry):
        raise InputTypeError(f"geom must be a pdvc.VectorGeometry, got {type(geom).__name__}")
    shape = np.shape(projections)
    expected = (geom.n_views, *geom.det_shape)
    if shape != expected:
        raise ShapeError(f"projections must have shape {expected} (n_views, n_rows, n_cols) like geom, got {shape}")
    if not isinstance(upsample, (int, np.integer)) or isinstance(upsample, bool) or upsample < 1:
        raise InputTypeError(f"upsample must be a positive int, got {upsample!r}")
    n_cols = geom.det_shape[1]
    lim = n_cols / 4 if max_offset is None else float(max_offset)
    if not (np.isfinite(lim) and lim > 0):
        raise InitError(f"max_offset must be a positive number of pixels, got {max_offset!r}")
    row_idx = _rows(rows, geom)

    theta = _scan_angles(geom)
    pairs, mismatch, step = _pairs(theta, max_mismatch)  # mismatch: extrapolated to 0 when the pairs are not opposite
    if pairs.shape[0] == 0:
        span = np.degrees(np.ptp(np.unwrap(np.sort(theta))))
        tol = np.degrees(0.5 * step if max_mismatch is None else max_mismatch)
        raise InitError(
            f"no pair of opposite views: expected for some view at θ another at θ+180° within {tol:.3g}° "
            f"(half the angular step), or views at two different mismatches within 2.5 steps to extrapolate "
            f"from, but the {geom.n_views} views span {span:.4g}° (or pass max_mismatch)"
        )

    offsets, nccs = [], []
    prepare, shift_of = ((lambda x: x), _shift_over_overlap) if overlap else (_prepare, _shift_by_correlation)
    extra = dict(smooth=bool(smooth)) if overlap else {}
    for i, j in pairs:
        a, b = (prepare(x) for x in _mirrored(projections, i, j, row_idx))
        s, ncc = shift_of(a, b, upsample=int(upsample), max_shift=2 * lim + 1, **extra)
        offsets.append(0.5 * s)
        nccs.append(ncc)
    offsets, nccs = np.array(offsets), np.array(nccs)
    good = np.isfinite(offsets)
    if not np.any(good):
        raise InitError(
            f"no reliable pair: every correlation peak lies at the search limit |offset| = {lim:g} px; "
            "expected the projected axis within max_offset of the detector centre (raise max_offset, or the "
            "opposite views do not overlap)"
        )
    if not np.all(good):
        log.warning("%d of %d pairs peak at the search limit and are left out", np.count_nonzero(~good), good.size)
    slope = 0.0
    if mismatch is None:
        med = float(np.median(offsets[good]))
        resid = offsets[good] - med
    else:
        # offset_ij = offset + slope * δ_ij near the end points: the line at δ = 0
        dg = mismatch[good]
        if np.unique(np.round(dg / step)).size < 2:
            raise InitError("no reliable pair: the pairs left after the search limit all have the same mismatch, "
                            "nothing to extrapolate to 180° from")
        slope, med = np.polyfit(dg, offsets[good], 1)
        med = float(med)
        resid = offsets[good] - (med + slope * dg)
        log.info("fewer than two pairs of views opposite within half a step: axis offset extrapolated to 180° from %d "
                 "pairs %.3g-%.3g steps from opposite (slope %.3g px per step)", dg.size, np.abs(dg).min() / step,
                 np.abs(dg).max() / step, slope * step)
    spread = float(_MAD_TO_SIGMA * np.median(np.abs(resid))) if resid.size > 1 else 0.0
    med_ncc = float(np.median(nccs))
    if not np.isfinite(med_ncc) or med_ncc < min_correlation:
        raise InitError(
            f"unreliable estimate: the opposite views correlate weakly (median normalised peak {med_ncc:.3f}, "
            f"expected >= {min_correlation}); check that the projections are line integrals and the angles "
            "are right"
        )
    if spread > max_spread:
        raise InitError(
            f"unreliable estimate: the {np.count_nonzero(good)} pairs disagree by {spread:.3g} px (robust spread, "
            f"expected <= {max_spread} px; median {med:+.3f} px)"
        )
    mag = _magnification(geom)
    pitch = np.linalg.norm(geom.u, axis=1)
    translation = float(np.mean(med * pitch / mag))
    log.info(
        "axis offset %+.3f px (%+.5g length along lab x) from %d pair(s) of opposite views, spread %.3f px",
        med,
        translation,
        pairs.shape[0],
        spread,
    )
    return AxisOffsetEstimate(
        offset_px=med,
        translation=translation,
        spread_px=spread,
        n_pairs=int(pairs.shape[0]),
        pairs=_read_only(pairs, np.int64),
        pair_offsets_px=_read_only(offsets),
        pair_correlation=_read_only(nccs),
        magnification=float(np.mean(mag)),
        pixel_size=float(np.mean(pitch)),
        rows=_read_only(row_idx, np.int64),
        mismatch_slope=float(slope),
    )


@dataclass(frozen=True)
class MirrorComparison:
    """Two axis offsets compared by how well each view matches its mirrored opposite (:func:`compare_offsets`)."""

    offsets_px: tuple
    msd: tuple  # mean over the pairs of each offset's mean squared difference
    t: float  # the paired difference (first minus second) over its standard error, over the pairs' bands of rows
    n_pairs: int

    @property
    def second_better(self) -> bool:
        """The second offset matches the opposite views better, by more than ``MIRROR_MIN_T`` standard errors."""
        return self.t > MIRROR_MIN_T


#: compare_offsets: the paired difference of the two offsets' mean squared differences, over its standard error, above
#: which the second is the better one
MIRROR_MIN_T = 3.0


def compare_offsets(projections, geom: VectorGeometry, first: float, second: float, *, rows=None,
                    mismatch_slope: float = 0.0) -> MirrorComparison:
    """Two axis offsets (pixels, as :func:`estimate_axis_offset`'s) compared without a reconstruction: each view and
    its mirrored opposite (the pairs within half an angular step of 180°) over the columns both hold, on one window of
    columns for both offsets, their mean squared difference with the axis at each; the paired difference over the
    pairs and bands of rows (:func:`estimate_axis_offset`'s, at most ``OVERLAP_BANDS`` per pair, each band of each
    pair one sample: a 180° scan has only 3 pairs, or 6 with its end point) and its standard error.

    A 180° scan has no opposite view within half a step (without its end point) or one pair (with it): there the views
    up to 2.5 steps from opposite are paired, as :func:`estimate_axis_offset` pairs them, each pair's mirror shifted
    by what the sample turned between its views (``mismatch_slope``, the estimate's, times the pair's mismatch) for
    both offsets.

    In parallel beam a view is its opposite's mirror image about the projected axis, whatever lies outside the
    field of view: a check of the axis that a region-of-interest scan's reconstruction cannot give. In cone beam
    the mirror is approximate (the central quarter of the rows by default, as in :func:`estimate_axis_offset`).

    Raises
    ------
    InitError
        No pair of opposite views within half a step, or offsets too far apart for a shared window.
    """
    row_idx = _rows(rows, geom)
    pairs, delta, _ = _pairs(_scan_angles(geom))
    delta = np.zeros(pairs.shape[0]) if delta is None else delta
    if pairs.shape[0] < 2:
        raise InitError("compare_offsets needs two pairs of opposite views or more (each view with one within half "
                        f"an angular step of 180 degrees, or 2.5 steps without one), got {pairs.shape[0]}")
    n = geom.det_shape[1]
    shifts = 2.0 * (np.array([float(first), float(second)])[None, :] + float(mismatch_slope) * delta[:, None])
    lo, hi = _window(shifts, n)
    if hi - lo < n // 2:
        raise InitError(f"compare_offsets: offsets {first:+.3g} and {second:+.3g} px leave less than half the "
                        f"{n} columns to compare")
    # (pair, shift, band of rows): each band of each pair a sample of the paired difference
    msd = np.array([_msd(*(_smoothed(_bands(x)) for x in _mirrored(projections, i, j, row_idx)), sh, lo, hi, per_row=True)
                    for (i, j), sh in zip(pairs, shifts)])
    t = _t((msd[:, 0] - msd[:, 1]).ravel())
    msd = msd.mean(axis=2)
    return MirrorComparison(offsets_px=(float(first), float(second)), msd=tuple(float(m) for m in msd.mean(axis=0)),
                            t=t, n_pairs=int(pairs.shape[0]))


#: estimate_axis_roll: the projected axis searched within this angle of the detector's columns, degrees; at most this many
#: pairs of opposite views (evenly chosen) and bands of rows take part
ROLL_MAX_DEG = 1.5
ROLL_MAX_PAIRS = 32
ROLL_MAX_BANDS = 64


@dataclass(frozen=True, eq=False)
class AxisRollEstimate:
    """The projected rotation axis as a line on the detector, from opposite views (:func:`estimate_axis_roll`).

    Attributes
    ----------
    offset_px : float, pixels
        Column of the line at the detector's centre row minus the centre column (as
        :attr:`AxisOffsetEstimate.offset_px`).
    slope : float
        Columns per row along the line (positive: the axis leans toward larger columns at larger rows).
    roll : float, radians
        The axis's tilt about the beam, ``arctan(slope · |u| / |v|)``: the ``roll`` of
        :func:`pdvc.calibration.tilt_poses` (and of :class:`AxisTiltEstimate`).
    comparison : MirrorComparison
        The line (second) against the best upright axis (first, its offset found the same way), each view against
        its opposite reflected about either (as :func:`compare_axes`): whether the views ask for the lean.
    n_pairs : int
        Pairs of opposite views used.
    upright_offset_px : float, pixels
        The best upright axis's offset, found the same way (each view against its opposite reflected about it).
    """

    offset_px: float
    slope: float
    roll: float
    comparison: MirrorComparison
    n_pairs: int
    upright_offset_px: float

    @property
    def roll_deg(self) -> float:
        return float(np.rad2deg(self.roll))


class _Reflection:
    """Views and their mirrored opposites in bands of rows, and how well each view matches its opposite reflected about
    a line ``c = c_centre + offset + slope · (r - r_centre)`` of the detector (parallel beam: exact).

    A reflection about a line that leans by ``slope`` is a flip of the columns, a shift that changes along the rows
    and a shift of the rows that changes along the columns (``2 slope Δ`` for a pixel ``Δ`` columns from the line):
    the last is what a per-row shift leaves out (2.2 rows at 80 columns from the axis leaning 0.8°)."""

    def __init__(self, projections, geom: VectorGeometry, max_slope: float, max_offset: float):
        from scipy import ndimage

        if geom.kind != "parallel":
            raise InitError("the axis's lean from opposite views is measured in parallel beam only (in cone beam a view "
                            "is its opposite's mirror image near the mid-plane only)")
        nr, n = geom.det_shape
        pairs, delta, _ = _pairs(_scan_angles(geom))
        if delta is not None or pairs.shape[0] < 2:
            # views 1-2 steps from opposite differ by what the sample turned between them, which no reflection holds
            n_opposite = _opposite_pairs(_scan_angles(geom), None)[0].shape[0]
            raise InitError("the axis's line needs two pairs of opposite views or more (each view with one within "
                            f"half an angular step of 180 degrees), got {n_opposite}")
        keep = np.unique(np.linspace(0, pairs.shape[0] - 1, min(pairs.shape[0], ROLL_MAX_PAIRS)).round().astype(int))
        pairs = pairs[keep]
        rows = np.arange(nr)
        nb = min(nr, ROLL_MAX_BANDS)

        def bands(x):
            return _bands(x, nb)

        self.centre_rows = bands(rows[:, None].astype(np.float64))[:, 0]
        self.height = float(nr) / nb
        self.r_centre, self.c_centre = (nr - 1) / 2.0, (n - 1) / 2.0
        self.coef, self.mirrored = [], []
        for i, j in pairs:
            # both smoothed alike along the rows too (OVERLAP_SMOOTH_PX: a lean found where there is none, 0.44° at
            # i0 = 2e4 unsmoothed)
            a, b = (_smoothed(bands(x), (0, 1)) for x in _mirrored(projections, int(i), int(j), rows))
            self.coef.append(ndimage.spline_filter(a, order=3))
            self.mirrored.append(b)
        # one window for every line within reach: columns a shift of twice the largest offset leaves inside, bands the
        # rows' shift leaves inside
        reach = 2.0 * max_slope * (n / 2.0 + max_offset) / self.height
        self.band_lo, self.band_hi = int(np.ceil(reach)) + OVERLAP_EDGE, nb - int(np.ceil(reach)) - OVERLAP_EDGE
        self.n_pairs, self.n = int(pairs.shape[0]), n
        if self.band_hi - self.band_lo < 2:
            raise InitError(f"the axis's line needs more rows: {nr} rows leave no band to compare within "
                            f"{np.degrees(np.arctan(max_slope)):.3g} degrees of lean")

    def window(self, shifts: np.ndarray) -> tuple[int, int]:
        lo, hi = _window(shifts, self.n)
        if hi - lo < self.n // 2:
            raise InitError(f"offsets of {0.5 * shifts.min():+.3g} to {0.5 * shifts.max():+.3g} px leave less than half "
                            f"the {self.n} columns to compare")
        return lo, hi

    def shifts(self, offset: float, slope: float) -> np.ndarray:
        """(band,): the column shift of each band."""
        return 2.0 * (offset + slope * (self.centre_rows - self.r_centre))

    def msd(self, offset: float, slope: float, cols: tuple[int, int]) -> np.ndarray:
        """(pair, band): the mean squared difference of each band of each view's mirrored opposite and the view
        reflected about the line, over the window's columns ``cols`` and bands."""
        from scipy import ndimage

        lo, hi = cols
        b0, b1 = self.band_lo, self.band_hi
        c = np.arange(lo, hi, dtype=np.float64)[None, :]
        k = np.arange(b0, b1, dtype=np.float64)[:, None]
        rows = self.centre_rows[b0:b1, None]
        dist = self.c_centre - c - offset - slope * (rows - self.r_centre)  # columns from the line, unflipped
        out = np.empty((self.n_pairs, b1 - b0))
        col = c + 2.0 * (offset + slope * (rows - self.r_centre))
        row = np.broadcast_to(k + 2.0 * slope * dist / self.height, col.shape)
        for q, (coef, b) in enumerate(zip(self.coef, self.mirrored)):
            pred = ndimage.map_coordinates(coef, [row, col], order=3, prefilter=False, mode="nearest")
            out[q] = np.mean((b[b0:b1, lo:hi] - pred) ** 2, axis=1)
        return out


def _paired(first: np.ndarray, second: np.ndarray, lines: tuple) -> MirrorComparison:
    """The paired difference of two (pair, band) mean squared differences over its standard error, each pair one
    sample (its bands share their smoothing along the rows: as samples they made a 0.026° lean of an upright foam
    3.7 standard errors better than none)."""
    return MirrorComparison(offsets_px=lines, msd=(float(first.mean()), float(second.mean())),
                            t=_t((first - second).mean(axis=1)), n_pairs=int(first.shape[0]))


def compare_axes(projections, geom: VectorGeometry, first: tuple, second: tuple) -> MirrorComparison:
    """Two lines of the projected axis, ``(offset_px, slope)`` each (columns at the centre row, columns per row),
    compared without a reconstruction: each view against its opposite reflected about either, on one window of
    columns and bands of rows, the paired difference of their mean squared differences, each pair one sample, over
    its standard error (``offsets_px`` holds both lines; :func:`compare_offsets` compares upright axes, on half turns
    too).

    Parallel beam, views with an opposite within half an angular step (a full turn): a view is its opposite's
    reflection about the projected axis, whatever lies outside the field.

    Raises
    ------
    InitError
        A cone-beam geometry, fewer than two pairs of opposite views, too few rows or columns to compare.
    """
    first, second = (tuple(float(x) for x in line) for line in (first, second))
    refl = _Reflection(projections, geom, max(abs(first[1]), abs(second[1])), max(abs(first[0]), abs(second[0])))
    cols = refl.window(np.concatenate([refl.shifts(*first), refl.shifts(*second)]))
    return _paired(refl.msd(*first, cols), refl.msd(*second, cols), (first, second))


def _quadratic_minimum(cost, x0, steps, rounds: int = 4) -> np.ndarray:
    """Where a smooth cost of two parameters is least: a quadratic fitted to a 3×3 stencil of ``steps`` about the
    current point, its minimum (at most two steps away; the stencil's best point where the quadratic has none), the
    steps halved, ``rounds`` times: 9 evaluations a round (a Nelder–Mead simplex took about 130 to the same 0.001)."""
    x, h = np.asarray(x0, np.float64), np.asarray(steps, np.float64)
    u = np.array([(i, j) for i in (-1.0, 0.0, 1.0) for j in (-1.0, 0.0, 1.0)])
    design = np.column_stack([np.ones(9), u[:, 0], u[:, 1], u[:, 0] ** 2, u[:, 1] ** 2, u[:, 0] * u[:, 1]])
    for _ in range(rounds):
        vals = np.array([cost(x + h * d) for d in u])
        c = np.linalg.lstsq(design, vals, rcond=None)[0]
        hess = np.array([[2.0 * c[3], c[5]], [c[5], 2.0 * c[4]]])
        if np.all(np.linalg.eigvalsh(hess) > 0):
            step = np.clip(-np.linalg.solve(hess, c[1:3]), -2.0, 2.0)
        else:
            step = u[int(np.argmin(vals))]
        x = x + h * step
        h = 0.5 * h
    return x


def estimate_axis_roll(projections, geom: VectorGeometry, offset: AxisOffsetEstimate) -> AxisRollEstimate:
    """The projected axis as a line on the detector: its offset and lean from opposite views, each view against its
    opposite reflected about the line (:class:`_Reflection`), the mean squared difference over one window of
    columns and bands of rows minimised from ``offset``'s upright axis (quadratic fits, within ``ROLL_MAX_DEG``).

    Parallel beam only (in cone beam a view is its opposite's mirror image only near the mid-plane: a lean of 0.96°
    found for 0.8° at a half-angle of 2.9°), with opposite views (a full turn; a 180° scan has none, or one pair with
    its end point). The estimate's ``comparison`` says whether the views prefer the line to the best upright axis.

    Raises
    ------
    InitError
        A cone-beam geometry, fewer than two pairs of opposite views, too few rows or columns to compare, or no
        minimum within reach.
    """
    from scipy.optimize import minimize_scalar

    if not isinstance(offset, AxisOffsetEstimate):
        raise InputTypeError(f"offset must be a pdvc.calibration.AxisOffsetEstimate, got {type(offset).__name__}")
    pu, pv = float(np.mean(np.linalg.norm(geom.u, axis=1))), float(np.mean(np.linalg.norm(geom.v, axis=1)))
    max_slope = np.tan(np.radians(ROLL_MAX_DEG)) * pv / pu
    refl = _Reflection(projections, geom, max_slope, abs(float(offset.offset_px)) + 1.0)
    o0 = float(offset.offset_px)
    cols = refl.window(np.concatenate([refl.shifts(o0 + d, s) for d in (-1.0, 1.0) for s in (-max_slope, max_slope)]))
    scale = max_slope / 4.0  # the slope searched in units of a quarter of its reach

    def cost(x):
        return float(np.mean(refl.msd(o0 + x[0], x[1] * scale, cols)))

    # the upright axis first (the best offset by the same measure), then the line from there: the comparison is then
    # of the lean alone (against the upright axis at o0, a better offset alone made an upright cylinder lean 0.14°)
    up = minimize_scalar(lambda d: cost((d, 0.0)), bounds=(-1.0, 1.0), method="bounded", options=dict(xatol=1e-3))
    d_up = float(up.x)
    x = _quadratic_minimum(cost, (d_up, 0.0), (0.25, 1.0))
    d_off, slope = float(x[0]), float(x[1] * scale)
    if abs(d_off) > 1.0 or abs(slope) > max_slope:
        raise InitError(f"the axis's line left its reach: {d_off:+.2f} px from the upright axis's offset (at most 1), "
                        f"a lean of {np.degrees(np.arctan(slope * pu / pv)):+.2f} degrees (at most {ROLL_MAX_DEG:g})")
    upright, line = (o0 + d_up, 0.0), (o0 + d_off, slope)
    comparison = _paired(refl.msd(*upright, cols), refl.msd(*line, cols), (upright, line))
    roll = float(np.arctan(slope * pu / pv))
    log.info("axis line from %d pairs of opposite views: offset %+.3f px at the centre row, lean %+.3f deg (%.1f standard "
             "errors better than the upright axis at %+.3f px)", refl.n_pairs, line[0], np.degrees(roll), comparison.t,
             upright[0])
    return AxisRollEstimate(offset_px=line[0], slope=slope, roll=roll, comparison=comparison, n_pairs=refl.n_pairs,
                            upright_offset_px=upright[0])


@dataclass(frozen=True)
class AxisLeanEstimate:
    """The projected rotation axis as a line on the detector, from the axis offsets of the detector's top and bottom
    halves of rows (:func:`estimate_axis_lean`), each measured as :func:`estimate_axis_offset` measures it.

    Attributes
    ----------
    offset_px, slope : float
        The line at the detector's centre row and its columns per row, as in :class:`AxisRollEstimate`.
    roll : float, radians
        The axis's tilt about the beam, ``± arctan(slope · |u| / |v|)``: the ``roll`` of
        :func:`pdvc.calibration.tilt_poses` (its sign that of the detector's handedness about the ray
        ``tilt_poses`` turns about: ``+`` on :func:`pdvc.geometry.parallel`, ``−`` on
        :func:`pdvc.geometry.circular_cone`).
    roll_sd : float, radians
        Its standard error from the scatter of each half's pairs about their offset (their straight line against
        the pairs' mismatch on a 180° scan).
    top, bottom : AxisOffsetEstimate
        The two halves' estimates.
    """

    offset_px: float
    slope: float
    roll: float
    roll_sd: float
    top: AxisOffsetEstimate
    bottom: AxisOffsetEstimate

    @property
    def roll_deg(self) -> float:
        return float(np.rad2deg(self.roll))


def _offset_se(est: AxisOffsetEstimate, theta: np.ndarray) -> float:
    """Standard error of ``est.offset_px``: its pairs' scatter about their median, or about their line against the
    mismatch (its intercept's error) where the pairs are near opposite."""
    off = np.asarray(est.pair_offsets_px, np.float64)
    good = np.isfinite(off)
    n = int(np.count_nonzero(good))
    if est.mismatch_slope == 0.0:
        return float(np.std(off[good], ddof=1) / np.sqrt(n)) if n > 1 else np.inf
    i, j = np.asarray(est.pairs).T
    d = _from_opposite(theta[j] - theta[i])[good]
    if n < 3:
        return np.inf
    A = np.stack([np.ones(n), d], axis=1)
    coef, *_ = np.linalg.lstsq(A, off[good], rcond=None)
    s2 = float(np.sum((off[good] - A @ coef) ** 2) / (n - 2))
    return float(np.sqrt(s2 * np.linalg.inv(A.T @ A)[0, 0]))


class _Upright:
    """The views as they are read, each rotated in the detector plane by ``-angle`` about the detector's centre row at
    ``offset_px`` from its centre column (pixels of pitch ``|u|`` by ``|v|``): a projected axis that leans by ``angle``
    through that point stands upright in them, and a view's opposite is then its mirror image about a column."""

    def __init__(self, projections, geom: VectorGeometry, offset_px: float, angle: float):
        self.p, self.shape = projections, np.shape(projections)
        nr, nc = geom.det_shape
        pu = float(np.mean(np.linalg.norm(geom.u, axis=1)))
        pv = float(np.mean(np.linalg.norm(geom.v, axis=1)))
        c, s = np.cos(angle), np.sin(angle)
        self.matrix = np.array([[c, -(pu / pv) * s], [(pv / pu) * s, c]])
        centre = np.array([(nr - 1) / 2.0, (nc - 1) / 2.0 + float(offset_px)])
        self.offset = centre - self.matrix @ centre
        self._turned: dict = {}  # each view turned once: both halves read it

    def __getitem__(self, k):
        from scipy import ndimage

        k = int(k)
        if k not in self._turned:
            self._turned[k] = ndimage.affine_transform(np.asarray(self.p[k], np.float64), self.matrix, self.offset,
                                                       order=3, mode="nearest")
        return self._turned[k]


#: estimate_axis_lean: the views turned upright by the lean found so far and measured again, this many times
LEAN_ROUNDS = 3


def _halves(projections, geom: VectorGeometry, trim: int, kwargs: dict):
    """The offsets of the detector's top and bottom halves of rows, ``trim`` rows left out at either end."""
    nr = geom.det_shape[0]
    half = nr // 2
    top, bottom = np.arange(trim, half), np.arange(nr - half, nr - trim)
    e_top = estimate_axis_offset(projections, geom, rows=top, **kwargs)
    e_bot = estimate_axis_offset(projections, geom, rows=bottom, **kwargs)
    return e_top, e_bot, float(bottom.mean() - top.mean())


def estimate_axis_lean(projections, geom: VectorGeometry, **kwargs) -> AxisLeanEstimate:
    """The projected axis as a leaning line: :func:`estimate_axis_offset` on the detector's top and bottom halves of
    rows, the line through the two offsets (what beamline tools measure for a centre of rotation and a camera tilt),
    then again on the views turned upright about that line, :data:`LEAN_ROUNDS` times.

    A view is its opposite's reflection about the projected axis (parallel beam); about a leaning line that is a
    mirror image turned by twice the lean, which moves a pixel ``Δ`` columns from the line by ``2 Δ tan(lean)`` rows:
    compared row by row, the halves alone found 0.81° and -0.43° for a rod leaning by 0.9° and -0.6° (128 columns
    across it, i0 = 2·10⁴), 0.38° for 0.9° on a Shepp–Logan head; turned upright they compare as mirror images.
    Unlike :func:`estimate_axis_roll` (each view reflected about a leaning line, parallel full turns) it works on a
    180° scan, whose views near opposite it pairs and extrapolates as :func:`estimate_axis_offset` does; in cone beam
    a view's opposite is its mirror image only near the mid-plane, and the halves' offsets are then approximate.
    ``kwargs`` go to :func:`estimate_axis_offset` (not ``rows``).

    Raises
    ------
    InitError
        Fewer than 8 detector rows, or either half's estimate refused.
    """
    if "rows" in kwargs:
        raise InputTypeError("estimate_axis_lean compares the detector's halves of rows: rows cannot be given")
    if not isinstance(geom, VectorGeometry):
        raise InputTypeError(f"geom must be a pdvc.VectorGeometry, got {type(geom).__name__}")
    nr, nc = geom.det_shape
    if nr < 8:
        raise InitError(f"an axis's lean needs at least 8 detector rows, got {nr}")
    pu = float(np.mean(np.linalg.norm(geom.u, axis=1)))
    pv = float(np.mean(np.linalg.norm(geom.v, axis=1)))
    theta = _scan_angles(geom)
    offset, angle, view = 0.0, 0.0, projections
    for k in range(LEAN_ROUNDS + 1):
        # the rows a turn by the lean so far brings in from beyond the detector's top and bottom are left out
        trim = min(int(np.ceil(abs(np.tan(angle)) * (pu / pv) * nc / 2.0)) + 1 if k else 0, nr // 4)
        e_top, e_bot, dr = _halves(view, geom, trim, kwargs)
        slope = (e_bot.offset_px - e_top.offset_px) / dr  # what the views as read (turned so far) still lean
        # the halves are symmetric about the centre row: their mean is the offset there (the views are turned about
        # that row, so the offsets they give are the detector's)
        offset = 0.5 * (e_top.offset_px + e_bot.offset_px)
        angle += float(np.arctan(slope * pu / pv))
        if k < LEAN_ROUNDS:
            view = _Upright(projections, geom, offset, angle)
    slope_sd = float(np.hypot(_offset_se(e_top, theta), _offset_se(e_bot, theta)) / dr)
    # the roll of tilt_poses, a rotation about the ray toward the detector's centre (geom.ray in parallel beam, the
    # source to the detector in cone beam): its sign on the detector follows the handedness of (u, v, that ray)
    ray = geom.ray if geom.kind == "parallel" else geom.det_center - geom.src
    hand = 1.0 if float(np.mean(np.einsum("ij,ij->i", np.cross(geom.u, geom.v), ray))) >= 0 else -1.0
    roll = hand * angle
    roll_sd = float(slope_sd * pu / pv)
    log.info("axis line from the offsets of the detector's top and bottom halves, the views turned upright %d times: "
             "offset %+.3f px at the centre row, leaning %+.3f ± %.3f deg on the detector (roll %+.3f deg)", LEAN_ROUNDS,
             offset, np.degrees(angle), np.degrees(roll_sd), np.degrees(roll))
    return AxisLeanEstimate(offset_px=float(offset), slope=float(np.tan(angle) * pv / pu), roll=roll, roll_sd=roll_sd,
                            top=e_top, bottom=e_bot)


#: estimate_detector_pattern: at most this many pairs of opposite views (evenly chosen) take part; a pattern is found
#: where it accounts for at least ``PATTERN_MIN_SHARE`` of the opposite views' mean squared difference and its
#: reduction of it stands ``MIRROR_MIN_T`` standard errors above zero (the 24 clean tuning scans of ``bench_accuracy.py
#: --quick --roi 1.0 --parallel``: at most 0.49 %; under issue #10's flat field 4-99 %, all found; docs/method.md §5.44)
PATTERN_MAX_PAIRS = 64
PATTERN_MIN_SHARE = 0.01
#: a 180-degree scan pairs only views up to 2.5 steps from opposite (three pairs without its end point, six with it,
#: too few for a standard error): there the pattern is found where it accounts for this share at least (the 12 tuning
#: half turns of ``--quick --roi 1.0 --half-turn``: at most 0.53 % clean, 7.8-51 % under issue #10's flat field,
#: docs/method.md §5.44; with ``--end-point``, at most 1.9 % clean, 6.3-84 % under the flat field, §5.45)
PATTERN_MIN_SHARE_NEAR = 0.03
#: the axis fitted with the line cannot be told from the line (a rod's dome shifted is nearly a line across the field)
#: where it is not held within a pixel by ``MIRROR_MIN_T`` standard errors and lies this many pixels or more from the
#: offset without the line: on the cone-beam short scans of ``bench_accuracy.py --quick --short-scan --roi 1.0``, five
#: rods and a granular scan at i0 = 2e3 put it 4.5-15.6 px away (held 0.3-1.6 standard errors within a pixel), where
#: issue #10's flat field pulls the offset without the line 1.8-2.3 px on the tuning rods (short scans and half turns,
#: docs/method.md §5.46)
PATTERN_CONFOUNDED_PX = 4.0
#: where no pattern is found but the offsets with and without the line (the first not held within a pixel) lie this
#: many pixels apart or more, the axis is not decided either: issue #10's flat field pulls the offset without the line
#: 1.8-2.3 px on the tuning rods (short scans and half turns), while without a pattern the two lie at most 0.52 px
#: apart on the tuning scans where the line does not run away (docs/method.md §5.46)
PATTERN_UNDECIDED_PX = 1.0


@dataclass(frozen=True)
class DetectorPatternEstimate:
    """A pattern fixed on the detector that opposite views see mirrored, fitted with the axis offset
    (:func:`estimate_detector_pattern`).

    Attributes
    ----------
    offset_px : float, pixels
        The axis offset (as :attr:`AxisOffsetEstimate.offset_px`) fitted with the pattern.
    slope : float, line integral per column
        The pattern's tilt across the columns, its part antisymmetric about the axis: what :meth:`pattern` holds.
    plain_offset_px : float, pixels
        The axis offset the same comparison gives without the pattern.
    share : float
        The fraction of the opposite views' mean squared difference (at their best offsets) the pattern accounts for.
    t : float
        That reduction, pair by pair (pair and band of rows on a 180° scan), over its standard error.
    n_pairs : int
    mismatch_slope : float, pixels per radian
        A 180° scan: the pairs' offsets' change with their mismatch, taken out of each pair's shift (as
        :attr:`AxisOffsetEstimate.mismatch_slope`); 0 where the pairs are opposite.
    near : bool
        The pairs are views near opposite (a 180° scan), not opposite.
    offset_t : float
        How firmly the fit with the line holds its offset: its mean squared difference at the offset one pixel either
        side, less at the offset, over its standard error (the smaller side).
    """

    offset_px: float
    slope: float
    plain_offset_px: float
    share: float
    t: float
    n_pairs: int
    mismatch_slope: float = 0.0
    near: bool = False
    offset_t: float = np.inf

    @property
    def confounded(self) -> bool:
        """The axis cannot be told from the pattern: the offset fitted with the line is not held within a pixel by
        ``MIRROR_MIN_T`` standard errors and lies ``PATTERN_CONFOUNDED_PX`` or more from the offset without it (a rod
        much wider than the field, its views nearly a dome, at low dose). Where nothing else measures the pattern (air,
        a full turn's mean), the offset without the line is then not confirmed either: it is where the pattern, if
        there is one, looks symmetric."""
        return self.offset_t < MIRROR_MIN_T and abs(self.offset_px - self.plain_offset_px) >= PATTERN_CONFOUNDED_PX

    @property
    def undecided(self) -> bool:
        """Whether the axis depends on a pattern that the opposite views cannot decide on: no pattern :attr:`found`
        (a :attr:`confounded` one never is) while the offset with the line, not held within a pixel by ``MIRROR_MIN_T``
        standard errors, lies ``PATTERN_UNDECIDED_PX`` or more from the offset without it."""
        return (not self.found and self.offset_t < MIRROR_MIN_T
                and abs(self.offset_px - self.plain_offset_px) >= PATTERN_UNDECIDED_PX)

    @property
    def found(self) -> bool:
        """The pattern accounts for ``PATTERN_MIN_SHARE`` of the difference at least, by ``MIRROR_MIN_T`` standard
        errors; for pairs of views near opposite (a 180° scan) ``PATTERN_MIN_SHARE_NEAR``; never where it is
        :attr:`confounded` with the axis."""
        if self.confounded:
            return False
        if self.near:
            return self.share >= PATTERN_MIN_SHARE_NEAR
        return self.share >= PATTERN_MIN_SHARE and self.t > MIRROR_MIN_T

    def describe(self) -> str:
        """The estimate in words (the log, ``pdvc inspect`` and the report)."""
        text = (f"a tilt of {self.slope:+.3g} per column antisymmetric about the axis, {100 * self.share:.1f}% of the "
                f"opposite views' mean squared difference ({self.t:.1f} standard errors), axis offset "
                f"{self.offset_px:+.2f} px with it, {self.plain_offset_px:+.2f} px without")
        if self.undecided:
            text += (f"; the axis with it not held within a pixel ({self.offset_t:.1f} standard errors): the axis "
                     f"cannot be told from such a pattern")
        return text

    def pattern(self, det_shape) -> np.ndarray:
        """The pattern on a detector of ``det_shape`` (rows, columns), float32: ``slope`` times the column's distance
        from the axis's column; subtracted from every view, each view and its opposite agree about the axis."""
        n_rows, n_cols = (int(x) for x in det_shape)
        u = np.arange(n_cols, dtype=np.float64) - (0.5 * (n_cols - 1) + self.offset_px)
        return np.broadcast_to((self.slope * u).astype(np.float32), (n_rows, n_cols))


def _shared_lines(r: np.ndarray, delta: np.ndarray, slope: bool) -> tuple[np.ndarray, float]:
    """What the pairs' differences ``r`` (pairs, bands, columns) share, fitted by least squares: a level per band, a
    slope along the columns in proportion to each pair's mismatch ``delta`` (what the sample turned between its views,
    where the pairs are near opposite), and with ``slope`` one slope common to every pair. Returns the fit
    (broadcastable to ``r``) and the common slope (0 without ``slope``)."""
    x = np.arange(r.shape[-1], dtype=np.float64) - 0.5 * (r.shape[-1] - 1)
    fit = np.mean(r, axis=(0, 2), keepdims=True)
    z = np.sum(r * x, axis=(1, 2)) / (r.shape[1] * np.sum(x * x))  # each pair's slope, over its bands
    design = ([np.ones_like(z)] if slope else []) + ([delta] if np.any(delta) else [])
    if not design:
        return fit, 0.0
    coef = np.linalg.lstsq(np.stack(design, axis=1), z, rcond=None)[0]
    return fit + (np.stack(design, axis=1) @ coef)[:, None, None] * x, float(coef[0]) if slope else 0.0


def _common_shift(a: np.ndarray, b: np.ndarray, delta: np.ndarray, *, slope: bool, upsample: int, max_shift: float):
    """The one shift ``s`` (columns) with ``b_k(j) ≈ a_k(j + s)`` for every pair ``k`` of ``(pairs, bands, columns)``
    stacks, by their mean squared difference over the columns both hold (whole shifts, each over its own overlap of at
    least half the row; then a fixed window at ``1/upsample`` pixel and a parabola), less what the pairs' differences
    share (:func:`_shared_lines`; ``delta`` the pairs' mismatches).

    Returns ``(s, residual, common slope)``, the ``(pairs, bands, window)`` differences at ``s``; ``s`` is infinite
    where the best whole shift lies at the search limit."""
    from scipy import ndimage

    n = a.shape[2]
    best, s0 = np.inf, 0
    for s in range(-int(max_shift), int(max_shift) + 1):
        lo, hi = max(0, -s) + OVERLAP_EDGE, min(n, n - s) - OVERLAP_EDGE
        if hi - lo < 0.5 * n:
            continue
        r = b[:, :, lo:hi] - a[:, :, lo + s:hi + s]
        cost = float(np.sum((r - _shared_lines(r, delta, slope)[0]) ** 2)) / (hi - lo)
        if cost < best:
            best, s0 = cost, s
    grid = s0 + np.arange(-upsample, upsample + 1) / upsample
    lo, hi = _window(grid, n)
    if abs(s0) >= max_shift - 1.0 or hi - lo < 2:
        return np.copysign(np.inf, s0), None, 0.0

    def residual(s):
        r = b[:, :, lo:hi] - ndimage.shift(a, (0.0, 0.0, -s), order=3, mode="nearest")[:, :, lo:hi]
        fit, common = _shared_lines(r, delta, slope)
        return r - fit, common

    msd = np.array([np.mean(residual(s)[0] ** 2) for s in grid])
    j = int(np.argmin(msd))
    s = float(grid[j] + _vertex(-msd, j) / upsample)
    return (s, *residual(s))


def _offset_held(a: np.ndarray, b: np.ndarray, delta: np.ndarray, s: float, samples) -> float:
    """How firmly :func:`_common_shift` with the common slope holds its shift ``s``: the mean squared difference (less
    the shared lines) at ``s`` and two columns (a pixel of offset) either side, over one window, each sample's
    increase over its standard error; the smaller side. ``samples`` makes the samples of a ``(pairs, bands, window)``
    residual."""
    from scipy import ndimage

    lo, hi = _window(np.array([s - 2.0, s + 2.0]), a.shape[2])
    if hi - lo < 2:
        return 0.0

    def q(x):
        r = b[:, :, lo:hi] - ndimage.shift(a, (0.0, 0.0, -x), order=3, mode="nearest")[:, :, lo:hi]
        return samples(r - _shared_lines(r, delta, True)[0])

    at = q(s)
    return min(_t(q(s - 2.0) - at), _t(q(s + 2.0) - at))


def estimate_detector_pattern(projections, geom: VectorGeometry, *, rows=None, upsample: int = 10,
                              max_offset: float | None = None, mismatch_slope: float | None = None) -> DetectorPatternEstimate:
    """A pattern fixed on the detector (a flat field tilted across the columns) and the axis offset, fitted together to
    each view and its mirrored opposite.

    What the detector adds to every view alike, ``f(j)`` at column ``j``, a view and its opposite see mirrored about
    the axis's column ``c``: the difference of a pair holds ``f(2c - j) - f(j)``, the same for every pair. A
    region-of-interest scan has no air to measure ``f``, and a comparison of opposite views finds the offset where
    ``f`` looks symmetric (issue #10's flat field, 8 % across the columns: 2 px off on rods wider than the field, 9 px
    on granular samples). Here the offset is fitted with a straight line along the columns common to every pair (one
    slope; a level per band of rows as a nuisance), so that the pattern's part antisymmetric about the axis, ``slope ·
    (j - c)``, comes out with the offset; the part symmetric about the axis is consistent data (a reconstruction
    explains it) and is left. The offset with the line is weaker where a view's profile is itself nearly a line
    across the field (a rod much wider than the field: a shift of its dome is such a line): there the two trade
    against each other, and the views less their mean (:func:`compare_offsets` on them, as the pipeline's check
    does) tell the offset without the pattern.

    Pairs of views within half an angular step of 180° (a full turn; at most ``PATTERN_MAX_PAIRS``), their rows in
    at most ``OVERLAP_BANDS`` bands smoothed along the columns as :func:`estimate_axis_offset` with ``overlap=True``
    smooths them (all rows in parallel beam, the central quarter in cone beam, ``rows`` to choose). A 180° scan
    has no such pair, or one with its end point: there the views up to 2.5 steps from opposite are paired, as
    :func:`estimate_axis_offset` pairs them, each pair's first view shifted by what the sample turned between them
    (``mismatch_slope`` times the pair's mismatch; by default :func:`estimate_axis_offset`'s with ``overlap=True``:
    the pattern is the same in every pair and does not change that slope).

    Raises
    ------
    InitError
        Fewer than two pairs of views (near) opposite, or the best offset at the search limit (``max_offset``,
        default a quarter of the columns).
    """
    if not isinstance(geom, VectorGeometry):
        raise InputTypeError(f"geom must be a pdvc.VectorGeometry, got {type(geom).__name__}")
    shape = np.shape(projections)
    if shape != (geom.n_views, *geom.det_shape):
        raise ShapeError(f"projections must have shape {(geom.n_views, *geom.det_shape)} (n_views, n_rows, n_cols) "
                         f"like geom, got {shape}")
    n = geom.det_shape[1]
    lim = n / 4 if max_offset is None else float(max_offset)
    if not (np.isfinite(lim) and lim > 0):
        raise InitError(f"max_offset must be a positive number of pixels, got {max_offset!r}")
    from scipy import ndimage

    pairs, delta, _ = _pairs(_scan_angles(geom))
    if pairs.shape[0] < 2:
        raise InitError("estimate_detector_pattern needs two pairs of opposite views or more (each view with one within "
                        f"half an angular step of 180 degrees, or 2.5 steps without one), got {pairs.shape[0]}")
    keep = np.unique(np.linspace(0, pairs.shape[0] - 1, min(PATTERN_MAX_PAIRS, pairs.shape[0])).round().astype(int))
    pairs, delta = pairs[keep], (np.zeros(keep.size) if delta is None else delta[keep])
    slope_m, near = 0.0, bool(np.any(delta))
    if near:
        # the line through the pairs' own offsets: a pattern shifts them all alike (and may weaken their correlation
        # below what an offset estimate accepts), not the line's slope
        slope_m = float(mismatch_slope if mismatch_slope is not None else estimate_axis_offset(
            projections, geom, rows=rows, overlap=True, min_correlation=-1.0, max_spread=np.inf).mismatch_slope)
    row_idx = _rows(rows, geom)
    stacks = [[_smoothed(_bands(x)) for x in _mirrored(projections, i, j, row_idx)] for i, j in pairs]
    a = np.array([ndimage.shift(s[0], (0.0, -2.0 * slope_m * d), order=3, mode="nearest") if d else s[0]
                  for s, d in zip(stacks, delta)])
    b = np.array([s[1] for s in stacks])
    (s0, r0, _), (s1, r1, common) = (_common_shift(a, b, delta, slope=f, upsample=int(upsample), max_shift=2 * lim + 1)
                                      for f in (False, True))
    if not (np.isfinite(s0) and np.isfinite(s1)):
        raise InitError(f"no estimate: the best whole shift of the opposite views lies at the search limit |offset| = "
                        f"{lim:g} px (raise max_offset, or the opposite views do not overlap)")
    # the samples of the paired reduction: the pairs, or where there are only a few near opposite, pairs and bands
    def samples(r):
        return np.mean(r ** 2, axis=2).ravel() if near else np.mean(r ** 2, axis=(1, 2))

    plain, fitted = samples(r0), samples(r1)
    slope = -0.5 * common  # the difference holds f(2c - j) - f(j): minus twice the antisymmetric part
    share = float(1.0 - np.mean(fitted) / np.mean(plain)) if np.mean(plain) > 0 else 0.0
    est = DetectorPatternEstimate(offset_px=0.5 * s1, slope=slope, plain_offset_px=0.5 * s0, share=share,
                                  t=_t(plain - fitted), n_pairs=int(pairs.shape[0]), mismatch_slope=slope_m, near=near,
                                  offset_t=_offset_held(a, b, delta, s1, samples))
    log.info("detector pattern from %d pairs of opposite views: tilt %+.3g per column antisymmetric about the axis, "
             "%.1f%% of their mean squared difference (%.1f standard errors); axis offset %+.3f px with it (held within "
             "a pixel by %.1f standard errors), %+.3f px without", est.n_pairs, slope, 100 * share, est.t,
             est.offset_px, est.offset_t, est.plain_offset_px)
    return est


def offset_poses(geom: VectorGeometry, offset_px: float) -> Poses:
    """Per-view sample-frame poses that move the nominal axis by ``offset_px`` columns.

    The sample is translated, at every view, along the lab ``x`` (the
    view's detector ``u``) by ``offset_px · |u_k| / M_k`` (``M_k`` the
    magnification of the nominal axis, 1 in parallel beam), a constant lab
    translation for a circular scan. Then
    ``geom.apply_poses(rotvecs, translations)`` projects every point of the
    nominal axis (x = y = 0 of the volume frame) exactly ``offset_px``
    columns further than ``geom`` does, at its row; the result is a
    starting point for the engine, e.g. from
    :func:`estimate_axis_offset`.

    Parameters
    ----------
    geom : VectorGeometry
        Nominal geometry.
    offset_px : float, pixels
        Signed, positive toward larger column indices.

    Returns
    -------
    Poses
        Zero rotations; translations in length units, sample xyz (unpacks
        as ``rotvecs, translations``).
    """
    if not isinstance(geom, VectorGeometry):
        raise InputTypeError(f"geom must be a pdvc.VectorGeometry, got {type(geom).__name__}")
    off = float(offset_px) if np.ndim(offset_px) == 0 else np.nan
    if not np.isfinite(off):
        raise InitError(f"offset_px must be a finite number of pixels, got {offset_px!r}")
    u = geom.u
    pitch = np.linalg.norm(u, axis=1)
    length = off * pitch / _magnification(geom)
    translations = (length / pitch)[:, None] * u
    return Poses(np.zeros((geom.n_views, 3)), translations)
