"""Solver mechanics of the P-DVC engine.

Here the data ARE made with the voxel projector the engine inverts, on
purpose: with a consistent model the injected motion must come back to the
solver's tolerance, which checks the algebra (bases, Kronecker assembly,
frames, composition of poses, PGD, observability). Accuracy claims against
analytic data live in tests/slow.
"""

import numpy as np
import pytest

import pdvc
from pdvc.correlation import CorrelationError, correlate, lab_to_sample_map
from pdvc.status import Status
from pdvc.geometry import reprojection_error, sample_points
from pdvc.projectors import forward

from ..conftest import gaussian_blob_volume


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(4)
    n = 32
    vg = pdvc.VolumeGeometry((n, n, n))
    vol = np.zeros(vg.shape, np.float32)
    for _ in range(40):  # textured sample: blobs of random size and contrast
        m = rng.uniform(-10, 10, 3)
        vol += gaussian_blob_volume(vg, m, rng.uniform(1.2, 2.5), rng.uniform(0.3, 1.0))
    angles = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    geom = pdvc.circular_cone(angles, sod=250.0, odd=125.0, det_shape=(40, 48), pixel=1.5)
    return vg, vol, geom, angles


def _data(vol, vg, geom, rv, t):
    return forward(vol, vg, geom.apply_poses(rv, t))


def _err(geom, res_geom, vg, rv, t):
    return reprojection_error(res_geom, geom.apply_poses(rv, t), sample_points(vg, 4), remove_gauge=False).rms


def test_free_dirac_modes_recover_random_poses(setup):
    vg, vol, geom, angles = setup
    rng = np.random.default_rng(0)
    rv = rng.normal(0, 0.01, (36, 3))
    t = rng.normal(0, 0.5, (36, 3))
    res = correlate(vol, vg, _data(vol, vg, geom, rv, t), geom, basis="dirac", noise_variance=1e-4, max_iter=15, tol_px=1e-4)
    assert res.success, res.message
    assert _err(geom, res.geometry, vg, rv, t) < 2e-3
    assert res.chi_history[-1] < 1e-2 * res.chi_history[0]
    assert res.params.shape == (36, 6) and res.std.shape == (36, 6)
    assert np.all(res.snr_after > res.snr_before + 20)


@pytest.mark.parametrize("basis", ["fourier:1", "poly:2", "spline:3"])
def test_temporal_bases_recover_motion_in_their_span(setup, basis):
    vg, vol, geom, angles = setup
    from pdvc.correlation import make_basis

    B = make_basis(basis, angles=angles).matrix
    rng = np.random.default_rng(1)
    coef = rng.normal(0, 1, (B.shape[1], 6)) * [0.4, 0.4, 0.4, 0.006, 0.006, 0.006]
    p = B @ coef  # params about the volume centre (the origin here)
    rv = p[:, 3:]
    t = p[:, :3]  # centre at the origin: x -> R x + tau
    res = correlate(vol, vg, _data(vol, vg, geom, rv, t), geom, basis=basis, noise_variance=1e-4, max_iter=15, tol_px=1e-4)
    assert res.success, res.message
    assert _err(geom, res.geometry, vg, rv, t) < 2e-3
    np.testing.assert_allclose(res.params, p, atol=5e-3)


def test_lab_frame_constant_offset_is_one_constant_mode(setup):
    """A fixed lab translation of the rotation axis = one constant lab-frame mode."""
    vg, vol, geom, angles = setup
    T = lab_to_sample_map(geom)
    p_lab = np.array([0.8, 0.0, -0.5, 0.0, 0.0, 0.0])
    p = np.einsum("kij,j->ki", T, p_lab)
    res = correlate(vol, vg, _data(vol, vg, geom, p[:, 3:], p[:, :3]), geom, basis="constant", frame="lab", noise_variance=1e-4, tol_px=1e-4)
    assert res.success
    np.testing.assert_allclose(res.params_lab, np.tile(p_lab, (36, 1)), atol=2e-3)


