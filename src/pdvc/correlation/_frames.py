"""Sample frame and lab frame of the rigid modes (``DESIGN.md`` §2, "Frames").

The engine measures, per view ``k``, six parameters ``p = (tx, ty, tz, rx,
ry, rz)`` (``pdvc.projectors.POSE_PARAMETERS``) of a small rigid motion of
the sample, ``x -> x + τ + ω × (x - c)``, written in the **sample frame**
(the volume frame, which turns with the sample). A motion that is fixed in
the **lab** (a drift of the table along the beam, a tilted axis) turns in
the sample frame, so it needs many temporal functions there; in the lab
frame it is one constant mode. This module gives the per-view rotation
between the two frames and applies it to the per-view normal equations.

The lab frame of view ``k`` is attached to the scanner as seen in the
volume frame, read off the detector vectors of that view:

* ``x_lab`` = ``û_k`` (along the detector columns);
* ``z_lab`` = ``v̂_k`` made orthogonal to ``û_k`` (up the detector rows);
* ``y_lab`` = ``z_lab × x_lab`` (right-handed; along the beam, source to
  detector, for the usual detector that faces the source).

``F_k = [x_lab | y_lab | z_lab]`` (columns = lab axes in sample
coordinates) maps lab components to sample components: ``a_sample =
F_k a_lab``. For the nominal scans (:func:`pdvc.geometry.circular_cone`,
:func:`pdvc.geometry.parallel`) ``F_k = Rz(θ_k)`` and ``F = I`` at θ = 0:
the lab frame is the sample frame at θ = 0, the convention of
:mod:`pdvc.simulate.motion` (``sample = Rz(θ) · lab``). For a calibrated
geometry ``F_k`` includes the view's pose: it is the scanner's own frame.
"""

from __future__ import annotations

import numpy as np

from ..errors import ShapeError
from ..geometry import VectorGeometry, lab_frames

__all__ = ["lab_frames", "lab_to_sample_map", "to_lab", "params_to_sample", "params_to_lab", "view_angles"]


def _skew(a: np.ndarray) -> np.ndarray:
    """``[a]×`` per row: ``(n, 3) -> (n, 3, 3)`` with ``[a]× b = a × b``."""
    z = np.zeros(a.shape[0])
    return np.stack(
        [
            np.stack([z, -a[:, 2], a[:, 1]], -1),
            np.stack([a[:, 2], z, -a[:, 0]], -1),
            np.stack([-a[:, 1], a[:, 0], z], -1),
        ],
        axis=1,
    )


def lab_to_sample_map(geom: VectorGeometry, *, center=None, pivot=None, rotvecs=None) -> np.ndarray:
    """Per-view 6x6 map ``T_k`` from lab-frame to sample-frame motion parameters.

    ``p_sample = T_k @ p_lab``, both in ``(tx, ty, tz, rx, ry, rz)`` order
    (length units and radians), for small motions.

    Parameters
    ----------
    geom : VectorGeometry
    center : (x, y, z), optional
        Centre ``c`` of the sample-frame rotation modes (the engine's
        ``center``; sample-frame point). Default the origin.
    pivot : (x, y, z), optional
        Lab point ``q`` about which the lab-frame rotations act (lab
        coordinates; the lab origin is the volume-frame origin, on the
        nominal rotation axis). Default: ``center`` read as a lab point.
    rotvecs : (n_views, 3), optional
        Rotations of the poses that a sample-frame increment is composed
        on (it acts before them: :meth:`pdvc.geometry.Poses.compose`). Its
        translation then moves the sample by ``R_k t`` in the volume frame,
        so the lab axes it is read in are those of the posed geometry,
        ``R_kᵀ F_k``. Default: none (the nominal axes ``F_k``).

    Returns
    -------
    (n_views, 6, 6) float64
        ``[[F_k, -[a_k]× F_k], [0, F_k]]`` with ``a_k = c - F_k q``:
        translations and rotation vectors both rotate with ``F_k``
        (:func:`lab_frames`), and a lab rotation about ``q`` is a rotation
        about ``c`` plus the translation ``(F_k ω) × (c - F_k q)``. With the
        defaults and ``c`` on the nominal axis (e.g. the volume centre),
        ``a_k = 0`` for the nominal scans and ``T_k = block-diag(F_k, F_k)``,
        an orthogonal matrix.
    """
    if rotvecs is not None:
        rv = np.asarray(rotvecs, dtype=np.float64)
        if rv.shape != (geom.n_views, 3):
            raise ShapeError(f"rotvecs must have shape ({geom.n_views}, 3), one row per view of geom, got {rv.shape}")
        geom = geom.apply_poses(rv, np.zeros_like(rv))
    F = lab_frames(geom)
    n = F.shape[0]
    c = np.zeros(3) if center is None else _point(center, "center")
    q = c if pivot is None else _point(pivot, "pivot")
    a = c[None, :] - F @ q
    T = np.zeros((n, 6, 6))
    T[:, :3, :3] = F
    T[:, 3:, 3:] = F
    T[:, :3, 3:] = -_skew(a) @ F
    return T


