"""Per-view rigid poses for the motions met on a lab scanner.

Conventions (``DESIGN.md`` §1)
------------------------------
A pose ``(rotvecs[k], translations[k])`` says that at view ``k`` the sample
really is at ``x -> R_k x + t_k`` of the volume (sample) frame, relative to
where the nominal geometry assumes it; the true geometry is
``geom.apply_poses(rotvecs, translations)``.

The nominal circular scans (:func:`pdvc.geometry.circular_cone`,
:func:`pdvc.geometry.parallel`) express a fixed lab scanner in the sample
frame: their vectors at angle θ are the θ = 0 vectors rotated by ``Rz(θ)``.
So the **lab frame** is the sample frame at θ = 0 (x along the detector
columns, y along the beam from source to detector, z up the nominal axis),
and a sample point ``x`` is nominally at the lab position ``B(θ) x`` with

    B(θ) = Rz(-θ)     (the table turns by -θ about z).

A rigid motion of the sample *in the lab*, ``y -> L_k y + l_k`` applied to
its nominal lab position, is the sample-frame pose

    R_k = B_kᵀ L_k B_k,     t_k = B_kᵀ l_k                      (1)

(:func:`lab_motion_to_poses`); every scenario below is built from (1) or its
direct analogue. Angles are radians; lengths in the user's length unit.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .._arrays import per_view_vectors
from ..errors import GeometryError, ShapeError
from ..geometry import compose_poses
from ._checks import as_finite, as_vec3

__all__ = [
    "lab_motion_to_poses",
    "poses_to_lab_motion",
    "tilted_axis_poses",
    "precession_poses",
    "drift_poses",
    "jolt_poses",
    "combine_poses",
]


def _angles(angles, name: str = "angles") -> np.ndarray:
    a = np.asarray(angles, dtype=np.float64)
    if a.ndim != 1 or a.size == 0:
        raise ShapeError(f"{name} must be a non-empty 1D array of radians, got shape {np.shape(angles)}")
    if not np.all(np.isfinite(a)):
        raise GeometryError(f"{name} must be finite radians")
    return a


_per_view = per_view_vectors


def _table(angles: np.ndarray) -> Rotation:
    """``B_k = Rz(-θ_k)``: nominal sample -> lab rotation per view."""
    return Rotation.from_rotvec(np.outer(-angles, [0.0, 0.0, 1.0]))


def lab_motion_to_poses(angles, rotvecs, translations) -> tuple[np.ndarray, np.ndarray]:
    """Sample-frame poses of a rigid motion given in the lab frame.

    At view ``k`` the sample, nominally at lab position ``y = B_k x``, is
    really at ``L_k y + l_k``. Returns ``R_k = B_kᵀ L_k B_k``, ``t_k = B_kᵀ l_k``
    (module docstring, eq. 1).

    Parameters
    ----------
    angles : (n_views,) array, radians
        Nominal scan angles (``circular_cone`` / ``parallel`` convention).
    rotvecs : (n_views, 3) or (3,) array, radians
        ``L_k`` as rotation vectors, about the lab origin.
    translations : (n_views, 3) or (3,) array, length, lab xyz
        ``l_k``.

    Returns
    -------
    rotvecs, translations : (n_views, 3) float64 arrays
    """
    a = _angles(angles)
    n = a.size
    L = Rotation.from_rotvec(_per_view(rotvecs, n, "rotvecs"))
    lt = _per_view(translations, n, "translations")
    B = _table(a)
    R = B.inv() * L * B
    return R.as_rotvec().reshape(n, 3), B.inv().apply(lt).reshape(n, 3)


def poses_to_lab_motion(angles, rotvecs, translations) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`lab_motion_to_poses`: ``L_k = B_k R_k B_kᵀ``, ``l_k = B_k t_k``.

    Parameters and returns as in :func:`lab_motion_to_poses`, swapped.
    """
    a = _angles(angles)
    n = a.size
    R = Rotation.from_rotvec(_per_view(rotvecs, n, "rotvecs"))
    t = _per_view(translations, n, "translations")
    B = _table(a)
    L = B * R * B.inv()
    return L.as_rotvec().reshape(n, 3), B.apply(t).reshape(n, 3)


def _tilted_axis(tilt: float, azimuth: float) -> np.ndarray:
    return np.array([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)])


