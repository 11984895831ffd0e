"""second_run: the precession recipe run as well, and the geometry whose reconstruction predicts the views left out better kept."""

import numpy as np
import pytest

import pdvc
from pdvc.calibration import _driver, _pipeline, _select, resolve_stages
from pdvc.calibration._select import ModelChoice
from pdvc.io._config import ConfigError
from tests.correlation.cases import make_case


class _Outcome:
    """What ``_second_run_reason`` reads of the driver's outcome."""

    def __init__(self, choice):
        self.model_choice = choice


AXIS_KEPT = ModelChoice(winner="axis", own="axis", scores={"axis": 1.0, "precession": 1.001})


def test_the_second_run_is_made_only_where_the_default_kept_a_model_without_the_precession_on_a_full_turn():
    vg = pdvc.VolumeGeometry((48, 48, 48))
    st = resolve_stages((58, 67), vol_shape=vg.shape)
    full = pdvc.parallel(np.linspace(0, 2 * np.pi, 90, endpoint=False), det_shape=(58, 67), pixel=1.0)
    half = pdvc.parallel(np.linspace(0, np.pi, 90, endpoint=False), det_shape=(58, 67), pixel=1.0)
    assert _pipeline._second_run_reason("default", _Outcome(AXIS_KEPT), full, {}, st, vg) == (True, "")
    assert _pipeline._second_run_reason("default", _Outcome(AXIS_KEPT), full, dict(tol_px=0.01), st, vg) == (True, "")
    chosen = ModelChoice(winner="precession", own="axis", scores={"axis": 1.0, "precession": 0.9}, gain=0.1)
    no_precession = ModelChoice(winner="axis", own="axis", scores={"fixed_axis": 1.0, "axis": 0.9})
    for recipe, choice, geom, model in (
        ("precession", AXIS_KEPT, full, {}),  # another recipe
        ("default", None, full, {}),  # no comparison made (the user chose the model)
        ("default", chosen, full, {}),  # the precession model runs already
        ("default", no_precession, full, {}),  # the precession is not among the candidates
        ("default", AXIS_KEPT, half, {}),  # half a turn: the views left out cannot tell the models apart
        ("default", AXIS_KEPT, full, dict(reconstruct="fdk")),  # the user's own volume
        ("default", AXIS_KEPT, full, dict(oversample=1)),
    ):
        assert _pipeline._second_run_reason(recipe, _Outcome(choice), geom, model, st, vg) == (False, "")
    # a region-of-interest scan (material outside the volume in every view): not made, and the note says why
    run, why = _pipeline._second_run_reason("default", _Outcome(AXIS_KEPT), full, {}, st, vg, roi_scan=True)
    assert not run and "region-of-interest" in why
    # a finest correlation grid above SECOND_RUN_MAX_VOXELS: made at the coarser scales whose grid is not
    # (docs/method.md §5.27); when no scale's is, not made, and the note says why and what to do
    big = pdvc.VolumeGeometry((128, 128, 128))
    two = resolve_stages((160, 128), vol_shape=big.shape)
    assert sorted({s.scale for s in two}) == [1, 2]
    assert _pipeline._second_run_reason("default", _Outcome(AXIS_KEPT), full, {}, two, big) == (True, "")
    assert _pipeline._second_run_scales(two, big, (160, 128)) == ((2,), (1,))  # 128^3 at 2; 256^3 at 1 left out
    assert _pipeline._second_run_scales(st, vg, full.det_shape) == ((1,), ())
    # many views on a large detector (bench_large.py's 2k scan of 1440 views binned by 4): grids within the voxel cap,
    # but at scale 4 the rays cross its 64^3 grid in 1440 x 128 x 128 x 64 = 1.5e9 voxel steps, above
    # SECOND_RUN_MAX_RAY_STEPS (scale 2: 1.2e10): no second run (no coarser scale either, as for the voxel cap: at scale
    # 8 its geometry came back 67 px off and was kept); 90 views fit at both (docs/method.md §5.57)
    wide = resolve_stages((512, 512), vol_shape=big.shape)
    assert sorted({s.scale for s in wide}) == [2, 4]
    assert _pipeline._second_run_scales(wide, big, (512, 512)) == ((4, 2), ())
    assert _pipeline._second_run_scales(wide, big, (512, 512), 90) == ((4, 2), ())
    assert _pipeline._second_run_scales(wide, big, (512, 512), 1440) == ((), (4, 2))
    assert _pipeline._second_run_scales(wide, big, (512, 512), 360) == ((4,), (2,))  # 3.8e8 at 4, 3e9 at 2
    run, why = _pipeline._second_run_reason("default", _Outcome(AXIS_KEPT), pdvc.circular_cone(
        np.linspace(0, 2 * np.pi, 1440, endpoint=False), sod=500.0, odd=250.0, det_shape=(512, 512), pixel=1.0), {},
        wide, big)
    assert not run and "not run as well: at scale 4 the 1440 views' rays" in why
    assert "1440 views' rays cross the 64x64x64 grid in 1.5e+09 voxel steps" in _pipeline._second_run_fits(
        wide, big, (512, 512), 1440, 4, 4)
    assert _pipeline._second_run_fits(wide, big, (512, 512), 90, 4, 4) == ""
    # a finest scale whose oversampling the 256^3 cap lowered (docs/method.md §5.29) is judged as the precession
    # recipe would correlate there, at the coarsest stages' 2x: 268 x 320 x 320, left out
    tall = pdvc.VolumeGeometry((134, 160, 160))
    capped = resolve_stages((134, 160), vol_shape=tall.shape)
    assert [s.oversample for s in capped if s.scale == 1] == [1, 1]
    assert _pipeline._second_run_scales(capped, tall, (134, 160)) == ((2,), (1,))
    # no scale of the default's below the cap: a coarser one (docs/method.md §5.28), the first whose grid is, while
    # the detector keeps SECOND_RUN_MIN_COLUMNS columns there
    one = resolve_stages((160, 128), vol_shape=big.shape, scales=(1,))
    assert _pipeline._second_run_scales(one, big, (160, 128)) == ((2,), (1,))
    huge = pdvc.VolumeGeometry((300, 300, 300))  # 300^3 at scale 2, 150^3 at scale 4
    assert _pipeline._second_run_scales(resolve_stages((160, 200), vol_shape=huge.shape, scales=(1,)), huge,
                                        (160, 200)) == ((4,), (1,))
    assert _pipeline._second_run_scales(one, big, (160, 95)) == ((), (1,))  # 47 columns at scale 2
    run, why = _pipeline._second_run_reason("default", _Outcome(AXIS_KEPT), full, {}, one, big)  # 33 columns
    assert not run and "256x256x256" in why and 'recipe = "precession"' in why