def test_fixed_parameters_stay_zero(setup):
    vg, vol, geom, angles = setup
    p_lab = np.array([0.5, 0.0, 0.3, 0.0, 0.0, 0.0])
    T = lab_to_sample_map(geom)
    p = np.einsum("kij,j->ki", T, p_lab)
    res = correlate(vol, vg, _data(vol, vg, geom, p[:, 3:], p[:, :3]), geom, basis="constant", frame="lab",
                    fixed=("ty", "rx", "ry", "rz"), noise_variance=1e-4, tol_px=1e-4)
    assert np.all(res.params_lab[:, [1, 3, 4, 5]] == pytest.approx(0, abs=1e-12))
    np.testing.assert_allclose(res.params_lab[:, [0, 2]], np.tile([0.5, 0.3], (36, 1)), atol=2e-3)


def test_pgd_finds_a_rank_one_motion_in_one_mode(setup):
    vg, vol, geom, angles = setup
    phi = np.array([0.6, -0.3, 0.4, 0.004, 0.0, -0.006])
    alpha = np.sin(angles) * 0.7 + 0.3 * np.linspace(-1, 1, 36)
    p = np.outer(alpha, phi)
    res = correlate(vol, vg, _data(vol, vg, geom, p[:, 3:], p[:, :3]), geom, basis="fourier:1", method="pgd",
                    noise_variance=1e-4, max_modes=3, tol_px=1e-4, min_gain=0.05)
    assert len(res.modes) >= 1
    m = res.modes[0]
    assert np.max(np.abs(m.alpha)) == pytest.approx(1.0)
    cos = abs(m.spatial @ phi) / (np.linalg.norm(m.spatial) * np.linalg.norm(phi))
    assert cos > 0.99
    assert _err(geom, res.geometry, vg, p[:, 3:], p[:, :3]) < 5e-3
    assert res.mode_table[0][0] == 0 and res.mode_table[1][1] < res.mode_table[0][1]
    np.testing.assert_allclose(m.alpha_free, m.alpha, atol=0.05)


def test_parallel_beam_translation_along_the_beam_is_reported_unobservable():
    rng = np.random.default_rng(2)
    vg = pdvc.VolumeGeometry((24, 24, 24))
    vol = sum(gaussian_blob_volume(vg, rng.uniform(-7, 7, 3), 2.0, 1.0) for _ in range(15))
    geom = pdvc.parallel(np.linspace(0, np.pi, 12, endpoint=False), det_shape=(28, 30), pixel=1.0)
    t = rng.normal(0, 0.3, (12, 3))
    res = correlate(vol, vg, forward(vol, vg, geom.apply_poses(np.zeros((12, 3)), t)), geom, basis="dirac",
                    fixed=("rx", "ry", "rz"), noise_variance=1e-4, tol_px=1e-4)
    obs = res.observability
    assert len(obs.directions) == 12  # one per view
    beam = geom.ray / np.linalg.norm(geom.ray, axis=1, keepdims=True)
    for d, v in zip(obs.directions, obs.views):
        assert abs(abs(d[:3] @ beam[v]) - 1) < 1e-6
    # reported, not invented: the along-beam component is left at zero, its std is nan
    along = np.einsum("ki,ki->k", res.params[:, :3], beam)
    assert np.all(np.abs(along) < 1e-9)
    assert np.all(np.isnan(res.std[:, :3]).any(axis=1))
    across = t - np.einsum("k,ki->ki", np.einsum("ki,ki->k", t, beam), beam)
    np.testing.assert_allclose(res.params[:, :3], across, atol=2e-3)


