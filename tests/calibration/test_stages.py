"""Stages as data: validation, recipes, TOML round trips, the config keys, and the pipeline's contract."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tomli_w

try:
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib

import pdvc
from pdvc import Status
from pdvc.calibration import (
    RECIPES,
    CalibrationError,
    Stage,
    StageError,
    auto_scales,
    capped_oversample,
    recipe_stages,
    refine_stage,
    resolve_stages,
    run_stages,
    stages_from_dicts,
    stages_to_dicts,
)
from pdvc.calibration._stages import FULL_TURN_FINE_ROUNDS, NONNEG_REFINE_SUBSETS, REFINE_ROUNDS
from pdvc.io import ConfigError, load_config, write_config


@pytest.mark.parametrize(
    "kw, field",
    [
        (dict(basis="fourier"), "basis"),
        (dict(frame="world"), "frame"),
        (dict(fixed=("tx", "yaw")), "fixed"),
        (dict(fixed=("tx", "ty", "tz", "rx", "ry", "rz")), "fixed"),
        (dict(reconstruct="sirt"), "reconstruct"),
        (dict(guards=("sharpness",)), "guards"),
        (dict(rounds=0), "rounds"),
        (dict(scale=1.5), "scale"),
        (dict(tol_px=0.0), "tol_px"),
        (dict(until="forever"), "until"),
        (dict(stall_ratio=-1.0), "stall_ratio"),
        (dict(oversample_by="zoom"), "oversample_by"),
        (dict(accelerate="yes"), "accelerate"),
        (dict(subsets=0), "subsets"),
        (dict(subsets=True), "subsets"),
        (dict(subsets="many"), "subsets"),
    ],
)
def test_a_bad_stage_field_is_named(kw, field):
    with pytest.raises(StageError, match=field):
        Stage(**kw)


def test_stage_round_trips_through_toml():
    stages = recipe_stages("precession", (100, 300), scales=(2, 1))
    text = tomli_w.dumps({"calibration": {"stage": stages_to_dicts(stages)}})
    again = stages_from_dicts(tomllib.loads(text)["calibration"]["stage"])
    assert again == stages
    with pytest.raises(StageError, match=r"stage\[0\].*unknown key.*'rotations'"):
        stages_from_dicts([{"name": "x", "rotations": 3}])


def test_default_recipe_on_nonneg_ls_spends_its_rounds_at_the_coarse_scale_and_refines_once():
    # a short scan (the pipeline sets reconstruct = "nonneg_ls"): the coarse scale gets twice the rounds,
    # the finest one refining round that is not asked to converge
    stages = recipe_stages("default", (134, 160), reconstruct="nonneg_ls")
    assert [(s.name, s.scale, s.rounds) for s in stages] == [("warmup", 2, 1), ("model", 2, 19), ("model", 1, 1), ("jolts", 1, 5)]
    coarse, fine = stages[1], stages[2]
    assert coarse.until == "converged" and fine.until == "rounds"
    assert fine.diverge_tol == 0.0 and fine.reconstruct == coarse.reconstruct == "nonneg_ls"
    # the refining round's one volume by more ordered subsets (§5.52); the coarse rounds keep the automatic ones
    assert [s.subsets for s in stages] == ["auto", "auto", NONNEG_REFINE_SUBSETS, NONNEG_REFINE_SUBSETS]
    assert [s.subsets for s in recipe_stages("default", (134, 160), reconstruct="nonneg_ls", subsets=2)] == [2] * 4
    assert {s.subsets for s in recipe_stages("default", (134, 160))} == {"auto"}
    assert {s.subsets for s in recipe_stages("default", (134, 160), reconstruct="nonneg_ls", max_outer=10)} == {"auto"}
    # the user's max_outer, FDK, one scale, the precession recipe: rounds as before
    assert [s.rounds for s in recipe_stages("default", (134, 160), reconstruct="nonneg_ls", max_outer=10)] == [1, 9, 10, 5]
    assert [s.rounds for s in recipe_stages("default", (134, 160))] == [1, 9, 10, 5]
    assert [s.rounds for s in recipe_stages("default", (76, 89), reconstruct="nonneg_ls")] == [1, 9, 5]
    assert [s.rounds for s in recipe_stages("precession", (134, 160))] == [1, 7, 8, 5]


def test_default_recipe_is_a_warmup_then_the_model_at_each_scale_the_warmup_at_the_first_only():
    stages = recipe_stages("default", (76, 89))
    assert auto_scales((76, 89)) == (1,)
    assert [(s.name, s.scale, s.rounds) for s in stages] == [("warmup", 1, 1), ("model", 1, 9), ("jolts", 1, 5)]
    warm, model, jolts = stages
    assert jolts.basis == "jolt_steps" and jolts.until == "rounds" and set(jolts.fixed) == {"rx", "ry", "rz", "ty"}
    assert warm.basis == "drift" and warm.frame == "lab" and set(warm.fixed) == {"rx", "ry", "rz"}
    assert warm.until == "rounds" and warm.guards == ()
    assert model.basis == "fourier:1" and model.frame == "sample" and model.fixed == ("rz",)
    assert model.until == "converged" and model.guards == ("consistency",)
    big = recipe_stages("default", (1024, 1024))
    # translations first at the coarsest scale; the finer one starts from the model's poses, with all its rounds
    assert [(s.name, s.scale, s.rounds) for s in big] == [("warmup", 4, 1), ("model", 4, 9), ("model", 2, 10), ("jolts", 2, 5)]
    # the finer scale refines: its model stops at the first fresh reconstruction that fits worse
    assert [s.diverge_tol for s in big if s.name == "model"] == [Stage().diverge_tol, 0.0]
    assert all(s.diverge_tol == 0.01 for s in recipe_stages("default", (1024, 1024), diverge_tol=0.01) if s.name == "model")
    assert len(recipe_stages("default", (76, 89), jolts=False)) == 2


def test_the_default_first_scale_stops_at_its_first_worse_reconstruction_on_full_turns_only():
    # strict_first_scale: the first scale's model stage gets the finer scales' diverge_tol, a user's diverge_tol wins
    big = recipe_stages("default", (1024, 1024), strict_first_scale=True)
    assert [s.diverge_tol for s in big if s.name == "model"] == [0.0, 0.0]
    assert all(s.diverge_tol == 0.01 for s in recipe_stages("default", (1024, 1024), diverge_tol=0.01,
                                                             strict_first_scale=True) if s.name == "model")
    # resolve_stages (what pdvc.calibrate runs) sets it for the default recipe on a full turn, where the precession
    # recipe's second run follows, and not on a half turn (none follows), nor without the geometry, nor for the
    # precession recipe
    tol = lambda **kw: [s.diverge_tol for s in resolve_stages((76, 89), **kw) if s.name == "model"]  # noqa: E731
    full = pdvc.circular_cone(np.linspace(0, 2 * np.pi, 90, endpoint=False), sod=200.0, odd=100.0, det_shape=(76, 89),
                              pixel=1.5)
    half = pdvc.parallel(np.linspace(0, np.pi, 90, endpoint=False), det_shape=(76, 89), pixel=1.0)
    assert tol(geom=full) == [0.0]
    assert tol(geom=half) == tol() == [Stage().diverge_tol]
    assert tol(geom=full, recipe="precession") == [Stage().diverge_tol]
    assert tol(geom=full, diverge_tol=0.02) == [0.02]


def test_the_default_finest_scale_refines_by_few_rounds_on_full_turns_only():
    # fine_rounds: the finest scale's model stage runs that many rounds, a refinement (until "rounds"); a user's
    # max_outer wins, and one scale has no finer one
    big = recipe_stages("default", (1024, 1024), fine_rounds=1)
    assert [(s.name, s.scale, s.rounds, s.until) for s in big] == [
        ("warmup", 4, 1, "rounds"), ("model", 4, 9, "converged"), ("model", 2, 1, "rounds"), ("jolts", 2, 5, "rounds")]
    assert [s.rounds for s in recipe_stages("default", (1024, 1024), fine_rounds=1, max_outer=4)] == [1, 3, 4, 5]
    assert [s.rounds for s in recipe_stages("default", (76, 89), fine_rounds=1)] == [1, 9, 5]
    for bad in (0, 1.5, True, "2"):
        with pytest.raises(StageError, match="fine_rounds"):
            recipe_stages("default", (1024, 1024), fine_rounds=bad)
    # resolve_stages sets FULL_TURN_FINE_ROUNDS with strict_first_scale: the default recipe on a full turn, where the
    # precession recipe's second run follows; a half turn and the precession recipe keep the recipe's rounds
    rounds = lambda **kw: [s.rounds for s in resolve_stages((1024, 1024), **kw) if s.name == "model"]  # noqa: E731
    full = pdvc.circular_cone(np.linspace(0, 2 * np.pi, 90, endpoint=False), sod=2000.0, odd=1000.0,
                              det_shape=(1024, 1024), pixel=1.5)
    half = pdvc.parallel(np.linspace(0, np.pi, 90, endpoint=False), det_shape=(1024, 1024), pixel=1.0)
    assert rounds(geom=full, scales=(4, 2)) == [9, FULL_TURN_FINE_ROUNDS]
    assert rounds(geom=half, scales=(4, 2)) == rounds(scales=(4, 2)) == [9, 10]
    assert rounds(geom=full, scales=(4, 2), recipe="precession") == [7, 8]


def test_the_refinement_is_an_option_of_the_default_recipe_with_its_own_model_and_volume():
    # refine = True: the precession model on nonneg_ls volumes at the coarsest scale, after the smooth model, at
    # most its rounds, stopping when they stop contracting; the jolts are still looked for at the finest scale on
    # the smooth model's own (FDK) volumes
    big = recipe_stages("default", (1024, 1024), refine=True)
    assert [(s.name, s.scale, s.rounds) for s in big] == [
        ("warmup", 4, 1), ("model", 4, 9), ("model", 2, 10), ("refine", 4, REFINE_ROUNDS), ("jolts", 2, 5)]
    refine, jolts = big[-2:]
    assert refine == refine_stage(big[1], scale=4)
    assert (refine.basis, refine.frame, refine.fixed, refine.reconstruct) == ("drift", "lab", ("rz",), "nonneg_ls")
    assert refine.until == "rounds" and refine.stall_ratio == 1.0 and refine.guards == ("consistency", "entropy")
    assert refine.candidates == () and refine.diverge_tol == Stage().diverge_tol
    assert jolts == recipe_stages("default", (1024, 1024))[-1] and jolts.reconstruct == "fdk"
    # off by default; never when the user chose the model or the volume (a short scan's nonneg_ls included), nor
    # in the other recipes
    names = lambda **kw: [s.name for s in recipe_stages(kw.pop("recipe", "default"), (76, 89), **kw)]  # noqa: E731
    assert "refine" in names(refine=True) and "refine" not in names()
    for kw in (dict(basis="fourier:2"), dict(reconstruct="nonneg_ls"), dict(reconstruct="fdk"), dict(recipe="precession")):
        assert "refine" not in names(refine=True, **kw)


def test_a_rounds_stage_stops_when_its_rounds_stop_contracting(small):
    # stall_ratio holds for either `until` (the refinement's rounds): the poses before the round that did not
    # contract are kept, and the stage's status says so
    p, g, vg = small.scan.projections, small.scan.geometry, small.vol_geom
    st = Stage(name="m", basis="constant", frame="lab", fixed=("rz", "ty"), until="rounds", rounds=6, tol_px=1e-9,
               stall_ratio=1e-9)  # any second round "does not contract"
    out = run_stages(p, g, vg, [st], noise_variance=1e-4)
    assert out.stages[0].status == Status.STOPPED_CONTRACTING and len(out.history) == 2
    # without the rule it runs its rounds
    free = run_stages(p, g, vg, [st.replace(stall_ratio=None, rounds=3)], noise_variance=1e-4)
    assert free.stages[0].status == Status.ROUNDS_DONE and len(free.history) == 3


def test_a_rounds_gauss_newton_stops_at_a_tenth_of_the_last_rounds_increment(small, monkeypatch):
    # inexact rounds on a full turn: the first round's passes run to the engine's 1e-3 px; each later one stops at a
    # step below INNER_FORCING x the last round's increment (full-resolution px, converted to the stage's scale)
    from pdvc.calibration import _driver

    p, g, vg = small.scan.projections, small.scan.geometry, small.vol_geom
    tols, passes = [], []
    real = _driver.correlate

    def spy(*a, **kw):
        tols.append(kw["tol_px"])
        res = real(*a, **kw)
        passes.append(int(res.n_iter))
        return res

    monkeypatch.setattr(_driver, "correlate", spy)
    st = Stage(name="m", basis="constant", frame="lab", fixed=("rz", "ty"), until="rounds", rounds=3, tol_px=1e-9,
               stall_ratio=None, scale=2)
    out = run_stages(p, g, vg, [st], noise_variance=1e-4)
    inc = [h["increment_px"] for h in out.history]
    assert len(tols) == 3 and tols[0] == _driver.INNER_TOL_PX
    assert tols[1:] == [max(_driver.INNER_TOL_PX, _driver.INNER_FORCING * i / 2) for i in inc[:2]]
    assert inc[0] > 1.0 and tols[1] > 0.03  # the 2-voxel offset's first round: its next one stops far sooner
    loose = passes[1]
    # a short scan (its first 202.5 deg) runs every round's passes to 1e-3 px: its rounds creep, the stall rule reads them
    tols.clear()
    run_stages(p[:28], g[:28], vg, [st], noise_variance=1e-4)
    assert len(tols) >= 3 and set(tols) == {_driver.INNER_TOL_PX}
    # ... and without the forcing term every round runs to 1e-3 px, with more passes after the first
    tols.clear(), passes.clear()
    monkeypatch.setattr(_driver, "INNER_FORCING", 0.0)
    exact = run_stages(p, g, vg, [st], noise_variance=1e-4)
    assert tols == [_driver.INNER_TOL_PX] * 3 and passes[1] > loose
    # the poses the rounds end at differ by less than half the last rounds' increments (0.006 px here)
    moves = np.linalg.norm(_driver.point_moves(g, _driver.increment_points(vg), out.poses, exact.poses), axis=-1)
    assert np.sqrt(np.mean(moves**2)) < 0.5 * min(inc[1:])


def test_auto_scales_cap_the_correlation_grid_of_the_finest_scale():
    # the standard problem: scale 1 would correlate on 512^3; an octave coarser it is 256^3 and scale 4 keeps 96 px
    assert auto_scales((256, 384)) == (2, 1)
    assert auto_scales((256, 384), (256, 256, 256)) == (4, 2)
    assert [s.scale for s in recipe_stages("default", (256, 384), vol_shape=(256, 256, 256))] == [4, 4, 2, 2]
    assert auto_scales((128, 160), (128, 128, 128)) == (2, 1)  # exactly 256^3 at scale 1: kept
    assert auto_scales((256, 384), (256, 256, 256), oversample=1) == (2, 1)  # 256^3 without refinement
    assert auto_scales((200, 200), (200, 200, 200)) == (2, 1)  # scale 4 would leave 50 px: not coarser
    assert auto_scales((2048, 2048), (1024, 1024, 1024)) == (16, 8)  # 128 px at scale 16
    assert auto_scales((48, 56), (400, 400, 400)) == (1,)
    # explicit scales are never changed
    assert [s.scale for s in recipe_stages("default", (256, 384), vol_shape=(256,) * 3, scales=(2, 1))][-1] == 1


def test_the_finest_scale_refines_less_where_a_coarser_schedule_cannot_keep_the_cap():
    # a 134 x 160 detector under a 134 x 160 x 160 volume: scale 4 would leave 40 columns, so the schedule stays 2 -> 1,
    # and scale 1 at 2x would correlate on 268 x 320 x 320 (27.4M voxels, above 256^3): it correlates at 1x
    assert auto_scales((134, 160), (134, 160, 160)) == (2, 1)
    st = recipe_stages("default", (134, 160), vol_shape=(134, 160, 160))
    assert [(s.name, s.scale, s.oversample) for s in st] == [("warmup", 2, 2), ("model", 2, 2), ("model", 1, 1),
                                                             ("jolts", 1, 1)]
    assert capped_oversample((134, 160, 160), 1, 2) == 1 and capped_oversample((134, 160, 160), 2, 2) == 2
    assert capped_oversample((100, 100, 100), 1, 3) == 2  # 300^3 above the cap, 200^3 below
    assert capped_oversample((400, 400, 400), 1, 2) == 1  # never below 1, even above the cap
    # exactly at the cap (the 128^3 benchmark scan): unchanged
    assert {s.oversample for s in recipe_stages("default", (128, 160), vol_shape=(128, 128, 128))} == {2}
    # the user's oversample, explicit scales, and no grid given: unchanged
    assert {s.oversample for s in recipe_stages("default", (134, 160), vol_shape=(134, 160, 160), oversample=2)} == {2}
    assert {s.oversample for s in recipe_stages("default", (134, 160), vol_shape=(134, 160, 160), scales=(2, 1))} == {2}
    assert {s.oversample for s in recipe_stages("default", (134, 160))} == {2}
    # the calibration's notes (the report's "scales" row) say so; not where nothing was capped
    notes = []
    resolve_stages((134, 160), vol_shape=(134, 160, 160), notes=notes)
    assert len(notes) == 1 and notes[0].startswith("scales: scale 1 correlates at 1x instead of 2x") and "27.4M" in notes[0]
    one = []  # one scale, every stage capped (a detector below 128 columns under a 300^3 volume): said too
    assert {s.oversample for s in resolve_stages((100, 120), vol_shape=(300, 300, 300), notes=one)} == {1}
    assert len(one) == 1 and "216.0M" in one[0]
    for kw in (dict(vol_shape=(128, 128, 128)), dict(vol_shape=(134, 160, 160), oversample=2)):
        quiet = []
        resolve_stages((134, 160), notes=quiet, **kw)
        assert quiet == []
    # the short-scan schedule (nonneg_ls: coarse rounds, one refining round at the finest scale) too
    short = recipe_stages("default", (134, 160), vol_shape=(134, 160, 160), reconstruct="nonneg_ls")
    assert [(s.scale, s.oversample, s.rounds) for s in short][-2:] == [(1, 1, 1), (1, 1, 5)]


def test_recipes_differ_in_their_model_and_take_overrides():
    assert set(RECIPES) == {"default", "precession", "jolts", "axis"}
    *_, prec, after = recipe_stages("precession", (50, 60))
    assert (prec.basis, prec.frame, prec.reconstruct, prec.guards) == ("drift", "lab", "nonneg_ls", ("consistency", "entropy"))
    # the jolt stage follows the precession model too (on its volume), unless jolts=False
    assert (after.name, after.basis, after.reconstruct) == ("jolts", "jolt_steps", "nonneg_ls")
    assert recipe_stages("precession", (50, 60), jolts=False)[-1] == prec
    jolts = recipe_stages("jolts", (50, 60))
    assert len(jolts) == 1 and jolts[0].basis == "dirac" and jolts[0].rounds == 8  # no free rotation: no warm-up
    mine = recipe_stages("default", (50, 60), max_outer=5, basis="spline:3", oversample=1)
    assert [s.rounds for s in mine] == [1, 4, 5] and mine[1].basis == "spline:3" and all(s.oversample == 1 for s in mine)
    # a lab-frame model's fixed translations are held in its warm-up too
    lab = recipe_stages("default", (50, 60), frame="lab", fixed=("rz", "ty"))
    assert set(lab[0].fixed) == {"rx", "ry", "rz", "ty"}
    with pytest.raises(StageError, match="recipe must be one of"):
        recipe_stages("wobble", (50, 60))
    with pytest.raises(StageError, match="unknown model option.*n_outer"):
        recipe_stages("default", (50, 60), n_outer=3)


# -- the configuration ---------------------------------------------------------
def _raw(**cal):
    return {"data": {"path": "p.npy"}, "geometry": {"type": "parallel", "pixel": 1.0}, "calibration": cal}


def test_config_selects_a_recipe_and_spells_out_stages(tmp_path):
    cfg = load_config(_raw(recipe="precession", max_outer=6), base_dir=tmp_path)
    assert cfg.calibration.recipe == "precession" and cfg.calibration.recipe_parameters() == {"max_outer": 6}
    stages = recipe_stages("jolts", (40, 50))
    cfg = load_config(_raw(stage=stages_to_dicts(stages)), base_dir=tmp_path)
    assert stages_from_dicts(list(cfg.calibration.stage)) == stages
    path = write_config(tmp_path / "c.toml", cfg)
    assert "[[calibration.stage]]" in path.read_text()
    assert load_config(path) == cfg
    with pytest.raises(ConfigError, match=r"calibration\.basis cannot be combined with \[\[calibration\.stage\]\]"):
        load_config(_raw(basis="dirac", stage=stages_to_dicts(stages)), base_dir=tmp_path)
    with pytest.raises(ConfigError, match=r"calibration\.stage\[0\].*frame"):
        load_config(_raw(stage=[{"name": "m", "frame": "world"}]), base_dir=tmp_path)
    with pytest.raises(ConfigError, match=r"calibration\.recipe must be one of"):
        load_config(_raw(recipe="wobble"), base_dir=tmp_path)
    # the default recipe's refinement: off unless refine = true, which goes to recipe_stages
    assert load_config(_raw(), base_dir=tmp_path).calibration.recipe_parameters() == {}
    on = load_config(_raw(refine=True), base_dir=tmp_path)
    assert on.calibration.recipe_parameters() == {"refine": True}
    assert "refine" in [s.name for s in recipe_stages("default", (76, 89), **on.calibration.recipe_parameters())]
    assert load_config(write_config(tmp_path / "r.toml", on)) == on
    with pytest.raises(ConfigError, match=r"calibration\.refine must be"):
        load_config(_raw(refine="yes"), base_dir=tmp_path)
    with pytest.raises(ConfigError, match=r"calibration\.refine cannot be combined"):
        load_config(_raw(refine=True, stage=stages_to_dicts(stages)), base_dir=tmp_path)


def test_background_is_a_stage_field_a_recipe_parameter_and_a_config_key(tmp_path):
    assert Stage().background == "auto"
    assert all(s.background == "auto" for r in RECIPES for s in recipe_stages(r, (50, 60)))
    assert all(s.background == 1 for s in recipe_stages("default", (50, 60), background=1))
    for st in (Stage(background=2), Stage(background=-1), Stage()):
        assert Stage.from_dict(st.to_dict()) == st
    for bad in (3, -2, True, 1.5, "none"):
        with pytest.raises(StageError, match="background must be 'auto', -1"):
            Stage(background=bad)
    cfg = load_config(_raw(background=0), base_dir=tmp_path)
    assert cfg.calibration.recipe_parameters() == {"background": 0}
    assert load_config(_raw(background="auto"), base_dir=tmp_path).calibration.recipe_parameters() == {"background": "auto"}
    for bad in (4, "plane"):
        with pytest.raises(ConfigError, match=r"calibration\.background"):
            load_config(_raw(background=bad), base_dir=tmp_path)


def test_resolved_config_holds_the_full_stage_list_that_runs(tmp_path):
    cfg = load_config(_raw(recipe="default", basis="spline:2", max_outer=4), base_dir=tmp_path)
    stages = recipe_stages("default", (40, 50), **cfg.calibration.recipe_parameters())
    res = cfg.resolved(stages=stages)
    assert res.calibration.basis is None and res.calibration.recipe == "default"
    assert stages_from_dicts(list(res.calibration.stage)) == stages
    again = load_config(write_config(tmp_path / "r.toml", res))
    assert again == res


# -- the pipeline's contract ----------------------------------------------------
@pytest.fixture(scope="module")
def small():
    from tests.correlation.cases import make_case

    return make_case("offset", n=24, n_views=48)


def test_a_result_worse_than_nominal_returns_the_nominal_geometry_and_fails(small, monkeypatch, tmp_path):
    # A driver that ends 3 px off (a broken calibration, made on purpose here: every other view shifted by 3 voxels,
    # which no global motion of the sample, the gauge, takes back): the pipeline's own check sees the fit worse than
    # nominal, returns the nominal geometry, and says it is no success; the CLI path writes every output and run.json
    # says why.
    from pdvc.calibration import _pipeline
    from pdvc.geometry import Poses

    c = small
    real = _pipeline.run_stages

    def broken(*a, **kw):
        out = real(*a, **kw)
        n = c.scan.geometry.n_views
        bad = Poses(np.zeros((n, 3)), np.tile([3.0, 0.0, 1.0], (n, 1)) * (np.arange(n) % 2)[:, None])
        import dataclasses

        return dataclasses.replace(out, poses=bad)

    monkeypatch.setattr(_pipeline, "run_stages", broken)
    res = pdvc.calibrate(c.scan.projections, c.scan.geometry, c.vol_geom, out_dir=tmp_path / "o", max_outer=2, fixed=("rx", "ry", "rz"))
    assert res.status == Status.WORSE_THAN_NOMINAL and not res.success
    assert res.geometry == c.scan.geometry and res.rejected_geometry is not None
    assert np.mean(res.snr_after) == pytest.approx(np.mean(res.snr_before))
    run = json.loads((tmp_path / "o" / "run.json").read_text())
    assert run["status"] == "complete" and run["success"] is False and run["status_name"] == "worse_than_nominal"
    assert "worse than the nominal" in run["message"]
    for name in ("geometry.npy", "motion.csv", "result.h5", "report.html", "volume.tif"):
        assert (tmp_path / "o" / name).is_file()


def test_the_distance_from_nominal_is_the_rms_displacement_of_the_sample_points_without_the_gauge():
    # Known answers in parallel beam (pixel = voxel = 1): a vertical shift of +a on even views and -a on odd ones moves
    # every sample point's projection by a along the rows; the same shift on every view moves the sample as a whole
    # (the gauge), which no data measure.
    from pdvc.calibration._pipeline import _moved_from_nominal
    from pdvc.geometry import Poses

    n = 40
    geom = pdvc.parallel(np.linspace(0.0, np.pi, n, endpoint=False), det_shape=(24, 32), pixel=1.0)
    vg = pdvc.VolumeGeometry((20, 24, 24))
    a = 0.004
    t = np.zeros((n, 3))
    t[:, 2] = a * (-1.0) ** np.arange(n)
    assert _moved_from_nominal(geom, vg, Poses(np.zeros((n, 3)), t), True) == pytest.approx(a, rel=1e-6)
    t[:, 2] = 0.7
    assert _moved_from_nominal(geom, vg, Poses(np.zeros((n, 3)), t), True) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("a, holds", [(0.004, "tol"), (0.05, "predicts"), (0.4, "")])
def test_stages_that_end_within_tol_px_of_nominal_return_it_as_a_success(small, monkeypatch, tmp_path, a, holds):
    # Stages that end 0.004 px RMS from the nominal geometry (below their tol_px of 0.01 px) measured no motion: the
    # nominal geometry is returned as a success (NOMINAL_HOLDS), the stages' in rejected_geometry. At 0.05 px (below
    # NEAR_NOMINAL_PX) the stages' geometry, a jitter of every other view, predicts the views left out of a
    # reconstruction worse than the nominal one: the nominal geometry holds too. 0.4 px is a measurement (here a wrong
    # one, which the SNR check rejects as worse than nominal).
    from pdvc.calibration import _pipeline
    from pdvc.calibration._pipeline import _moved_from_nominal
    from pdvc.geometry import Poses

    c = small
    real = _pipeline.run_stages
    n = c.scan.geometry.n_views
    t = np.zeros((n, 3))
    t[:, 2] = a * (-1.0) ** np.arange(n)
    near = Poses(np.zeros((n, 3)), t)
    scale = _moved_from_nominal(c.scan.geometry, c.vol_geom, near, True) / a  # the cone's magnification over the pixel
    near = Poses(np.zeros((n, 3)), t / scale)  # a px RMS on the detector

    def ended_near_nominal(*args, **kw):
        import dataclasses

        return dataclasses.replace(real(*args, **kw), poses=near)

    monkeypatch.setattr(_pipeline, "run_stages", ended_near_nominal)
    res = pdvc.calibrate(c.scan.projections, c.scan.geometry, c.vol_geom, out_dir=tmp_path / "o", max_outer=1,
                         fixed=("rx", "ry", "rz"))
    assert res.geometry == c.scan.geometry and res.rejected_geometry is not None
    if holds:
        assert res.status == Status.NOMINAL_HOLDS and res.success
        if holds == "tol":
            assert f"{a:.4f} px RMS from the nominal one, less than 0.01 px" in res.message
        else:
            assert f"{a:.4f} px RMS from the nominal one, and its reconstruction predicts the views" in res.message
            assert "worse than the nominal one's" in res.message and "near-nominal check" in res.timings
        assert np.all(res.poses.translations == 0.0) and np.all(res.snr_after == res.snr_before)
        run = json.loads((tmp_path / "o" / "run.json").read_text())
        assert run["success"] is True and run["status_name"] == "nominal_holds"
    else:
        assert res.status == Status.WORSE_THAN_NOMINAL and not res.success


def test_the_near_nominal_check_keeps_a_small_real_motion_and_drops_a_walk():
    # Known answers, analytic projector: on a scan whose axis is 0.05 px off centre, the true geometry predicts the
    # views left out of a reconstruction better than the nominal one by more than NEAR_NOMINAL_GAIN (no reason to hold
    # the nominal one); on a still scan the same 0.05 px offset predicts them worse (the nominal geometry holds).
    from pdvc.calibration import Stage
    from pdvc.calibration._pipeline import NEAR_NOMINAL_GAIN, NEAR_NOMINAL_PX, _nominal_predicts_as_well
    from pdvc.simulate import cast_iron_phantom, simulate_scan, tilted_axis_poses

    n, nv, a = 24, 48, 0.05
    assert a < NEAR_NOMINAL_PX
    angles = np.linspace(0, 2 * np.pi, nv, endpoint=False)
    geom = pdvc.circular_cone(angles, sod=8 * n, odd=4 * n, det_shape=(int(1.2 * n), int(1.4 * n)), pixel=1.5)
    vg = pdvc.VolumeGeometry((n, n, n))
    phantom = cast_iron_phantom(0.36 * n, 0.8 * n, n_nodules=3 * n, seed=0)
    rv, t = tilted_axis_poses(angles, tilt=0.0, offset=(a, 0.0, 0.0))
    off = geom.apply_poses(rv, t)
    moving = simulate_scan(phantom, geom, rotvecs=rv, translations=t, i0=2e4, seed=1, supersampling=2).projections
    still = simulate_scan(phantom, geom, i0=2e4, seed=1, supersampling=2).projections
    timings = {}
    assert _nominal_predicts_as_well(moving, geom, vg, off, [Stage()], None, None, "auto", a, timings) == ""
    assert timings["near-nominal check"] > 0
    held = _nominal_predicts_as_well(still, geom, vg, off, [Stage()], None, None, "auto", a, {})
    assert "0.0500 px RMS from the nominal one" in held and "worse than the nominal one's" in held
    assert f"more than {100 * NEAR_NOMINAL_GAIN:.2g} % better needed" in held


def test_final_volume_is_on_the_grid_asked_for_whatever_the_scales(small):
    c = small
    res = pdvc.calibrate(c.scan.projections, c.scan.geometry, c.vol_geom, scales=(2,), max_outer=1, fixed=("rx", "ry", "rz"))
    assert res.vol_geom == c.vol_geom and res.volume.shape == c.vol_geom.shape
    assert res.volume_initial.shape == c.vol_geom.shape
    assert {h["scale"] for h in res.history} == {2}


def test_calibrate_refuses_stages_mixed_with_recipe_parameters(small):
    c = small
    with pytest.raises(CalibrationError, match="stages= is given"):
        pdvc.calibrate(c.scan.projections, c.scan.geometry, c.vol_geom, stages=[Stage()], basis="dirac")


def test_the_report_describes_the_poses_kept_after_a_rollback(small, tmp_path):
    # The correlation volume gets better once, then worse: the consistency guard rolls back to the
    # best round's poses. Every output (result, motion.csv, the assessment behind the report's modes
    # and uncertainties) must describe those poses, not the discarded last round.
    import h5py

    from tests.correlation.cases import best_at_second_call

    c = small
    calls = []
    reconstruct = best_at_second_call(calls)

    stages = [Stage(fixed=("rx", "ry", "rz"), reconstruct=reconstruct, rounds=5, stall_ratio=None, tol_px=1e-9)]
    res = pdvc.calibrate(c.scan.projections, c.scan.geometry, c.vol_geom, stages=stages, init="none", out_dir=tmp_path / "o")
    assert res.stage_outcomes[-1].status == Status.CONSISTENCY_GUARD
    assert len(res.history) >= 2  # rounds ran past the one whose poses are kept
    assert res.geometry == calls[1]
    assert res.assessment is not None and res.assessment.poses is res.poses
    with h5py.File(tmp_path / "o" / "result.h5") as f:
        np.testing.assert_allclose(f["poses/translations"][()], res.translations)
        np.testing.assert_allclose(f["assessment/std_sample"][()], res.assessment.std, equal_nan=True)
    motion = np.genfromtxt(tmp_path / "o" / "motion.csv", delimiter=",", names=True)
    np.testing.assert_allclose(motion["tx_sample"], res.poses.to_params(c.vol_geom.offset)[:, 0], atol=1e-6)


@pytest.mark.slow
def test_a_good_calibration_of_a_small_drift_is_not_rejected_as_worse_than_nominal():
    # A granular sample drifting by a fraction of a pixel (bench_accuracy's tuning seed 22). The
    # calibration reaches 0.023 px from 0.162 px; on the user's grid (voxel = pixel) the
    # interpolating projector still ranked it below nominal (SNR 18.11 < 18.64 dB) and the check
    # returned the nominal geometry. Measured as the correlation measures it (the 2x grid) it is
    # better (21.05 > 18.70 dB) and kept.
    from pdvc.geometry import fix_gauge, reprojection_error, sample_points
    from pdvc.simulate import drift_poses, granular_phantom, simulate_scan

    n, n_views = 40, 90
    angles = np.linspace(0.0, 2 * np.pi, n_views, endpoint=False)
    sod = 24.0 / np.tan(np.deg2rad(2.4))
    geom = pdvc.circular_cone(angles, sod=sod, odd=0.5 * sod, det_shape=(48, 56), pixel=1.5)
    rv, t = drift_poses(np.linspace(0, 1, n_views), angles, velocity=[0.064, -0.052, -0.388], acceleration=[-0.13, 0.992, -0.329])
    scan = simulate_scan(granular_phantom(0.36 * n, 0.8 * n, seed=22), geom, rotvecs=rv, translations=t, i0=2e5, seed=22, supersampling=2)
    vg = pdvc.VolumeGeometry((n, n, n))
    res = pdvc.calibrate(scan.projections, geom, vg)
    assert res.status != Status.WORSE_THAN_NOMINAL and res.success, res.message
    truth = geom.apply_poses(*fix_gauge(rv, t, geom, center=vg.offset))
    pts = sample_points(vg, 5, fraction=0.6)
    assert reprojection_error(res.geometry, truth, pts).rms < 0.5 * reprojection_error(geom, truth, pts).rms
    assert np.mean(res.snr_after) > np.mean(res.snr_before)


def test_correlation_volume_by_spline_is_the_upsampled_stage_reconstruction():
    """oversample_by="spline": FDK on the stage's grid, then the cubic B-spline onto the finer grid."""
    from pdvc.calibration import correlation_volume, reconstruct, refined_grid
    from pdvc.recon import spline_upsample
    from tests.correlation.cases import make_case

    c = make_case("offset", n=24, n_views=48)
    p, g, vg = c.scan.projections, c.scan.geometry, c.vol_geom
    by_spline = correlation_volume(p, vg, g, Stage(oversample=2, oversample_by="spline"))
    np.testing.assert_allclose(by_spline, spline_upsample(reconstruct(p, vg, g), 2), rtol=1e-6, atol=1e-6)
    direct = correlation_volume(p, vg, g, Stage(oversample=2, oversample_by="reconstruction"))
    np.testing.assert_allclose(direct, reconstruct(p, refined_grid(vg, 2), g), rtol=1e-6, atol=1e-6)
    # the two fine volumes describe the same object: close, not equal
    assert by_spline.shape == direct.shape == refined_grid(vg, 2).shape
    assert np.linalg.norm(by_spline - direct) < 0.2 * np.linalg.norm(direct)


