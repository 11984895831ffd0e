"""Public projector functions: argument checks, then the chosen backend."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..compute._scheduler import current_session
from ..errors import InputTypeError, ShapeError
from ..geometry import VectorGeometry, VolumeGeometry
from ._registry import get_backend

__all__ = [
    "forward",
    "backproject",
    "jacobian",
    "reduce_views",
    "ViewReduction",
    "bin_projections",
    "POSE_PARAMETERS",
]

#: Order of the 6 rigid-motion parameters everywhere in pdvc.
POSE_PARAMETERS = ("tx", "ty", "tz", "rx", "ry", "rz")


def _check_geoms(vol_geom, geom) -> None:
    if not isinstance(vol_geom, VolumeGeometry):
        raise InputTypeError(f"vol_geom must be a pdvc.VolumeGeometry, got {type(vol_geom).__name__}")
    if not isinstance(geom, VectorGeometry):
        raise InputTypeError(f"geom must be a pdvc.VectorGeometry, got {type(geom).__name__}")


def _as_volume(volume, vol_geom: VolumeGeometry, name: str = "volume") -> np.ndarray:
    arr = np.asarray(volume)
    if arr.shape != vol_geom.shape:
        raise ShapeError(f"{name} must have shape {vol_geom.shape} (nz, ny, nx) of vol_geom, got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise ShapeError(f"{name} must be real numbers, got dtype {arr.dtype}")
    return np.ascontiguousarray(arr, dtype=np.float32)


def _as_projections(projections, geom: VectorGeometry, name: str = "projections") -> np.ndarray:
    arr = np.asarray(projections)
    want = (geom.n_views,) + geom.det_shape
    if arr.shape != want:
        raise ShapeError(f"{name} must have shape {want} (n_views, n_rows, n_cols) of geom, got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise ShapeError(f"{name} must be real numbers, got dtype {arr.dtype}")
    return np.ascontiguousarray(arr, dtype=np.float32)


def _check_out(out, shape, name="out") -> np.ndarray:
    if not isinstance(out, np.ndarray) or out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ShapeError(
            f"{name} must be a C-contiguous float32 array of shape {shape}, got "
            f"{getattr(out, 'dtype', type(out).__name__)} {getattr(out, 'shape', '')}"
        )
    return out


def _center(center, vol_geom: VolumeGeometry) -> np.ndarray:
    if center is None:
        return np.asarray(vol_geom.offset, dtype=np.float64)
    c = np.asarray(center, dtype=np.float64)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise ShapeError(f"center must be a finite (x, y, z) point, got {center!r}")
    return c


def forward(volume, vol_geom: VolumeGeometry, geom: VectorGeometry, *, backend="auto", out=None) -> np.ndarray:
    """Line integrals of ``volume`` along every detector ray.

    Parameters
    ----------
    volume : (nz, ny, nx) array
        Attenuation per length unit; converted to float32 (not modified).
    vol_geom : VolumeGeometry
    geom : VectorGeometry
    backend : str
        Projector backend name (see :func:`available_backends`).
    out : (n_views, n_rows, n_cols) float32 array, optional
        Written in place if given.

    Returns
    -------
    (n_views, n_rows, n_cols) float32
        Line integrals (attenuation x length).

    Notes
    -----
    Joseph-type model: bilinear interpolation on the grid planes crossed by
    each ray along its dominant axis (see :mod:`pdvc.projectors._kernels`).
    """
    _check_geoms(vol_geom, geom)
    vol = _as_volume(volume, vol_geom)
    shape = (geom.n_views,) + geom.det_shape
    out = np.empty(shape, np.float32) if out is None else _check_out(out, shape)
    session = current_session()  # a Dask cluster made current by pdvc.compute.use_scheduler
    if session is not None:
        return session.forward(vol, vol_geom, geom, out, backend)
    return get_backend(backend).forward(vol, vol_geom, geom, out)


def backproject(projections, vol_geom: VolumeGeometry, geom: VectorGeometry, *, backend="auto", out=None) -> np.ndarray:
    """Exact adjoint of :func:`forward` (unfiltered, unweighted back-projection).

    ``<forward(x), y> == <x, backproject(y)>`` to float rounding.

    Returns
    -------
    (nz, ny, nx) float32
    """
    _check_geoms(vol_geom, geom)
    proj = _as_projections(projections, geom)
    out = np.empty(vol_geom.shape, np.float32) if out is None else _check_out(out, vol_geom.shape)
    return get_backend(backend).backproject(proj, vol_geom, geom, out)


def jacobian(volume, vol_geom: VolumeGeometry, geom: VectorGeometry, *, center=None, backend="auto"):
    """Projections and their derivatives with respect to a rigid motion of the sample.

    The motion is ``x -> x + tau + omega x (x - center)`` applied to the
    sample in the volume frame, i.e. the geometry
    ``geom.apply_poses(omega, tau, center=center)`` for small
    ``(tau, omega)``. One pass per ray gives the projection and its six
    sensitivities.

    Parameters
    ----------
    center : (x, y, z), optional
        Centre of the rotations, world units; default the volume centre.

    Returns
    -------
    proj : (n_views, n_rows, n_cols) float32
    sens : (n_views, 6, n_rows, n_cols) float32
        Derivatives along ``POSE_PARAMETERS`` = (tx, ty, tz) per length unit
        and (rx, ry, rz) per radian.
    """
    _check_geoms(vol_geom, geom)
    vol = _as_volume(volume, vol_geom)
    c = _center(center, vol_geom)
    nv, (nr, nc) = geom.n_views, geom.det_shape
    proj = np.empty((nv, nr, nc), np.float32)
    sens = np.empty((nv, 6, nr, nc), np.float32)
    return get_backend(backend).jacobian(vol, vol_geom, geom, c, proj, sens)


@dataclass(frozen=True)
class ViewReduction:
    """Per-view normal equations of the rigid registration of one pass.

    Attributes
    ----------
    M : (n_views, 6, 6) float64
        ``G_kᵀ W G_k``, G_k the (n_pixels, 6) sensitivities of view k.
    b : (n_views, 6) float64
        ``G_kᵀ W (s_k - Π_k f)``: ``M_k⁻¹ b_k`` is the Gauss–Newton step of
        view k alone (pose increment in ``POSE_PARAMETERS`` order).
    rss : (n_views,) float64
        Weighted residual sum of squares ``Σ w (s - Π f)²``.
    weight_sum, meas_sum, meas_sq_sum, resid_sum : (n_views,) float64
        ``Σ w``, ``Σ w s``, ``Σ w s²``, ``Σ w ρ`` (for χ and the SNR of each view).
    grad_sum : (n_views, 6) float64 or None
        ``Σ w g``: with ``resid_sum`` and ``weight_sum``, what eliminating an
        offset per view from the normal equations needs.
    center : (3,) float64
        Centre of the rotations used.
    """

    M: np.ndarray
    b: np.ndarray
    rss: np.ndarray
    weight_sum: np.ndarray
    meas_sum: np.ndarray
    meas_sq_sum: np.ndarray
    resid_sum: np.ndarray
    center: np.ndarray
    grad_sum: Optional[np.ndarray] = None

    @property
    def n_views(self) -> int:
        return self.M.shape[0]

    def snr_db(self) -> np.ndarray:
        """Per-view ``20 log10(std(s) / std(ρ))`` over the weighted pixels, dB."""
        w = np.maximum(self.weight_sum, 1e-300)
        var_s = self.meas_sq_sum / w - (self.meas_sum / w) ** 2
        var_r = self.rss / w - (self.resid_sum / w) ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            return 10.0 * np.log10(var_s / var_r)


def reduce_views(
    volume,
    vol_geom: VolumeGeometry,
    geom: VectorGeometry,
    measured,
    *,
    weights=None,
    center=None,
    backend="auto",
    robust=None,
) -> ViewReduction:
    """Fused Jacobian pass reduced per view to a 6x6 matrix and a 6-vector.

    One march per ray gives the re-projection and its six sensitivities; they
    are folded at once into ``M_k``, ``b_k`` and the residual sum of squares,
    so no image of the pass is stored.

    Parameters
    ----------
    measured : (n_views, n_rows, n_cols) array
        Measured line integrals ``s``.
    weights : (n_rows, n_cols) or (n_views, n_rows, n_cols) array, optional
        Non-negative pixel weights (a ROI mask is 0/1); rays of weight 0 are
        not traced. Default: all ones.
    center : (x, y, z), optional
        Centre of the rotation modes; default the volume centre.
    robust : (cut, shift), optional
        Huber weights of this pass's own residual (one step of iteratively
        reweighted least squares): with ``e = s - Π f - shift[k]`` (``shift``
        an offset per view, ``(n_views,)``), a pixel weighs
        ``w min(1, cut / |e|)`` in ``M``, ``b`` (on ``e``), ``weight_sum``,
        ``resid_sum`` (``Σ w' e``) and ``grad_sum``, and ``rss`` holds Huber's
        loss ``Σ w L(e)``, ``L(e) = e²`` for ``|e| <= cut`` and
        ``2 cut |e| - cut²`` beyond. ``meas_sum`` and ``meas_sq_sum`` keep ``w``.
    """
    _check_geoms(vol_geom, geom)
    vol = _as_volume(volume, vol_geom)
    meas = _as_projections(measured, geom, "measured")
    if robust is not None:
        try:
            cut, shift = float(robust[0]), np.asarray(robust[1], np.float64).reshape(-1)
        except (TypeError, ValueError, IndexError):
            raise ShapeError(f"robust must be (cut, shift), a positive number and one offset per view, got {robust!r}") from None
        if not (np.isfinite(cut) and cut > 0) or shift.shape != (geom.n_views,) or not np.all(np.isfinite(shift)):
            raise ShapeError(f"robust must be (cut, shift): cut positive and finite, shift finite of shape ({geom.n_views},); "
                             f"got cut {cut!r}, shift of shape {shift.shape}")
        robust = (cut, shift)
    nr, nc = geom.det_shape
    if weights is None:
        w = np.ones((1, nr, nc), np.float32)
    else:
        w = np.asarray(weights)
        if w.shape == (nr, nc):
            w = w[None]
        if w.shape not in ((1, nr, nc), (geom.n_views, nr, nc)):
            raise ShapeError(
                f"weights must have shape {(nr, nc)} or {(geom.n_views, nr, nc)}, got {np.shape(weights)}"
            )
        w = np.ascontiguousarray(w, dtype=np.float32)
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise ShapeError("weights must be finite and non-negative")
    if not np.all(np.isfinite(meas)):
        raise ShapeError("measured must be finite (no NaN or Inf); mask bad pixels with weights instead")
    c = _center(center, vol_geom)
    session = current_session()  # a Dask cluster made current by pdvc.compute.use_scheduler
    extra = {} if robust is None else dict(robust=robust)  # a backend without robust weights is called as before
    if session is not None:
        red = session.reduce(vol, vol_geom, geom, c, meas, w, backend, **extra)
    else:
        red = get_backend(backend).reduce(vol, vol_geom, geom, c, meas, w, **extra)
    iu = np.triu_indices(6)
    M = np.zeros((geom.n_views, 6, 6))
    M[:, iu[0], iu[1]] = red[:, :21]
    M = M + np.triu(M, 1).transpose(0, 2, 1)
    return ViewReduction(
        M=M,
        b=red[:, 21:27].copy(),
        rss=red[:, 27].copy(),
        weight_sum=red[:, 28].copy(),
        meas_sum=red[:, 29].copy(),
        meas_sq_sum=red[:, 30].copy(),
        resid_sum=red[:, 31].copy(),
        center=c,
        grad_sum=red[:, 32:38].copy() if red.shape[1] >= 38 else None,  # a backend that sums w g too
    )


def bin_projections(projections, factor: int) -> np.ndarray:
    """Mean over ``factor`` x ``factor`` pixel blocks, trailing partial blocks dropped.

    Matches :meth:`VectorGeometry.binned`.

    Returns
    -------
    (n_views, n_rows // factor, n_cols // factor) float32
    """
    arr = np.asarray(projections, dtype=np.float32)
    if arr.ndim != 3:
        raise ShapeError(f"projections must have shape (n_views, n_rows, n_cols), got {arr.shape}")
    if not isinstance(factor, (int, np.integer)) or isinstance(factor, bool) or factor < 1:
        raise ShapeError(f"factor must be a positive int, got {factor!r}")
    s = int(factor)
    nv, nr, nc = arr.shape
    if nr < s or nc < s:
        raise ShapeError(f"factor {s} is larger than the detector {(nr, nc)}")
    a = arr[:, : nr // s * s, : nc // s * s]
    return a.reshape(nv, nr // s, s, nc // s, s).mean(axis=(2, 4), dtype=np.float64).astype(np.float32)