def tilted_axis_poses(angles, *, tilt: float, tilt_azimuth: float = 0.0, offset=(0.0, 0.0, 0.0)):
    """Poses of a sample turning about a tilted, off-centre axis.

    The table really turns about the lab axis ``n = (sin τ cos φ, sin τ sin φ,
    cos τ)`` through the lab point ``o`` (τ = ``tilt``, φ = ``tilt_azimuth``),
    by the same angle and sense as the nominal turn about z through the
    origin, and the sample is aligned with the lab at θ = 0. The sample point
    ``x`` is then at the lab position ``Q_k (x - o) + o`` with ``Q_k`` the
    rotation by ``-θ_k`` about ``n``, while the nominal geometry assumes
    ``B_k x = Rz(-θ_k) x``. Solving ``B_k (R_k x + t_k) = Q_k (x - o) + o``:

        R_k = Rz(θ_k) Q_k,     t_k = Rz(θ_k) (o - Q_k o).

    Points on the true axis (``o + λ n``) stay fixed in the lab.

    Parameters
    ----------
    angles : (n_views,) array, radians
        Nominal scan angles θ_k.
    tilt : float, radians
        Angle between the true axis and z.
    tilt_azimuth : float, radians
        Lab azimuth of the direction the axis leans to: 0 leans toward +x
        (along the detector columns: seen as a tilt in the projections),
        π/2 toward +y (along the beam: nearly invisible in parallel beam).
    offset : (3,) array, length, lab xyz
        A point of the true axis (a shift of the axis; its component along
        the axis has no effect).

    Returns
    -------
    rotvecs, translations : (n_views, 3) float64 arrays
        Radians and length units. Zero tilt and zero offset give zero poses.
    """
    a = _angles(angles)
    tau = as_finite(tilt, "tilt", error=GeometryError)
    phi = as_finite(tilt_azimuth, "tilt_azimuth", error=GeometryError)
    o = as_vec3(offset, "offset")
    n_ax = _tilted_axis(tau, phi)
    Q = Rotation.from_rotvec(np.outer(-a, n_ax))
    Binv = _table(a).inv()  # Rz(θ_k)
    R = Binv * Q
    t = Binv.apply(o - Q.apply(o))
    return R.as_rotvec().reshape(-1, 3), t.reshape(-1, 3)


def precession_poses(
    angles,
    *,
    amplitude: float,
    phase: float = 0.0,
    cycles_per_turn: float = 1.0,
    pivot=(0.0, 0.0, 0.0),
):
    """Poses of a wobbling table: its axis precesses about z.

    At view ``k`` the table (and the sample on it) is tipped by
    ``amplitude`` so that its axis, nominally z, leans toward the lab azimuth
    ``ψ_k = phase + cycles_per_turn · θ_k``, about the lab point ``pivot``
    (e.g. the bearing). The tipping is the rotation ``W_k`` by ``amplitude``
    about the horizontal lab axis ``m_k = (-sin ψ_k, cos ψ_k, 0)``, applied
    after the nominal turn: the sample point ``x`` is at ``W_k (B_k x - p) + p``,
    so by eq. (1)

        R_k = B_kᵀ W_k B_k = rotation by ``amplitude`` about Rz(θ_k) m_k,
        t_k = B_kᵀ (p - W_k p).

    ``cycles_per_turn = 0`` is a fixed tilted axis: exactly
    ``combine_poses((W.rotvec, p - W p), tilted_axis_poses(angles,
    tilt=amplitude, tilt_azimuth=phase, offset=p - W p))``, i.e. the tilted
    axis after a constant pose (a global rigid motion, unobservable);
    ``cycles_per_turn = -1`` turns the lean with the table, i.e. the
    sample is merely mounted tilted (a constant pose: no error at all).
    Other values (default 1: once per turn, the other way) are periodic
    rotation errors of period ``2π / |cycles_per_turn + 1|`` in the sample
    frame.

    Parameters
    ----------
    angles : (n_views,) array, radians
    amplitude : float, radians
        Half-angle of the precession cone.
    phase : float, radians
        Lean azimuth at θ = 0.
    cycles_per_turn : float
        Turns of the lean direction in the lab per turn of θ.
    pivot : (3,) array, length, lab xyz
        Fixed point of the wobble.

    Returns
    -------
    rotvecs, translations : (n_views, 3) float64 arrays
    """
    a = _angles(angles)
    amp = as_finite(amplitude, "amplitude", error=GeometryError)
    ph = as_finite(phase, "phase", error=GeometryError)
    cyc = as_finite(cycles_per_turn, "cycles_per_turn", error=GeometryError)
    p = as_vec3(pivot, "pivot")
    psi = ph + cyc * a
    m = np.column_stack([-np.sin(psi), np.cos(psi), np.zeros_like(psi)])
    W = Rotation.from_rotvec(amp * m)
    return lab_motion_to_poses(a, W.as_rotvec(), p - W.apply(p))


