"""Nominal builders: circular cone beam and parallel beam (DESIGN.md §1)."""

from __future__ import annotations

import warnings

import numpy as np

from ..errors import GeometryError
from ._vector import VectorGeometry, check_det_shape

__all__ = ["circular_cone", "parallel"]


_SPAN_EPS = 1e-6  # radians; 0..2*pi with endpoint must not warn


def _angles(angles) -> np.ndarray:
    a = np.asarray(angles, dtype=np.float64)
    if a.ndim == 0:
        a = a[None]
    if a.ndim != 1 or a.size == 0 or not np.all(np.isfinite(a)):
        raise GeometryError(f"angles must be a non-empty 1D array of finite radians, got shape {np.shape(angles)}")
    span = float(a.max() - a.min())
    if span > 2.0 * np.pi + _SPAN_EPS:
        # stacklevel 3: the user's call of circular_cone / parallel
        warnings.warn(
            f"angles span {span:.6g} (max - min), more than one full turn (2*pi = 6.283); angles are "
            "expected in radians: were degrees given? Convert them with numpy.deg2rad(angles) "
            "(a scan of several turns in radians is fine).",
            UserWarning,
            stacklevel=3,
        )
    return a


def _pitch(pixel) -> tuple[float, float]:
    p = np.asarray(pixel, dtype=np.float64)
    if p.ndim == 0:
        p = np.repeat(p, 2)
    if p.shape != (2,) or not np.all(np.isfinite(p)) or np.any(p <= 0):
        raise GeometryError(f"pixel must be a positive pitch or (row_pitch, col_pitch), got {pixel!r}")
    return float(p[0]), float(p[1])


def _offset(det_offset) -> tuple[float, float]:
    o = np.asarray(det_offset, dtype=np.float64)
    if o.shape != (2,) or not np.all(np.isfinite(o)):
        raise GeometryError(f"det_offset must be (row_offset, col_offset) in pixels, got {det_offset!r}")
    return float(o[0]), float(o[1])


def circular_cone(angles, *, sod: float, odd: float, det_shape, pixel, det_offset=(0.0, 0.0)) -> VectorGeometry:
    """Nominal circular cone-beam scan, ASTRA ``cone`` converted to ``cone_vec``.

    At angle θ: ``src = (SOD sinθ, -SOD cosθ, 0)``, ``d = (-ODD sinθ, ODD cosθ, 0)``,
    ``u = (px cosθ, px sinθ, 0)``, ``v = (0, 0, py)``; the rotation axis is z.

    Parameters
    ----------
    angles : (n_views,) array, radians
    sod : float
        Source to rotation-axis distance (length units, > 0).
    odd : float
        Rotation-axis to detector distance (length units; SDD = SOD + ODD).
    det_shape : (n_rows, n_cols)
    pixel : float or (row_pitch, col_pitch)
        Detector pixel pitch, length units.
    det_offset : (row_offset, col_offset), pixels
        Shift of the detector centre along ``v`` and ``u`` (e.g. a detector
        that is not centred on the rotation axis).
    """
    a = _angles(angles)
    shape = check_det_shape(det_shape)
    py, px = _pitch(pixel)
    if not (np.isfinite(sod) and sod > 0):
        raise GeometryError(f"sod must be a positive distance, got {sod!r}")
    if not np.isfinite(odd) or sod + odd <= 0:
        raise GeometryError(f"odd must be finite with sod + odd > 0 (detector beyond the source), got odd={odd!r}")
    ro, co = _offset(det_offset)
    s, c = np.sin(a), np.cos(a)
    z = np.zeros_like(a)
    vec = np.stack(
        [sod * s, -sod * c, z, -odd * s, odd * c, z, px * c, px * s, z, z, z, z + py], axis=1
    )
    vec[:, 3:6] += co * vec[:, 6:9] + ro * vec[:, 9:12]
    return VectorGeometry(vec, shape, "cone")


def parallel(angles, *, det_shape, pixel, det_offset=(0.0, 0.0)) -> VectorGeometry:
    """Nominal parallel-beam scan, ASTRA ``parallel3d`` converted to ``parallel3d_vec``.

    At angle θ: ``ray = (sinθ, -cosθ, 0)``, ``d = 0``,
    ``u = (px cosθ, px sinθ, 0)``, ``v = (0, 0, py)``.

    Parameters are as in :func:`circular_cone`.
    """
    a = _angles(angles)
    shape = check_det_shape(det_shape)
    py, px = _pitch(pixel)
    ro, co = _offset(det_offset)
    s, c = np.sin(a), np.cos(a)
    z = np.zeros_like(a)
    vec = np.stack([s, -c, z, z, z, z, px * c, px * s, z, z, z, z + py], axis=1)
    vec[:, 3:6] += co * vec[:, 6:9] + ro * vec[:, 9:12]
    return VectorGeometry(vec, shape, "parallel")
