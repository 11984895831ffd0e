"""What moved, from the per-view poses (pdvc.calibration.describe_motion).

Known answers: motions are injected with the simulate helpers (whose lab
convention is tested in tests/simulate) and read back in the lab frame.
The checks of the detector displacements go through an independent route:
the nominal scan at angle θ is the θ = 0 scanner looking at a sample turned
by Rz(-θ), so a sample point is projected from its lab position with the
θ = 0 geometry, never through ``apply_poses``.
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation

from pdvc.calibration import MotionSummary, describe_motion, offset_poses
from pdvc.errors import GeometryError, InputTypeError, ShapeError
from pdvc.geometry import VolumeGeometry, circular_cone, compose_poses, parallel
from pdvc.simulate import combine_poses, drift_poses, jolt_poses, precession_poses, tilted_axis_poses

ANGLES = np.linspace(0, 2 * np.pi, 144, endpoint=False) + 0.05
DEG = np.pi / 180
VOL = VolumeGeometry((40, 32, 32), voxel_size=0.1)
SOD, ODD, PIXEL, SHAPE = 100.0, 60.0, 0.16, (48, 64)


def _geom(kind, angles=ANGLES):
    if kind == "cone":
        return circular_cone(angles, sod=SOD, odd=ODD, det_shape=SHAPE, pixel=PIXEL)
    return parallel(angles, det_shape=SHAPE, pixel=PIXEL)


def _scale(kind):
    """Detector pixels per length unit at the nominal axis."""
    return ((SOD + ODD) / SOD if kind == "cone" else 1.0) / PIXEL


KINDS = ["cone", "parallel"]


# -- (a) axis offset ---------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("delta", [0.037, -0.12])
def test_pure_axis_offset(kind, delta):
    geom = _geom(kind)
    rv, t = tilted_axis_poses(ANGLES, tilt=0.0, offset=(delta, 0.0, 0.0))
    m = describe_motion(geom, rv, t, VOL)
    # float64 pose arithmetic and a linear least-squares fit: ~1e-15 of the lengths
    assert abs(m.offset - delta) < 1e-9
    assert abs(m.offset_beam) < 1e-9
    assert abs(m.roll_deg) < 1e-9 and abs(m.pitch_deg) < 1e-9
    assert_allclose(m.axis_direction, [0, 0, 1], atol=1e-12)
    assert m.offset_px == pytest.approx(delta * _scale(kind), abs=1e-8)
    assert m.precession_max_deg < 1e-9
    assert_allclose(m.drift_velocity, 0, atol=1e-12)
    assert m.jolts.size == 0


@pytest.mark.parametrize("kind", KINDS)
def test_offset_px_is_the_projected_axis_column(kind):
    """offset_px is where the θ = 0 scanner sees the fitted axis point, minus the centre column."""
    geom = _geom(kind)
    rv, t = tilted_axis_poses(ANGLES, tilt=0.0, offset=(0.05, 0.0, 0.0))
    m = describe_motion(geom, rv, t, VOL)
    col = _geom(kind, np.zeros(1)).project_points(m.axis_point[None])[0, 0, 1]
    assert m.offset_px == pytest.approx(col - (SHAPE[1] - 1) / 2, abs=1e-9)


@pytest.mark.parametrize("kind", KINDS)
def test_offset_poses_agree_with_the_summary(kind):
    """The coarse initialiser's poses read back as the same pixel offset (one convention)."""
    geom = _geom(kind)
    m = describe_motion(geom, *offset_poses(geom, -7.25), VOL)
    assert m.offset_px == pytest.approx(-7.25, abs=1e-9)
    assert abs(m.roll_deg) < 1e-9 and abs(m.pitch_deg) < 1e-9


# -- (b) tilted axis ---------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("azimuth, roll, pitch", [(0.0, 0.5, 0.0), (np.pi / 2, 0.0, 0.5), (np.pi, -0.5, 0.0)])
def test_tilted_axis(kind, azimuth, roll, pitch):
    geom = _geom(kind)
    o = np.array([0.03, -0.02, 0.4])
    rv, t = tilted_axis_poses(ANGLES, tilt=0.5 * DEG, tilt_azimuth=azimuth, offset=o)
    m = describe_motion(geom, rv, t, VOL)
    assert m.roll_deg == pytest.approx(roll, abs=1e-3)
    assert m.pitch_deg == pytest.approx(pitch, abs=1e-3)
    n = m.axis_direction
    # the axis point: on the true axis, at the height of the volume centre (0 here)
    want = o + (0.0 - o[2]) / n[2] * n
    assert_allclose(m.axis_point, want, atol=1e-9)
    assert m.offset == pytest.approx(want[0], abs=1e-9)
    assert m.precession_max_deg < 1e-6


