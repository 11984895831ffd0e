"""The outer loop's contract: inputs checked, same result structure always, gauge, stopping rules."""

from __future__ import annotations

import numpy as np
import pytest

import pdvc
from pdvc import Status
from pdvc.calibration import OuterError, OuterResult, drift_basis, refined_grid, self_calibrate
from pdvc.errors import ShapeError
from pdvc.geometry import Poses, fix_gauge, remove_mean_pose, reprojection_error
from pdvc.recon import fdk
from tests.correlation.cases import make_case

HISTORY_KEYS = {
    "iteration", "stage", "stage_index", "scale", "round", "chi_before", "chi_after", "snr_before", "snr", "entropy",
    "increment_px", "increment_max_px", "n_iter", "engine_status", "elapsed_s", "background", "offset_sigma", "model",
    "extrapolated",
}


@pytest.fixture(scope="module")
def small_case():
    # 24³ phantom, 48 views, a 2-voxel axis offset (nominal error 2 px); runs in ~1 s
    return make_case("offset", n=24, n_views=48)


# The small case has no rotation, and on a 24³ object the rotations are poorly determined
# (free rotations add ~0.1 px there): the contract tests measure translations only.
TRANSLATIONS = dict(fixed=("rx", "ry", "rz"))


def test_refined_grid_covers_the_same_region():
    vg = pdvc.VolumeGeometry((10, 12, 14), voxel_size=(1.0, 0.5, 2.0), offset=(1.0, -2.0, 3.0))
    fine = refined_grid(vg, 3)
    assert fine.shape == (30, 36, 42)
    np.testing.assert_allclose(fine.voxel_size, (1 / 3, 0.5 / 3, 2 / 3))
    np.testing.assert_allclose(fine.extent_xyz, vg.extent_xyz)
    np.testing.assert_allclose(fine.offset, vg.offset)


def test_drift_basis_spans_offset_drift_and_shifted_axis():
    th = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    b = drift_basis(th)
    assert b.matrix.shape == (90, 5)
    t = np.arange(90.0)
    for f in (np.ones(90), t, t**2, np.cos(th), np.sin(th)):
        coef = np.linalg.lstsq(b.matrix, f, rcond=None)[0]
        np.testing.assert_allclose(b.matrix @ coef, f, atol=1e-8 * np.abs(f).max())


def test_drift_basis_falls_back_on_few_views():
    b = drift_basis(np.array([0.0, 2.0, 4.0]))
    assert b.n_views == 3 and b.n_funcs <= 3


@pytest.mark.parametrize(
    "kw, err",
    [
        (dict(oversample=0), OuterError),
        (dict(max_outer=0), OuterError),
        (dict(warmup=-1), OuterError),
        (dict(oversample=1.5), OuterError),
        (dict(tol_px=0.0), OuterError),
        (dict(guard="sharpness"), OuterError),
        (dict(entropy_tol=0.0), OuterError),
        (dict(reconstruct="sirt"), OuterError),
        (dict(reconstruct=3), OuterError),
        (dict(recipe="wobble"), OuterError),
    ],
)
def test_bad_options_are_rejected(small_case, kw, err):
    c = small_case
    with pytest.raises(err, match=next(iter(kw))):
        self_calibrate(c.scan.projections, c.scan.geometry, c.vol_geom, **kw)


def test_bad_inputs_are_rejected(small_case):
    c = small_case
    with pytest.raises(ShapeError, match="projections must have shape"):
        self_calibrate(c.scan.projections[:-1], c.scan.geometry, c.vol_geom)
    with pytest.raises(OuterError, match="geom must be a VectorGeometry"):
        self_calibrate(c.scan.projections, c.scan.geometry.vectors, c.vol_geom)
    with pytest.raises(OuterError, match="vol_geom must be a VolumeGeometry"):
        self_calibrate(c.scan.projections, c.scan.geometry, (24, 24, 24))


@pytest.fixture(scope="module")
def small_run(small_case):
    c = small_case
    seen = []
    proj = c.scan.projections.copy()
    out = self_calibrate(proj, c.scan.geometry, c.vol_geom, max_outer=5, callback=seen.append, **TRANSLATIONS)
    np.testing.assert_array_equal(proj, c.scan.projections)  # input untouched
    return out, seen


