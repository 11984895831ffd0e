"""Iterative reconstruction on the projector pair (forward, exact adjoint)."""

from __future__ import annotations

import logging
from typing import Callable, Optional

import numba
import numpy as np

from ..errors import PdvcError, ShapeError
from ..geometry import VectorGeometry, VolumeGeometry
from ..projectors import backproject, forward
from ._fbp import analytic

logger = logging.getLogger(__name__)

__all__ = ["cgls", "nonneg_ls", "nonneg_ls_lipschitz"]

# FISTA's step is 1 / (STEP_MARGIN L), L from nonneg_ls_lipschitz (3 power iterations from ones, within 0.3 % of the
# top eigenvalue, from below). 1.15 keeps the step the calibration's defaults were tuned with, when L came from 8
# iterations from a random vector (4.5 % short) and the margin was 1.2: 1 / (1.2 x 26325) against 1 / (1.15 x 27495)
# on the 180-degree stand-in's scale-2 grid (docs/method.md §5.16)
STEP_MARGIN = 1.15
# ... and L is measured on every k-th view, k the largest that keeps LIPSCHITZ_VIEWS views or more, times the views'
# number over the sample's: each view adds nearly the same to the quadratic form of the smooth top eigenvector, so
# the sample's is the full one's within 0.1 % (the 180-degree stand-in's 91 views, a cone full turn of 150 or 180)
# at a fraction of its cost (3 power iterations of all views: 7.4 s of the stand-in's 48 s calibration)
LIPSCHITZ_VIEWS = 30
# nonneg_ls(precondition=True): Πᵀ Π of rays normal to the rotation axis is a convolution by 1/r in each plane normal to
# it, whose inverse is the ramp |k|; the preconditioner is that ramp, plus RAMP_FLOOR (cycles per voxel) so that it stays
# positive definite at k = 0 (docs/method.md §5.20)
RAMP_FLOOR = 0.005


def cgls(
    projections,
    vol_geom: VolumeGeometry,
    geom: VectorGeometry,
    *,
    n_iter: int = 10,
    x0=None,
    backend: str = "auto",
    callback: Optional[Callable[[int, float], None]] = None,
) -> np.ndarray:
    """Least-squares reconstruction ``min_f |Π f − p|²`` by conjugate gradients (CGLS).

    Each iteration is one forward projection and one exact back-projection
    (:func:`pdvc.forward`, :func:`pdvc.backproject`), so the volume is the
    one most consistent with the data under the very model the P-DVC engine
    uses — whatever the orbit (non-planar, non-closed, irregular).

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) array
        Line integrals; not modified.
    vol_geom : VolumeGeometry
    geom : VectorGeometry
    n_iter : int
        Iterations (early stopping is the regularisation: 5–20 is typical
        from an FDK start).
    x0 : (nz, ny, nx) array, optional
        Start (e.g. an FDK volume); default zero.
    callback : callable, optional
        ``callback(iteration, residual_norm)`` after each iteration.

    Returns
    -------
    (nz, ny, nx) float32
    """
    if not (isinstance(n_iter, (int, np.integer)) and n_iter >= 0):
        raise PdvcError(f"n_iter must be a non-negative int, got {n_iter!r}")
    b = np.asarray(projections, np.float32)
    if b.shape != (geom.n_views,) + tuple(geom.det_shape):
        raise ShapeError(f"projections must have shape {(geom.n_views,) + tuple(geom.det_shape)}, got {b.shape}")
    x = np.zeros(vol_geom.shape, np.float32) if x0 is None else np.array(x0, np.float32, copy=True)
    if x.shape != tuple(vol_geom.shape):
        raise ShapeError(f"x0 must have the grid's shape {tuple(vol_geom.shape)}, got {x.shape}")
    r = b - forward(x, vol_geom, geom, backend=backend) if x0 is not None else b.copy()
    s = backproject(r, vol_geom, geom, backend=backend)
    p = s.copy()
    gamma = float(np.vdot(s, s))
    for it in range(int(n_iter)):
        if gamma == 0.0:
            break
        q = forward(p, vol_geom, geom, backend=backend)
        qq = float(np.vdot(q, q))
        if qq == 0.0:
            break
        alpha = gamma / qq
        x += np.float32(alpha) * p
        r -= np.float32(alpha) * q
        s = backproject(r, vol_geom, geom, backend=backend)
        gamma_new = float(np.vdot(s, s))
        p *= np.float32(gamma_new / gamma)
        p += s
        gamma = gamma_new
        rn = float(np.linalg.norm(r))
        logger.debug("cgls %d: |r| = %.6g", it + 1, rn)
        if callback is not None:
            callback(it + 1, rn)
    return x


