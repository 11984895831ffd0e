"""Small things a new user tripped over (issue #9, item 8): each one pinned by a test."""

from __future__ import annotations

import logging
import os
import stat
import warnings

import numpy as np
import pytest

from pdvc.calibration import describe_motion
from pdvc.geometry import VolumeGeometry, circular_cone, parallel
from pdvc.io import AngleRange, resolve_angles
from pdvc.io._atomic import atomic_path, atomic_write_text
from pdvc.io._export import write_exports
from pdvc.recon import _fbp, fbp, fdk
from pdvc.report import write_report
from pdvc.simulate import tilted_axis_poses


# -- 1. angles that look like degrees ---------------------------------------------------
@pytest.mark.parametrize("build", [
    lambda a: parallel(a, det_shape=(2, 4), pixel=1.0),
    lambda a: circular_cone(a, sod=10.0, odd=5.0, det_shape=(2, 4), pixel=1.0),
])
def test_degrees_given_as_angles_warn(build):
    with pytest.warns(UserWarning, match=r"angles span 359 .*radians"):
        build(np.arange(360.0))


@pytest.mark.parametrize("angles", [
    np.linspace(0, 2 * np.pi, 91),  # with the end point: span exactly 2 pi
    np.linspace(0, 2 * np.pi, 90, endpoint=False),
    np.linspace(-np.pi, np.pi, 11),
    np.deg2rad(np.arange(91) * 2 - 88.2),
    [0.3],
])
def test_radians_do_not_warn(angles):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        parallel(angles, det_shape=(2, 4), pixel=1.0)
        circular_cone(angles, sod=10.0, odd=5.0, det_shape=(2, 4), pixel=1.0)


def test_config_angles_in_degrees_reach_the_builders_as_radians():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for spec, n in ((AngleRange(0.0, 360.0, 37, True), 37), (AngleRange(), 10), ("auto", 10), ((0.0, 90.0, 360.0), 3)):
            a = resolve_angles(spec, n, kind="cone")
            circular_cone(a, sod=10.0, odd=5.0, det_shape=(2, 4), pixel=1.0)
            parallel(resolve_angles(spec, n, kind="parallel"), det_shape=(2, 4), pixel=1.0)


# -- 2. print(result.motion) ------------------------------------------------------------
def _motion():
    angles = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    geom = circular_cone(angles, sod=100.0, odd=100.0, det_shape=(16, 16), pixel=0.2)
    rv, t = tilted_axis_poses(angles, tilt=np.deg2rad(0.5), offset=(0.05, 0.0, 0.0))
    return describe_motion(geom, rv, t, VolumeGeometry((8, 8, 8), 0.2))


def test_motion_summary_prints_readably():
    m = _motion()
    text = str(m)
    lines = text.splitlines()
    assert lines[0].startswith("What moved") and "36 views" in lines[0]
    assert [line.strip() for line in lines[1:]] == m.describe()
    assert "array(" not in text and "[[" not in text
    r = repr(m)
    assert r.startswith("MotionSummary(") and "offset_px=+0.5" in r and "roll_deg=+0.5" in r
    assert "\n" not in r and "array" not in r and len(r) < 300


def test_motion_summary_says_what_the_detector_displacement_is():
    line = _motion().describe()[-1]
    assert "detector displacement of the volume's top, centre and bottom points" in line
    assert "placement of the reconstruction" in line and "zero mean pose" in line
    assert "axis offset is above" in line
    assert "axis points" not in line


# -- 3. parallel beam: TIGRE, LEAP, CIL exports ------------------------------------------
def test_parallel_exports_skip_quietly(tmp_path, caplog):
    g = parallel(np.linspace(0, np.pi, 4, endpoint=False), det_shape=(4, 5), pixel=0.1)
    caplog.set_level(logging.DEBUG, logger="pdvc")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = write_exports(tmp_path, g, VolumeGeometry((4, 5, 5), 0.1))
    assert list(out) == ["astra"]
    mine = [r for r in caplog.records if r.name == "pdvc.io._export"]
    assert len(mine) == 1 and mine[0].levelno == logging.INFO
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