def test_the_check_against_nominal_reuses_a_volume_only_when_it_is_the_one_it_would_make():
    """``_fit`` takes a driver's ``fit_volume`` for the same poses (identity), grid and FDK; else it reconstructs."""
    from pdvc.calibration import correlation_volume
    from pdvc.calibration._driver import data_at_scale
    from pdvc.calibration._pipeline import _fit
    from pdvc.geometry import Poses
    from tests.correlation.cases import make_case

    c = make_case("offset", n=24, n_views=48)
    p, g, vg = c.scan.projections, c.scan.geometry, c.vol_geom
    st = Stage(oversample=2)
    scaled = data_at_scale(p, g, vg, None, 1e-3, 1)
    n = g.n_views
    poses = Poses(np.zeros((n, 3)), np.tile([0.3, 0.0, 0.1], (n, 1)))
    made = correlation_volume(p, vg, g.apply(poses), st)
    own = _fit(scaled, poses, st)[0]
    np.testing.assert_array_equal(_fit(scaled, poses, st, made=(poses, st, made))[0], own)
    blank = np.zeros_like(made)  # a volume that fits nothing: shows whether it was used
    assert np.mean(_fit(scaled, poses, st, made=(poses, st, blank))[0]) < np.mean(own) - 5  # 0 dB: residual = data
    for other in ((Poses(poses.rotvecs.copy(), poses.translations.copy()), st), (poses, st.replace(oversample=1)),
                  (poses, st.replace(reconstruct="cgls")), (poses, st.replace(oversample_by="spline"))):
        q, by = other
        np.testing.assert_array_equal(_fit(scaled, q, st, made=(poses, by, blank))[0], own)


