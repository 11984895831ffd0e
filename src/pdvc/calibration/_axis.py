"""What moved: the rotation axis, precession, drift and jolts, read off the per-view poses.

The poses ``x -> R_k x + t_k`` of the sample relative to the nominal
geometry (``DESIGN.md`` §1) are written in the sample frame, which turns
with the table. What a user asks ("is my axis tilted, off-centre, wobbling?
did the set-up drift?") is about the **lab**. This module expresses every
pose in the lab frame of its view and fits the motion of an ideal table,
a rotation about one fixed axis, to it; what the fit does not explain is
precession (orientation), drift and jolts (position).

Lab frame (:func:`pdvc.correlation.lab_frames`): ``x`` along the detector
columns, ``y`` along the beam (source to detector), ``z`` up the detector
rows, with its origin at the origin of the volume frame (on the nominal
rotation axis). ``F_k`` maps lab components to sample components; a sample
point ``x`` sits nominally at the lab position ``F_kᵀ x`` and really at

    ``y_k(x) = A_k x + l_k``,   ``A_k = F_kᵀ R_k``,   ``l_k = F_kᵀ t_k``.

For the nominal circular scans ``F_kᵀ = Rz(-θ_k)``: the table turns by
``-θ_k`` about ``+z`` (:mod:`pdvc.simulate.motion`).

The ideal table turns about the lab axis ``n`` through the lab point ``o``:

    ``A_k ≈ Q_k A_0``,   ``y_k(x*) ≈ Q_k a + o + v (τ_k - τ̄)``,
    ``Q_k`` = rotation by ``-θ_k`` about ``n``,

fitted in two steps: ``n, A_0`` by non-linear least squares on the
rotation vectors of ``Q_k A_0 A_kᵀ`` (exact on SO(3)), then ``a, o, v``
linearly from the lab positions of one material point ``x*`` (``v`` the
linear drift, ``τ`` the acquisition times, ``τ̄`` their mean). ``x*`` is
the point that sits, on average, at the nominal rotation centre. The
direction of ``n`` is that of :func:`pdvc.simulate.tilted_axis_poses`
(``+z`` for a perfect scan).

The axis, its offset, the precession and the drift are invariant under
the gauge (a global rigid motion of the volume frame,
:func:`pdvc.geometry.fix_gauge`); the detector displacements of sample
points are not (they move with the reconstruction), so pass gauge-fixed
poses when they are compared between runs.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .._arrays import frozen, per_view_vectors
from ..correlation import lab_frames
from ..errors import GeometryError, InputTypeError, ShapeError
from ..geometry import VectorGeometry, VolumeGeometry

__all__ = ["MotionSummary", "describe_motion"]

log = logging.getLogger(__name__)

_MAD_TO_SIGMA = 1.4826  # MAD of a normal distribution -> its standard deviation


@dataclass(frozen=True, eq=False)
class MotionSummary:
    """What moved during a scan, in the lab frame (all arrays read-only).

    Lengths are in the unit of the geometry ("volume units"), detector
    displacements in pixels, angles in **degrees** (this is a user-facing
    summary). Views are in the order of the geometry; "per view" arrays
    have ``n_views`` rows.

    Attributes
    ----------
    kind : {"cone", "parallel"}
    angles : (n_views,) float64, radians
        Nominal scan angles used in the fit.
    times : (n_views,) float64, time units
        Acquisition times (view index when none were given).
    axis_direction : (3,) float64, lab xyz, unit
        Mean rotation axis ``n`` (``+z`` for a perfect scan).
    roll_deg : float, degrees
        Tilt of the axis within the detector plane,
        ``atan2(n_x, n_z)``: positive when the axis leans toward ``+x``
        (larger column indices) going up (toward larger row indices),
        i.e. the projection of the axis is rotated on the detector.
    pitch_deg : float, degrees
        Tilt of the axis in the plane of the beam, ``atan2(n_y, n_z)``:
        positive when it leans toward ``+y`` going up, i.e. its top leans
        away from the source, toward the detector. Nearly invisible in
        parallel beam; in cone beam it makes top and bottom rows disagree.
    axis_point : (3,) float64, lab xyz, length
        The point of the mean axis at the height of the volume centre
        (the rotation centre), at the mean acquisition time (a linear drift
        moves the axis with the sample; see ``drift_velocity``).
    offset : float, length
        Lateral offset of the axis at the rotation centre, the lab ``x``
        of ``axis_point``: positive toward larger detector columns.
    offset_px : float, pixels
        ``offset`` on the detector at the magnification of ``axis_point``:
        for a nominal circular scan with a centred detector it is the
        column of the projected axis minus ``(n_cols - 1)/2``, the
        convention of :func:`pdvc.calibration.estimate_axis_offset`.
    offset_beam : float, length
        The lab ``y`` of ``axis_point`` (along the beam; in cone beam a
        change of magnification, in parallel beam unobservable).
    magnification : float
        Source-to-detector over source-to-``axis_point`` distance, mean over
        views (1 for parallel beam).
    pixel_size : float, length
        Mean detector column pitch ``|u|``.
    axis_per_view : (n_views, 3) float64, lab xyz, unit
        The mean axis carried by each view's orientation error
        ``E_k = A_k (Q_k A_0)ᵀ``: where the table's axis pointed at view k.
    wobble_deg : (n_views,) float64, degrees
        Angle between ``axis_per_view`` and ``axis_direction``.
    precession_rms_deg, precession_max_deg : float, degrees
        RMS and maximum of ``wobble_deg``: the precession amplitude. For
        :func:`pdvc.simulate.precession_poses` (``cycles_per_turn=1``)
        this is its ``amplitude``.
    spin_error_deg : (n_views,) float64, degrees
        Twist of ``E_k`` about the mean axis (right-handed about
        ``axis_direction``): how far the sample turned about the axis beyond
        the ideal turn. The nominal turn is by ``-θ`` about the axis, so a
        positive value means the table lagged behind its nominal angle by
        that much (up to a constant absorbed by ``A_0``).
    axis_fit_rms_deg : float, degrees
        RMS angle of ``E_k`` (everything the ideal rotation leaves over).
    center : (3,) float64, sample xyz, length
        The volume centre ``c``.
    tracked_point : (3,) float64, sample xyz, length
        The sample's centre of rotation: the material point that sits, on
        average over the views, at the nominal rotation centre (lab
        ``(0, 0, h)``, ``h`` the height of the volume centre). Its lab
        trajectory gives the axis position and the drift; being defined in
        the lab, it is the same piece of sample whatever the gauge.
    center_shift : (n_views, 3) float64, lab xyz, length
        Lab position of the volume centre minus its nominal lab position
        (raw: includes its circle about an off-centre axis).
    drift : (n_views, 3) float64, lab xyz, length
        Lab position of the tracked point minus where the ideal rotation
        about the mean axis puts it: the linear drift ``v (τ_k - τ̄)``
        (zero at the mean time ``τ̄``) plus what no model term explains
        (jolts, wobble of the position).
    drift_velocity : (3,) float64, lab xyz, length per time unit
        ``v``: per view when no times were given.
    drift_total : (3,) float64, lab xyz, length
        ``v (τ_max - τ_min)``.
    drift_total_px : float, pixels
        Norm of the ``x, z`` components of ``drift_total`` on the detector
        (at the magnification of the centre).
    jolts : (n_jumps,) int64
        Views (indices into the geometry) reached by a sudden step: the
        jump of the lab position (``drift``) or of the orientation error
        (``E_k``) from the previous view in acquisition order exceeds
        ``median + k·σ`` of all jumps (σ = 1.4826·MAD) and ``jolt_min_px``.
    translation_jumps : (n_views,) float64, length
        ``|drift_k - drift_prev|`` (0 at the first acquired view).
    rotation_jumps_deg : (n_views,) float64, degrees
        Angle of ``E_k E_prevᵀ`` (0 at the first acquired view).
    points : (3, 3) float64, sample xyz, length
        Top, centre and bottom of the volume on its axis: the volume centre
        shifted by ``+0.9, 0, -0.9`` of the half height along z.
    det_shift_top, det_shift_center, det_shift_bottom : (n_views, 2) float64, pixels
        ``(row, col)`` where the calibrated geometry projects the point
        minus where the nominal one does (paper Figs 6 and 14).
    det_shift_rms : (3,) float64, pixels
        RMS over views of the length of each of those displacements (top,
        centre, bottom).
    """

    kind: str
    angles: np.ndarray
    times: np.ndarray
    axis_direction: np.ndarray
    roll_deg: float
    pitch_deg: float
    axis_point: np.ndarray
    offset: float
    offset_px: float
    offset_beam: float
    magnification: float
    pixel_size: float
    axis_per_view: np.ndarray
    wobble_deg: np.ndarray
    precession_rms_deg: float
    precession_max_deg: float
    spin_error_deg: np.ndarray
    axis_fit_rms_deg: float
    center: np.ndarray
    tracked_point: np.ndarray
    center_shift: np.ndarray
    drift: np.ndarray
    drift_velocity: np.ndarray
    drift_total: np.ndarray
    drift_total_px: float
    jolts: np.ndarray
    translation_jumps: np.ndarray
    rotation_jumps_deg: np.ndarray
    points: np.ndarray
    det_shift_top: np.ndarray
    det_shift_center: np.ndarray
    det_shift_bottom: np.ndarray
    det_shift_rms: np.ndarray

    @property
    def n_views(self) -> int:
        return self.angles.shape[0]

    def as_dict(self) -> dict:
        """Plain mapping for the report and HDF5: arrays, floats, ints and a conventions string."""
        out = {}
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            out[name] = np.array(value) if isinstance(value, np.ndarray) else value
        out["n_views"] = self.n_views
        out["conventions"] = (
            "lab frame: x along detector columns, y along the beam (source to detector), z up the rows; "
            "roll = atan2(n_x, n_z) > 0 leaning to +x, pitch = atan2(n_y, n_z) > 0 leaning to +y (away from "
            "the source); offset = lab x of the axis at the height of the volume centre, > 0 toward larger "
            "columns; detector shifts (row, col) calibrated minus nominal, pixels; angles in degrees"
        )
        return out

    def describe(self) -> list[str]:
        """A few human-readable lines (a list of str)."""
        n = self.axis_direction
        lines = [
            f"mean rotation axis: roll {self.roll_deg:+.4f} deg, pitch {self.pitch_deg:+.4f} deg "
            f"(lab direction {n[0]:+.5f}, {n[1]:+.5f}, {n[2]:+.5f})",
            f"axis offset at the rotation centre: {self.offset:+.5g} (length) = {self.offset_px:+.3f} px "
            f"along the detector columns; {self.offset_beam:+.5g} along the beam",
            f"precession (axis wobble about the mean): RMS {self.precession_rms_deg:.4f} deg, "
            f"max {self.precession_max_deg:.4f} deg",
            "drift of the sample: velocity ({:+.3g}, {:+.3g}, {:+.3g}) per time unit, total ({:+.3g}, {:+.3g}, "
            "{:+.3g}) = {:.3f} px on the detector".format(*self.drift_velocity, *self.drift_total, self.drift_total_px),
            (f"jolts at views {self.jolts.tolist()}" if self.jolts.size else "no jolts detected"),
            "detector displacement of the volume's top, centre and bottom points, calibrated minus nominal "
            "geometry (RMS over views): top {:.3f} px, centre {:.3f} px, bottom {:.3f} px (includes the placement "
            "of the reconstruction under the gauge of the poses, zero mean pose over the views in a calibration; "
            "the axis offset is above)".format(*self.det_shift_rms),
        ]
        return lines

    def __str__(self) -> str:
        title = f"What moved ({self.kind} beam, {self.n_views} views):"
        return "\n".join([title] + ["  " + line for line in self.describe()])

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(kind={self.kind!r}, n_views={self.n_views}, roll_deg={self.roll_deg:+.4g}, "
            f"pitch_deg={self.pitch_deg:+.4g}, offset_px={self.offset_px:+.4g}, "
            f"precession_rms_deg={self.precession_rms_deg:.4g}, drift_total_px={self.drift_total_px:.4g}, "
            f"jolts={int(self.jolts.size)})"
        )


def _frozen(a) -> np.ndarray:
    return frozen(np.array(a, dtype=np.float64))


_per_view = per_view_vectors


def _vector(value, n: int, name: str, unit: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (n,):
        raise ShapeError(f"{name} must have shape ({n},) (one per view, {unit}), got {np.shape(value)}")
    if not np.all(np.isfinite(arr)):
        raise GeometryError(f"{name} must be finite {unit}")
    return arr


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _orthonormal_pair(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


def _fit_axis(A: Rotation, theta: np.ndarray, order: np.ndarray) -> tuple[np.ndarray, Rotation]:
    """Least-squares ``n, A_0`` with ``A_k ≈ Rot(n, -θ_k) A_0`` (rotation-vector residuals)."""
    # first guess: the axes of the view-to-view increments, D_k ≈ Rot(n, -Δθ_k)
    Ao, tho = A[order], theta[order]
    dth = _wrap(np.diff(tho))
    use = (np.abs(dth) > 1e-9) & (np.abs(dth) < np.pi / 2)
    n0 = np.array([0.0, 0.0, 1.0])
    if np.any(use):
        inc = (Ao[1:] * Ao[:-1].inv()).as_rotvec()[use]
        m = -(inc * dth[use, None]).sum(axis=0)
        if np.linalg.norm(m) > 1e-12:
            n0 = m / np.linalg.norm(m)
    e1, e2 = _orthonormal_pair(n0)
    A0_init = (Rotation.from_rotvec(theta[:, None] * n0) * A).mean()

    def unpack(p):
        n = n0 + p[0] * e1 + p[1] * e2
        return n / np.linalg.norm(n), Rotation.from_rotvec(p[2:]) * A0_init

    def residual(p):
        n, A0 = unpack(p)
        Q = Rotation.from_rotvec(-theta[:, None] * n)
        return ((Q * A0) * A.inv()).as_rotvec().ravel()

    sol = least_squares(residual, np.zeros(5), method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    n, A0 = unpack(sol.x)
    log.debug("axis fit: %d evaluations, rms %.3g rad", sol.nfev, np.sqrt(np.mean(sol.fun**2)))
    return n, A0


def _twist(E: Rotation, n: np.ndarray) -> np.ndarray:
    """Signed angle of the twist of each rotation about ``n`` (swing–twist split), radians."""
    q = E.as_quat()  # x, y, z, w
    return _wrap(2.0 * np.arctan2(q[:, :3] @ n, q[:, 3]))


def _magnification(geom: VectorGeometry, points_sample: np.ndarray) -> np.ndarray:
    """Per-view magnification of one sample point per view, ``(n_views,)``."""
    if geom.kind != "cone":
        return np.ones(geom.n_views)
    N = geom.det_normal
    src = geom.src
    sdd = np.einsum("ij,ij->i", geom.det_center - src, N)
    sod = np.einsum("ij,ij->i", points_sample - src, N)
    return sdd / sod


def _jumps(values, order: np.ndarray, *, rotations: bool) -> np.ndarray:
    """Jump from the previous view in acquisition order, per view (0 at the first).

    ``values`` is an ``(n_views, 3)`` array of positions, or a ``Rotation`` of
    ``n_views`` orientations when ``rotations`` (the jump is then an angle).
    """
    out = np.zeros(len(order))
    if len(order) < 2:
        return out
    if rotations:
        step = (values[order[1:]] * values[order[:-1]].inv()).magnitude()
    else:
        step = np.linalg.norm(values[order[1:]] - values[order[:-1]], axis=1)
    out[order[1:]] = step
    return out


def _flag(jumps: np.ndarray, order: np.ndarray, k: float, floor: float) -> set[int]:
    d = jumps[order[1:]]
    if d.size == 0:
        return set()
    med = float(np.median(d))
    sigma = _MAD_TO_SIGMA * float(np.median(np.abs(d - med)))
    hit = (d > med + k * sigma) & (d > floor)
    return {int(i) for i in order[1:][hit]}


def describe_motion(
    geom_nominal: VectorGeometry,
    rotvecs,
    translations,
    vol_geom: VolumeGeometry,
    *,
    angles=None,
    times=None,
    jolt_threshold: float = 6.0,
    jolt_min_px: float = 0.1,
) -> MotionSummary:
    """Rotation axis, precession, drift and jolts of a scan, from its per-view poses.

    Parameters
    ----------
    geom_nominal : VectorGeometry
        The nominal geometry the poses are relative to (the calibrated one
        is ``geom_nominal.apply_poses(rotvecs, translations)``).
    rotvecs : (n_views, 3) or (3,) array, radians
        Sample-frame rotation of each pose (axis x angle).
    translations : (n_views, 3) or (3,) array, length, sample xyz
    vol_geom : VolumeGeometry
        The reconstruction grid: its centre is the point whose drift is
        reported, its height places the top and bottom points.
    angles : (n_views,) array, radians, optional
        Nominal scan angles. Default: read off the nominal geometry as
        ``atan2(x_lab,y, x_lab,x)`` of its lab frames (exact for
        :func:`pdvc.geometry.circular_cone` and :func:`pdvc.geometry.parallel`).
    times : (n_views,) array, time units, optional
        Acquisition time of each view; sets the acquisition order (for the
        jumps) and the unit of ``drift_velocity``. Default: the view index.
    jolt_threshold : float
        ``k``: a jump is a jolt above ``median + k·σ`` of all jumps.
    jolt_min_px : float, pixels
        And above this many detector pixels (at the magnification of the
        centre; rotations times the radius of the volume's corner), so that
        a perfectly smooth motion, whose jumps all agree, flags nothing.

    Returns
    -------
    MotionSummary

    Examples
    --------
    >>> import numpy as np
    >>> from pdvc.geometry import VolumeGeometry, circular_cone
    >>> from pdvc.simulate import tilted_axis_poses
    >>> angles = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    >>> geom = circular_cone(angles, sod=100, odd=100, det_shape=(64, 64), pixel=0.2)
    >>> rv, t = tilted_axis_poses(angles, tilt=np.deg2rad(0.5), offset=(0.05, 0, 0))
    >>> m = describe_motion(geom, rv, t, VolumeGeometry((32, 32, 32), 0.2))
    >>> round(m.roll_deg, 6), round(m.offset, 9), round(m.offset_px, 6)
    (0.5, 0.05, 0.5)
    """
    if not isinstance(geom_nominal, VectorGeometry):
        raise InputTypeError(f"geom_nominal must be a pdvc.VectorGeometry, got {type(geom_nominal).__name__}")
    if not isinstance(vol_geom, VolumeGeometry):
        raise InputTypeError(f"vol_geom must be a pdvc.VolumeGeometry, got {type(vol_geom).__name__}")
    n = geom_nominal.n_views
    rv = _per_view(rotvecs, n, "rotvecs")
    tr = _per_view(translations, n, "translations")
    F = lab_frames(geom_nominal)  # sample = F lab
    theta_geom = np.arctan2(F[:, 1, 0], F[:, 0, 0])
    if angles is None:
        theta = theta_geom
    else:
        theta = _vector(angles, n, "angles", "radians")
        worst = float(np.max(np.abs(_wrap(theta - theta_geom))))
        if worst > 1e-3:
            log.warning(
                "angles differ from the nominal geometry's scan angles by up to %.3g deg (radians expected); "
                "the axis fit uses the given angles",
                np.degrees(worst),
            )
    tau = np.arange(n, dtype=np.float64) if times is None else _vector(times, n, "times", "time units")
    if not (np.isfinite(jolt_threshold) and jolt_threshold > 0):
        raise GeometryError(f"jolt_threshold must be a positive number, got {jolt_threshold!r}")
    if not (np.isfinite(jolt_min_px) and jolt_min_px >= 0):
        raise GeometryError(f"jolt_min_px must be a non-negative number of pixels, got {jolt_min_px!r}")
    spread = np.ptp(np.stack([np.cos(theta), np.sin(theta)]), axis=1).max() if n > 1 else 0.0
    if spread < 1e-6:
        raise GeometryError(
            f"describe_motion needs views at two or more distinct angles to fit a rotation axis, got {n} view(s) "
            "at one angle"
        )
    order = np.argsort(tau, kind="stable")

    Ft = Rotation.from_matrix(np.transpose(F, (0, 2, 1)))  # lab <- sample (nominal)
    A = Ft * Rotation.from_rotvec(rv)
    l = Ft.apply(tr)

    # -- orientation: mean axis, per-view error ---------------------------------
    axis, A0 = _fit_axis(A, theta, order)
    Q = Rotation.from_rotvec(-theta[:, None] * axis)
    E = A * (Q * A0).inv()
    axis_k = E.apply(axis)
    wobble = np.arccos(np.clip(axis_k @ axis, -1.0, 1.0))
    spin = _twist(E, axis)

    # -- position: axis line, drift -------------------------------------------
    c = np.asarray(vol_geom.offset, np.float64)
    y_nom = Ft.apply(c)  # nominal lab position of the volume centre
    height = float(np.mean(y_nom[:, 2]))
    # The tracked material point: the one that sits, on average over the views,
    # at the nominal rotation centre (lab (0, 0, height)). Unlike the volume
    # centre it is the same piece of sample whatever the gauge of the poses.
    rc = np.array([0.0, 0.0, height])
    x_star = np.mean(A.inv().apply(rc - l), axis=0)
    y = A.apply(x_star) + l  # its true lab positions
    dt = tau - float(np.mean(tau))
    Qm = Q.as_matrix()
    eye = np.broadcast_to(np.eye(3), (n, 3, 3))
    M = np.concatenate([Qm, eye, dt[:, None, None] * eye], axis=2).reshape(3 * n, 9)
    sol, _, rank, _ = np.linalg.lstsq(M, y.reshape(-1), rcond=None)
    if rank < 8:
        log.warning("axis position and drift are poorly determined (rank %d of 8): too few or too close angles", rank)
    a_vec, o, v = sol[:3], sol[3:6], sol[6:9]
    if abs(axis[2]) > 1e-6:
        axis_point = o + (height - o[2]) / axis[2] * axis
    else:  # a horizontal axis: the point closest to the nominal centre
        axis_point = o + ((np.array([0.0, 0.0, height]) - o) @ axis) * axis
    drift = y - Q.apply(a_vec) - o

    # -- detector scale ---------------------------------------------------------
    pitch_u = np.linalg.norm(geom_nominal.u, axis=1)
    axis_sample = np.einsum("nij,j->ni", F, axis_point)
    mag_axis = _magnification(geom_nominal, axis_sample)
    offset = float(axis_point[0])
    offset_px = float(np.mean(offset * mag_axis / pitch_u))
    mag_c = _magnification(geom_nominal, np.broadcast_to(c, (n, 3)))
    px_len = float(np.mean(pitch_u / mag_c))  # length per pixel at the centre
    drift_total = v * (tau.max() - tau.min())

    # -- jolts -------------------------------------------------------------------
    radius = 0.5 * float(np.linalg.norm(vol_geom.extent_xyz))
    t_jumps = _jumps(drift, order, rotations=False)
    r_jumps = _jumps(E, order, rotations=True)
    jolts = _flag(t_jumps, order, jolt_threshold, jolt_min_px * px_len) | _flag(
        r_jumps, order, jolt_threshold, jolt_min_px * px_len / radius
    )

    # -- detector displacements of three axis points -----------------------------
    half = 0.5 * float(vol_geom.extent_xyz[2])
    pts = c + np.array([[0.0, 0.0, 0.9 * half], [0.0, 0.0, 0.0], [0.0, 0.0, -0.9 * half]])
    calibrated = geom_nominal.apply_poses(rv, tr)
    shift = calibrated.project_points(pts) - geom_nominal.project_points(pts)  # (n, 3, 2)
    rms = np.sqrt(np.mean(np.sum(shift**2, axis=2), axis=0))

    summary = MotionSummary(
        kind=geom_nominal.kind,
        angles=_frozen(theta),
        times=_frozen(tau),
        axis_direction=_frozen(axis),
        roll_deg=float(np.degrees(np.arctan2(axis[0], axis[2]))),
        pitch_deg=float(np.degrees(np.arctan2(axis[1], axis[2]))),
        axis_point=_frozen(axis_point),
        offset=offset,
        offset_px=offset_px,
        offset_beam=float(axis_point[1]),
        magnification=float(np.mean(mag_axis)),
        pixel_size=float(np.mean(pitch_u)),
        axis_per_view=_frozen(axis_k),
        wobble_deg=_frozen(np.degrees(wobble)),
        precession_rms_deg=float(np.degrees(np.sqrt(np.mean(wobble**2)))),
        precession_max_deg=float(np.degrees(wobble.max())),
        spin_error_deg=_frozen(np.degrees(spin)),
        axis_fit_rms_deg=float(np.degrees(np.sqrt(np.mean(E.magnitude() ** 2)))),
        center=_frozen(c),
        tracked_point=_frozen(x_star),
        center_shift=_frozen(A.apply(c) + l - y_nom),
        drift=_frozen(drift),
        drift_velocity=_frozen(v),
        drift_total=_frozen(drift_total),
        drift_total_px=float(np.hypot(drift_total[0], drift_total[2]) / px_len),
        jolts=np.array(sorted(jolts), dtype=np.int64),
        translation_jumps=_frozen(t_jumps),
        rotation_jumps_deg=_frozen(np.degrees(r_jumps)),
        points=_frozen(pts),
        det_shift_top=_frozen(shift[:, 0]),
        det_shift_center=_frozen(shift[:, 1]),
        det_shift_bottom=_frozen(shift[:, 2]),
        det_shift_rms=_frozen(rms),
    )
    summary.jolts.setflags(write=False)
    log.info("motion: %s", "; ".join(summary.describe()))
    return summary