def test_result_structure(small_case, small_run):
    c = small_case
    out, seen = small_run
    assert isinstance(out, OuterResult)
    n = c.scan.geometry.n_views
    assert isinstance(out.poses, Poses) and out.poses.n_views == n
    assert out.rotvecs.shape == (n, 3) and out.translations.shape == (n, 3)
    assert out.geometry == c.scan.geometry.apply(out.poses)
    assert out.volume.shape == c.vol_geom.shape and out.volume.dtype == np.float32
    assert out.vol_geom == c.vol_geom
    assert out.corr_vol_geom.shape == tuple(2 * s for s in c.vol_geom.shape)
    assert isinstance(out.status, Status) and out.message == out.status.message
    assert 1 <= out.n_outer <= 5
    assert all(set(h) - {"model_choice"} == HISTORY_KEYS for h in out.history)
    assert out.history[0]["stage"] == "model"  # no rotation free (TRANSLATIONS): the warm-up is skipped
    assert [h["iteration"] for h in out.history] == list(range(out.n_outer))
    assert seen == [dict(h) for h in out.history]  # the callback saw every iteration
    assert out.result.basis is not None  # the CorrelationResult whose poses were kept
    assert [o.name for o in out.stages] == ["model", "jolts"] and out.stages[0].status == out.status
    assert "magnification" in out.gauge and "mean rotation" in out.gauge


def test_small_offset_is_recovered(small_case, small_run):
    c = small_case
    out, _ = small_run
    assert out.success, out.message
    before = reprojection_error(c.scan.geometry, c.scan.true_geometry, c.points).rms
    after = reprojection_error(out.geometry, c.scan.true_geometry, c.points).rms
    assert before == pytest.approx(2.0, abs=0.05)
    assert after < 0.05  # measured 0.007 px
    assert out.history[0]["chi_before"] > 5 * out.history[-1]["chi_before"]


def test_poses_are_gauge_fixed(small_case, small_run):
    c = small_case
    out, _ = small_run
    rv, t = fix_gauge(out.rotvecs, out.translations, c.scan.geometry, center=c.vol_geom.offset)
    np.testing.assert_allclose(rv, out.rotvecs, atol=1e-9)
    np.testing.assert_allclose(t, out.translations, atol=1e-7)
    rv0, t0 = remove_mean_pose(out.rotvecs, out.translations, center=c.vol_geom.offset)
    np.testing.assert_allclose(t0, out.translations, atol=1e-7)


def test_increment_below_tolerance_stops_the_loop(small_case):
    c = small_case
    out = self_calibrate(
        c.scan.projections, c.scan.geometry, c.vol_geom, max_outer=10, tol_px=0.5, warmup=0, **TRANSLATIONS
    )
    assert out.status == Status.CONVERGED and out.success
    assert out.history[-1]["increment_px"] < 0.5 <= out.history[-2]["increment_px"]


def test_rising_data_inconsistency_from_the_start_is_divergence(small_case):
    # a reconstruction that gets worse at every call: chi_before rises from the first round on
    c = small_case
    calls = []

    def bad_reconstruct(p, vg, g):
        calls.append(g)
        vol = fdk(p, vg, g)
        return vol * (1.0 + 0.5 * (len(calls) - 1))

    out = self_calibrate(
        c.scan.projections, c.scan.geometry, c.vol_geom, reconstruct=bad_reconstruct, warmup=0, max_outer=6
    )
    assert out.status == Status.DIVERGED and not out.success
    chis = out.chi_before
    assert int(np.argmin(chis)) == 0
    # the poses returned are those the best reconstruction was made with: where the stage started
    assert out.geometry == calls[0] == c.scan.geometry