def _point(value, name: str) -> np.ndarray:
    p = np.asarray(value, dtype=np.float64)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ShapeError(f"{name} must be a finite (x, y, z) point, got {value!r}")
    return p


def _maps(T, n_lead: tuple, name: str = "T") -> np.ndarray:
    t = np.asarray(T, dtype=np.float64)
    if t.shape[-2:] != (6, 6) or t.ndim not in (2, 3):
        raise ShapeError(f"{name} must have shape (n_views, 6, 6) or (6, 6), got {t.shape}")
    if t.ndim == 3 and n_lead and t.shape[0] != n_lead[0]:
        raise ShapeError(f"{name} has {t.shape[0]} views but the other argument has {n_lead[0]}")
    return t


def to_lab(M, b, T) -> tuple[np.ndarray, np.ndarray]:
    """Normal equations of the sample-frame parameters rewritten for lab-frame ones.

    The residual is linear in ``p_sample = T_k p_lab``, so the Gauss–Newton
    system ``M_k p_sample = b_k`` becomes ``(T_kᵀ M_k T_k) p_lab = T_kᵀ b_k``
    (the same quadratic form: ``p_labᵀ M_lab p_lab = p_sampleᵀ M p_sample``).

    Parameters
    ----------
    M : (n_views, 6, 6) or (6, 6) array
        ``G_kᵀ W G_k`` of :class:`pdvc.projectors.ViewReduction`.
    b : (n_views, 6) or (6,) array
        ``G_kᵀ W ρ_k``.
    T : (n_views, 6, 6) or (6, 6) array
        From :func:`lab_to_sample_map` (one per view, or one for all).

    Returns
    -------
    M_lab : (n_views, 6, 6) float64
    b_lab : (n_views, 6) float64
        New arrays (inputs not modified); a single view in gives ``(6, 6)``
        and ``(6,)`` back.
    """
    m = np.asarray(M, dtype=np.float64)
    v = np.asarray(b, dtype=np.float64)
    if m.shape[-2:] != (6, 6) or m.ndim not in (2, 3):
        raise ShapeError(f"M must have shape (n_views, 6, 6) or (6, 6), got {m.shape}")
    if v.shape != m.shape[:-1]:
        raise ShapeError(f"b must have shape {m.shape[:-1]} to match M {m.shape}, got {v.shape}")
    t = _maps(T, m.shape[:-2])
    if m.ndim == 2 and t.ndim == 3:
        raise ShapeError(f"T has shape {t.shape} for a single-view M of shape (6, 6); pass T[k]")
    tt = np.swapaxes(t, -1, -2)
    M_lab = tt @ m @ t
    b_lab = np.einsum("...ij,...j->...i", tt, v)
    return M_lab, b_lab


def _params(p, name: str) -> np.ndarray:
    arr = np.asarray(p, dtype=np.float64)
    if arr.shape[-1:] != (6,) or arr.ndim not in (1, 2):
        raise ShapeError(
            f"{name} must have shape (n_views, 6) or (6,) in (tx, ty, tz, rx, ry, rz) order, got {arr.shape}"
        )
    return arr


def params_to_sample(p_lab, T) -> np.ndarray:
    """Sample-frame parameters ``T_k p_lab`` per view.

    Parameters
    ----------
    p_lab : (n_views, 6) or (6,) array
        Lab-frame ``(tx, ty, tz, rx, ry, rz)`` (length units, radians); a
        single 6-vector is the same lab motion at every view.
    T : (n_views, 6, 6) array (or (6, 6))

    Returns
    -------
    (n_views, 6) float64 (``(6,)`` if both inputs are single)
    """
    p = _params(p_lab, "p_lab")
    t = _maps(T, p.shape[:-1] if p.ndim == 2 else ())
    return np.einsum("...ij,...j->...i", t, p)


def params_to_lab(p_sample, T) -> np.ndarray:
    """Lab-frame parameters ``T_k⁻¹ p_sample`` per view (inverse of :func:`params_to_sample`)."""
    p = _params(p_sample, "p_sample")
    t = _maps(T, p.shape[:-1] if p.ndim == 2 else ())
    if p.ndim == 1 and t.ndim == 3:
        p = np.broadcast_to(p, (t.shape[0], 6))
    return np.linalg.solve(t, p[..., None])[..., 0]


def view_angles(geom: VectorGeometry) -> np.ndarray:
    """Rotation angle of every view (rad, unwrapped in view order) read off its lab frame."""
    F = lab_frames(geom)
    return np.unwrap(np.arctan2(F[:, 1, 0], F[:, 0, 0]))
