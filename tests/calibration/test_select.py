"""Automatic choice of the motion model: candidates scored on the views they were not fitted to."""

from __future__ import annotations

import numpy as np
import pytest

import pdvc
from pdvc.calibration import MODELS, ModelChoice, Stage, StageError, compare_models, recipe_stages, run_stages
from pdvc.calibration._select import (
    MIN_MODEL_GAIN, MODEL_FIT_TOL_PX, OWN_MODEL_GAIN, halves, model_name, pick_model, richer_than_simpler, with_model,
)
from pdvc.correlation import estimate_noise_variance
from pdvc.geometry import Poses, fix_gauge, reprojection_error
from tests.correlation.cases import make_case

_CASES: dict = {}


def _case(name):
    if name not in _CASES:
        _CASES[name] = make_case(name, n=24, n_views=48)
    return _CASES[name]


def test_halves_are_complementary_interleaved_blocks():
    a, b = halves(48)
    assert np.array_equal(np.sort(np.concatenate([a, b])), np.arange(48))
    assert a.size == b.size == 24 and 0 in a
    assert np.count_nonzero(np.diff(a) > 1) == 7  # 8 blocks of 3 consecutive views in each half
    a, b = halves(91)
    assert abs(a.size - b.size) <= 6 and not set(a) & set(b)


@pytest.mark.parametrize("name, wins", [("precession_drift", "precession"), ("tilted_axis", "axis"), ("offset", "axis")])
def test_compare_models_picks_the_model_that_holds_the_motion(name, wins):
    # The sharp object (a voxelised analytic phantom: the data come from the analytic projector) and
    # the nominal poses. A 0.3 deg once-per-turn precession with a drift that accelerates is not in
    # the sample-frame {1, t, cos, sin} model: the lab-frame drift:2 model predicts the half of the
    # views it did not see 11 % better (measured); a fixed tilted or offset axis is in both, and the
    # richer model predicts no better (measured -0.2 and -0.6 %): the axis model is kept.
    c = _case(name)
    g = c.scan.geometry
    choice = compare_models(
        c.truth, c.vol_geom, c.scan.projections, g, Poses.identity(g.n_views), dict(MODELS["axis"]),
        {"precession": dict(MODELS["precession"])}, noise_variance=estimate_noise_variance(c.scan.projections),
        angles=np.linspace(0, 2 * np.pi, g.n_views, endpoint=False), center=c.vol_geom.offset, own_name="axis",
    )
    assert choice.winner == wins
    assert set(choice.scores) == {"axis", "precession"}
    gain = 1 - choice.scores["precession"] / choice.scores["axis"]
    if wins == "precession":
        assert gain > 0.05 and choice.gain == pytest.approx(gain) and choice.changed
        assert "precession" in choice.text() and "better than axis" in choice.text()
    else:
        assert gain < 0.001 and choice.gain == 0.0 and not choice.changed
        assert choice.text().startswith("axis kept")
    assert choice.n_passes > 4 and ModelChoice(**choice.to_dict()) == choice
    # how far each model moves the sample from the (nominal) poses: the injected motion, gauge-free
    truth = np.sqrt(np.mean(np.sum((g.apply_poses(*fix_gauge(c.scan.rotvecs, c.scan.translations, g, center=c.vol_geom.offset))
                                    .project_points(c.points) - g.project_points(c.points)) ** 2, axis=-1)))
    assert choice.shifts_px[wins] == pytest.approx(truth, rel=0.35)


def test_the_fits_of_the_model_choice_stop_at_their_own_tolerance_with_the_same_verdict():
    # The choice's fits stop at a Gauss-Newton step below MODEL_FIT_TOL_PX (0.01 px), not at the 0.001 px of a round:
    # fewer passes, and scores (predictions of the other half) that the last thousandths of a pixel do not move. As
    # the calibration calls it (10 passes at most, a stage's max_iter); measured 48 against 39 passes, the axis model's
    # score 0.976511 against 0.976529
    c = _case("offset")
    g = c.scan.geometry
    kw = dict(noise_variance=estimate_noise_variance(c.scan.projections),
              angles=np.linspace(0, 2 * np.pi, g.n_views, endpoint=False), center=c.vol_geom.offset, own_name="axis")
    args = (c.truth, c.vol_geom, c.scan.projections, g, Poses.identity(g.n_views), dict(MODELS["axis"]),
            {"precession": dict(MODELS["precession"])})
    fine = compare_models(*args, tol_px=1e-3, max_iter=10, **kw)
    default = compare_models(*args, max_iter=10, **kw)
    assert MODEL_FIT_TOL_PX == 0.01
    assert default.n_passes <= fine.n_passes - 6
    assert default.winner == fine.winner == "axis"
    for k in fine.scores:
        assert default.scores[k] == pytest.approx(fine.scores[k], rel=1e-4)


