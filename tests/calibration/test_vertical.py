"""The vertical motion of a parallel scan from the registration of its row sums (``RowSumConsistency.vertical_motion``).

Known answers: a cast-iron rod three times longer than the volume (exact line
integrals of ellipsoids, ``pdvc.simulate.simulate_scan``, Poisson noise; no
voxel projector) turns over half a turn while it drifts up with acceleration,
or jumps up once (a jolt), or stays still on a tilted axis. The row sums'
registration must give the vertical motion; the calibration starts there and
its smooth stages hold it (``docs/method.md`` §5.35).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation
import pytest
from numpy.testing import assert_allclose

import pdvc
from pdvc.calibration import RowSumConsistency, Stage, VerticalMotion, jolt_stage, offset_poses, run_stages
from pdvc.calibration._driver import hold_vertical
from pdvc.calibration._pipeline import VERTICAL_MIN_F, VERTICAL_MIN_RMS_PX, _with_vertical
from pdvc.geometry import Poses, fix_gauge, parallel, reprojection_error, sample_points
from pdvc.simulate import cast_iron_phantom, combine_poses, drift_poses, jolt_poses, simulate_scan, tilted_axis_poses

N = 40
ANGLES = np.linspace(0.0, np.pi, 120, endpoint=False)
GEOM = parallel(ANGLES, det_shape=(48, 56), pixel=1.0)
VG = pdvc.VolumeGeometry((N, N, N))
ROD = cast_iron_phantom(0.36 * N, 3 * N, n_nodules=440, seed=5)
AXIS = tilted_axis_poses(ANGLES, tilt=0.0, offset=(1.1, 0.0, 0.0))
DRIFT = combine_poses(AXIS, drift_poses(np.linspace(0.0, 1.0, ANGLES.size), ANGLES, velocity=[0.5, 0.3, 1.2],
                                        acceleration=[-0.6, 0.4, -0.9]))
JOLT = combine_poses(AXIS, jolt_poses(ANGLES, at=np.array([70]), translations=[[0.3, 0.0, 0.8]]))
STILL = tilted_axis_poses(ANGLES, tilt=np.deg2rad(0.5), offset=(1.1, 0.0, 0.0))


def _scan(poses, i0, seed=1):
    return simulate_scan(ROD, GEOM, rotvecs=poses[0], translations=poses[1], i0=i0, seed=seed,
                         supersampling=2).projections


def _vertical(poses) -> np.ndarray:
    z = Poses(*poses).lab_params(GEOM, VG.offset)[:, 2]
    return z - z.mean()


def _rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


@pytest.mark.parametrize("i0, tol", [(2e3, 0.04), (2e4, 0.02)])
def test_a_drift_with_acceleration_is_measured(i0, tol):
    # measured: 0.019 px at i0 2e3 (a view's shift alone 0.13 px), 0.009 px at 2e4, of a motion of 0.22 px RMS
    vm = RowSumConsistency(_scan(DRIFT, i0), GEOM).vertical_motion()
    assert isinstance(vm, VerticalMotion) and vm.steps.size == 0
    assert _rms(vm.translation - _vertical(DRIFT)) < tol
    assert vm.f_stat > 4 * VERTICAL_MIN_F and 0.7 < vm.misfit < 1.3, vm


@pytest.mark.parametrize("air", [0.05, 0.15])
def test_an_air_level_that_drifts_does_not_move_the_sample(air):
    # an air level rising 0 -> air over the scan, plus a ramp across the columns that flips halfway (as
    # bench_accuracy.py --air): each row sum gains a constant per view, and a rod's mass profile, cut by the field, has
    # ends that differ: a registration of the shift alone read 0.15 px (air 0.05) and 0.50 px (0.15) of false motion
    p = _scan(DRIFT, 2e4)
    k = np.arange(p.shape[0])[:, None, None]
    u = np.linspace(-1.0, 1.0, p.shape[2])[None, None, :]
    p_air = p + (air * k / p.shape[0] + air / 3 * u * np.where(k < p.shape[0] // 2, 1.0, -1.0)).astype(np.float32)
    vm = RowSumConsistency(p_air, GEOM).vertical_motion()
    assert _rms(vm.translation - _vertical(DRIFT)) < 0.02


@pytest.mark.parametrize("i0, seed", [(2e4, 1), (2e3, 1), (2e3, 3)])
def test_a_jolt_is_a_step_of_the_fit(i0, seed):
    # 0.8 px up at view 70: 4-7 standard deviations of the views' shifts at i0 2e3 (measured 0.004-0.03 px), many more at 2e4
    vm = RowSumConsistency(_scan(JOLT, i0, seed), GEOM).vertical_motion()
    assert vm.steps.tolist() == [70]
    assert _rms(vm.translation - _vertical(JOLT)) < (0.02 if i0 > 1e4 else 0.05)


def test_a_still_sample_on_a_tilted_axis_holds_nothing():
    p = _scan(STILL, 2e4)
    rs = RowSumConsistency(p, GEOM, offset_px=1.1)
    vm = rs.vertical_motion()
    assert vm.f_stat < VERTICAL_MIN_F or _rms(vm.translation) < VERTICAL_MIN_RMS_PX, vm
    start = offset_poses(GEOM, 1.1)
    poses, held, jolts, text = _with_vertical(start, rs, GEOM, VG, False)
    assert poses is start and held == () and len(jolts) == 0 and "not used" in text


def test_the_start_and_what_the_stages_hold():
    p = _scan(DRIFT, 2e4)
    rs = RowSumConsistency(p, GEOM, offset_px=1.1)
    start = offset_poses(GEOM, 1.1)
    poses, held, jolts, text = _with_vertical(start, rs, GEOM, VG, False)
    assert held == ("tz",) and len(jolts) == 0 and "the stages start there and hold it" in text, text
    lab0, lab1 = start.lab_params(GEOM, VG.offset), poses.lab_params(GEOM, VG.offset)
    v = rs.vertical_motion().translation
    assert rs.vertical_motion() is rs.vertical_motion() and not v.flags.writeable  # measured once, shared read-only
    assert_allclose(lab1[:, 2] - lab0[:, 2], v - v[0], atol=1e-12)  # relative to the first view (hold_vertical)
    assert_allclose(np.delete(lab1, 2, axis=1), np.delete(lab0, 2, axis=1), atol=1e-12)
    # a region-of-interest scan: the row sums miss what lies outside the field
    assert _with_vertical(start, rs, GEOM, VG, True) == (start, (), (), "")
    # a stage of a smooth model leaves a held parameter where it started; the jolt stage is not held
    st = Stage(name="m", basis="drift", frame="lab", fixed=("rx", "ry", "rz"), until="rounds", rounds=1, scale=2, guards=())
    out = run_stages(p, GEOM, VG, [st], noise_variance=1e-4, poses=poses, held=held)
    lab2 = out.poses.lab_params(GEOM, VG.offset)
    assert_allclose(lab2[:, 2] - lab2[:, 2].mean(), lab1[:, 2] - lab1[:, 2].mean(), atol=1e-9)
    assert _rms(lab2[:, 0] - lab1[:, 0]) > 1e-3  # what it does not hold moved
    free = run_stages(p, GEOM, VG, [st], noise_variance=1e-4, poses=poses)
    assert _rms(np.diff(free.poses.lab_params(GEOM, VG.offset)[:, 2])) > 1e-5


@pytest.mark.slow
def test_a_rod_drifting_at_low_dose_is_calibrated_with_the_held_vertical_motion(monkeypatch):
    """The drifting rod at i0 2e3: the stages' volumes fit the noise and their rounds walk the vertical motion away.

    Measured (2 threads, 7-10 s each): 0.052 px without holding it, 0.022 px held.
    """
    from pdvc.calibration import _pipeline

    p = _scan(DRIFT, 2e3)
    pts = sample_points(VG, 5, fraction=0.6)
    truth = GEOM.apply_poses(*fix_gauge(*DRIFT, GEOM, center=VG.offset))
    res = pdvc.calibrate(p, GEOM, VG)
    assert "the stages start there and hold it" in res.options["vertical_motion"]
    err = reprojection_error(res.geometry, truth, pts).rms
    monkeypatch.setattr(_pipeline, "VERTICAL_MIN_F", np.inf)
    free = pdvc.calibrate(p, GEOM, VG)
    assert "not used" in free.options["vertical_motion"]
    err_free = reprojection_error(free.geometry, truth, pts).rms
    assert err < 0.035 and err_free > 1.8 * err, (err, err_free)


def test_the_steps_of_the_vertical_motion_are_jolts_the_jolt_stage_frees():
    p = _scan(JOLT, 2e4)
    rs = RowSumConsistency(p, GEOM, offset_px=1.1)
    poses, held, jolts, text = _with_vertical(offset_poses(GEOM, 1.1), rs, GEOM, VG, False)
    assert held == ("tz",) and list(jolts) == [70] and "steps at views 70" in text, text
    model = Stage(name="m", basis="fourier:1", frame="sample", fixed=("rz",), rounds=1, scale=2)
    st = jolt_stage(model).replace(rounds=1)
    out = run_stages(p, GEOM, VG, [st], noise_variance=1e-4, poses=poses, held=held, known_jolts=jolts)
    assert out.stages[0].rounds == 1  # not skipped: the stage frees a step at views 69-71
    lab0, lab1 = poses.lab_params(GEOM, VG.offset), out.poses.lab_params(GEOM, VG.offset)
    assert _rms(lab1[:, 0] - lab0[:, 0]) > 1e-3  # the jolt stage holds nothing: across the beam too


def test_a_full_turn_holds_it_too_and_its_warm_up_keeps_the_sample_in_place():
    # a full turn: the rounds walked a rod's vertical position away there too (docs/method.md §5.36). Holding it on the
    # real 360° neutron scan (psi-neutron360) once let the warm-up drift the sample along the beam by 39 length units:
    # the lab frame of the increments was the nominal one, so the start's tilt gave the translation along the rays a
    # curvature of its own; read in the posed axes it is a null direction, and the warm-up leaves it where it started
    from pdvc.calibration import tilt_poses, warmup_stage

    angles = np.linspace(0.0, 2 * np.pi, 120, endpoint=False)
    geom = parallel(angles, det_shape=(48, 56), pixel=1.0)
    poses = combine_poses(tilted_axis_poses(angles, tilt=0.0, offset=(1.1, 0.0, 0.0)),
                          drift_poses(np.linspace(0.0, 1.0, angles.size), angles, velocity=[0.5, 0.3, 1.2]))
    p = simulate_scan(ROD, geom, rotvecs=poses[0], translations=poses[1], i0=2e4, seed=1, supersampling=2).projections
    rs = RowSumConsistency(p, geom, offset_px=1.1)
    start = tilt_poses(geom, roll=np.deg2rad(0.4), pitch=np.deg2rad(1.5), offset_px=1.1)  # a start off the truth
    held_poses, held, _, text = _with_vertical(start, rs, geom, VG, False)
    assert held == ("tz",) and "the stages start there and hold it" in text, text
    model = Stage(name="m", basis="fourier:1", frame="sample", fixed=("rz",), rounds=2, scale=1)
    st = warmup_stage(model, scale=1, rounds=1)
    out = run_stages(p, geom, VG, [st], noise_variance=1e-4, poses=held_poses, held=held)
    inc = out.history[-1]["increment_px"]
    lab0, lab1 = held_poses.lab_params(geom, VG.offset), out.poses.lab_params(geom, VG.offset)
    assert inc < 1.0, inc  # the drift across the beam and the offset's correction, not a walk along the rays (2.7 px)
    assert _rms((lab1[:, 1] - lab1[:, 1].mean()) - (lab0[:, 1] - lab0[:, 1].mean())) < 0.02  # psi: 13


def test_the_held_vertical_motion_is_the_samples_own_in_any_gauge():
    # a sample on an axis tilted 1° and 6 voxels off the centre, drifting up: its own vertical motion (what the row
    # sums measure) written into poses that describe the same scan in another frame (a global rotation and shift, as
    # a tilted start or the gauge's mean pose gives) gives that scan back
    angles = np.linspace(0.0, np.pi, 90, endpoint=False)
    geom = parallel(angles, det_shape=(48, 56), pixel=1.0)
    c = np.zeros(3)
    truth = Poses(*combine_poses(
        tilted_axis_poses(angles, tilt=np.deg2rad(1.0), tilt_azimuth=0.7, offset=(6.0, 0.0, 0.0)),
        drift_poses(np.linspace(0.0, 1.0, angles.size), angles, velocity=[0.8, 0.0, 2.4], acceleration=[0.0, 0.0, -1.0])))
    assert np.allclose(truth.rotvecs[0], 0) and np.allclose(truth.translations[0], 0)
    vertical = truth.lab_params(geom, c)[:, 2]  # the first view's pose is the identity: the sample's own motion
    q = truth.lab_params(geom, c)
    q[:, 2] = 0.0
    flat = Poses.from_lab_params(q, geom, c)  # everything but the vertical motion
    n = angles.size
    g = Poses(np.tile([0.02, -0.025, 0.01], (n, 1)), np.tile([6.0, -2.0, 0.5], (n, 1)))  # another frame
    held = hold_vertical(flat.compose(g), vertical, geom, c)
    want = truth.compose(g).gauge_fixed(geom, center=c)
    assert_allclose(held.gauge_fixed(geom, center=c).lab_params(geom, c), want.lab_params(geom, c), atol=1e-9)
    assert_allclose(held.rotvecs, flat.compose(g).rotvecs, atol=1e-12)  # the rotations are kept


def test_the_held_vertical_motion_follows_the_rotations_the_rounds_change():
    # the rounds turn the sample about the centre (an increment acts before the pose) while "tz" is held: the
    # vertical translation at the centre stays, but the sample's own vertical motion (of the point that sat at the
    # centre at the first view, offset by the first view's shift) changes by the lever arm. Set again after each
    # round, it stays what the row sums measured (the 180° stand-in: 0.0878 px held once, 0.023 px set again;
    # docs/method.md §5.36)
    angles = np.linspace(0.0, np.pi, 90, endpoint=False)
    geom = parallel(angles, det_shape=(48, 56), pixel=1.0)
    c = np.zeros(3)
    t = np.linspace(0.0, 1.0, angles.size)
    vertical = 2.4 * t - 1.0 * t * t
    start = offset_poses(geom, 6.4)  # the axis offset as a shift of the sample, the first view's too
    start = hold_vertical(start, vertical, geom, c)
    turned = start.compose(Poses(np.outer(np.cos(angles), [0.0, 0.0087, 0.0]), np.zeros((angles.size, 3))))

    def own(p):  # the vertical motion of the point at the centre at the first view
        x0 = np.array(p.inverse().translations[0])
        x = Rotation.from_rotvec(np.array(p.rotvecs)).apply(x0) + p.translations
        return x[:, 2] - x[0, 2]

    assert_allclose(own(start), vertical - vertical[0], atol=1e-9)
    assert _rms(own(turned) - (vertical - vertical[0])) > 0.02  # held as a number: off by the lever arm
    again = hold_vertical(turned, vertical, geom, c)
    assert_allclose(own(again), vertical - vertical[0], atol=1e-9)
    assert_allclose(again.rotvecs, turned.rotvecs, atol=1e-12)


def test_run_stages_checks_the_vertical_motion_it_holds():
    from pdvc.calibration import StageError

    st = Stage(name="m", basis="drift", frame="lab", fixed=("rx", "ry", "rz"), until="rounds", rounds=1, scale=2, guards=())
    p = np.zeros((GEOM.n_views,) + GEOM.det_shape, np.float32)
    with pytest.raises(StageError, match="vertical must be 120 finite values"):
        run_stages(p, GEOM, VG, [st], noise_variance=1e-4, held=("tz",), vertical=np.zeros(7))
    with pytest.raises(StageError, match="held to name 'tz'"):
        run_stages(p, GEOM, VG, [st], noise_variance=1e-4, vertical=np.zeros(GEOM.n_views))