def test_background_auto_fits_a_plane_only_when_the_air_level_drifts_and_the_log_suggests_it_when_off(caplog):
    from tests.correlation.cases import make_case

    c = make_case("offset", n=24, n_views=48)
    # air = "off": the engine's background at work (air = "auto", the default, subtracts such a drift first: below)
    kw = dict(max_outer=2, fixed=("rx", "ry", "rz"), air="off")
    clean = pdvc.calibrate(c.scan.projections, c.scan.geometry, c.vol_geom, **kw)
    assert all(h["background"] == -1 for h in clean.history) and clean.history[0]["offset_sigma"] < 0.1
    assert clean.options["background"].startswith("none")
    p = c.scan.projections + np.linspace(0.0, 0.3, c.scan.geometry.n_views, dtype=np.float32)[:, None, None]
    with caplog.at_level("INFO", logger="pdvc.calibration"):
        auto = pdvc.calibrate(p, c.scan.geometry, c.vol_geom, **kw)
    # decided at the first round, on the offset its poses left (that round is then measured again with it), and
    # kept at every later round and stage
    assert auto.history[0]["offset_sigma"] > 0.2
    assert all(h["background"] == 1 for h in auto.history)
    assert all(h["offset_sigma"] < 1e-6 for h in auto.history[1:])
    assert auto.options["background"].startswith("a plane per view")
    assert "background = 0" not in caplog.text

    def final_diagnosis():
        lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("calibrated geometry: ")]
        assert len(lines) == 1
        return lines[0]

    # the residual's diagnosis is of the data against the volume: the log says the fitted background is still in it
    assert final_diagnosis().endswith("(before the background per view fitted with the motion)")
    caplog.clear()
    with caplog.at_level("INFO", logger="pdvc.calibration"):
        off = pdvc.calibrate(p, c.scan.geometry, c.vol_geom, background=-1, **kw)
    assert all(h["background"] == -1 for h in off.history)
    assert "background = 0" in caplog.text and "before the background" not in final_diagnosis()
    # the default: the air level the views share is subtracted before the rounds; its drift is left to the background
    default = pdvc.calibrate(p, c.scan.geometry, c.vol_geom, max_outer=2, fixed=("rx", "ry", "rz"))
    assert default.options["air"].startswith("subtracted") and all(h["background"] == 1 for h in default.history)