def test_candidates_are_a_stage_field_the_default_recipe_sets_unless_the_model_is_given():
    st = recipe_stages("default", (50, 60), scales=(2, 1))
    fa = ("fixed_axis", "precession")
    assert [s.candidates for s in st] == [(), fa, fa, ()]  # warm-up, two scales, jolts
    assert all(s.candidates == () for s in recipe_stages("default", (50, 60), basis="fourier:2"))
    assert all(s.candidates == () for s in recipe_stages("default", (50, 60), frame="lab"))
    assert all(s.candidates == () for s in recipe_stages("default", (50, 60), candidates=()))
    assert all(s.candidates == () for r in ("precession", "jolts", "axis") for s in recipe_stages(r, (50, 60)))
    assert Stage(candidates="precession").candidates == ("precession",)
    assert Stage.from_dict(Stage(candidates=("precession",)).to_dict()).candidates == ("precession",)
    for bad in (("wobble",), ("precession", "precession")):
        with pytest.raises(StageError, match="candidates"):
            Stage(candidates=bad)
    model = st[1]
    assert model_name(model) == "axis" and with_model(model, None) is model
    won = ModelChoice(winner="precession", own="axis", scores={"axis": 1.0, "precession": 0.9}, gain=0.1)
    chosen = with_model(model, won)
    assert (chosen.basis, chosen.frame, chosen.reconstruct, chosen.name) == ("drift:2", "lab", "nonneg_ls", "model:precession")
    assert model_name(chosen) == "precession" and chosen.scale == model.scale
    assert with_model(st[0], won) is st[0]  # a stage without candidates keeps its model
    assert with_model(model, ModelChoice(winner="axis", own="axis")) is model


def test_a_kept_axis_model_says_what_the_comparison_cannot_see():
    # a precession once per turn hardly changes the cross-validated scores (docs/method.md §5.12): the text
    # of an axis model kept over the precession model points to the comparison of finished calibrations
    # (second_run), and only that text
    kept = ModelChoice(winner="axis", own="axis", scores={"axis": 1.0, "precession": 0.998})
    assert kept.text().startswith("axis kept: no candidate") and 'second_run = "auto"' in kept.text()
    won = ModelChoice(winner="precession", own="axis", scores={"axis": 1.0, "precession": 0.9}, gain=0.1)
    simpler = ModelChoice(winner="fixed_axis", own="axis", scores={"fixed_axis": 1.0, "axis": 0.999}, simpler=True,
                          sizes={"fixed_axis": 5, "axis": 20})
    other = ModelChoice(winner="precession", own="precession", scores={"precession": 1.0, "axis": 1.0})
    assert all("second_run" not in c.text() for c in (won, simpler, other))


def test_an_axis_model_kept_because_a_richer_model_sees_beyond_the_fixed_axis_says_so():
    # held-out foam 9 of the quick benchmark (a precession twice a turn at i0 = 2e3): measured scores
    sizes = {"fixed_axis": 5, "axis": 20, "precession": 35}
    scores = {"axis": 0.9463, "fixed_axis": 0.949, "precession": 0.9433}
    assert pick_model(scores, sizes, "axis") == "axis"
    assert richer_than_simpler(scores, sizes, "fixed_axis") == ["precession"]
    assert richer_than_simpler(scores, sizes, "axis") == []
    text = ModelChoice(winner="axis", own="axis", scores=scores, sizes=sizes).text()
    assert text.startswith("axis kept: a richer model predicts the views it was not fitted to better than the simpler one "
                           "by more than 0.4 % (precession 0.6 % better than fixed_axis: a motion beyond it)")
    assert 'second_run = "auto"' in text
    # the own model beating the fixed axis by itself keeps the older text
    beat = ModelChoice(winner="axis", own="axis", scores=dict(scores, axis=0.94), sizes=sizes).text()
    assert beat.startswith("axis kept: it predicts the views it was not fitted to 0.95 % better than fixed_axis")


