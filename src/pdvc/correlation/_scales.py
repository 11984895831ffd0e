"""Coarse graining of projections and volumes (``DESIGN.md`` §2, paper §3).

Scale ``s`` (an int, 1 = full resolution): the projections are blurred by a
Gaussian and averaged over ``s x s`` pixel blocks (superpixels), and the
detector of the geometry gets ``s`` times larger pixels. The registration
starts at a coarse scale, where large motions are small in pixels and the
images are smooth, then refines.

Blur width
----------
The paper convolves "by a Gaussian kernel with a characteristic width of 2
(and 4) pixels" before down-sampling by 2 (and 4). The width is read here
as ``sigma = s / 2`` pixels by default (the kernel's ±1σ span is the
superpixel, ``s`` pixels). With the block mean that follows (a box of ``s``
pixels, standard deviation ``s/√12``) the total blur has standard deviation
``√(1/4 + 1/12) s ≈ 0.58 s`` pixels: about half a coarse pixel, enough to
suppress the aliasing of the down-sampling while keeping the coarse image
as sharp as its grid allows. ``sigma`` is a keyword for those who read the
paper's width as ``sigma = s`` (smoother, more robust to large motion).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
from scipy.ndimage import gaussian_filter, gaussian_filter1d

from ..errors import GeometryError, InputTypeError, ShapeError
from ..geometry import VectorGeometry, VolumeGeometry
from ..projectors import bin_projections

__all__ = ["coarse_grain", "coarse_volume", "coarse_weights", "scale_schedule", "coarse_noise_factor"]


def _scale(scale) -> int:
    if not isinstance(scale, (int, np.integer)) or isinstance(scale, bool) or scale < 1:
        raise ShapeError(f"scale must be a positive int (1 = full resolution), got {scale!r}")
    return int(scale)


def _sigma(sigma, s: int) -> float:
    if sigma is None:
        return s / 2.0 if s > 1 else 0.0
    if not (np.isscalar(sigma) and np.isfinite(sigma) and sigma >= 0):
        raise ShapeError(f"sigma must be a non-negative number of pixels, got {sigma!r}")
    return float(sigma)


def coarse_grain(projections, geom: VectorGeometry, scale: int, *, sigma: float | None = None):
    """Projections and geometry at a coarser scale: Gaussian blur, then ``s x s`` block mean.

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) array
        Line integrals; not modified.
    geom : VectorGeometry
        Their geometry.
    scale : int, >= 1
        Superpixel size ``s``.
    sigma : float, optional
        Standard deviation of the Gaussian blur, in **fine** pixels, applied
        along rows and columns only: views are separate images taken at
        different angles, so nothing is mixed across views. Default
        ``scale / 2`` (module docstring), and none at scale 1, which then
        returns an unchanged float32 copy; 0 skips the blur (plain binning).

    Returns
    -------
    projections_s : (n_views, n_rows // s, n_cols // s) float32
        New array. Coarse pixel ``(I, J)`` is the mean of the blurred fine
        pixels ``s I … s I + s - 1`` (rows) and likewise for columns;
        trailing rows/columns that do not fill a block are dropped
        (:func:`pdvc.projectors.bin_projections`). The blur uses mirror
        boundaries (``scipy.ndimage`` ``"reflect"``).
    geom_s : VectorGeometry
        ``geom.binned(s)``: pixel steps ``s u``, ``s v``; detector centre
        moved to the centre of the kept pixels, so every coarse pixel centre
        is the centre of its block.

    Notes
    -----
    The blur also lowers the noise: for white noise of variance γ² the
    coarse pixels have variance ``γ² · coarse_noise_factor(s, sigma=...)``
    and are correlated with their neighbours.
    """
    if not isinstance(geom, VectorGeometry):
        raise InputTypeError(f"geom must be a pdvc.VectorGeometry, got {type(geom).__name__}")
    s = _scale(scale)
    arr = np.asarray(projections)
    want = (geom.n_views,) + geom.det_shape
    if arr.shape != want:
        raise ShapeError(f"projections must have shape {want} (n_views, n_rows, n_cols) of geom, got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise InputTypeError(f"projections must be real numbers, got dtype {arr.dtype}")
    sig = _sigma(sigma, s)
    if s == 1 and sig == 0:
        return np.array(arr, dtype=np.float32, copy=True), geom
    if s > min(geom.det_shape):
        raise ShapeError(f"scale {s} is larger than the detector {geom.det_shape}")
    if s == 1:
        return gaussian_filter(arr.astype(np.float32), sigma=(0.0, sig, sig), mode="reflect"), geom
    if sig == 0:
        return bin_projections(arr, s), geom.binned(s)
    # the blur and the block mean are one linear map per axis, evaluated only at the coarse pixels (s² x fewer
    # outputs than blurring every fine pixel): the same numbers as gaussian_filter + bin_projections, in float64
    nv, nr, nc = arr.shape
    rows, cols = _blur_and_bin(nr, s, sig), _blur_and_bin(nc, s, sig).T.tocsr()
    out = np.empty((nv, nr // s, nc // s), np.float32)
    for k in range(nv):
        out[k] = (rows @ np.asarray(arr[k], np.float32)) @ cols
    return out, geom.binned(s)


@functools.lru_cache(maxsize=16)
def _blur_and_bin(n: int, s: int, sigma: float):
    """The ``(n // s, n)`` sparse matrix of a Gaussian blur (``sigma`` pixels, mirror boundaries, as
    ``scipy.ndimage.gaussian_filter1d``) followed by the mean over blocks of ``s`` (trailing pixels dropped)."""
    from scipy import sparse

    r = int(4.0 * sigma + 0.5)  # gaussian_filter1d's radius (truncate = 4)
    impulse = np.zeros(2 * r + 1)
    impulse[r] = 1.0
    w = gaussian_filter1d(impulse, sigma, mode="constant")  # its weights, exactly
    m = n // s
    i = np.arange(m * s)
    j = i[:, None] + np.arange(-r, r + 1)[None, :]  # the fine pixels each kept pixel's blur reads ...
    j = np.mod(j, 2 * n)
    j = np.where(j >= n, 2 * n - 1 - j, j)  # ... mirrored at the edges ("reflect": d c b a | a b c d | d c b a)
    blur = sparse.csr_matrix((np.broadcast_to(w, j.shape).ravel(), (np.repeat(i, 2 * r + 1), j.ravel())), shape=(m * s, n))
    mean = sparse.csr_matrix((np.full(m * s, 1.0 / s), (i // s, i)), shape=(m, m * s))
    return (mean @ blur).tocsr()


def coarse_volume(volume, vol_geom: VolumeGeometry, scale: int):
    """A volume averaged over ``s x s x s`` voxel blocks, and its grid.

    Parameters
    ----------
    volume : (nz, ny, nx) array
        Not modified.
    vol_geom : VolumeGeometry
    scale : int, >= 1

    Returns
    -------
    volume_s : (nz // s, ny // s, nx // s) float32
        Block means (no blur: a volume is usually rebuilt from the coarse
        projections instead; this one serves as a start or a check).
    vol_geom_s : VolumeGeometry
        Voxel size ``s`` times larger; every coarse voxel centre is the
        centre of its block. Along an axis whose length ``n`` is not a
        multiple of ``s``, the ``r = n mod s`` voxels left over are dropped
        as evenly as possible, ``r // 2`` at the start and the rest at the
        end: the grid is then ``vol_geom.binned(s)`` exactly when every
        ``r`` is even, and otherwise its offset moves by half a *fine*
        voxel toward the start on the odd axes (``vol_geom.binned`` keeps
        the centre fixed, which no block grid can then do).

    Raises
    ------
    ShapeError
        If an axis would have fewer than 2 coarse voxels.
    """
    if not isinstance(vol_geom, VolumeGeometry):
        raise InputTypeError(f"vol_geom must be a pdvc.VolumeGeometry, got {type(vol_geom).__name__}")
    s = _scale(scale)
    vol = np.asarray(volume)
    vol_geom.check_volume(vol)
    if not np.issubdtype(vol.dtype, np.number) or np.iscomplexobj(vol):
        raise InputTypeError(f"volume must be real numbers, got dtype {vol.dtype}")
    if s == 1:
        return np.array(vol, dtype=np.float32, copy=True), vol_geom
    shape = vol_geom.shape
    m = tuple(n // s for n in shape)
    if min(m) < 2:
        raise ShapeError(f"scale {s} leaves fewer than 2 voxels along an axis of the volume {shape}")
    rem = tuple(n - s * k for n, k in zip(shape, m))
    start = tuple(r // 2 for r in rem)
    sub = vol[tuple(slice(a, a + s * k) for a, k in zip(start, m))]
    out = sub.reshape(m[0], s, m[1], s, m[2], s).mean(axis=(1, 3, 5), dtype=np.float64).astype(np.float32)
    # centre of the kept voxels relative to the grid centre, fine voxels, (z, y, x)
    shift_zyx = np.array([a - r / 2 for a, r in zip(start, rem)])
    coarse = vol_geom.binned(s)
    if np.any(shift_zyx != 0):
        offset = np.asarray(vol_geom.offset) + shift_zyx[::-1] * np.asarray(vol_geom.voxel_size[::-1])
        coarse = dataclasses.replace(coarse, offset=tuple(offset))
    if coarse.shape != m:  # pragma: no cover - binned agrees whenever min(m) >= 2
        raise GeometryError(f"binned grid {coarse.shape} does not match the block means {m}")
    return out, coarse


def scale_schedule(start: int, stop: int = 1) -> tuple[int, ...]:
    """Scales from coarse to fine by successive halving: ``scale_schedule(4) == (4, 2, 1)``.

    Each scale is half the previous one (integer division), and ``stop`` is
    always the last: ``scale_schedule(6) == (6, 3, 1)``,
    ``scale_schedule(8, 2) == (8, 4, 2)``, ``scale_schedule(3, 2) == (3, 2)``.

    Parameters
    ----------
    start : int, >= stop
        Coarsest scale (superpixel size).
    stop : int, >= 1
        Finest scale.
    """
    a, b = _scale(start), _scale(stop)
    if a < b:
        raise ShapeError(f"start must be >= stop (coarse to fine), got start={start!r}, stop={stop!r}")
    out = [a]
    while out[-1] // 2 > b:
        out.append(out[-1] // 2)
    if out[-1] != b:
        out.append(b)
    return tuple(out)


def coarse_noise_factor(scale: int, *, sigma: float | None = None) -> float:
    """Variance of a coarse-grained pixel of unit white noise (away from the edges).

    :func:`coarse_grain` is linear: each coarse pixel is ``Σ w_ij n_ij`` over
    fine pixels with the separable kernel ``w = (g * box_s)/s`` (``g`` the
    discrete Gaussian of ``scipy.ndimage``, ``box_s`` the ``s``-pixel sum),
    so white noise of variance γ² becomes ``γ² Σ w²``. Use it to carry a
    noise variance estimated on the raw projections (where Immerkær's
    estimator is valid; the coarse noise is correlated) to scale ``s``.

    Parameters
    ----------
    scale : int, >= 1
    sigma : float, optional
        As in :func:`coarse_grain` (default ``scale / 2``; none at scale 1).

    Returns
    -------
    float
        ``Σ w²``; e.g. 1 at scale 1 without blur, ``1/s²`` for plain
        binning, ≈ 0.063 at scale 2 and ≈ 0.015 at scale 4 with the default
        blur (vs 0.25 and 0.0625 for binning alone).
    """
    s = _scale(scale)
    sig = _sigma(sigma, s)
    half = int(4 * sig + 0.5) + s + 2
    delta = np.zeros(2 * half + 1)
    delta[half] = 1.0
    g = gaussian_filter1d(delta, sig, mode="constant") if sig > 0 else delta
    w = np.convolve(g, np.ones(s) / s)
    return float(np.sum(w**2) ** 2)


def coarse_weights(weights, s: int, det_shape):
    """Detector weights at scale ``s``: block means, cropped like :func:`coarse_grain` (None stays None)."""
    if weights is None:
        return None
    w = np.asarray(weights, np.float32)
    if s == 1:
        return w
    nr, nc = det_shape
    w = w[..., : nr * s, : nc * s]
    return w.reshape(w.shape[:-2] + (nr, s, nc, s)).mean(axis=(-3, -1))