def drift_poses(
    times,
    angles,
    *,
    velocity=(0.0, 0.0, 0.0),
    acceleration=(0.0, 0.0, 0.0),
    rot_rate=(0.0, 0.0, 0.0),
    pivot=(0.0, 0.0, 0.0),
):
    """Poses of a slow drift of the set-up in the lab (e.g. thermal).

    At time ``τ_k`` the sample has moved in the lab by
    ``y -> Ω_k (y - p) + p + d_k`` with ``d_k = velocity·τ_k +
    acceleration·τ_k²/2`` and ``Ω_k`` the rotation by ``rot_rate·τ_k``
    (rotation vector) about the lab point ``p``; zero motion at τ = 0. By
    eq. (1): ``R_k = B_kᵀ Ω_k B_k``, ``t_k = B_kᵀ (p - Ω_k p + d_k)``.

    Parameters
    ----------
    times : (n_views,) array, time units (e.g. s)
        Acquisition time of each view.
    angles : (n_views,) array, radians
        Nominal scan angle of each view (needed to express the lab drift in
        the turning sample frame).
    velocity : (3,) array, length / time, lab xyz
    acceleration : (3,) array, length / time², lab xyz
    rot_rate : (3,) array, radians / time, lab rotation vector per unit time
    pivot : (3,) array, length, lab xyz

    Returns
    -------
    rotvecs, translations : (n_views, 3) float64 arrays
    """
    tt = _angles(times, "times")
    a = _angles(angles)
    if tt.shape != a.shape:
        raise ShapeError(f"times and angles must have the same shape, got {tt.shape} and {a.shape}")
    v = as_vec3(velocity, "velocity")
    acc = as_vec3(acceleration, "acceleration")
    w = as_vec3(rot_rate, "rot_rate")
    p = as_vec3(pivot, "pivot")
    d = np.outer(tt, v) + 0.5 * np.outer(tt**2, acc)
    Om = Rotation.from_rotvec(np.outer(tt, w))
    return lab_motion_to_poses(a, Om.as_rotvec(), p - Om.apply(p) + d)