def test_lab_frame_increments_are_read_in_the_posed_lab_axes():
    # an increment acts before the current pose: with the nominal lab axes, a tilt of the current poses leaked each lab
    # parameter into the others. On a parallel beam the lab translation along y moves every point along its own ray
    # (no view sees it); leaked, it got a small curvature of its own, and a real 360° scan's warm-up (its poses tilted
    # 0.2° by the row sums) drifted along it by 39 length units
    from pdvc.geometry import Poses

    rng = np.random.default_rng(5)
    vg = pdvc.VolumeGeometry((24, 24, 24))
    vol = sum(gaussian_blob_volume(vg, rng.uniform(-7, 7, 3), 2.0, 1.0) for _ in range(15))
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    geom = pdvc.parallel(angles, det_shape=(28, 30), pixel=1.0)
    c = np.asarray(vg.offset, float)
    t = np.linspace(-1, 1, angles.size)
    tilt = np.radians(2.0)

    def poses(tx, ty):
        q = np.zeros((angles.size, 6))
        q[:, 0], q[:, 1], q[:, 3] = tx, ty, tilt  # the axis tilted toward the beam, as a start from the row sums
        return Poses.from_lab_params(q, geom, c)

    # the premise: a lab ty that drifts by 2 voxels changes the views 100x less than a tx of a tenth of that
    p0 = forward(vol, vg, geom.apply(poses(0.0, 0.0)))
    d_ty = np.abs(forward(vol, vg, geom.apply(poses(0.0, 2.0 * t))) - p0).max()
    d_tx = np.abs(forward(vol, vg, geom.apply(poses(0.2 * t, 0.0))) - p0).max()
    assert d_ty < 1e-2 * d_tx
    truth, start = poses(0.3 * t, 0.0), poses(0.0, 1.5 * t)  # the solve starts from a ty the data cannot see
    data = forward(vol, vg, geom.apply(truth))
    data += rng.normal(0, 0.02 * data.std(), data.shape).astype(np.float32)
    res = correlate(vol, vg, data, geom, basis="poly:2", frame="lab", fixed=("rx", "ry", "rz", "tz"),
                    initial_rotvecs=start.rotvecs, initial_translations=start.translations, tol_px=1e-5, max_iter=20)
    q = res.poses.lab_params(geom, c)
    np.testing.assert_allclose(q[:, 1], 1.5 * t, atol=1e-6)  # where it started
    np.testing.assert_allclose(q[:, 0], 0.3 * t, atol=3e-3)
    np.testing.assert_allclose(q[:, 2:], truth.lab_params(geom, c)[:, 2:], atol=1e-9)  # fixed: as they started
    assert len(res.observability.directions) >= 1  # ty: reported unobservable, not invented
    assert all(abs(abs(d[1]) - 1) < 1e-6 for d in res.observability.directions)


def test_bad_options_raise(setup):
    vg, vol, geom, angles = setup
    s = np.zeros((36, 40, 48), np.float32)
    with pytest.raises(CorrelationError, match="method"):
        correlate(vol, vg, s, geom, method="newton")
    with pytest.raises(CorrelationError, match="frame"):
        correlate(vol, vg, s, geom, frame="detector")
    with pytest.raises(CorrelationError, match="fixed"):
        correlate(vol, vg, s, geom, fixed=("tw",))
    with pytest.raises(pdvc.ShapeError, match="projections"):
        correlate(vol, vg, s[:3], geom)
    with pytest.raises(CorrelationError, match="max_iter"):
        correlate(vol, vg, s, geom, max_iter=0)


def test_multiscale_converges_from_a_motion_too_large_for_one_scale(setup):
    """A 14-voxel lab offset: with the same 4 passes per scale, one scale stalls, 4-2-1 converges."""
    vg, vol, geom, angles = setup
    T = lab_to_sample_map(geom)
    p_lab = np.array([14.0, 0.0, 3.0, 0.0, 0.0, 0.0])
    p = np.einsum("kij,j->ki", T, p_lab)
    data = _data(vol, vg, geom, p[:, 3:], p[:, :3])
    kw = dict(basis="constant", frame="lab", noise_variance=1e-4, tol_px=1e-4, max_iter=4)
    single = correlate(vol, vg, data, geom, **kw)
    multi = correlate(vol, vg, data, geom, scales=(4, 2, 1), **kw)
    assert [h[0] for h in multi.scale_history] == [4, 2, 1]
    assert multi.geometry.det_shape == geom.det_shape
    e_multi = _err(geom, multi.geometry, vg, p[:, 3:], p[:, :3])
    e_single = _err(geom, single.geometry, vg, p[:, 3:], p[:, :3])
    assert e_multi < 5e-3
    assert e_single > 1.0 and not single.success
    assert multi.scale_history[-1][1] < 1e-3 * multi.scale_history[0][1]  # the fine scale starts converged-ish
    np.testing.assert_allclose(multi.params_lab.mean(axis=0)[:3], p_lab[:3], atol=2e-3)