def test_a_refinement_that_finds_nothing_better_keeps_the_converged_poses(small_case):
    # a converged model, then a second stage whose reconstructions get worse at every call: the
    # second stage keeps the poses it started from, and the run is a success (not "diverged")
    from pdvc.calibration import Stage, run_stages

    c = small_case
    calls = []

    volumes = []

    def worse_and_worse(p, vg, g):
        calls.append(g)
        volumes.append(fdk(p, vg, g) * (1.0 + 0.5 * (len(calls) - 1)))
        return volumes[-1]

    first = Stage(name="model", basis="constant", frame="lab", fixed=("rx", "ry", "rz"), rounds=6, tol_px=0.05)  # converges
    second = first.replace(name="refine", reconstruct=worse_and_worse, rounds=4, tol_px=1e-9)
    from pdvc.correlation import estimate_noise_variance

    import pdvc.calibration._driver as driver

    measured = []

    def counted(*a, **kw):
        res = correlate(*a, **kw)
        measured.append(res)
        return res

    correlate = driver.correlate
    driver.correlate = counted
    try:
        drv = run_stages(c.scan.projections, c.scan.geometry, c.vol_geom, [first, second],
                         noise_variance=estimate_noise_variance(c.scan.projections))
    finally:
        driver.correlate = correlate
    # the round whose fresh reconstruction fitted worse was not measured: one pass, then the guard
    assert measured[-1].status == Status.CONSISTENCY_GUARD and measured[-1].n_iter == 1
    assert drv.stages[0].status.success
    assert drv.stages[1].status == Status.CONSISTENCY_GUARD and drv.success
    refine_rounds = [h for h in drv.history if h["stage"] == "refine"]
    assert len(refine_rounds) == 1  # the first refinement round was recorded; the second's chi_before rose
    # the poses kept are those the first stage converged to: the geometry of the first refinement call
    assert c.scan.geometry.apply(drv.poses) == calls[0]
    # and the volume reconstructed there is handed on (the check against nominal reuses it)
    assert drv.fit_volume[0] is drv.poses and drv.fit_volume[1] is second and drv.fit_volume[2] is volumes[0]
    # alone (nothing converged before it), the same stage diverges
    calls.clear()
    alone = run_stages(c.scan.projections, c.scan.geometry, c.vol_geom, [second],
                       noise_variance=estimate_noise_variance(c.scan.projections))
    assert alone.status == Status.DIVERGED and not alone.success


def test_rising_data_inconsistency_after_the_best_round_keeps_the_best_poses(small_case):
    # better at the second call, then worse and worse: the guard keeps the poses of the best (a success)
    c = small_case
    from tests.correlation.cases import best_at_second_call

    calls = []
    reconstruct = best_at_second_call(calls)

    out = self_calibrate(
        c.scan.projections, c.scan.geometry, c.vol_geom, reconstruct=reconstruct, warmup=0, max_outer=6,
        stall_ratio=None, tol_px=1e-9, **TRANSLATIONS,
    )
    assert out.status == Status.CONSISTENCY_GUARD and out.success, out.message
    assert int(np.argmin(out.chi_before)) == 1
    assert out.geometry == calls[1]


def test_rising_entropy_stops_and_returns_the_poses_before_the_last_iteration(small_case):
    # a reconstruction that gets noisier at every call: its entropy rises in the model stage
    c = small_case
    calls = []
    rng = np.random.default_rng(0)

    def noisier(p, vg, g):
        calls.append(g)
        vol = fdk(p, vg, g)
        return vol + rng.normal(0.0, 0.02 * (len(calls) - 1) * float(vol.max()), vol.shape).astype(np.float32)

    out = self_calibrate(
        c.scan.projections, c.scan.geometry, c.vol_geom, reconstruct=noisier, guard="entropy", warmup=0,
        max_outer=6, stall_ratio=None, tol_px=1e-9, **TRANSLATIONS,
    )
    assert out.status == Status.ENTROPY_GUARD and out.success, out.message
    ent = [h["entropy"] for h in out.history]
    assert all(np.isfinite(ent)) and len(out.history) >= 1
    # the guard looks before each iteration: the geometry returned is the one the last
    # iteration started from, i.e. before the poses whose reconstruction tripped the guard
    starts = calls[::2]  # each iteration: guard reconstruction on vol_geom, then the correlation volume
    assert out.geometry == starts[len(out.history) - 1]
    # ... and its volume on vol_geom is the guard's, not made again
    assert len(calls) == 2 * len(out.history) + 1


