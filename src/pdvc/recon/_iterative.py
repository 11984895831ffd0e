"""Iterative reconstruction on the projector pair (forward, exact adjoint)."""

from __future__ import annotations

import logging
from typing import Callable, Optional

import numpy as np

from ..errors import PdvcError, ShapeError
from ..geometry import VectorGeometry, VolumeGeometry
from ..projectors import backproject, forward

logger = logging.getLogger(__name__)

__all__ = ["cgls"]


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