def test_tilted_axis_180_degree_scan():
    angles = np.linspace(0, np.pi, 181)
    geom = _geom("parallel", angles)
    rv, t = tilted_axis_poses(angles, tilt=0.5 * DEG, offset=(0.02, 0.0, 0.0))
    m = describe_motion(geom, rv, t, VOL)
    assert m.roll_deg == pytest.approx(0.5, abs=1e-3)
    assert m.offset == pytest.approx(0.02, abs=1e-9)


# -- (c) precession ----------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("amplitude", [0.1, 0.4])
def test_precession_amplitude(kind, amplitude):
    geom = _geom(kind)
    rv, t = precession_poses(ANGLES, amplitude=amplitude * DEG, phase=0.7, pivot=(0.0, 0.0, -1.5))
    m = describe_motion(geom, rv, t, VOL)
    assert m.precession_rms_deg == pytest.approx(amplitude, rel=0.05)
    assert m.precession_max_deg == pytest.approx(amplitude, rel=0.05)
    # a full-turn precession leaves the mean axis vertical
    assert abs(m.roll_deg) < 0.05 * amplitude and abs(m.pitch_deg) < 0.05 * amplitude
    assert m.jolts.size == 0


def test_sample_mounted_tilted_is_no_precession():
    """cycles_per_turn = -1 is a constant pose (the sample sits tilted): nothing wobbles."""
    rv, t = precession_poses(ANGLES, amplitude=1.0 * DEG, cycles_per_turn=-1.0)
    m = describe_motion(_geom("cone"), rv, t, VOL)
    assert m.precession_max_deg < 1e-6
    assert abs(m.roll_deg) < 1e-6 and abs(m.pitch_deg) < 1e-6


# -- (d) drift ---------------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
def test_linear_drift_velocity_exact(kind):
    rng = np.random.default_rng(3)
    times = np.cumsum(rng.uniform(0.8, 1.2, ANGLES.size)) + 5.0
    v = np.array([2e-4, -1e-4, 3e-4])
    geom = _geom(kind)
    drift = drift_poses(times, ANGLES, velocity=v)
    axis = tilted_axis_poses(ANGLES, tilt=0.3 * DEG, offset=(0.04, 0.0, 0.0))
    m = describe_motion(geom, *combine_poses(axis, drift), VOL, times=times)
    assert_allclose(m.drift_velocity, v, rtol=0, atol=1e-12)
    assert_allclose(m.drift_total, v * np.ptp(times), atol=1e-10)
    # drift_poses moves the set-up from time 0; the summary's axis is the one at the mean time
    assert_allclose(m.drift, np.outer(times - times.mean(), v), atol=1e-10)
    # the true axis carried by the drift to the mean time, cut at the height of the centre (0)
    o = np.array([0.04, 0.0, 0.0]) + v * times.mean()
    n = m.axis_direction
    assert m.offset == pytest.approx(o[0] - o[2] / n[2] * n[0], abs=1e-9)
    assert m.roll_deg == pytest.approx(0.3, abs=1e-6)
    assert m.jolts.size == 0


def test_drift_per_view_without_times():
    v = np.array([1e-4, 0.0, -2e-4])
    rv, t = drift_poses(np.arange(ANGLES.size, dtype=float), ANGLES, velocity=v)
    m = describe_motion(_geom("cone"), rv, t, VOL)
    assert_allclose(m.drift_velocity, v, atol=1e-13)
    assert m.drift_total_px == pytest.approx(np.hypot(v[0], v[2]) * (ANGLES.size - 1) * _scale("cone"), rel=1e-9)


def test_table_spin_drift_is_a_twist_not_a_wobble():
    w = 2e-5  # rad per view about lab z
    rv, t = drift_poses(np.arange(ANGLES.size, dtype=float), ANGLES, rot_rate=(0.0, 0.0, w))
    m = describe_motion(_geom("cone"), rv, t, VOL)
    # second order only (twist x fitted tilt): (w · n_views)² rad
    assert m.precession_max_deg < 1e-5
    slope = np.polyfit(np.arange(ANGLES.size), np.radians(m.spin_error_deg), 1)[0]
    assert slope == pytest.approx(w, rel=1e-6)