@pytest.fixture(scope="module")
def case():
    return make_case("offset", n=24, n_views=48, seed=3)


@pytest.mark.parametrize("misfits, taken", [((1.0, 0.99), True), ((1.0, 1.0001), False)])
def test_the_geometry_whose_reconstruction_predicts_better_is_returned(case, monkeypatch, misfits, taken):
    # the rule, with the comparison's verdict given: the precession recipe's geometry only when it predicts
    # the views left out better by more than SECOND_RUN_GAIN, and the motion model's note says so
    seen = []

    def misfit(p, vg, geometries, **kw):
        seen.append((len(geometries), kw.get("scale"), kw.get("weights"), kw.get("subsets"), kw.get("background")))
        return np.array(misfits, float)

    calls = []
    inner = _pipeline.calibrate

    def calibrate(*a, **kw):
        calls.append({k: kw.get(k) for k in ("recipe", "rings", "zingers", "second_run", "checkpoint", "jolts")})
        return inner(*a, **kw)

    monkeypatch.setattr(_pipeline, "_second_run_reason", lambda *a: (True, ""))
    monkeypatch.setattr(_select, "cross_validated_misfit", misfit)
    monkeypatch.setattr(_pipeline, "calibrate", calibrate)
    # subsets of >= 8 views here (15 by default), so that the 24 views of each comparison volume make 3 of them, where
    # the rounds' rule (>= 30 views) makes 1
    monkeypatch.setattr(_driver, "NONNEG_MIN_SUBSET_VIEWS", 8)
    g, p, vg = case.scan.geometry, case.scan.projections, case.vol_geom
    before = p.copy()
    res = pdvc.calibrate(p, g, vg, jolts=False, rings="off", zingers="off", checkpoint=lambda state: None)
    assert np.array_equal(p, before)
    # the precession recipe, on the data as the first run treated them, its own run (no checkpoints, no third run)
    assert calls == [dict(recipe="precession", rings="off", zingers="off", second_run="off", checkpoint=None, jolts=False)]
    # one comparison of the two geometries, at the default's coarsest scale, each volume by at most SECOND_RUN_SUBSETS
    # ordered subsets (a single fit, as the short scans' refining round), the residual as it is (the clean scan fitted
    # no background per view)
    assert _pipeline.SECOND_RUN_SUBSETS == 6 and _driver.nonneg_subsets(24) == 1
    assert seen == [(2, 1, None, 3, None)]
    assert res.options["recipe"] == ("precession" if taken else "default")
    assert ("precession recipe's geometry is returned" in res.options["second_run"]) is taken
    assert res.options["second_run"] in res.options["model"]
    assert {"second run (precession recipe)", "second run (comparison)"} <= set(res.timings)
    if taken:
        assert res.timings["first run (default recipe)"] > 0