def _run(case, stages, **kw):
    g = case.scan.geometry
    return run_stages(case.scan.projections, g, case.vol_geom, stages, noise_variance=estimate_noise_variance(case.scan.projections),
                      **kw)


def _error(case, poses):
    g = case.scan.geometry
    truth = g.apply_poses(*fix_gauge(case.scan.rotvecs, case.scan.translations, g, center=case.vol_geom.offset))
    return reprojection_error(g.apply(poses), truth, case.points).rms


def _case48(name):
    key = name + "48"
    if key not in _CASES:
        _CASES[key] = make_case(name, n=48, n_views=90)
    return _CASES[key]


def test_the_driver_chooses_once_before_the_model_runs_the_winner_and_keeps_the_choice_on_resume():
    # The README's precession case (48^3, 90 views, 0.3 deg once-per-turn precession and a drift that
    # accelerates): from the warm-up's poses the precession model predicts the views it did not see
    # 0.89 % better (measured), above MIN_MODEL_GAIN; it then runs the model stage. Measured: 0.030 px
    # against 0.09 px for the axis model (nominal 1.02 px).
    c = _case48("precession_drift")
    stages = recipe_stages("default", c.scan.geometry.det_shape, scales=(1,), max_outer=2, jolts=False)
    saved, events = [], []
    out = _run(c, stages, checkpoint=lambda d: saved.append(d), progress=lambda d: events.append((d["event"], d.get("index"))))
    # the choice is announced, reported, then the stage runs the winner (its time holds the choice)
    assert [e for e in events if e[0] in ("choosing", "model", "stage")] == [("stage", 0), ("choosing", 1), ("model", None), ("stage", 1)]
    ch = out.model_choice
    assert ch is not None and ch.winner == "precession" and ch.gain > 0.007
    models = [h["model"] for h in out.history]
    assert models[0] == "drift (lab frame)" and set(models[1:]) == {"precession"} and len(models) >= 2
    assert [o.name for o in out.stages] == ["warmup", "model:precession"]
    assert [("model_choice" in h) for h in out.history] == [False, True] + [False] * (len(models) - 2)
    assert _error(c, out.poses) < 0.05
    # a run resumed after the model stage's first round reads the choice back: no comparison again
    first = next(d for d in saved if d["stage_index"] == 1 and d["rounds_done"] == 1)
    again = _run(c, stages, poses=first["poses"], start=(1, 1), history=first["history"])
    assert again.model_choice == ch
    assert [o.name for o in again.stages] == ["model:precession"]
    assert [h["model"] for h in again.history] == models


def test_the_driver_takes_the_fixed_axis_on_an_offset_axis_and_keeps_its_own_model_without_that_candidate():
    c = _case48("offset")  # measured: the precession model predicts 0.28 % better, below MIN_MODEL_GAIN
    stages = recipe_stages("default", c.scan.geometry.det_shape, scales=(1,), max_outer=3, jolts=False,
                           candidates=("precession",))
    out = _run(c, stages)
    assert out.model_choice.winner == "axis" and not out.model_choice.changed and out.model_choice.gain == 0.0
    assert out.model_choice.text().startswith("axis kept: no candidate")
    assert {h["model"] for h in out.history[1:]} == {"axis"} and [o.name for o in out.stages] == ["warmup", "model"]
    assert _error(c, out.poses) < 0.02
    # measured from the warm-up's poses: the axis model predicts the views it was not fitted to 0.1 % worse than
    # the fixed axis (it needs OWN_MODEL_GAIN), the precession model 0.1 % better than that (it needs MIN_MODEL_GAIN,
    # and more than OWN_MODEL_GAIN to keep the axis model): the default candidates (docs/method.md §5.48)
    fixed = recipe_stages("default", c.scan.geometry.det_shape, scales=(1,), max_outer=3, jolts=False)
    assert [s.candidates for s in fixed if s.name == "model"] == [("fixed_axis", "precession")]
    out = _run(c, fixed)
    ch = out.model_choice
    assert ch.winner == "fixed_axis" and ch.changed and ch.simpler and ch.own == "axis"
    assert set(ch.scores) == {"axis", "fixed_axis", "precession"} and ch.sizes == {"fixed_axis": 5, "axis": 20, "precession": 35}
    assert ch.text().startswith("fixed_axis: predicts the views it was not fitted to as well as axis, with fewer parameters")
    assert {h["model"] for h in out.history[1:]} == {"fixed_axis"} and [o.name for o in out.stages] == ["warmup", "model:fixed_axis"]
    assert _error(c, out.poses) < 0.02