# -- (e) jolts ---------------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
def test_translation_jolt_flagged(kind):
    geom = _geom(kind)
    rng = np.random.default_rng(7)
    px = 1 / _scale(kind)  # length of one pixel at the axis
    base = combine_poses(
        tilted_axis_poses(ANGLES, tilt=0.2 * DEG, offset=(0.05, 0.0, 0.0)),
        jolt_poses(ANGLES, at=[37], translations=[(0.6 * px, 0.0, 0.3 * px)]),
    )
    noise = (rng.normal(0, 1e-4, (ANGLES.size, 3)), rng.normal(0, 0.01 * px, (ANGLES.size, 3)))
    m = describe_motion(geom, *compose_poses(*noise, *base), VOL)
    assert m.jolts.tolist() == [37]
    assert m.translation_jumps[37] == pytest.approx(np.hypot(0.6, 0.3) * px, rel=0.1)


def test_rotation_jolt_flagged_and_smooth_motion_is_not():
    geom = _geom("cone")
    slip = jolt_poses(ANGLES, at=[90], translations=[(0.0, 0.0, 0.0)], rotvecs=[(0.2 * DEG, 0.0, 0.0)], frame="sample")
    smooth = precession_poses(ANGLES, amplitude=0.3 * DEG)
    m = describe_motion(geom, *combine_poses(smooth, slip), VOL)
    assert 90 in m.jolts.tolist()
    assert set(m.jolts.tolist()) <= {90}
    assert m.rotation_jumps_deg[90] == pytest.approx(0.2, rel=0.2)
    assert describe_motion(geom, *smooth, VOL).jolts.size == 0


def test_jolts_follow_acquisition_order():
    """With times in reverse order, the jump is reached going backwards: the later-acquired view is flagged."""
    geom = _geom("parallel")
    times = np.arange(ANGLES.size, dtype=float)[::-1].copy()
    rv, t = jolt_poses(ANGLES, at=[60], translations=[(0.05, 0.0, 0.0)])
    m = describe_motion(geom, rv, t, VOL, times=times)
    assert m.jolts.tolist() == [59]


# -- (f) detector displacements ----------------------------------------------------
def _independent_projection(kind, angles, rv, t, points):
    """(row, col) of sample points: lab position Rz(-θ)(R p + t), projected with the θ = 0 scanner."""
    g0 = _geom(kind, np.zeros(1))
    B = Rotation.from_rotvec(np.outer(-angles, [0, 0, 1]))
    R = Rotation.from_rotvec(rv)
    out = np.empty((angles.size, len(points), 2))
    for k in range(angles.size):
        lab = B[k].apply(R[k].apply(points) + t[k])
        out[k] = g0.project_points(lab)[0]
    return out


@pytest.mark.parametrize("kind", KINDS)
def test_detector_displacements_of_the_axis_points(kind):
    vol = VolumeGeometry((40, 32, 32), voxel_size=0.1, offset=(0.1, -0.05, 0.2))
    rv, t = combine_poses(
        tilted_axis_poses(ANGLES, tilt=0.4 * DEG, tilt_azimuth=0.3, offset=(0.05, 0.02, 0.0)),
        precession_poses(ANGLES, amplitude=0.2 * DEG),
        drift_poses(np.arange(ANGLES.size, dtype=float), ANGLES, velocity=(1e-4, 5e-5, -1e-4)),
    )
    m = describe_motion(_geom(kind), rv, t, vol)
    c = np.array([0.1, -0.05, 0.2])
    half = 0.5 * 40 * 0.1
    pts = np.array([c + [0, 0, 0.9 * half], c, c - [0, 0, 0.9 * half]])
    assert_allclose(m.points, pts, atol=1e-15)
    zero = np.zeros_like(rv)
    want = _independent_projection(kind, ANGLES, rv, t, pts) - _independent_projection(kind, ANGLES, zero, zero, pts)
    assert_allclose(m.det_shift_top, want[:, 0], atol=1e-8)
    assert_allclose(m.det_shift_center, want[:, 1], atol=1e-8)
    assert_allclose(m.det_shift_bottom, want[:, 2], atol=1e-8)
    rms = np.sqrt(np.mean(np.sum(want**2, axis=2), axis=0))
    assert_allclose(m.det_shift_rms, rms, rtol=1e-9)
    assert np.all(rms > 0.1)  # a real motion, not a vacuous comparison