def test_the_comparison_takes_out_the_background_per_view_the_default_run_fitted(case, monkeypatch):
    # an air level drifting over the scan (air = "off", so that it is left to the background per view): the default
    # run fits a plane per view with the motion, and the comparison of the finished calibrations takes the plane of
    # each predicted view out too (docs/method.md §5.25)
    seen = []
    monkeypatch.setattr(_pipeline, "_second_run_reason", lambda *a: (True, ""))
    monkeypatch.setattr(_select, "cross_validated_misfit",
                        lambda p, vg, gs, **kw: seen.append(kw.get("background")) or np.ones(len(gs)))
    g, vg = case.scan.geometry, case.vol_geom
    p = case.scan.projections + np.linspace(0.0, 0.3, g.n_views, dtype=np.float32)[:, None, None]
    res = pdvc.calibrate(p, g, vg, max_outer=2, jolts=False, rings="off", zingers="off", air="off", second_run="auto")
    assert res.options["background"].startswith("a plane per view")
    assert seen == [1]


@pytest.mark.parametrize("first, second, runs, taken", [
    ((1.0, 1.01), (0.99,), 2, "twice"),  # once per turn 1 % worse: run again twice a turn, which predicts 1 % better
    ((1.0, 1.01), (1.0001,), 2, None),  # ... and predicts worse than the default: the default's kept
    ((1.0, 1.0003), None, 1, None),  # 0.03 % worse, within SECOND_RUN_TWICE_LOSS: no third run
])
def test_a_precession_recipe_that_predicts_worse_runs_again_with_a_precession_twice_a_turn(
        case, monkeypatch, first, second, runs, taken):
    # the rule of docs/method.md §5.26, with the comparisons' verdicts given: the once-per-turn recipe predicting the
    # views left out worse than the default by more than SECOND_RUN_TWICE_LOSS runs again with basis drift:2, whose
    # geometry alone is then scored (the default's misfit is reused) and returned when it predicts better than the
    # default's by more than SECOND_RUN_GAIN
    assert _pipeline.SECOND_RUN_TWICE_LOSS > _pipeline.SECOND_RUN_GAIN
    answers, seen = [first, second], []

    def misfit(p, vg, geometries, **kw):
        seen.append((len(geometries), kw.get("scale"), kw.get("subsets")))
        return np.array(answers[len(seen) - 1], float)

    calls, inner = [], _pipeline.calibrate

    def calibrate(*a, **kw):
        calls.append((kw.get("recipe"), kw.get("basis"), kw.get("second_run"), kw.get("max_outer")))
        return inner(*a, **kw)

    monkeypatch.setattr(_pipeline, "_second_run_reason", lambda *a: (True, ""))
    monkeypatch.setattr(_select, "cross_validated_misfit", misfit)
    monkeypatch.setattr(_pipeline, "calibrate", calibrate)
    g, p, vg = case.scan.geometry, case.scan.projections, case.vol_geom
    res = pdvc.calibrate(p, g, vg, jolts=False, rings="off", zingers="off")
    # the run twice a turn gets more rounds (a richer model) unless the user set them
    twice = ("precession", "drift:2", "off", _pipeline.SECOND_RUN_TWICE_ROUNDS)
    assert calls == [("precession", None, "off", None), twice][:runs]
    assert seen == [(2, 1, 1), (1, 1, 1)][:runs]
    text = res.options["second_run"]
    assert ("(basis drift:2)" in text) is (runs == 2)
    assert ("precession recipe's geometry is returned" in text) is (taken is not None)
    assert ("second run (precession twice a turn)" in res.timings) is (runs == 2)
    if taken:
        assert any("basis=drift:2" in st for st in res.options["stages"]) and text.endswith("(basis drift:2)")
        assert res.timings["first run (default recipe)"] > 0 and res.options["recipe"] == "precession"
    else:
        assert res.options["recipe"] == "default"