def test_multiscale_rejects_bad_schedule(setup):
    vg, vol, geom, angles = setup
    with pytest.raises(CorrelationError, match="scales"):
        correlate(vol, vg, _data(vol, vg, geom, np.zeros((36, 3)), np.zeros((36, 3))), geom, scales=(2, 0))


@pytest.mark.parametrize("method", ["full", "pgd"])
def test_a_rejected_step_is_never_reported_converged(setup, monkeypatch, method):
    # Every step the engine tries raises chi (chi is made to grow with each evaluation). Damping
    # shrinks the step below the tolerance; the engine used to accept that tiny step and say
    # "converged". Now no step is kept, and the status says that chi could not be lowered.
    from pdvc import Status
    from pdvc.correlation import _engine

    vg, vol, geom, angles = setup
    t = np.zeros((36, 3))
    t[:, 0] = 0.5
    data = _data(vol, vg, geom, np.zeros((36, 3)), t)
    calls = {"n": 0}

    def rising_chi(self, red):  # whatever the step, chi is higher than before
        calls["n"] += 1
        return 1.0 + calls["n"]

    monkeypatch.setattr(_engine._Problem, "chi", rising_chi)
    res = correlate(vol, vg, data, geom, basis="constant", method=method, noise_variance=1e-4, max_iter=30, noise_floor=0.0)
    assert len(res.chi_history) == 1  # nothing accepted
    np.testing.assert_array_equal(res.translations, 0.0)
    if method == "full":
        assert res.status == Status.NO_DESCENT and not res.success
    assert res.status != Status.CONVERGED


def test_anderson_acceleration_solves_a_slow_linear_iteration():
    """x <- x + f(x), f = -A (x - x*) with A's eigenvalues 1 and 0.05: plain steps shrink by 0.95 per
    iteration along the slow direction; depth-3 Anderson acceleration (GMRES on a linear map) is exact
    after n + 1 = 3 steps in 2-D."""
    from pdvc.correlation._engine import _Anderson

    rng = np.random.default_rng(0)
    Q = np.linalg.qr(rng.normal(size=(2, 2)))[0]
    A = Q @ np.diag([1.0, 0.05]) @ Q.T
    x_star = np.array([0.3, -1.2])
    f = lambda x: -A @ (x - x_star)  # noqa: E731

    x = np.zeros(2)
    for _ in range(50):
        x = x + f(x)
    assert np.linalg.norm(x - x_star) > 1e-3  # plain: still far after 50 steps (0.95**50 = 0.08 of the slow part)
    aa, x = _Anderson(depth=3), np.zeros(2)
    for _ in range(4):
        x = x + aa.step(x, f(x))
    assert np.linalg.norm(x - x_star) < 1e-9
    aa.reset()
    assert np.allclose(aa.step(x, f(x)), f(x))  # after a reset: the plain step