# ----------------------------------------------------------------------------
# non-negative least squares on a cubic B-spline grid
# ----------------------------------------------------------------------------
def _bspline3(d: np.ndarray) -> np.ndarray:
    d = np.abs(d)
    return np.where(d < 1, (4 - 6 * d**2 + 3 * d**3) / 6, np.where(d < 2, (2 - d) ** 3 / 6, 0.0))


def spline_upsampling_matrix(n: int, factor: int) -> np.ndarray:
    """Samples, on a grid ``factor`` x finer, of the cubic B-splines centred on ``n`` coarse voxels.

    Both grids cover the same interval (voxel edges to voxel edges), as the
    outer loop's refined correlation grid does: fine voxel ``j`` sits at
    coarse index ``(j - (factor n - 1)/2) / factor + (n - 1)/2``. Coefficients
    beyond the grid are zero. Returns ``(factor n, n)`` float32; ``factor=1``
    is the identity (the voxels themselves are the unknowns).
    """
    if factor == 1:
        return np.eye(n, dtype=np.float32)
    j = np.arange(factor * n)
    xc = (j - (factor * n - 1) / 2) / factor + (n - 1) / 2
    return _bspline3(xc[:, None] - np.arange(n)[None, :]).astype(np.float32)


def _banded(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A matrix of few non-zeros per row as (first column, weights): ``M[j, s_j + k] = W[j, k]``.

    Every row keeps the same number ``K`` of columns (the widest row's
    span; zero-padded, shifted left at the end so that ``s_j + K <= n``).
    """
    M = np.asarray(M, np.float32)
    m, n = M.shape
    nz = M != 0
    first = np.where(nz.any(axis=1), nz.argmax(axis=1), 0)
    last = np.where(nz.any(axis=1), n - 1 - nz[:, ::-1].argmax(axis=1), 0)
    K = int(max(1, (last - first).max() + 1))
    start = np.minimum(first, n - K).astype(np.int64)
    W = np.stack([M[np.arange(m), start + k] for k in range(K)], axis=1).astype(np.float32)
    return start, np.ascontiguousarray(W)


@numba.njit(parallel=True, cache=True)
def _banded0(x, start, W, out):  # pragma: no cover - compiled
    for j in numba.prange(out.shape[0]):
        out[j] = 0.0
        for k in range(W.shape[1]):
            w = W[j, k]
            if w != 0.0:
                xi = x[start[j] + k]
                for a in range(out.shape[1]):
                    for b in range(out.shape[2]):
                        out[j, a, b] += w * xi[a, b]


@numba.njit(parallel=True, cache=True)
def _banded1(x, start, W, out):  # pragma: no cover - compiled
    for a in numba.prange(out.shape[0]):
        for j in range(out.shape[1]):
            out[a, j] = 0.0
            for k in range(W.shape[1]):
                w = W[j, k]
                if w != 0.0:
                    i = start[j] + k
                    for b in range(out.shape[2]):
                        out[a, j, b] += w * x[a, i, b]


@numba.njit(parallel=True, cache=True)
def _banded2(x, start, W, out):  # pragma: no cover - compiled
    # k outside j: the loop over a row's outputs is the inner one (each output's sum still taken in the order of k,
    # so the result is the same to the bit); measured on 64 x 64 x 64 -> 128 along the last axis, 2 threads, AMD
    # EPYC: 1.35 -> 0.79 ms (k inside: a short reduction per output)
    for a in numba.prange(out.shape[0]):
        for b in range(out.shape[1]):
            row = out[a, b]
            xr = x[a, b]
            for j in range(row.shape[0]):
                row[j] = 0.0
            for k in range(W.shape[1]):
                for j in range(row.shape[0]):
                    row[j] += W[j, k] * xr[start[j] + k]


def _along(band: tuple[np.ndarray, np.ndarray], x: np.ndarray, axis: int) -> np.ndarray:
    """``M`` (given as :func:`_banded` of it) applied along ``axis`` of the 3-D ``x``, float32.

    One pass per axis in the volume's memory order, parallel over the outer
    axis; a dense ``tensordot`` with its two transposing copies took about a
    quarter of each :func:`nonneg_ls` iteration on a 268 x 320 x 320 grid.
    """
    start, W = band
    x = np.ascontiguousarray(x, np.float32)
    shape = list(x.shape)
    shape[axis] = start.shape[0]
    out = np.empty(shape, np.float32)
    (_banded0, _banded1, _banded2)[axis](x, start, W, out)
    return out


def nonneg_ls(
    projections,
    vol_geom: VolumeGeometry,
    geom: VectorGeometry,
    *,
    coarsen: int = 1,
    n_iter: int = 30,
    support=True,
    weights=None,
    lipschitz: Optional[float] = None,
    precondition: bool = False,
    subsets: int = 1,
    backend: str = "auto",
    callback: Optional[Callable[[int, float], None]] = None,
) -> np.ndarray:
    """Least squares ``min_c |W^½ (Π U c − p)|²`` with ``c >= 0`` on a support, by FISTA.

    The unknowns ``c`` are cubic B-spline coefficients on a grid ``coarsen``
    times coarser than ``vol_geom`` (same region); ``U`` samples the spline
    on ``vol_geom`` and ``Π`` is :func:`pdvc.forward` there. With
    ``coarsen=2`` the projector runs on half-size voxels (less interpolation
    bias) while the problem keeps as many unknowns as the coarse grid, i.e.
    stays overdetermined; the non-negativity of attenuation and a support
    around the sample are the other priors. Unlike FDK the result is the
    most consistent volume under the projector model for any orbit
    (non-planar, non-closed), which is what the outer loop of
    :func:`pdvc.calibration.self_calibrate` needs on precessing axes
    (``reconstruct="nonneg_ls"``).

    Algorithm: start from FDK (cone) or FBP (parallel) on the coarse grid,
    clipped to the constraints; projected gradient with Nesterov momentum
    (FISTA), step ``1 / (1.15 L)`` with ``L`` the largest eigenvalue of
    ``UᵀΠᵀΠU`` (:func:`nonneg_ls_lipschitz`: 3 power iterations, or
    ``lipschitz`` when the caller knows it), momentum reset when it points uphill
    (gradient restart of O'Donoghue & Candès). Each iteration is one
    forward projection and one exact back-projection on ``vol_geom``.
    With ``precondition`` the gradient is filtered by a ramp ``|k| +
    RAMP_FLOOR`` in the planes normal to the rotation axis (``z``), the
    inverse of ``ΠᵀΠ`` for rays normal to it: the fine detail, which plain
    gradient steps fit last, converges with the coarse (on the 180° stand-in
    of ``bench_calibrate.py`` 10 iterations fit the data as closely as 30
    without it; ``docs/method.md`` §5.20). ``L`` is then that of the
    filtered operator.

    With ``subsets`` = m > 1 (ordered subsets: Hudson & Larkin 1994; with
    momentum, Kim, Ramani & Fessler 2015) each iteration uses the views
    ``j, j + m, j + 2m, …`` of one subset only, j cycling, its gradient
    scaled by m: one forward and one back-projection of a m-th of the views.
    An early-stopped fit gets its coarse structure from the first iterations,
    which every interleaved subset sees as the whole scan does: on the 180°
    stand-in of ``bench_calibrate.py`` (91 parallel views, 30 iterations from
    FBP, the 2× grid of scale 1) the last iterate of 3 subsets is within
    0.01 % of the plain iteration's volume, in 42 % of the time. Each
    subset's iterate leans towards its own views, so the mean of the last m
    iterates (one per subset) is returned: within 0.11 % of the plain
    volume there, residual norm 20.50 against 20.42 (``docs/method.md``
    §5.24). ``n_iter`` counts the subset iterations.

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) array
        Line integrals; not modified.
    vol_geom : VolumeGeometry
        Grid of the returned volume; each of its dimensions must be a
        multiple of ``coarsen``.
    geom : VectorGeometry
    coarsen : int
        Coarse-grid factor of the spline coefficients; 1: the voxels of
        ``vol_geom`` themselves are the unknowns.
    n_iter : int
        FISTA iterations (early stopping also regularises).
    support : bool or (nz, ny, nx) bool array of the coarse grid
        True: the voxels where the (Gaussian-smoothed, σ = 1 voxel) start
        volume exceeds 10 % of its 99.5th percentile, dilated by 2 voxels;
        False: the whole grid.
    weights : (n_rows, n_cols) or (n_views, n_rows, n_cols) array in [0, 1], optional
        Detector weights ``W`` (e.g. 0 on the rays that leave the volume
        through a face the sample crosses, :func:`pdvc.calibration.truncation_weights`):
        rays of weight 0 do not pull the volume. Default: all 1.
    lipschitz : float, optional
        ``L`` as :func:`nonneg_ls_lipschitz` returns it for this grid,
        ``coarsen`` and (nearly) this geometry: a caller that reconstructs
        again and again while the poses move by fractions of a voxel (the
        calibration's rounds) passes the first estimate and saves its 3
        forward and 3 back-projections; the 1.15 margin of the step covers
        the change. Default: estimated here.
    precondition : bool
        Filter the gradient by the ramp of the planes normal to ``z`` (see
        above); ``lipschitz`` must then come from
        ``nonneg_ls_lipschitz(..., precondition=True)``.
    subsets : int
        Ordered subsets of the views, interleaved (1: every view at every
        iteration). At most ``n_views``.
    callback : callable, optional
        ``callback(iteration, residual_norm)`` after each iteration
        (residual at the extrapolated point; with ``subsets`` the subset's,
        times √m: an estimate of the whole residual's).

    Returns
    -------
    (nz, ny, nx) float32 on ``vol_geom``, non-negative.
    """
    from scipy import ndimage

    if not (isinstance(n_iter, (int, np.integer)) and not isinstance(n_iter, bool) and n_iter >= 0):
        raise PdvcError(f"n_iter must be a non-negative int, got {n_iter!r}")
    f = _coarsen_factor(coarsen, vol_geom)
    b = np.asarray(projections, np.float32)
    if b.shape != (geom.n_views,) + tuple(geom.det_shape):
        raise ShapeError(f"projections must have shape {(geom.n_views,) + tuple(geom.det_shape)}, got {b.shape}")
    w = None
    if weights is not None:
        w = np.asarray(weights, np.float32)
        if w.shape not in (b.shape, b.shape[1:]) or not np.all((w >= 0) & (w <= 1)):
            raise ShapeError(f"weights must have shape {b.shape[1:]} or {b.shape} with values in [0, 1], got {w.shape}")
    if lipschitz is not None and not (isinstance(lipschitz, (int, float, np.floating)) and lipschitz >= 0
                                      and np.isfinite(lipschitz)):
        raise PdvcError(f"lipschitz must be a finite float >= 0 (or None), got {lipschitz!r}")
    if not (isinstance(subsets, (int, np.integer)) and not isinstance(subsets, bool) and 1 <= subsets <= geom.n_views):
        raise PdvcError(f"subsets must be an int from 1 to the number of views ({geom.n_views}), got {subsets!r}")
    shape, vg_c, up, up_t = _spline_maps(vol_geom, f)
    A, AT = _spline_pair(vol_geom, geom, up, up_t, backend)
    M = _ramp_preconditioner(shape, vg_c.voxel_size) if precondition else None
    m = int(subsets)
    parts = [(A, AT, b, w)]
    if m > 1:  # interleaved subsets of the views, each with its projector pair on the same spline
        parts = []
        for j in range(m):
            views = np.arange(j, geom.n_views, m)
            parts.append((*_spline_pair(vol_geom, geom[views], up, up_t, backend), b[views],
                          None if w is None else (w[views] if w.ndim == 3 else w)))

    x0 = analytic(b, vg_c, geom)  # only the start: a short arc costs it its Parker weights, not the fit
    if support is True:
        sm = ndimage.gaussian_filter(x0, 1.0)
        mask = ndimage.binary_dilation(sm > 0.1 * np.percentile(sm, 99.5), iterations=2)
    elif support is False or support is None:
        mask = np.ones(shape, bool)
    else:
        mask = np.asarray(support, bool)
        if mask.shape != shape:
            raise ShapeError(f"support must have the coarse grid's shape {shape}, got {mask.shape}")

    def project(c):
        return np.where(mask, np.maximum(c, 0), 0).astype(np.float32)

    x = project(x0)
    if n_iter == 0:
        return up(x)
    lip = _sampled_lipschitz(vol_geom, geom, shape, up, up_t, M, backend) if lipschitz is None else float(lipschitz)
    if lip == 0.0:
        return up(x)
    step = np.float32(1.0 / (STEP_MARGIN * lip))
    y = x.copy()
    tk = 1.0
    n = int(n_iter)
    avg_from = n - min(m, n) if m > 1 else n  # ordered subsets: the mean of the last cycle's iterates is returned
    acc = None
    for it in range(n):
        Aj, ATj, bj, wj = parts[it % m]
        r = Aj(y) - bj
        if wj is not None:  # weights <= 1: the unweighted Lipschitz bound still holds
            r *= wj
        g = ATj(r)
        if m > 1:
            g *= np.float32(m)
        x_new = project(y - step * (g if M is None else M(g)))
        if float(np.vdot(y - x_new, x_new - x)) > 0:  # momentum uphill: restart
            tk = 1.0
        t_new = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * tk * tk))
        y = (x_new + np.float32((tk - 1.0) / t_new) * (x_new - x)).astype(np.float32)
        x, tk = x_new, t_new
        if it >= avg_from:
            if acc is None:
                acc = x.copy()
            else:
                acc += x
        rn = float(np.linalg.norm(r) * np.sqrt(m))
        logger.debug("nonneg_ls %d: |r| = %.6g", it + 1, rn)
        if callback is not None:
            callback(it + 1, rn)
    if acc is not None:  # each subset's iterate leans towards its own views; their mean towards none
        x = acc / np.float32(n - avg_from)
    return up(x)


def _coarsen_factor(coarsen, vol_geom: VolumeGeometry) -> int:
    if not (isinstance(coarsen, (int, np.integer)) and not isinstance(coarsen, bool) and coarsen >= 1):
        raise PdvcError(f"coarsen must be an int >= 1, got {coarsen!r}")
    f = int(coarsen)
    if any(n % f or n // f < 2 for n in vol_geom.shape):
        raise ShapeError(f"vol_geom.shape {tuple(vol_geom.shape)} must be multiples of coarsen={f} (at least 2x)")
    return f


def _spline_maps(vol_geom: VolumeGeometry, f: int):
    """(coarse shape, coarse grid, U, Uᵀ): the cubic B-spline on a grid ``f`` times coarser, sampled on ``vol_geom``."""
    shape = tuple(n // f for n in vol_geom.shape)
    vg_c = VolumeGeometry(shape, voxel_size=tuple(s * f for s in vol_geom.voxel_size), offset=vol_geom.offset)
    if f == 1:
        # the voxels themselves are the unknowns (spline_upsampling_matrix(n, 1) is the identity): no pass over the
        # volume (six per iteration, 4 % of the 180-degree stand-in's calibration)
        def same(c):
            return c

        return shape, vg_c, same, same
    mats = [spline_upsampling_matrix(n, f) for n in shape]
    bands = [_banded(M) for M in mats]
    bands_t = [_banded(M.T) for M in mats]

    def up(c):
        for ax, band in enumerate(bands):
            c = _along(band, c, ax)
        return c

    def up_t(x):
        for ax, band in enumerate(bands_t):
            x = _along(band, x, ax)
        return x

    return shape, vg_c, up, up_t


def _spline_pair(vol_geom: VolumeGeometry, geom: VectorGeometry, up, up_t, backend: str):
    """(Π U, Uᵀ Πᵀ) on ``geom`` for the spline maps of :func:`_spline_maps`."""

    def A(c):
        return forward(up(c), vol_geom, geom, backend=backend)

    def AT(r):
        return up_t(backproject(r, vol_geom, geom, backend=backend))

    return A, AT


def _ramp_preconditioner(shape, voxel_size) -> Callable[[np.ndarray], np.ndarray]:
    """``v -> M v``: the ramp ``|k| + RAMP_FLOOR`` (cycles per voxel) over the (y, x) planes of a ``(nz, ny, nx)`` grid.

    Symmetric and positive definite; zero-padded to twice the plane so that
    the filter does not wrap around.
    """
    from scipy import fft

    _, ny, nx = shape
    sy, sx = float(voxel_size[1]), float(voxel_size[2])
    h = 0.5 * (sy + sx)  # frequencies in cycles per mean in-plane voxel
    n2 = (fft.next_fast_len(2 * ny, real=True), fft.next_fast_len(2 * nx, real=True))
    ky = np.fft.fftfreq(n2[0], d=sy / h)[:, None]
    kx = np.fft.rfftfreq(n2[1], d=sx / h)[None, :]
    H = (np.hypot(ky, kx) + RAMP_FLOOR).astype(np.float32)

    def M(v):
        V = fft.rfft2(v, s=n2, axes=(1, 2), workers=-1)
        V *= H
        return np.ascontiguousarray(fft.irfft2(V, s=n2, axes=(1, 2), workers=-1)[:, :ny, :nx], dtype=np.float32)

    return M


def _power_iteration(shape, A, AT, M=None, n_iter: int = 3) -> float:
    """Largest eigenvalue of ``AᵀA`` (``M AᵀA``) from below, by power iterations from the constant vector.

    ``A`` (``Π U``) has non-negative entries, so its top eigenvector is
    non-negative (Perron–Frobenius) and smooth, close to a constant: three
    iterations from ones reach it within 0.3 % where eight from a random
    vector stopped 4.5 % short (an 80 x 80 x 67 grid, 91 parallel views).
    """
    v = np.full(shape, 1.0 / np.sqrt(float(np.prod(shape))), np.float32)
    lip = 0.0
    for _ in range(n_iter):
        v = AT(A(v))
        if M is not None:
            v = M(v)
        lip = float(np.linalg.norm(v))
        if lip == 0.0:
            break
        v /= np.float32(lip)
    return lip


def _lipschitz_views(n_views: int) -> np.ndarray:
    """Every k-th view, k the largest that keeps at least ``LIPSCHITZ_VIEWS`` of ``n_views`` (all of fewer)."""
    return np.arange(0, n_views, max(1, n_views // LIPSCHITZ_VIEWS))


def _sampled_lipschitz(vol_geom, geom, shape, up, up_t, M, backend) -> float:
    """The top eigenvalue of ``UᵀΠᵀΠU`` (``M UᵀΠᵀΠU``) over all views, from the views of :func:`_lipschitz_views`:
    theirs times the views' number over theirs (``LIPSCHITZ_VIEWS``)."""
    views = _lipschitz_views(geom.n_views)
    A, AT = _spline_pair(vol_geom, geom[views] if views.size < geom.n_views else geom, up, up_t, backend)
    return _power_iteration(shape, A, AT, M) * (geom.n_views / views.size)


def nonneg_ls_lipschitz(vol_geom: VolumeGeometry, geom: VectorGeometry, *, coarsen: int = 1, precondition: bool = False,
                        backend: str = "auto") -> float:
    """The largest eigenvalue ``L`` of ``UᵀΠᵀΠU`` that :func:`nonneg_ls` steps by (3 power iterations from ones, on
    every k-th view when there are at least ``2 LIPSCHITZ_VIEWS``, scaled to all of them).

    With ``precondition``, that of ``M UᵀΠᵀΠU`` (``M`` the ramp of
    :func:`nonneg_ls`).

    It depends on the grid, ``coarsen`` and the geometry only (not on the
    data, the support or the weights); pass it as ``nonneg_ls(...,
    lipschitz=L)`` to reconstructions on the same grid at nearly the same
    geometry.
    """
    f = _coarsen_factor(coarsen, vol_geom)
    shape, vg_c, up, up_t = _spline_maps(vol_geom, f)
    M = _ramp_preconditioner(shape, vg_c.voxel_size) if precondition else None
    return _sampled_lipschitz(vol_geom, geom, shape, up, up_t, M, backend)
