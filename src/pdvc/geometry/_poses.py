"""Rigid poses: rotation vectors, exact composition on SO(3)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import GeometryError

__all__ = ["rotvec_to_matrix", "matrix_to_rotvec", "compose_poses", "invert_poses", "remove_mean_pose"]


def rotvec_to_matrix(rotvecs) -> np.ndarray:
    """Rotation matrices from rotation vectors (axis x angle, radians).

    ``(3,)`` gives ``(3, 3)``; ``(n, 3)`` gives ``(n, 3, 3)``.
    """
    rv = np.array(rotvecs, dtype=np.float64)  # writable copy (scipy needs one)
    if rv.shape[-1:] != (3,) or rv.ndim > 2:
        raise GeometryError(f"rotation vectors must have shape (3,) or (n, 3), got {rv.shape}")
    return Rotation.from_rotvec(rv).as_matrix()


def matrix_to_rotvec(matrices) -> np.ndarray:
    """Rotation vectors from rotation matrices ``(3, 3)`` or ``(n, 3, 3)``."""
    m = np.array(matrices, dtype=np.float64)
    if m.shape[-2:] != (3, 3) or m.ndim > 3:
        raise GeometryError(f"rotation matrices must have shape (3, 3) or (n, 3, 3), got {m.shape}")
    return Rotation.from_matrix(m).as_rotvec()


def compose_poses(rv_a, t_a, rv_b, t_b) -> tuple[np.ndarray, np.ndarray]:
    """Pose ``a ∘ b``: first ``x -> R_b x + t_b``, then ``x -> R_a x + t_a``.

    Exact on SO(3). Arrays broadcast over a leading view axis.
    """
    Ra, Rb = Rotation.from_rotvec(np.array(rv_a, np.float64)), Rotation.from_rotvec(np.array(rv_b, np.float64))
    rv = (Ra * Rb).as_rotvec()
    t = Ra.apply(np.array(t_b, np.float64)) + np.asarray(t_a, np.float64)
    return rv, t


def invert_poses(rv, t) -> tuple[np.ndarray, np.ndarray]:
    """Inverse pose: ``x -> Rᵀ x - Rᵀ t``."""
    R = Rotation.from_rotvec(np.array(rv, np.float64))
    Rinv = R.inv()
    return Rinv.as_rotvec(), -Rinv.apply(np.array(t, np.float64))


def remove_mean_pose(rv, t, *, center=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Fix the gauge: right-compose every pose with one rigid motion so the mean pose is the identity.

    A global rigid motion ``G`` of the volume frame is unobservable: the
    poses ``P_k`` and ``P_k ∘ G⁻¹`` describe the same scan with the
    reconstruction moved by ``G``. This picks ``G`` so that the mean
    rotation (chordal mean) is the identity and the mean position of
    ``center`` is unchanged.

    Returns
    -------
    rv, t : (n_views, 3) arrays, the re-gauged poses (``x -> R x + t``).
    """
    rv = np.array(rv, np.float64)
    t = np.array(t, np.float64)
    c = np.asarray(center, np.float64).reshape(3)
    R = Rotation.from_rotvec(rv)
    Rbar = R.mean()
    # G⁻¹: x -> Rbarᵀ (x - g) with g chosen so that mean_k P_k(G⁻¹(c)) = c ... solved exactly:
    Rk = (R * Rbar.inv()).as_matrix()  # R_k R̄ᵀ
    A = Rk.mean(axis=0)
    # mean_k [R_k R̄ᵀ (c - g) + t_k] = c  ->  A (c - g) = c - mean t
    g = c - np.linalg.solve(A, c - t.mean(axis=0))
    new_R = R * Rbar.inv()
    new_t = t - np.einsum("kij,j->ki", Rk, g)
    return new_R.as_rotvec(), new_t


def magnification_mode(geom, center) -> np.ndarray:
    """Per-view translation of the cone-beam scale ambiguity, ``(n_views, 3)``.

    Scaling the whole scene by ``1 + ε`` about the source of view k leaves
    that view's projection unchanged.  About the volume centre ``c`` this is
    a scaling of the volume (absorbed by the next reconstruction) plus a
    translation ``ε (c − src_k)`` of the sample.  Hence, when the volume is
    re-reconstructed, the per-view translations ``ε (c − src_k)`` (a constant
    lab-frame shift along the beam for a circular scan, i.e. the source–object
    distance) cannot be told from a change of voxel size.  Returns
    ``c − src_k``; zeros for parallel beam, where no such ambiguity exists.
    """
    c = np.asarray(center, np.float64).reshape(3)
    if geom.kind != "cone":
        return np.zeros((geom.n_views, 3))
    return c[None, :] - geom.src


def fix_gauge(rv, t, geom, *, center, scale: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Fix the gauge of self-calibration poses (relative to the nominal ``geom``).

    Two ambiguities are removed, as stated in every pdvc output:

    * **rigid**: a global rigid motion of the reconstruction frame, fixed by
      :func:`remove_mean_pose` (mean rotation = identity, mean position of
      ``center`` unchanged);
    * **scale** (cone beam, ``scale=True``): a common change of the
      source–object distance, which the reconstruction absorbs as a change
      of voxel size (see :func:`magnification_mode`).  Fixed by making the
      poses' least-squares component along that mode zero, i.e. the nominal
      source–object distance is the mean one: the voxel size stays the
      nominal one.

    Returns the re-gauged ``rv, t`` (new arrays).
    """
    c = np.asarray(center, np.float64).reshape(3)
    rv, t = remove_mean_pose(rv, t, center=c)
    if scale and geom.kind == "cone":
        m = magnification_mode(geom, c)
        for _ in range(2):
            R = Rotation.from_rotvec(rv)
            tau = R.apply(c) + t - c  # displacement of the centre
            eps = float(np.sum(tau * m) / max(np.sum(m * m), 1e-300))
            t = t - eps * m
            rv, t = remove_mean_pose(rv, t, center=c)
    return rv, t
