"""Lab frame of every view: the scanner's axes seen in the volume (sample) frame."""

from __future__ import annotations

import numpy as np

from ..errors import GeometryError, InputTypeError
from ._vector import VectorGeometry

__all__ = ["lab_frames"]


def lab_frames(geom: VectorGeometry) -> np.ndarray:
    """Lab axes of every view in the sample frame.

    Parameters
    ----------
    geom : VectorGeometry
        Cone or parallel; only the detector steps ``u``, ``v`` are used.

    Returns
    -------
    (n_views, 3, 3) float64
        ``F[k]``, a rotation matrix (orthonormal, det +1) whose columns are
        the lab axes ``x_lab``, ``y_lab``, ``z_lab`` of view ``k`` in sample
        (volume-frame) coordinates: ``a_sample = F[k] @ a_lab``. Exactly
        ``Rz(θ_k)`` for the nominal circular scans.
    """
    if not isinstance(geom, VectorGeometry):
        raise InputTypeError(f"geom must be a pdvc.VectorGeometry, got {type(geom).__name__}")
    u, v = geom.u, geom.v
    x = u / np.linalg.norm(u, axis=1, keepdims=True)
    z = v - np.einsum("ij,ij->i", v, x)[:, None] * x
    nz = np.linalg.norm(z, axis=1, keepdims=True)
    if np.any(nz <= 1e-12 * np.linalg.norm(v, axis=1, keepdims=True)):  # pragma: no cover - VectorGeometry forbids it
        raise GeometryError("detector steps u and v are parallel; no lab frame")
    z = z / nz
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=2)