def test_pick_model_takes_the_simplest_model_no_richer_one_beats_by_its_threshold():
    sizes = {"fixed_axis": 5, "axis": 20, "precession": 35}
    assert OWN_MODEL_GAIN < MIN_MODEL_GAIN
    pick = lambda f, a, p: pick_model({"fixed_axis": f, "axis": a, "precession": p}, sizes, "axis")  # noqa: E731
    assert pick(1.0, 1.0, 1.0) == "fixed_axis"  # ties: the simplest
    assert pick(1.0, 0.997, 0.9965) == "fixed_axis"  # the own model 0.3 % better (< 0.4 %), precession 0.35 % (< 0.4 %)
    assert pick(1.0, 0.995, 0.99) == "axis"  # axis 0.5 % better; precession only 0.5 % better than axis
    assert pick(1.0, 0.995, 0.98) == "precession"  # 1.5 % better than axis
    assert pick(1.0, 0.998, 0.99) == "precession"  # axis not kept, but precession 1 % better than the fixed axis
    assert pick(1.0, 1.01, 1.005) == "fixed_axis"  # both richer models worse
    # neither richer model is chosen over the fixed axis (axis 0.3 % < 0.4 %, precession 0.5 % < 0.7 %), but the
    # precession model sees more than OWN_MODEL_GAIN beyond it: the fixed axis is not kept, and the choice is the
    # one made without it (from the own model up; docs/method.md §5.48)
    assert pick(1.0, 0.997, 0.995) == "axis"
    assert pick(1.0, 1.01, 0.994) == "precession"  # 0.6 % better than the fixed axis, 1.6 % better than axis
    assert pick(1.0, 1.0, 0.9955) == "axis"  # just above OWN_MODEL_GAIN
    assert pick(1.0, 1.0, 0.9965) == "fixed_axis"  # just below
    # the own model first among equal sizes; a candidate alone against it
    assert pick_model({"own": 1.0, "other": 0.999}, {"own": 5, "other": 5}, "own") == "own"
    assert pick_model({"axis": 1.0, "precession": 0.992}, sizes, "axis") == "precession"
    assert pick_model({"axis": 1.0, "precession": 0.994}, sizes, "axis") == "axis"


def test_calibrate_reports_the_model_it_chose():
    c = _case("offset")
    res = pdvc.calibrate(c.scan.projections, c.scan.geometry, c.vol_geom, max_outer=2)
    assert "cross-validated chi^2: axis" in res.options["model"]
    given = pdvc.calibrate(c.scan.projections, c.scan.geometry, c.vol_geom, max_outer=2, basis="fourier:1")
    assert given.options["model"].startswith("as given")


def test_candidates_are_a_config_key(tmp_path):
    from pdvc.io import ConfigError, load_config

    raw = lambda **cal: {"data": {"path": "p.npy"}, "geometry": {"type": "parallel", "pixel": 1.0}, "calibration": cal}  # noqa: E731
    assert load_config(raw(candidates=[]), base_dir=tmp_path).calibration.recipe_parameters() == {"candidates": ()}
    cfg = load_config(raw(candidates=["precession"]), base_dir=tmp_path)
    assert cfg.calibration.recipe_parameters() == {"candidates": ("precession",)}
    cfg = load_config(raw(candidates=["fixed_axis", "precession"]), base_dir=tmp_path)
    assert cfg.calibration.recipe_parameters() == {"candidates": ("fixed_axis", "precession")}
    for bad in (["wobble"], "precession", ["precession", "precession"]):
        with pytest.raises(ConfigError, match=r"calibration\.candidates"):
            load_config(raw(candidates=bad), base_dir=tmp_path)