def test_nonneg_ls_correlation_volume_by_spline_is_the_upsampled_stage_fit():
    """oversample_by="spline" with nonneg_ls (the precession model): the fit on the stage's grid, weighted, by ordered
    subsets of at least 30 views (3 of a 90-view scan; 2 of the 64 here), then the cubic B-spline onto the finer grid."""
    from pdvc.calibration import correlation_volume
    from pdvc.calibration._driver import nonneg_subsets
    from pdvc.recon import nonneg_ls, spline_upsample
    from tests.correlation.cases import make_case

    c = make_case("offset", n=24, n_views=64)
    p, g, vg = c.scan.projections, c.scan.geometry, c.vol_geom
    w = np.ones(g.det_shape, np.float32)
    w[:4] = 0.0
    st = Stage(reconstruct="nonneg_ls", oversample=2, oversample_by="spline")
    assert [nonneg_subsets(n) for n in (29, 64, 90, 91, 180, 1440)] == [1, 2, 3, 3, 3, 3]
    np.testing.assert_allclose(correlation_volume(p, vg, g, st, weights=w),
                               spline_upsample(nonneg_ls(p, vg, g, weights=w, subsets=2), 2), rtol=1e-6, atol=1e-6)
    assert not np.allclose(correlation_volume(p, vg, g, st), correlation_volume(p, vg, g, st, weights=w))