# -- invariances, outputs and errors -----------------------------------------------
def test_lab_quantities_do_not_depend_on_the_gauge():
    geom = _geom("cone")
    rv, t = combine_poses(
        tilted_axis_poses(ANGLES, tilt=0.4 * DEG, tilt_azimuth=1.0, offset=(0.05, 0.0, 0.0)),
        precession_poses(ANGLES, amplitude=0.2 * DEG),
        drift_poses(np.arange(ANGLES.size, dtype=float), ANGLES, velocity=(1e-4, 0.0, 2e-4)),
    )
    a = describe_motion(geom, rv, t, VOL)
    g_rv, g_t = np.array([0.01, -0.02, 0.3]), np.array([0.1, -0.2, 0.05])
    n = ANGLES.size
    b = describe_motion(geom, *compose_poses(rv, t, np.tile(g_rv, (n, 1)), np.tile(g_t, (n, 1))), VOL)
    assert_allclose(b.axis_direction, a.axis_direction, atol=1e-10)
    assert_allclose(b.axis_point, a.axis_point, atol=1e-9)
    assert_allclose(b.wobble_deg, a.wobble_deg, atol=1e-8)
    assert_allclose(b.drift_velocity, a.drift_velocity, atol=1e-10)


def test_zero_motion_reads_as_nothing():
    n = ANGLES.size
    m = describe_motion(_geom("cone"), np.zeros((n, 3)), np.zeros(3), VOL)
    assert m.offset == pytest.approx(0, abs=1e-12) and m.offset_px == pytest.approx(0, abs=1e-10)
    assert m.precession_max_deg < 1e-9 and m.jolts.size == 0
    assert_allclose(m.det_shift_rms, 0, atol=1e-12)
    assert_allclose(m.center_shift, 0, atol=1e-12)


def test_as_dict_and_describe():
    geom = _geom("cone")
    rv, t = combine_poses(
        tilted_axis_poses(ANGLES, tilt=0.5 * DEG, offset=(0.05, 0.0, 0.0)),
        jolt_poses(ANGLES, at=[37], translations=[(0.05, 0.0, 0.0)]),
    )
    m = describe_motion(geom, rv, t, VOL)
    assert isinstance(m, MotionSummary) and m.n_views == ANGLES.size
    d = m.as_dict()
    for key in ("axis_direction", "roll_deg", "pitch_deg", "offset", "offset_px", "precession_rms_deg",
                "drift", "drift_velocity", "jolts", "det_shift_top", "det_shift_rms", "conventions"):
        assert key in d
    for key, value in d.items():
        assert isinstance(value, (np.ndarray, float, int, str)), (key, type(value))
    assert d["jolts"].dtype.kind == "i"
    d["drift"][0] = 99.0  # a copy: the summary is untouched
    assert m.drift[0, 0] != 99.0
    with pytest.raises(ValueError):
        m.drift[0, 0] = 1.0  # read-only
    lines = m.describe()
    assert isinstance(lines, list) and all(isinstance(s, str) for s in lines)
    text = "\n".join(lines)
    assert "roll +0.5000 deg" in text and "jolts at views [37]" in text


def test_input_errors():
    geom = _geom("cone")
    n = ANGLES.size
    z = np.zeros((n, 3))
    with pytest.raises(ShapeError, match="rotvecs"):
        describe_motion(geom, np.zeros((n - 1, 3)), z, VOL)
    with pytest.raises(ShapeError, match="translations"):
        describe_motion(geom, z, np.zeros((n, 2)), VOL)
    with pytest.raises(ShapeError, match="times"):
        describe_motion(geom, z, z, VOL, times=np.arange(3.0))
    with pytest.raises(ShapeError, match="angles"):
        describe_motion(geom, z, z, VOL, angles=np.zeros(2))
    with pytest.raises(InputTypeError, match="geom_nominal"):
        describe_motion(geom.vectors, z, z, VOL)
    with pytest.raises(InputTypeError, match="vol_geom"):
        describe_motion(geom, z, z, (32, 32, 32))
    with pytest.raises(GeometryError, match="distinct angles"):
        describe_motion(_geom("cone", np.zeros(4)), np.zeros((4, 3)), np.zeros(3), VOL)
    with pytest.raises(GeometryError, match="finite"):
        describe_motion(geom, np.full((n, 3), np.nan), z, VOL)
