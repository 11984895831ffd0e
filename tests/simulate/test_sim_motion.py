"""Per-view poses of lab-scanner motions (pdvc.simulate.motion).

The checks go through the geometry (``apply_poses`` and ``project_points``)
and an independent statement of the lab: the nominal circular scan at angle
θ is the θ = 0 scanner seen from a sample turned by ``Rz(-θ)``, so a lab
motion is checked by projecting lab positions with the θ = 0 geometry.
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation

from pdvc.errors import GeometryError, ShapeError
from pdvc.geometry import circular_cone, compose_poses, parallel
from pdvc.simulate import (
    EllipsoidPhantom,
    combine_poses,
    drift_poses,
    jolt_poses,
    lab_motion_to_poses,
    poses_to_lab_motion,
    precession_poses,
    project_analytic,
    tilted_axis_poses,
)

ANGLES = np.linspace(0, 2 * np.pi, 37)[:-1] + 0.1
# Pure float64 geometry: agreement to ~1e-12 of the lengths; 1e-8 pixel is
# far above round-off and far below what any convention error would do
# (it moves points by a sizeable fraction of the motion: tenths of pixels).
PX_TOL = 1e-8


def _geoms(angles):
    kw = dict(det_shape=(40, 50), pixel=0.05)
    return {
        "cone": (circular_cone(angles, sod=10.0, odd=5.0, **kw), circular_cone(np.zeros_like(angles), sod=10.0, odd=5.0, **kw)),
        "parallel": (parallel(angles, **kw), parallel(np.zeros_like(angles), **kw)),
    }


def _lab_position(angles, rv, t, x):
    """Lab position B_k (R_k x + t_k) of sample point x, B_k = Rz(-θ_k)."""
    B = Rotation.from_rotvec(np.outer(-angles, [0, 0, 1]))
    return B.apply(Rotation.from_rotvec(rv).apply(x) + t)


@pytest.mark.parametrize("kind", ["cone", "parallel"])
def test_nominal_lab_convention(kind):
    """Sanity of the convention all poses rely on: the nominal geometry at θ
    sees sample point x where the θ = 0 geometry sees Rz(-θ) x."""
    geom, lab = _geoms(ANGLES)[kind]
    x = np.array([[0.3, -0.2, 0.4]])
    zero = np.zeros((len(ANGLES), 3))
    lab_pos = _lab_position(ANGLES, zero, zero, x[0])
    got = geom.project_points(x)[:, 0]
    want = np.stack([lab[k].project_points(lab_pos[k : k + 1])[0, 0] for k in range(len(ANGLES))])
    assert_allclose(got, want, atol=PX_TOL)


def test_tilted_axis_zero_is_identity():
    rv, t = tilted_axis_poses(ANGLES, tilt=0.0)
    assert rv.shape == t.shape == (36, 3)
    assert_allclose(rv, 0, atol=1e-14)
    assert_allclose(t, 0, atol=1e-14)


@pytest.mark.parametrize("kind", ["cone", "parallel"])
def test_points_on_the_true_axis_stay_fixed(kind):
    tilt, az, off = 0.03, 0.4, np.array([0.12, -0.05, 0.3])
    rv, t = tilted_axis_poses(ANGLES, tilt=tilt, tilt_azimuth=az, offset=off)
    geom, _ = _geoms(ANGLES)[kind]
    true = geom.apply_poses(rv, t)
    n = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
    on_axis = off + np.array([-0.5, 0.0, 0.7])[:, None] * n
    rc = true.project_points(on_axis)  # (views, points, 2)
    assert_allclose(rc, np.broadcast_to(rc[:1], rc.shape), atol=PX_TOL)
    # ... while with the nominal geometry they move (the test can fail)
    nominal = geom.project_points(on_axis)
    assert np.ptp(nominal[:, 1, 1]) > 0.5


@pytest.mark.parametrize("kind", ["cone", "parallel"])
def test_a_ball_follows_the_tilted_circle(kind):
    tilt, az, off = 0.05, 1.1, np.array([-0.1, 0.2, 0.0])
    rv, t = tilted_axis_poses(ANGLES, tilt=tilt, tilt_azimuth=az, offset=off)
    geom, lab = _geoms(ANGLES)[kind]
    x = np.array([0.4, 0.1, 0.3])
    n = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
    # independent statement: the ball turns by -θ about n through off
    circle = Rotation.from_rotvec(np.outer(-ANGLES, n)).apply(x - off) + off
    got = geom.apply_poses(rv, t).project_points(x[None])[:, 0]
    want = np.stack([lab[k].project_points(circle[k : k + 1])[0, 0] for k in range(len(ANGLES))])
    assert_allclose(got, want, atol=PX_TOL)


def test_tilted_ball_shadow_centroid_end_to_end():
    """Analytic projection with the true geometry: the shadow of a small
    ball (parallel beam, so the centroid of the shadow is the projected
    centre) sits where the tilted-axis circle puts the ball."""
    angles = ANGLES[::4]
    tilt, az, off = 0.08, 0.0, np.array([0.05, 0.0, 0.0])
    rv, t = tilted_axis_poses(angles, tilt=tilt, tilt_azimuth=az, offset=off)
    geom, lab = _geoms(angles)["parallel"]
    x = np.array([0.3, 0.2, 0.25])
    ball = EllipsoidPhantom(1.0, x, (0.15, 0.15, 0.15))
    p = project_analytic(ball, geom.apply_poses(rv, t), supersampling=4).astype(np.float64)
    rows, cols = np.mgrid[: p.shape[1], : p.shape[2]]
    mass = p.sum(axis=(1, 2))
    centroid = np.stack([(p * rows).sum(axis=(1, 2)) / mass, (p * cols).sum(axis=(1, 2)) / mass], axis=1)
    n = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    circle = Rotation.from_rotvec(np.outer(-angles, n)).apply(x - off) + off
    want = np.stack([lab[k].project_points(circle[k : k + 1])[0, 0] for k in range(len(angles))])
    # the shadow (radius 3 pixels) is sampled with 4 x 4 sub-rays per pixel:
    # the centroid of the sampled disk is off by well under 0.01 pixel
    assert_allclose(centroid, want, atol=0.01)
    # the tilt is visible: the ball's row changes over the turn by ~ 2 * 0.3 * sin(0.08) / 0.05 px
    assert np.ptp(centroid[:, 0]) > 0.5


def test_precession_static_is_a_tilted_axis():
    """cycles_per_turn = 0 is a fixed tilt: the tilted axis through
    o = p - W p, after the constant pose x -> W x + (p - W p)."""
    amp, phase, pivot = 0.02, 0.7, np.array([0.1, -0.3, -0.8])
    rv, t = precession_poses(ANGLES, amplitude=amp, phase=phase, cycles_per_turn=0.0, pivot=pivot)
    m = np.array([-np.sin(phase), np.cos(phase), 0.0])
    W = Rotation.from_rotvec(amp * m)
    o = pivot - W.apply(pivot)
    tilted = tilted_axis_poses(ANGLES, tilt=amp, tilt_azimuth=phase, offset=o)
    want = combine_poses((W.as_rotvec(), o), tilted)
    assert_allclose(rv, want[0], atol=1e-12)
    assert_allclose(t, want[1], atol=1e-12)


def test_precession_axis_direction_and_period():
    amp, phase = 0.01, 0.3
    rv, t = precession_poses(ANGLES, amplitude=amp, phase=phase)  # once per turn
    L, _ = poses_to_lab_motion(ANGLES, rv, t)
    # the sample's (= table's) axis leans by amp toward azimuth phase + θ in the lab
    B = Rotation.from_rotvec(np.outer(-ANGLES, [0, 0, 1]))
    axis_lab = (B * Rotation.from_rotvec(rv)).apply([0, 0, 1])
    psi = phase + ANGLES
    want = np.column_stack([np.sin(amp) * np.cos(psi), np.sin(amp) * np.sin(psi), np.full_like(psi, np.cos(amp))])
    assert_allclose(axis_lab, want, atol=1e-12)
    assert_allclose(np.linalg.norm(L, axis=1), amp, atol=1e-12)
    # in the sample frame the error has period 2π / |1 + 1| = π
    half = len(ANGLES) // 2
    assert_allclose(rv[:half], rv[half:], atol=1e-12)
    # co-rotating lean (-1) is only a mounting tilt: constant poses
    rv1, t1 = precession_poses(ANGLES, amplitude=amp, cycles_per_turn=-1.0, pivot=(0, 0, 0.5))
    assert_allclose(rv1, np.broadcast_to(rv1[0], rv1.shape), atol=1e-12)
    assert_allclose(t1, np.broadcast_to(t1[0], t1.shape), atol=1e-12)


@pytest.mark.parametrize("kind", ["cone", "parallel"])
def test_drift_gives_the_stated_lab_displacement(kind):
    times = np.arange(len(ANGLES)) * 2.0
    vel, acc = np.array([1e-3, -2e-3, 5e-4]), np.array([0.0, 1e-5, -2e-5])
    rv, t = drift_poses(times, ANGLES, velocity=vel, acceleration=acc)
    x = np.array([0.2, -0.1, 0.3])
    d = np.outer(times, vel) + 0.5 * np.outer(times**2, acc)
    nominal_lab = Rotation.from_rotvec(np.outer(-ANGLES, [0, 0, 1])).apply(x)
    assert_allclose(_lab_position(ANGLES, rv, t, x) - nominal_lab, d, atol=1e-14)
    # and the geometry sees it there
    geom, lab = _geoms(ANGLES)[kind]
    got = geom.apply_poses(rv, t).project_points(x[None])[:, 0]
    want = np.stack([lab[k].project_points((nominal_lab + d)[k : k + 1])[0, 0] for k in range(len(ANGLES))])
    assert_allclose(got, want, atol=PX_TOL)


def test_drift_rotation_about_pivot():
    times = np.linspace(0, 100, len(ANGLES))
    w, pivot = np.array([0.0, 1e-4, 2e-4]), np.array([0.0, 0.0, -2.0])
    rv, t = drift_poses(times, ANGLES, rot_rate=w, pivot=pivot)
    x = np.array([0.3, 0.1, 0.5])
    y = Rotation.from_rotvec(np.outer(-ANGLES, [0, 0, 1])).apply(x)
    want = Rotation.from_rotvec(np.outer(times, w)).apply(y - pivot) + pivot
    assert_allclose(_lab_position(ANGLES, rv, t, x), want, atol=1e-14)
    # the pivot itself does not move
    B = Rotation.from_rotvec(np.outer(-ANGLES, [0, 0, 1]))
    p_sample = B.inv().apply(pivot)
    lab_pivot = B.apply(Rotation.from_rotvec(rv).apply(p_sample) + t)
    assert_allclose(lab_pivot, np.broadcast_to(pivot, lab_pivot.shape), atol=1e-14)


def test_jolts_step_and_persist():
    n = len(ANGLES)
    steps = np.array([[0.01, 0.0, 0.0], [0.0, -0.02, 0.005]])
    rv, t = jolt_poses(ANGLES, at=[10, 25], translations=steps)
    x = np.array([0.1, 0.2, -0.3])
    nominal_lab = Rotation.from_rotvec(np.outer(-ANGLES, [0, 0, 1])).apply(x)
    disp = _lab_position(ANGLES, rv, t, x) - nominal_lab
    want = np.zeros((n, 3))
    want[10:] += steps[0]
    want[25:] += steps[1]
    assert_allclose(disp, want, atol=1e-14)
    # a rotational jolt in the sample frame (the sample slipped): constant pose afterwards
    rvs, ts = jolt_poses(ANGLES, at=[5], translations=[0.0, 0.01, 0.0], rotvecs=[0.0, 0.0, 0.02], frame="sample")
    assert_allclose(rvs[:5], 0, atol=0)
    assert_allclose(rvs[5:], np.broadcast_to([0, 0, 0.02], (n - 5, 3)), atol=1e-15)
    assert_allclose(ts[5:], np.broadcast_to([0, 0.01, 0], (n - 5, 3)), atol=1e-15)


def test_combine_order_and_lab_round_trip(rng):
    n = len(ANGLES)
    p1 = (rng.normal(scale=0.1, size=(n, 3)), rng.normal(scale=0.1, size=(n, 3)))
    p2 = (rng.normal(scale=0.1, size=(n, 3)), rng.normal(scale=0.1, size=(n, 3)))
    rv, t = combine_poses(p1, p2)
    x = rng.normal(size=3)
    after1 = Rotation.from_rotvec(p1[0]).apply(x) + p1[1]
    after2 = Rotation.from_rotvec(p2[0]).apply(after1) + p2[1]
    assert_allclose(Rotation.from_rotvec(rv).apply(x) + t, after2, atol=1e-13)
    # (3,) poses broadcast; one pose is itself
    rvb, tb = combine_poses(p1, ([0, 0, 0.1], [1.0, 0, 0]))
    assert rvb.shape == (n, 3)
    assert_allclose(combine_poses(p1)[0], p1[0])
    # lab <-> sample conversions are inverse to each other
    L, lt = poses_to_lab_motion(ANGLES, *p1)
    back = lab_motion_to_poses(ANGLES, L, lt)
    assert_allclose(back[0], p1[0], atol=1e-12)
    assert_allclose(back[1], p1[1], atol=1e-12)
    # composing lab motions = composing their poses in the same order
    q1, q2 = lab_motion_to_poses(ANGLES, *p1), lab_motion_to_poses(ANGLES, *p2)
    lab_composed = compose_poses(p2[0], p2[1], p1[0], p1[1])
    want = lab_motion_to_poses(ANGLES, *lab_composed)
    got = combine_poses(q1, q2)
    assert_allclose(got[0], want[0], atol=1e-12)
    assert_allclose(got[1], want[1], atol=1e-12)


def test_bad_inputs_name_the_parameter():
    with pytest.raises(ShapeError, match="angles"):
        tilted_axis_poses(np.zeros((3, 2)), tilt=0.1)
    with pytest.raises(GeometryError, match="tilt"):
        tilted_axis_poses(ANGLES, tilt=np.nan)
    with pytest.raises(ShapeError, match="offset"):
        tilted_axis_poses(ANGLES, tilt=0.1, offset=(1, 2))
    with pytest.raises(ShapeError, match="times and angles"):
        drift_poses(np.arange(3.0), ANGLES, velocity=(1, 0, 0))
    with pytest.raises(ShapeError, match="at"):
        jolt_poses(ANGLES, at=[len(ANGLES)], translations=[1, 0, 0])
    with pytest.raises(ShapeError, match="translations"):
        jolt_poses(ANGLES, at=[1, 2], translations=[1, 0, 0])
    with pytest.raises(GeometryError, match="frame"):
        jolt_poses(ANGLES, at=[1], translations=[1, 0, 0], frame="stage")
    with pytest.raises(ShapeError, match="same number of views"):
        combine_poses((np.zeros((3, 3)), np.zeros((3, 3))), (np.zeros((4, 3)), np.zeros((4, 3))))
    with pytest.raises(ShapeError, match="pose_pairs"):
        combine_poses((np.zeros(3),))
