"""The two real parallel-beam scans of ../shared/data, calibrated through the CLI.

Both have a centre-of-rotation error (a constant lab-frame translation of
the sample across the beam). The recovered axis offset must agree with the
estimates of the data's README (other methods, good to a few tenths of a
pixel) within 0.5 px, and the SNR of the projections must rise. The runs
use the documented example configs (examples/*/config.toml) unchanged
except for the data path and the output folder.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from pdvc.cli import main
from pdvc.report import read_result_h5

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data"

CASES = {
    # example, data file, README estimate of the offset (px, axis column - detector centre)
    "tooth": ("tomopy-tooth/tooth.h5", -23.6),
    "neutron360": ("sarepy-neutron360/sinogram_360_neutron_image.tif", -6.0),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_real_scan_axis_offset_and_snr(name, tmp_path, capsys):
    rel, expected = CASES[name]
    data = DATA / rel
    if not data.is_file():
        pytest.skip(f"real data not found at {data} (the shared data folder is absent)")
    text = (ROOT / "examples" / name / "config.toml").read_text()
    text = re.sub(r'^path = ".*"$', f'path = "{data.as_posix()}"', text, count=1, flags=re.M)
    cfg = tmp_path / "config.toml"
    cfg.write_text(text)
    out = tmp_path / "out"
    assert main(["-q", "calibrate", str(cfg), "--out", str(out)]) == 0, capsys.readouterr().err
    res = read_result_h5(out / "result.h5")
    offset = float(res["motion"]["offset_px"])
    assert abs(offset - expected) < 0.5, offset
    snr_before = float(res["metrics"]["snr_before_db"].mean())
    snr_after = float(res["metrics"]["snr_after_db"].mean())
    assert snr_after > snr_before + 3.0, (snr_before, snr_after)
    printed = capsys.readouterr().out
    assert "axis offset" in printed
