"""Comparing two geometries of the same scan: gauge-free reprojection error."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from ..errors import GeometryError
from ._poses import rotvec_to_matrix
from ._vector import VectorGeometry
from ._volume import VolumeGeometry

__all__ = ["ReprojectionError", "reprojection_error", "sample_points"]


@dataclass(frozen=True)
class ReprojectionError:
    """Distance on the detector between where two geometries project the same points.

    Attributes
    ----------
    rms : float
        Root mean square over points and views, pixels.
    per_view : (n_views,) float64
        RMS over points for each view, pixels.
    max : float
        Largest single-point distance, pixels.
    gauge_rotvec, gauge_translation : (3,) float64
        The global rigid motion ``x -> R x + t`` of the volume frame that was
        removed (identity if ``remove_gauge`` was False).
    """

    rms: float
    per_view: np.ndarray
    max: float
    gauge_rotvec: np.ndarray
    gauge_translation: np.ndarray


def sample_points(vol_geom: VolumeGeometry, n: int = 5, *, fraction: float = 0.8) -> np.ndarray:
    """A regular ``n`` x ``n`` x ``n`` grid of world points inside the volume.

    ``fraction`` of the extent along each axis, centred; (n³, 3) xyz.
    """
    zc, yc, xc = (np.linspace(-0.5, 0.5, n) * fraction * e for e in vol_geom.extent_xyz[::-1])
    Z, Y, X = np.meshgrid(zc, yc, xc, indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1) + np.asarray(vol_geom.offset)


def _check_pair(a: VectorGeometry, b: VectorGeometry) -> None:
    if a.n_views != b.n_views or a.det_shape != b.det_shape or a.kind != b.kind:
        raise GeometryError(
            f"geometries must describe the same scan: got {a!r} and {b!r}"
        )


def reprojection_error(
    geom: VectorGeometry, reference: VectorGeometry, points, *, remove_gauge: bool = True
) -> ReprojectionError:
    """How far ``geom`` projects ``points`` from where ``reference`` does, in pixels.

    A global rigid motion of the volume frame is unobservable (the
    reconstruction can sit anywhere), so by default the best single rigid
    motion ``x -> R x + t`` (one for all views) is removed first: the error
    is ``min_{R,t} |proj_geom(x) - proj_reference(R x + t)|``.

    Parameters
    ----------
    geom, reference : VectorGeometry
        Same views and detector.
    points : (n_points, 3) array
        World points inside the sample (see :func:`sample_points`).
    """
    _check_pair(geom, reference)
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 3:
        raise GeometryError(f"points must have shape (n_points >= 3, 3), got {pts.shape}")
    target = geom.project_points(pts)
    scale = float(np.ptp(pts, axis=0).max()) or 1.0

    def residual(q):
        R = rotvec_to_matrix(q[:3])
        moved = pts @ R.T + q[3:] * scale
        return (reference.project_points(moved) - target).ravel()

    q = np.zeros(6)
    if remove_gauge:
        q = least_squares(residual, q, method="lm", xtol=1e-12, ftol=1e-12).x
    d = np.linalg.norm(residual(q).reshape(geom.n_views, len(pts), 2), axis=-1)
    return ReprojectionError(
        rms=float(np.sqrt(np.mean(d**2))),
        per_view=np.sqrt(np.mean(d**2, axis=1)),
        max=float(d.max()),
        gauge_rotvec=q[:3].copy(),
        gauge_translation=q[3:] * scale,
    )