def test_on_a_large_scan_the_precession_recipe_runs_at_the_coarse_scales_only(case, monkeypatch):
    # the finest scale's correlation grid above SECOND_RUN_MAX_VOXELS (here lowered so that the 24^3 case's scale 1,
    # a 48^3 grid, is above it and scale 2's 24^3 grid is not): the precession recipe runs at scale 2 alone with
    # SECOND_RUN_COARSE_ROUNDS rounds, its geometry is compared at scale 2 and the note says which scales ran
    monkeypatch.setattr(_pipeline, "SECOND_RUN_MAX_VOXELS", 30**3)
    monkeypatch.setattr(_pipeline, "_second_run_reason", lambda *a: (True, ""))
    monkeypatch.setattr(_select, "cross_validated_misfit", lambda p, vg, gs, **kw: seen.append(kw["scale"]) or np.ones(len(gs)))
    calls, seen, inner = [], [], _pipeline.calibrate

    def calibrate(*a, **kw):
        calls.append({k: kw.get(k) for k in ("recipe", "scales", "max_outer", "guards", "basis")})
        return inner(*a, **kw)

    monkeypatch.setattr(_pipeline, "calibrate", calibrate)
    g, p, vg = case.scan.geometry, case.scan.projections, case.vol_geom
    res = pdvc.calibrate(p, g, vg, scales=(2, 1), jolts=False, rings="off", zingers="off")
    assert calls == [dict(recipe="precession", scales=(2,), max_outer=_pipeline.SECOND_RUN_COARSE_ROUNDS,
                          guards=_pipeline.SECOND_RUN_COARSE_GUARDS, basis=None)]
    assert seen == [2] and res.options["recipe"] == "default"  # predicts no better: the default's geometry kept
    assert "at scale 2 only (the correlation grid of scale 1, 48x48x48" in res.options["second_run"]
    # the user's rounds are kept
    calls.clear()
    pdvc.calibrate(p, g, vg, scales=(2, 1), max_outer=3, jolts=False, rings="off", zingers="off")
    assert calls[0]["max_outer"] == 3 and calls[0]["scales"] == (2,)


def test_second_run_off_runs_the_default_alone_and_bad_values_are_refused(case, monkeypatch):
    monkeypatch.setattr(_pipeline, "_second_run_reason", lambda *a: pytest.fail("second_run='off' must not ask"))
    g, p, vg = case.scan.geometry, case.scan.projections, case.vol_geom
    res = pdvc.calibrate(p, g, vg, jolts=False, second_run="off")
    assert "second_run" not in res.options and res.options["recipe"] == "default"
    with pytest.raises(pdvc.calibration.CalibrationError, match="second_run must be 'auto' or 'off'"):
        pdvc.calibrate(p, g, vg, second_run="on")


