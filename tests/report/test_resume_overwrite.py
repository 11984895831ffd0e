"""``--resume`` checks the run's fingerprint; ``--overwrite`` removes what pdvc owns (issue #9, item 6)."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from pdvc.errors import PdvcError
from pdvc.geometry import VolumeGeometry, parallel
from pdvc.io import run_fingerprint
from pdvc.report._outputs import OWNED_OUTPUTS, OutputWriter, ResumeMismatchError, remove_owned_outputs


@pytest.fixture
def inputs(rng):
    proj = rng.standard_normal((6, 4, 5)).astype(np.float32)
    geom = parallel(np.linspace(0, np.pi, 6, endpoint=False), det_shape=(4, 5), pixel=1.0)
    vg = VolumeGeometry((4, 5, 5), voxel_size=1.0)
    settings = {"options": {"n_outer": 3, "basis": "fourier:1", "weights": np.ones((4, 5))}, "config": {"data": {"path": "x.tif"}}}
    return proj, geom, vg, settings


def _fake(data="d0", geometry="g0", settings="s0"):
    return {"data": data, "geometry": geometry, "settings": settings}


# -- fingerprint -------------------------------------------------------------------
def test_fingerprint_is_stable_and_ignores_memory_layout(inputs):
    proj, geom, vg, settings = inputs
    fp = run_fingerprint(proj, geom, vg, settings)
    assert set(fp) == {"data", "geometry", "settings"}
    assert all(isinstance(v, str) and len(v) == 32 for v in fp.values())
    assert run_fingerprint(proj.copy(), geom, vg, dict(settings)) == fp
    # a non-contiguous view hashes like its contiguous copy
    big = np.zeros((6, 4, 10), np.float32)
    big[:, :, ::2] = proj
    view = big[:, :, ::2]
    assert not view.flags.c_contiguous
    assert run_fingerprint(view, geom, vg, settings) == fp
    # key order does not matter
    assert run_fingerprint(proj, geom, vg, dict(reversed(list(settings.items()))))["settings"] == fp["settings"]


def test_fingerprint_changes_with_one_value_geometry_or_setting(inputs):
    proj, geom, vg, settings = inputs
    fp = run_fingerprint(proj, geom, vg, settings)
    p2 = proj.copy()
    p2[3, 2, 1] += 1e-3
    fp2 = run_fingerprint(p2, geom, vg, settings)
    assert fp2["data"] != fp["data"] and fp2["geometry"] == fp["geometry"] and fp2["settings"] == fp["settings"]
    assert run_fingerprint(proj.astype(np.float64), geom, vg, settings)["data"] != fp["data"]  # dtype counts

    vec = geom.vectors.copy()
    vec[2, 0] += 1e-6
    g2 = type(geom).from_vectors(vec, geom.det_shape, geom.kind)
    assert run_fingerprint(proj, g2, vg, settings)["geometry"] != fp["geometry"]
    vg2 = VolumeGeometry((4, 5, 5), voxel_size=1.0, offset=(0.0, 0.0, 0.5))
    assert run_fingerprint(proj, geom, vg2, settings)["geometry"] != fp["geometry"]

    s2 = {**settings, "options": {**settings["options"], "n_outer": 4}}
    fp3 = run_fingerprint(proj, geom, vg, s2)
    assert fp3["settings"] != fp["settings"] and fp3["data"] == fp["data"]
    w = settings["options"]["weights"].copy()
    w[0, 0] = 0.5
    s3 = {**settings, "options": {**settings["options"], "weights": w}}
    assert run_fingerprint(proj, geom, vg, s3)["settings"] != fp["settings"]


# -- resume --------------------------------------------------------------------------
def test_resume_with_other_projections_is_refused(tmp_path):
    OutputWriter(tmp_path / "run", fingerprint=_fake())
    with pytest.raises(ResumeMismatchError, match="projections differ") as exc:
        OutputWriter(tmp_path / "run", resume=True, fingerprint=_fake(data="d1"))
    assert isinstance(exc.value, PdvcError) and isinstance(exc.value, ValueError)
    msg = str(exc.value)
    assert "--resume" in msg and "--overwrite" in msg and "--out" in msg
    assert "settings" not in msg  # only what changed is named
    with pytest.raises(ResumeMismatchError, match="geometry or volume grid") as exc:
        OutputWriter(tmp_path / "run", resume=True, fingerprint=_fake(geometry="g1", settings="s1"))
    assert "calibration settings differ" in str(exc.value)
    # the refused resume left the folder as it was
    assert json.loads((tmp_path / "run" / "run.json").read_text())["fingerprint"] == _fake()


def test_resume_with_the_same_fingerprint_works(tmp_path):
    OutputWriter(tmp_path / "run", fingerprint=_fake())
    (tmp_path / "run" / "checkpoint.npz").write_bytes(b"state")  # the checkpoint API is tested elsewhere
    w2 = OutputWriter(tmp_path / "run", resume=True, fingerprint=_fake())
    assert (w2.out / "checkpoint.npz").read_bytes() == b"state"  # resume removes nothing
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    assert info["status"] == "running" and info["fingerprint"] == _fake()


def test_the_checkpoint_keeps_the_parameters_the_stages_held(tmp_path):
    from pdvc.geometry import Poses

    w = OutputWriter(tmp_path / "run", fingerprint=_fake())
    state = dict(poses=Poses.identity(4), history=[], stage_index=1, rounds_done=2, offset_px=0.5, rings="on")
    w.save_checkpoint(dict(state, held=["tz"]))
    back = w.load_checkpoint()
    assert back["held"] == ("tz",) and back["stage_index"] == 1 and back["offset_px"] == 0.5
    w.save_checkpoint(state)  # nothing held
    assert w.load_checkpoint()["held"] == ()


def test_resume_of_an_older_run_without_fingerprint_warns(tmp_path, caplog):
    out = tmp_path / "run"
    OutputWriter(out)  # no fingerprint
    assert "fingerprint" not in json.loads((out / "run.json").read_text())
    with caplog.at_level(logging.WARNING, logger="pdvc"):
        w = OutputWriter(out, resume=True, fingerprint=_fake())
    assert "no fingerprint" in caplog.text
    w._run_file("complete")
    assert json.loads((out / "run.json").read_text())["fingerprint"] == _fake()


def test_fingerprint_kept_when_run_json_is_rewritten(tmp_path):
    w = OutputWriter(tmp_path / "run", fingerprint=_fake())
    assert json.loads((tmp_path / "run" / "run.json").read_text())["fingerprint"] == _fake()
    w._run_file("complete", gauge="sample", elapsed_s=1.0)
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    assert info["status"] == "complete" and info["gauge"] == "sample" and info["fingerprint"] == _fake()


# -- overwrite -----------------------------------------------------------------------
def test_overwrite_removes_owned_outputs_only(tmp_path, caplog):
    out = tmp_path / "run"
    out.mkdir()
    stale = ["motion.csv", "snr_per_view.png", "residuals.png", "volume_initial.h5", "checkpoint.npz", ".volume.tif.abc.tmp", "pdvc.log"]
    mine = ["my_notes.txt", "photo.png", "volume.tif.bak", ".hidden.tmp", "motion.csv.old"]
    for name in stale + mine:
        (out / name).write_text("x")
    (out / "sub").mkdir()
    (out / "sub" / "motion.csv").write_text("x")
    with caplog.at_level(logging.INFO, logger="pdvc"):
        OutputWriter(out, overwrite=True, fingerprint=_fake())
    assert "motion.csv" in caplog.text and "removed" in caplog.text
    for name in stale:
        assert not (out / name).exists(), name
    for name in mine:
        assert (out / name).exists(), name
    assert (out / "sub" / "motion.csv").exists()
    assert json.loads((out / "run.json").read_text())["status"] == "running"


def test_remove_owned_outputs_lists_and_resume_keeps_files(tmp_path):
    out = tmp_path / "run"
    OutputWriter(out, fingerprint=_fake())
    (out / "motion.csv").write_text("x")
    OutputWriter(out, resume=True, fingerprint=_fake())  # resume removes nothing
    assert (out / "motion.csv").exists()
    assert remove_owned_outputs(out) == ["motion.csv", "run.json"]
    assert remove_owned_outputs(tmp_path / "missing") == []
    assert {"report.html", "geometry_cil.json", "volume.npy", "config.toml"} <= set(OWNED_OUTPUTS)


def test_owned_outputs_name_every_report_figure():
    import inspect
    import re

    from pdvc.report import _calibration

    names = set(re.findall(r'figs\["([^"]+)"\]', inspect.getsource(_calibration.build_report)))
    assert names and {f"{n}.png" for n in names} <= set(OWNED_OUTPUTS)


def test_overwrite_keeps_the_run_inputs(tmp_path):
    # `pdvc simulate` writes its config.toml into the folder a user may then calibrate into with --overwrite
    out = tmp_path / "sim"
    out.mkdir()
    (out / "config.toml").write_text("[data]\n")
    (out / "motion.csv").write_text("stale\n")
    OutputWriter(out, overwrite=True, keep=[out / "config.toml"])
    assert (out / "config.toml").read_text() == "[data]\n"
    assert not (out / "motion.csv").exists()