def test_entropy_is_nan_without_the_guard(small_case, small_run):
    out, _ = small_run
    assert all(np.isnan(h["entropy"]) for h in out.history)


def test_nonneg_ls_reconstruction_in_the_loop(small_case):
    c = small_case
    out = self_calibrate(
        c.scan.projections, c.scan.geometry, c.vol_geom, reconstruct="nonneg_ls", warmup=0, max_outer=2,
        **TRANSLATIONS,
    )
    assert reprojection_error(out.geometry, c.scan.true_geometry, c.points).rms < 0.15
    assert out.volume.shape == c.vol_geom.shape


def test_initial_poses_are_used(small_case):
    c = small_case
    out = self_calibrate(
        c.scan.projections, c.scan.geometry, c.vol_geom, max_outer=2, warmup=0,
        initial_poses=Poses(c.scan.rotvecs, c.scan.translations),
    )
    # started at the truth, the first reconstruction is already consistent
    assert out.history[0]["chi_before"] < 1.5


def test_free_rotations_start_with_the_translation_warmup(small_case):
    """Rotations free (default: rz fixed only): round 0 measures translations only, in the lab frame."""
    c = small_case
    out = self_calibrate(c.scan.projections, c.scan.geometry, c.vol_geom, max_outer=2, oversample=1, tol_px=1e-9)
    # the model stage, under the model its choice took ("model:fixed_axis" when the fixed axis won)
    assert [h["stage"].split(":")[0] for h in out.history][:2] == ["warmup", "model"]
    assert out.stages[0].status == Status.ROUNDS_DONE  # a warm-up that ran its round is done, not "not converged"


def test_a_round_whose_correlation_lowers_nothing_is_a_fixed_point_not_a_convergence(small_case, monkeypatch):
    # every step the engine tries raises chi: no step is ever kept, so nothing moved. The loop says
    # so (FIXED_POINT) instead of reading the zero increment as convergence.
    from pdvc.correlation import _engine

    c = small_case
    calls = {"n": 0}

    def rising_chi(self, red):  # whatever the step, chi is higher than before
        calls["n"] += 1
        return 1.0 + calls["n"]

    monkeypatch.setattr(_engine._Problem, "chi", rising_chi)
    # (the consistency guard is off: the fake chi of each fresh reconstruction rises too)
    out = self_calibrate(c.scan.projections, c.scan.geometry, c.vol_geom, max_outer=3, warmup=0, guards=(), **TRANSLATIONS)
    assert out.status == Status.FIXED_POINT
    assert out.history == ()  # no round was recorded as a move
    assert out.geometry == c.scan.geometry


def test_nonneg_ls_step_bound_is_estimated_once_per_grid(small_case, monkeypatch):
    """The rounds of a nonneg_ls stage reconstruct again and again on one grid: the
    step bound (3 forward and 3 back-projections) is estimated at the first and
    reused, and the volumes are those nonneg_ls makes with that bound."""
    from pdvc.calibration import _driver
    from pdvc.recon import nonneg_ls_lipschitz

    c = small_case
    calls, bounds = [], []
    monkeypatch.setattr(_driver, "nonneg_ls_lipschitz",
                        lambda *a, **k: calls.append(a[0].shape) or nonneg_ls_lipschitz(*a, **k))
    real = _driver.nonneg_ls
    monkeypatch.setattr(_driver, "nonneg_ls", lambda *a, **k: bounds.append(k["lipschitz"]) or real(*a, **k))
    out = self_calibrate(
        c.scan.projections, c.scan.geometry, c.vol_geom, reconstruct="nonneg_ls", warmup=0, max_outer=3, tol_px=1e-9,
        **TRANSLATIONS,
    )
    assert len(out.history) >= 2 and len(bounds) >= 2
    assert len(calls) == len(set(calls)) == 1
    assert all(b == bounds[0] and b > 0 for b in bounds)