def test_too_few_views_to_compare_keep_the_model_and_say_why():
    # 12 views: halves of 6 cannot determine the precession model's 7 functions (and a comparison needs 8 per half)
    c = make_case("offset", n=24, n_views=12)
    g = c.scan.geometry
    kw = dict(noise_variance=estimate_noise_variance(c.scan.projections), angles=np.linspace(0, 2 * np.pi, 12, endpoint=False),
              center=c.vol_geom.offset, own_name="axis")
    args = (c.truth, c.vol_geom, c.scan.projections, g, Poses.identity(12), dict(MODELS["axis"]), {"precession": dict(MODELS["precession"])})
    ch = compare_models(*args, **kw)
    assert ch.winner == "axis" and not ch.scores and "12 views" in ch.text() and "not compared" in ch.text()
    c20 = make_case("offset", n=24, n_views=20)
    kw["angles"] = np.linspace(0, 2 * np.pi, 20, endpoint=False)
    ch = compare_models(c20.truth, c20.vol_geom, c20.scan.projections, c20.scan.geometry, Poses.identity(20), dict(MODELS["axis"]),
                        {"precession": dict(MODELS["precession"])}, **kw)
    assert ch.winner == "axis" and not ch.scores and "cannot determine precession" in ch.note
    res = pdvc.calibrate(c.scan.projections, g, c.vol_geom, max_outer=2)  # runs, and says so
    assert "not compared" in res.options["model"]


def test_simpler_candidates_are_not_compared_on_a_short_scan():
    from pdvc.calibration._init import opposite_fraction
    from pdvc.geometry import parallel

    full = parallel(np.linspace(0, 2 * np.pi, 90, endpoint=False), det_shape=(8, 10), pixel=1.0)
    half = parallel(np.linspace(0, np.pi, 91, endpoint=False), det_shape=(8, 10), pixel=1.0)
    assert opposite_fraction(full) == 1.0 and opposite_fraction(half) < 0.1
    # the reason given leaves out the models simpler than the own one, and the choice says why
    c = _case("offset")
    g = c.scan.geometry
    kw = dict(noise_variance=estimate_noise_variance(c.scan.projections), angles=np.linspace(0, 2 * np.pi, g.n_views, endpoint=False),
              center=c.vol_geom.offset, own_name="axis", max_iter=2)
    cands = {k: dict(MODELS[k]) for k in ("fixed_axis", "precession")}
    ch = compare_models(c.truth, c.vol_geom, c.scan.projections, g, Poses.identity(g.n_views), dict(MODELS["axis"]), cands,
                        skip_simpler="a short scan", **kw)
    assert set(ch.scores) == {"axis", "precession"} and ch.note == "fixed_axis left out: a short scan"
    assert ch.text().endswith("; fixed_axis left out: a short scan")
    only = compare_models(c.truth, c.vol_geom, c.scan.projections, g, Poses.identity(g.n_views), dict(MODELS["axis"]),
                          {"fixed_axis": cands["fixed_axis"]}, skip_simpler="a short scan", **kw)
    assert only.winner == "axis" and not only.scores and only.text() == "axis (not compared: fixed_axis left out: a short scan)"


def test_the_driver_leaves_simpler_candidates_out_on_a_half_turn():
    from pdvc.geometry import parallel

    c = _case("offset")  # the phantom and grid; the scan made again over half a turn of parallel beam
    g = parallel(np.linspace(0, np.pi, 48, endpoint=False), det_shape=c.scan.geometry.det_shape, pixel=1.0)
    p = pdvc.forward(c.truth, c.vol_geom, g)
    stages = recipe_stages("default", g.det_shape, scales=(1,), max_outer=1, jolts=False, candidates=("fixed_axis", "precession"))
    out = run_stages(p, g, c.vol_geom, stages, noise_variance=1e-4)
    ch = out.model_choice
    assert "fixed_axis" not in ch.scores and set(ch.scores) == {"axis", "precession"}
    assert ch.note.startswith("fixed_axis left out: a short scan (0 % of the views have an opposite view)")
