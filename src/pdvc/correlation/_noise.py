"""Noise variance γ² of the projections, so that χ ≈ 1 when only noise is left.

Two estimates (``DESIGN.md`` §2, paper eq. 1):

* :func:`estimate_noise_variance` from the projections themselves
  (Immerkær's estimator): no knowledge of the detector needed;
* :func:`poisson_variance` from counting statistics, per pixel, when the
  open-beam counts (and the number of averaged flat frames) are known.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_erosion, convolve

from ..errors import InputTypeError, PdvcError, ShapeError

__all__ = ["NoiseEstimateError", "estimate_noise_variance", "poisson_variance", "IMMERKAER_KERNEL"]

#: Immerkær's 3x3 mask: the outer product of two second differences
#: ``[1, -2, 1]``; it annihilates ``x^a y^b`` unless both a, b >= 2.
IMMERKAER_KERNEL = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])
IMMERKAER_KERNEL.setflags(write=False)

#: Views examined by default (evenly spaced): the median of this many per-view
#: estimates is already within ~1 % of the all-view one on a stationary scan.
_DEFAULT_MAX_VIEWS = 32


class NoiseEstimateError(PdvcError, ValueError):
    """The noise variance cannot be estimated from the data given."""


def _as_stack(projections) -> np.ndarray:
    try:
        arr = np.asarray(projections)
    except (TypeError, ValueError):
        raise InputTypeError(f"projections must be an array of numbers, got {type(projections).__name__}") from None
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise ShapeError(f"projections must have shape (n_views, n_rows, n_cols) or (n_rows, n_cols), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise InputTypeError(f"projections must be real numbers, got dtype {arr.dtype}")
    if arr.shape[1] < 3 or arr.shape[2] < 3:
        if arr.shape[2] < 3:
            raise ShapeError(f"projections must have at least 3 columns per view, got {arr.shape[1:]}")
    return arr


def _select_views(n: int, views) -> np.ndarray:
    if views is None:
        return np.unique(np.linspace(0, n - 1, min(n, _DEFAULT_MAX_VIEWS)).round().astype(np.intp))
    if isinstance(views, slice):
        idx = np.arange(n)[views]
    else:
        idx = np.atleast_1d(np.asarray(views))
        if idx.dtype == bool:
            if idx.shape != (n,):
                raise ShapeError(f"views as a boolean mask must have shape ({n},), got {idx.shape}")
            idx = np.nonzero(idx)[0]
        elif idx.size == 0:
            idx = idx.astype(np.intp)
        elif idx.ndim != 1 or idx.dtype.kind not in "iu":
            raise InputTypeError(f"views must be None, a slice, a boolean mask or view indices (ints), got {views!r}")
        if np.any(idx < -n) or np.any(idx >= n):
            raise ShapeError(f"views must be indices in [0, {n}), got {idx.tolist()[:10]}")
    if idx.size == 0:
        raise NoiseEstimateError(f"views selects no view, got {views!r}")
    return idx


def estimate_noise_variance(projections, *, views=None, mask=None) -> float:
    """Variance γ² of white noise in the projections, by Immerkær's estimator.

    Each selected view ``I`` (``W x H`` pixels) is convolved with the mask
    ``N = [[1, -2, 1], [-2, 4, -2], [1, -2, 1]]`` and its noise standard
    deviation estimated as

        σ = sqrt(π/2) / (6 (W - 2)(H - 2)) · Σ |I * N|

    over the ``(W-2)(H-2)`` pixels whose 3x3 neighbourhood is inside the
    image (J. Immerkær, "Fast noise variance estimation", Computer Vision
    and Image Understanding 64(2):300-302, 1996). The result is the square
    of the median of the per-view σ.

    Why it works: ``N`` is the product of second differences along rows and
    columns, so it cancels every signal that is locally linear along either
    axis (planes, ramps, edges parallel to the pixel grid, smooth
    projections); on white Gaussian noise of variance σ², ``I * N`` is
    Gaussian with variance ``Σ N² σ² = 36 σ²``, whose mean absolute value is
    ``6 σ sqrt(2/π)``, hence the factor. The median over views discards
    views spoiled by a defect.

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) or (n_rows, n_cols) array
        Line integrals (dimensionless); not modified.
    views : None, slice, int indices or boolean mask
        Views to examine. Default: at most 32 views evenly spread over the
        scan (the estimate of one view already averages ~``n_rows·n_cols``
        pixels; more views only make the median robust).
    mask : (n_rows, n_cols) array, optional
        Pixels to use (non-zero = use), e.g. the ROI. A pixel contributes
        when its whole 3x3 neighbourhood lies in the mask.

    Returns
    -------
    float
        γ², in (line-integral units)², the variance per pixel.

    Notes
    -----
    * It is a fast, robust figure, not an exact one: sharp features that
      are curved or oblique at the pixel scale (the edge of the sample's
      shadow, small pores) leak into ``I * N`` and bias σ upward by a few
      per cent on typical projections; mask them out if that matters.
    * Signal-dependent noise (Poisson) gives roughly the square of the
      *mean* σ over the pixels, slightly below the mean variance;
      :func:`poisson_variance` gives the per-pixel variance when the counts
      are known.
    * Correlated noise (e.g. after coarse graining, or detector blur) is
      underestimated: estimate γ² on the raw projections and scale it (see
      :func:`pdvc.correlation._scales.coarse_noise_factor`).
    """
    arr = _as_stack(projections)
    n, nr, nc = arr.shape
    idx = _select_views(n, views)
    if nr < 3:
        return _row_estimate(arr, idx, mask)
    if mask is None:
        valid = np.zeros((nr, nc), bool)
        valid[1:-1, 1:-1] = True
    else:
        m = np.asarray(mask)
        if m.shape != (nr, nc):
            raise ShapeError(f"mask must have shape {(nr, nc)} (n_rows, n_cols), got {m.shape}")
        valid = binary_erosion(m != 0, structure=np.ones((3, 3), bool), border_value=0)
    n_valid = int(np.count_nonzero(valid))
    if n_valid == 0:
        raise NoiseEstimateError("mask leaves no pixel with its whole 3x3 neighbourhood inside it")
    sigmas = np.empty(idx.size)
    for i, k in enumerate(idx):
        view = np.asarray(arr[k], dtype=np.float64)
        conv = convolve(view, IMMERKAER_KERNEL, mode="nearest")
        vals = np.abs(conv[valid])
        if not np.all(np.isfinite(vals)):
            raise NoiseEstimateError(f"projections hold NaN or Inf in view {int(k)}; mask those pixels out")
        sigmas[i] = np.sqrt(np.pi / 2) / 6.0 * vals.mean()
    return float(np.median(sigmas) ** 2)


def _row_estimate(arr, idx, mask) -> float:
    """Immerkær's idea in 1-D, for detectors of one or two rows (sinograms).

    The second difference ``[1, -2, 1]`` along each row cancels locally
    linear signal; on white noise it has variance ``6 σ²`` and mean absolute
    value ``σ sqrt(12/π)``, hence ``σ = sqrt(π/12) · mean |Δ²I|``.
    """
    nr, nc = arr.shape[1:]
    valid = np.ones((nr, nc - 2), bool)
    if mask is not None:
        m = np.asarray(mask) != 0
        if m.shape != (nr, nc):
            raise ShapeError(f"mask must have shape {(nr, nc)} (n_rows, n_cols), got {m.shape}")
        valid = m[:, :-2] & m[:, 1:-1] & m[:, 2:]
    if not valid.any():
        raise NoiseEstimateError("mask leaves no pixel with both row neighbours inside it")
    sigmas = np.empty(idx.size)
    for i, k in enumerate(idx):
        view = np.asarray(arr[k], dtype=np.float64)
        d2 = np.abs(view[:, :-2] - 2 * view[:, 1:-1] + view[:, 2:])[valid]
        if not np.all(np.isfinite(d2)):
            raise NoiseEstimateError(f"projections hold NaN or Inf in view {int(k)}; mask those pixels out")
        sigmas[i] = np.sqrt(np.pi / 12.0) * d2.mean()
    return float(np.median(sigmas) ** 2)


def poisson_variance(line_integrals, *, i0, n_flats=None, dark_noise: float = 0.0) -> np.ndarray:
    """Per-pixel variance of ``p = -log(I / I0)`` for photon-counting noise.

    By the delta method (first order in 1/counts), with ``N = i0 e^{-p}``
    the expected counts of the pixel:

        Var p ≈ (N + σ_d²) / N²  +  (i0 + σ_d²) / (n_flats · i0²)

    The first term is the projection's Poisson (and read) noise,
    ``e^{p} / i0`` without read noise; the second the noise of the flat
    field averaged over ``n_flats`` frames, ``1 / (n_flats · i0)`` without
    read noise (omitted when ``n_flats`` is None: a noise-free flat). This
    is the model of :func:`pdvc.simulate.simulate_scan`.

    Parameters
    ----------
    line_integrals : array, dimensionless
        Clean or measured line integrals ``p`` (any shape; the measured
        ones give a noisy but unbiased-to-first-order estimate). Not
        modified.
    i0 : float or array broadcastable to ``line_integrals``, counts
        Open-beam counts per pixel and frame (flat minus dark), > 0;
        per-pixel arrays, e.g. ``(n_rows, n_cols)``, are welcome.
    n_flats : int, optional
        Number of flat frames averaged in the normalisation.
    dark_noise : float, counts
        Standard deviation σ_d of the read (dark) noise per frame, >= 0.

    Returns
    -------
    float32 array, the broadcast shape
        Variance of each pixel, (line-integral units)². Use its mean over
        the ROI as γ², or its inverse as pixel weights.

    Notes
    -----
    Valid while counts are well above ~10 per pixel (higher orders of the
    delta method are ``O(1/N²)``); below that ``-log`` of a count is
    strongly biased and clipped anyway.
    """
    try:
        p = np.asarray(line_integrals, dtype=np.float64)
        i0a = np.asarray(i0, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputTypeError("line_integrals and i0 must be arrays of numbers") from None
    if not np.all(np.isfinite(p)):
        raise ShapeError("line_integrals must be finite")
    if not np.all(np.isfinite(i0a)) or np.any(i0a <= 0):
        got = f"got {i0!r}" if i0a.ndim == 0 else f"got min {np.nanmin(i0a)!r} in an array of shape {i0a.shape}"
        raise ShapeError(f"i0 must be positive, finite counts, {got}")
    try:
        np.broadcast_shapes(p.shape, i0a.shape)
    except ValueError:
        raise ShapeError(
            f"i0 of shape {i0a.shape} does not broadcast against line_integrals of shape {p.shape}"
        ) from None
    if not (np.isfinite(dark_noise) and dark_noise >= 0):
        raise ShapeError(f"dark_noise must be a non-negative number of counts, got {dark_noise!r}")
    s2 = float(dark_noise) ** 2
    n = i0a * np.exp(-p)
    var = (n + s2) / n**2
    if n_flats is not None:
        if not isinstance(n_flats, (int, np.integer)) or isinstance(n_flats, bool) or n_flats < 1:
            raise ShapeError(f"n_flats must be a positive int (frames averaged), got {n_flats!r}")
        var = var + (i0a + s2) / (int(n_flats) * i0a**2)
    return var.astype(np.float32)