def test_the_config_takes_second_run_and_a_written_stage_list_runs_alone(tmp_path):
    from pdvc._inputs import calibration_options
    from pdvc.io import load_config

    def cfg(**cal):
        d = {"data": {"path": "scan"}, "geometry": {"type": "parallel", "pixel": 1.0}}
        if cal:
            d["calibration"] = cal
        return load_config(d, base_dir=tmp_path).calibration

    assert cfg().second_run == "auto" and cfg(second_run="off").second_run == "off"
    with pytest.raises(ConfigError, match="second_run"):
        cfg(second_run="sometimes")
    assert calibration_options(cfg(), (64, 64))["second_run"] == "auto"
    assert calibration_options(cfg(second_run="off"), (64, 64))["second_run"] == "off"
    staged = cfg(stage=[{"name": "model", "basis": "fourier:1"}])
    assert calibration_options(staged, (64, 64))["second_run"] == "off"
    # a volume of the user's own (the PSI example's oversample = 1), as pdvc.calibrate(oversample=1) decides
    assert calibration_options(cfg(oversample=1), (64, 64))["second_run"] == "off"
    assert calibration_options(cfg(tol_px=0.005), (64, 64))["second_run"] == "auto"


def test_a_second_run_that_fails_keeps_the_first_runs_result(case, monkeypatch):
    # the precession recipe raising (here: a library error from inside its run) must not lose the default's result
    inner = _pipeline.calibrate

    def calibrate(*a, **kw):
        if kw.get("recipe") == "precession":
            raise pdvc.calibration.CalibrationError("the precession recipe could not run")
        return inner(*a, **kw)

    monkeypatch.setattr(_pipeline, "_second_run_reason", lambda *a: (True, ""))
    monkeypatch.setattr(_pipeline, "calibrate", calibrate)
    g, p, vg = case.scan.geometry, case.scan.projections, case.vol_geom
    res = pdvc.calibrate(p, g, vg, jolts=False)
    alone = pdvc.calibrate(p, g, vg, jolts=False, second_run="off")
    assert res.options["recipe"] == "default" and res.status == alone.status
    assert np.allclose(res.geometry.vectors, alone.geometry.vectors)
    assert "failed" in res.options["second_run"] and "could not run" in res.options["model"]


@pytest.mark.parametrize("misfits, taken", [((1.0, 0.99), True), ((1.0, 1.0001), False)])
def test_on_a_large_scan_the_comparison_comes_before_the_defaults_finer_scale(case, monkeypatch, misfits, taken):
    # the finest scale above the cap (lowered, as above): the precession recipe runs and is compared with the default's
    # geometry at the end of its scale-2 stages, before its scale-1 stages (docs/method.md §5.55). Taken: the default
    # never runs at scale 1; kept: the default goes on exactly as it runs alone
    monkeypatch.setattr(_pipeline, "SECOND_RUN_MAX_VOXELS", 30**3)
    monkeypatch.setattr(_pipeline, "_second_run_reason", lambda *a: (True, ""))
    compared = []

    def misfit(p, vg, gs, **kw):
        compared.append(gs[0])
        events.append(("compare", kw["scale"]))
        return np.array(misfits[:len(gs)], float)

    monkeypatch.setattr(_select, "cross_validated_misfit", misfit)
    events = []

    def progress(info):
        if info["event"] in ("stage", "second_run"):
            events.append((info["event"], info.get("scale")))

    g, p, vg = case.scan.geometry, case.scan.projections, case.vol_geom
    kw = dict(scales=(2, 1), jolts=False, rings="off", zingers="off", progress=progress)
    res = pdvc.calibrate(p, g, vg, **kw)
    first = events.index(("second_run", None))
    assert ("stage", 1) not in events[:first]  # nothing at scale 1 before the comparison
    assert events[first:].count(("compare", 2)) == 1
    assert ("stage", 1) in events[first:] or taken  # ... and the default's scale 1 only where its geometry is kept
    assert (("stage", 1) in events) is (not taken)
    assert "before the default's scale 1" in res.options["second_run"]
    assert ("precession recipe's geometry is returned" in res.options["second_run"]) is taken
    assert res.options["recipe"] == ("precession" if taken else "default")
    assert {"second run (precession recipe)", "second run (comparison)"} <= set(res.timings)
    assert (res.timings.get("first run (default recipe)", 0) > 0) is taken
    # the default's geometry compared is the one its scale-2 stages reached, not the nominal one
    assert not np.allclose(compared[0].vectors, g.vectors)
    if not taken:
        alone = pdvc.calibrate(p, g, vg, **dict(kw, second_run="off", progress=None))
        np.testing.assert_array_equal(res.geometry.vectors, alone.geometry.vectors)
        assert res.status == alone.status