def test_max_start_chi_stops_after_the_first_pass_only_when_chi_is_above_it(setup):
    """Above the limit: one pass, poses unchanged, CONSISTENCY_GUARD; at or below it: the run without a limit."""
    vg, vol, geom, angles = setup
    rng = np.random.default_rng(5)
    t = rng.normal(0, 0.4, (geom.n_views, 3))
    data = _data(vol, vg, geom, np.zeros((geom.n_views, 3)), t)
    kw = dict(basis="constant", noise_variance=1e-4, max_iter=8)
    free = correlate(vol, vg, data, geom, **kw)
    chi0 = float(free.chi_history[0])
    stopped = correlate(vol, vg, data, geom, max_start_chi=0.999 * chi0, **kw)
    assert stopped.status == Status.CONSISTENCY_GUARD and stopped.n_iter == 1
    assert np.array_equal(stopped.rotvecs, np.zeros((geom.n_views, 3))) and not np.any(stopped.translations)
    assert stopped.chi_history.tolist() == [chi0] and np.all(np.isnan(stopped.std))
    same = correlate(vol, vg, data, geom, max_start_chi=chi0, **kw)
    assert same.n_iter == free.n_iter and np.array_equal(same.params, free.params)
    with pytest.raises(CorrelationError, match="max_start_chi"):
        correlate(vol, vg, data, geom, max_start_chi=chi0, scales=(2, 1), **kw)


def test_acceleration_reaches_the_plain_solution_in_fewer_passes(setup):
    """Same poses with and without Anderson acceleration; never more Jacobian passes with it."""
    vg, vol, geom, angles = setup
    from pdvc.correlation import make_basis

    B = make_basis("fourier:1", angles=angles).matrix
    rng = np.random.default_rng(3)
    p = B @ (rng.normal(0, 1, (B.shape[1], 6)) * [0.4, 0.4, 0.4, 0.006, 0.006, 0.006])
    data = _data(vol, vg, geom, p[:, 3:], p[:, :3])
    kw = dict(basis="fourier:1", noise_variance=1e-4, max_iter=30, tol_px=1e-5)
    plain = correlate(vol, vg, data, geom, accelerate=False, **kw)
    fast = correlate(vol, vg, data, geom, accelerate=True, **kw)
    assert plain.success and fast.success
    assert fast.n_iter <= plain.n_iter
    np.testing.assert_allclose(fast.params, plain.params, atol=2e-4)
    assert _err(geom, fast.geometry, vg, p[:, 3:], p[:, :3]) < 2e-3


def test_a_correlation_stops_where_the_next_step_would_move_less_than_tol_px_without_a_pass_to_evaluate_it(setup):
    """Started where a first correlation converged, the next Gauss-Newton step is below ``tol_px``: one pass,
    ``CONVERGED``, the poses as given; from the nominal poses the run ends within ``tol_px`` of the truth, and a
    tolerance above the first step takes that step before it stops."""
    vg, vol, geom, angles = setup
    t = np.tile([0.35, -0.25, 0.3], (geom.n_views, 1))  # a constant shift, as the constant basis models it
    zero = np.zeros((geom.n_views, 3))
    data = _data(vol, vg, geom, zero, t)
    kw = dict(basis="constant", noise_variance=1e-4, max_iter=10, tol_px=1e-3)
    first = correlate(vol, vg, data, geom, **kw)
    assert first.status == Status.CONVERGED and first.n_iter >= 2
    assert _err(geom, first.geometry, vg, zero, t) < 2e-3
    again = correlate(vol, vg, data, geom, initial_rotvecs=first.rotvecs, initial_translations=first.translations, **kw)
    assert again.status == Status.CONVERGED and again.n_iter == 1 and again.chi_history.size == 1
    assert np.array_equal(again.rotvecs, first.rotvecs) and np.array_equal(again.translations, first.translations)
    # a tolerance below that step's size takes it, with the pass that evaluates it
    tight = correlate(vol, vg, data, geom, initial_rotvecs=first.rotvecs, initial_translations=first.translations,
                      **dict(kw, tol_px=1e-9))
    assert tight.n_iter >= 2 and not np.array_equal(tight.translations, first.translations)
    # a tolerance above the first step (a round's forcing term) still takes that step, then stops: 2 passes
    loose = correlate(vol, vg, data, geom, **dict(kw, tol_px=50.0))
    assert loose.status == Status.CONVERGED and loose.n_iter == 2 and loose.chi_history.size == 2
    assert _err(geom, loose.geometry, vg, zero, t) < 0.5 * _err(geom, geom, vg, zero, t)