def jolt_poses(
    angles,
    *,
    at,
    translations,
    rotvecs=None,
    frame: str = "lab",
    pivot=(0.0, 0.0, 0.0),
):
    """Poses of sudden steps (backlash, a knock) that persist afterwards.

    Jolt ``j`` happens just before view ``at[j]`` and is the rigid step
    ``y -> J_j (y - p) + p + translations[j]`` (``J_j`` the rotation of
    ``rotvecs[j]`` about the point ``p``). From view ``at[j]`` on it is
    composed after the earlier jolts (in order of ``at``; equal views in the
    given order).

    * ``frame="lab"``: the set-up moved; the step is fixed in the lab and
      turned into sample-frame poses by eq. (1) (in the sample frame it
      turns with θ).
    * ``frame="sample"``: the sample slipped on its holder; the step is fixed
      in the sample frame and is the pose itself (``p`` in sample xyz).

    Parameters
    ----------
    angles : (n_views,) array, radians
        Nominal scan angles (their number is the number of views).
    at : (n_jolts,) ints
        View index of each jolt, ``0 <= at < n_views``.
    translations : (n_jolts, 3) array, length, xyz of ``frame``
    rotvecs : (n_jolts, 3) array, radians, optional
    frame : {"lab", "sample"}
    pivot : (3,) array, length

    Returns
    -------
    rotvecs, translations : (n_views, 3) float64 arrays
    """
    a = _angles(angles)
    n = a.size
    if frame not in ("lab", "sample"):
        raise GeometryError(f"frame must be 'lab' or 'sample', got {frame!r}")
    at_arr = np.atleast_1d(np.asarray(at))
    if at_arr.ndim != 1 or at_arr.dtype.kind not in "iu":
        raise ShapeError(f"at must be a 1D array of view indices (ints), got {at!r}")
    if np.any(at_arr < 0) or np.any(at_arr >= n):
        raise ShapeError(f"at must hold view indices in [0, {n}), got {at_arr.tolist()}")
    m = at_arr.size
    tr = np.asarray(translations, np.float64)
    if tr.ndim == 1:
        tr = tr[None, :]
    if tr.shape != (m, 3):
        raise ShapeError(f"translations must have shape ({m}, 3) (one per jolt in at), got {np.shape(translations)}")
    rv = np.zeros((m, 3)) if rotvecs is None else np.asarray(rotvecs, np.float64)
    if rv.ndim == 1:
        rv = rv[None, :]
    if rv.shape != (m, 3):
        raise ShapeError(f"rotvecs must have shape ({m}, 3) (one per jolt in at), got {np.shape(rotvecs)}")
    if not (np.all(np.isfinite(tr)) and np.all(np.isfinite(rv))):
        raise GeometryError("translations and rotvecs must be finite")
    p = as_vec3(pivot, "pivot")
    # the cumulated step before each view
    step_rv, step_t = np.zeros((n, 3)), np.zeros((n, 3))
    for j in np.argsort(at_arr, kind="stable"):
        Jr = Rotation.from_rotvec(rv[j])
        jt = p - Jr.apply(p) + tr[j]
        sel = slice(int(at_arr[j]), n)
        step_rv[sel], step_t[sel] = compose_poses(rv[j], jt, step_rv[sel], step_t[sel])
    if frame == "sample":
        return step_rv, step_t
    return lab_motion_to_poses(a, step_rv, step_t)


def combine_poses(*pose_pairs) -> tuple[np.ndarray, np.ndarray]:
    """Exact composition of several per-view poses; the first is applied first.

    ``combine_poses(P1, P2, ..., Pm)`` is ``x -> Pm(...P2(P1(x)))`` per view,
    each ``P = (rotvecs, translations)`` with arrays ``(n_views, 3)`` (or
    ``(3,)``, shared by all views). For poses built from lab motions by
    eq. (1) this is the lab motion of P1 followed by that of P2, etc.: e.g.
    ``combine_poses(tilted_axis_poses(...), drift_poses(...))`` is a tilted
    axis whose whole set-up also drifts.

    Returns
    -------
    rotvecs, translations : float64 arrays
    """
    if not pose_pairs:
        raise ShapeError("combine_poses needs at least one (rotvecs, translations) pair")
    pairs = []
    for k, pair in enumerate(pose_pairs):
        try:
            rv, t = pair
        except (TypeError, ValueError):
            raise ShapeError(f"pose_pairs[{k}] must be a (rotvecs, translations) pair") from None
        rv, t = np.asarray(rv, np.float64), np.asarray(t, np.float64)
        if rv.shape[-1:] != (3,) or t.shape[-1:] != (3,) or rv.ndim > 2 or t.ndim > 2:
            raise ShapeError(
                f"pose_pairs[{k}] must hold arrays of shape (n_views, 3) or (3,), got {rv.shape} and {t.shape}"
            )
        pairs.append((rv, t))
    try:
        n = np.broadcast_shapes(*[p[0].shape for p in pairs], *[p[1].shape for p in pairs])
    except ValueError:
        raise ShapeError(
            "pose_pairs must all have the same number of views, got shapes "
            f"{[(p[0].shape, p[1].shape) for p in pairs]}"
        ) from None
    # writable copies throughout: scipy's Rotation.apply refuses read-only buffers
    rv_acc, t_acc = np.broadcast_to(pairs[0][0], n).copy(), np.broadcast_to(pairs[0][1], n).copy()
    for rv, t in pairs[1:]:
        rv_acc, t_acc = compose_poses(np.broadcast_to(rv, n).copy(), np.broadcast_to(t, n).copy(), rv_acc, t_acc)
    return np.asarray(rv_acc, np.float64), np.asarray(t_acc, np.float64)