def test_a_stage_that_sets_its_subsets_fits_its_nonneg_ls_volume_by_them():
    """Stage.subsets = m: at most m ordered subsets of at least 15 views each (the refining round's 6 of a 91-view
    half turn); the volume is nonneg_ls's with those subsets, bit for bit, and differs from the automatic one's."""
    from pdvc.calibration import correlation_volume
    from pdvc.calibration._driver import nonneg_subsets
    from pdvc.recon import nonneg_ls, spline_upsample
    from tests.correlation.cases import make_case

    assert [nonneg_subsets(n, 6) for n in (14, 29, 45, 60, 91, 1440)] == [1, 1, 3, 4, 6, 6]
    assert [nonneg_subsets(n, 2) for n in (29, 30, 91)] == [1, 2, 2]
    assert nonneg_subsets(91, "auto") == nonneg_subsets(91) == 3
    c = make_case("offset", n=24, n_views=64)
    p, g, vg = c.scan.projections, c.scan.geometry, c.vol_geom
    st = Stage(reconstruct="nonneg_ls", oversample=2, oversample_by="spline", subsets=6)
    got = correlation_volume(p, vg, g, st)
    np.testing.assert_array_equal(got, spline_upsample(nonneg_ls(p, vg, g, subsets=4), 2))
    assert not np.allclose(got, correlation_volume(p, vg, g, st.replace(subsets="auto")), rtol=1e-4, atol=1e-4)