# -- 4. the report's "What moved" section ------------------------------------------------
def test_report_notes_are_headed_what_moved(tmp_path):
    path = write_report(tmp_path, title="t", summary={"chi": 1.0}, figures={}, notes=["axis offset +1 px"])
    text = path.read_text(encoding="utf-8")
    assert "<h2>What moved</h2>" in text and "<h2>Notes</h2>" not in text
    assert text.index("<h2>What moved</h2>") < text.index("axis offset +1 px")


# -- 5. FBP coverage ---------------------------------------------------------------------
def _coverage_message(caplog, monkeypatch, run):
    # only the log line is under test: skip the back-projection (and its JIT compilation)
    monkeypatch.setattr(_fbp, "_reconstruct", lambda *args, **kwargs: None)
    caplog.set_level(logging.INFO, logger="pdvc.recon._fbp")
    run()
    msgs = [r.getMessage() for r in caplog.records if r.name == "pdvc.recon._fbp" and "coverage" in r.getMessage()]
    assert len(msgs) == 1
    return msgs[0]


def test_fbp_coverage_counts_one_step_per_view(caplog, monkeypatch):
    g = parallel(np.deg2rad(np.arange(91) * 2.0 - 88.2), det_shape=(2, 12), pixel=1.0)
    vg = VolumeGeometry((2, 8, 8))
    msg = _coverage_message(caplog, monkeypatch, lambda: fbp(np.zeros((91, 2, 12), np.float32), vg, g))
    assert "91 views, coverage 180.0 of 180 deg" in msg


def test_fbp_coverage_of_a_partial_arc(caplog, monkeypatch):
    g = parallel(np.deg2rad(np.arange(60) * 2.0), det_shape=(2, 12), pixel=1.0)  # 0..118 deg
    vg = VolumeGeometry((2, 8, 8))
    msg = _coverage_message(caplog, monkeypatch, lambda: fbp(np.zeros((60, 2, 12), np.float32), vg, g))
    assert "coverage 120.0 of 180 deg" in msg


def test_fdk_coverage_of_a_full_turn(caplog, monkeypatch):
    g = circular_cone(np.linspace(0, 2 * np.pi, 36, endpoint=False), sod=50.0, odd=25.0, det_shape=(4, 12), pixel=1.5)
    vg = VolumeGeometry((4, 8, 8))
    msg = _coverage_message(caplog, monkeypatch, lambda: fdk(np.zeros((36, 4, 12), np.float32), vg, g))
    assert "36 views, coverage 360.0 of 360 deg" in msg


# -- 6. permissions of atomically written files -----------------------------------------
@pytest.mark.skipif(os.name != "posix", reason="POSIX permissions")
@pytest.mark.parametrize("umask", [0o022, 0o002, 0o077])
def test_atomic_files_get_the_usual_permissions(tmp_path, umask):
    old = os.umask(umask)
    try:
        with open(tmp_path / "plain.txt", "w") as fh:
            fh.write("x")
        atomic_write_text(tmp_path / "atomic.txt", "x")
        with atomic_path(tmp_path / "named.bin") as tmp:
            tmp.write_bytes(b"x")
    finally:
        os.umask(old)
    want = stat.S_IMODE((tmp_path / "plain.txt").stat().st_mode)
    assert want == 0o666 & ~umask
    assert stat.S_IMODE((tmp_path / "atomic.txt").stat().st_mode) == want
    assert stat.S_IMODE((tmp_path / "named.bin").stat().st_mode) == want


# -- a half turn without its end point: 91 views over [0, 180) cover 180 degrees -----------
@pytest.mark.parametrize("stop, flagged", [(180, False), (160, True)])
def test_inspect_counts_one_step_per_view_in_the_angular_span(tmp_path, stop, flagged):
    from pdvc._inputs import inspect_scan

    np.save(tmp_path / "p.npy", np.zeros((91, 4, 16), np.float32) + np.float32(0.5))
    (tmp_path / "scan.toml").write_text(
        '[data]\npath = "p.npy"\nis_raw = false\n[geometry]\ntype = "parallel"\npixel = 1.0\n'
        f"angles = {{ start = 0, stop = {stop}, count = 91 }}\n"
    )
    lines, problems = inspect_scan(tmp_path / "scan.toml")
    assert any("span 178.0 deg" in line or "span 158.2 deg" in line for line in lines)
    assert any("a tomographic scan needs at least 180 deg" in p for p in problems) == flagged
