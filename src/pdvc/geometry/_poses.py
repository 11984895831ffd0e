"""Rigid poses: rotation vectors, exact composition on SO(3)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import GeometryError

__all__ = ["Poses", "rotvec_to_matrix", "matrix_to_rotvec", "compose_poses", "invert_poses", "remove_mean_pose", "fix_gauge"]


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


class Poses:
    """The rigid pose of the sample at every view of one scan (frozen value).

    View ``k`` sees the sample at ``x -> R_k x + t_k`` of the volume frame,
    relative to where the geometry it is applied to assumes it
    (``DESIGN.md`` §1). Rotations are rotation vectors (radians), composed
    exactly on SO(3).

    Build one with :meth:`identity`, :meth:`from_params` (the six rigid
    parameters ``(tx, ty, tz, rx, ry, rz)`` about a centre, sample frame) or
    ``Poses(rotvecs, translations)``; apply it with
    ``VectorGeometry.apply(poses)``.

    Attributes
    ----------
    rotvecs, translations : (n_views, 3) float64, read-only
    """

    __slots__ = ("_rv", "_t")

    def __init__(self, rotvecs, translations):
        rv = np.array(rotvecs, dtype=np.float64)
        t = np.array(translations, dtype=np.float64)
        if rv.ndim != 2 or rv.shape[1] != 3 or t.shape != rv.shape:
            raise GeometryError(
                f"rotvecs and translations must both have shape (n_views, 3), got {rv.shape} and {t.shape}"
            )
        if not (np.all(np.isfinite(rv)) and np.all(np.isfinite(t))):
            raise GeometryError("rotvecs and translations must be finite")
        rv.flags.writeable = False
        t.flags.writeable = False
        object.__setattr__(self, "_rv", rv)
        object.__setattr__(self, "_t", t)

    def __setattr__(self, name, value):
        raise AttributeError("Poses is immutable")

    # -- construction ---------------------------------------------------------
    @classmethod
    def identity(cls, n_views: int) -> "Poses":
        """No motion at any of ``n_views`` views."""
        n = int(n_views)
        if n < 1:
            raise GeometryError(f"n_views must be a positive int, got {n_views!r}")
        return cls(np.zeros((n, 3)), np.zeros((n, 3)))

    @classmethod
    def from_params(cls, params, center=(0.0, 0.0, 0.0)) -> "Poses":
        """From ``(n_views, 6)`` parameters ``(tx, ty, tz, rx, ry, rz)`` about ``center``.

        The pose is ``x -> R (x - c) + c + τ``: ``τ`` moves the centre,
        ``(rx, ry, rz)`` is the rotation vector about it.
        """
        q = np.asarray(params, np.float64)
        if q.ndim != 2 or q.shape[1] != 6:
            raise GeometryError(f"params must have shape (n_views, 6) in (tx, ty, tz, rx, ry, rz) order, got {q.shape}")
        c = _center(center)
        rv = np.array(q[:, 3:])
        t = q[:, :3] + c - Rotation.from_rotvec(rv).apply(c)
        return cls(rv, t)

    # -- views ----------------------------------------------------------------
    @property
    def rotvecs(self) -> np.ndarray:
        return self._rv

    @property
    def translations(self) -> np.ndarray:
        return self._t

    @property
    def n_views(self) -> int:
        return self._rv.shape[0]

    def __len__(self) -> int:
        return self.n_views

    def __iter__(self):  # ``rv, t = poses``
        return iter((self._rv, self._t))

    def __getitem__(self, index) -> "Poses":
        idx = np.arange(self.n_views)[index]
        return Poses(self._rv[np.atleast_1d(idx)], self._t[np.atleast_1d(idx)])

    def __eq__(self, other) -> bool:
        return isinstance(other, Poses) and np.array_equal(self._rv, other._rv) and np.array_equal(self._t, other._t)

    __hash__ = None  # arrays: equal values, no hash

    def __repr__(self) -> str:
        ang = np.degrees(np.linalg.norm(self._rv, axis=1))
        mv = np.linalg.norm(self._t, axis=1)
        return f"Poses(n_views={self.n_views}, max rotation {ang.max():.3g} deg, max translation {mv.max():.3g})"

    def to_params(self, center=(0.0, 0.0, 0.0)) -> np.ndarray:
        """``(n_views, 6)`` parameters about ``center`` (sample frame); inverse of :meth:`from_params`."""
        c = _center(center)
        tau = self._t - c + Rotation.from_rotvec(np.array(self._rv)).apply(c)
        return np.hstack([tau, self._rv])

    def lab_params(self, geom, center=(0.0, 0.0, 0.0)) -> np.ndarray:
        """The parameters about ``center`` with their vectors in the lab frame of each view of ``geom``.

        Translation and rotation vector are both rotated into the view's
        lab axes (:func:`lab_frames`): ``(tx, ty, tz)`` are then across the
        beam, along the beam and up, whatever the view's angle.
        """
        from ._frames import lab_frames

        if geom.n_views != self.n_views:
            raise GeometryError(f"geom has {geom.n_views} views but the poses {self.n_views}")
        F = lab_frames(geom)
        q = self.to_params(center)
        return np.hstack([np.einsum("kji,kj->ki", F, q[:, :3]), np.einsum("kji,kj->ki", F, q[:, 3:])])

    @classmethod
    def from_lab_params(cls, params, geom, center=(0.0, 0.0, 0.0)) -> "Poses":
        """From ``(n_views, 6)`` lab parameters of each view of ``geom``; inverse of :meth:`lab_params`."""
        from ._frames import lab_frames

        q = np.asarray(params, np.float64)
        if q.ndim != 2 or q.shape != (geom.n_views, 6):
            raise GeometryError(f"params must have shape ({geom.n_views}, 6), one row per view of geom, got {q.shape}")
        F = lab_frames(geom)
        return cls.from_params(np.hstack([np.einsum("kij,kj->ki", F, q[:, :3]), np.einsum("kij,kj->ki", F, q[:, 3:])]),
                               center)

    # -- algebra --------------------------------------------------------------
    def compose(self, other: "Poses") -> "Poses":
        """``self ∘ other``: first ``other``, then ``self`` (exact on SO(3))."""
        if not isinstance(other, Poses) or other.n_views != self.n_views:
            raise GeometryError("compose needs Poses with the same number of views")
        return Poses(*compose_poses(self._rv, self._t, other._rv, other._t))

    def __matmul__(self, other: "Poses") -> "Poses":
        return self.compose(other)

    def inverse(self) -> "Poses":
        """The inverse motion at every view: ``p.compose(p.inverse())`` is the identity."""
        return Poses(*invert_poses(self._rv, self._t))

    def gauge_fixed(self, geom, *, center, scale: bool = True) -> "Poses":
        """These poses with the unobservable global motion removed (:func:`fix_gauge`)."""
        return Poses(*fix_gauge(self._rv, self._t, geom, center=center, scale=scale))


def _center(center) -> np.ndarray:
    c = np.asarray(center, np.float64)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise GeometryError(f"center must be a finite (x, y, z) point, got {center!r}")
    return c
