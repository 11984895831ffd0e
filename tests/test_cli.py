"""The demo and the command line."""

import numpy as np
import pytest

from pdvc._demo import run_demo
from pdvc.cli import main


def test_demo_true_geometry_reconstructs_better_than_nominal():
    res = run_demo(size=40, n_views=60, seed=1)
    nominal, true = res.rows
    assert res.nominal_error.rms > 0.5  # the simulated motion is visible
    assert true.rmse < 0.6 * nominal.rmse
    assert true.entropy < nominal.entropy
    assert true.snr_db > nominal.snr_db + 3


def test_cli_demo_writes_outputs_and_refuses_non_empty_folder(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["demo", "--size", "24", "--views", "24", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "nominal geometry" in text and "true geometry" in text
    vec = np.load(out / "geometry_true.npy")
    assert vec.shape == (24, 12)
    assert np.load(out / "volume_true_geometry.npy").shape == (24, 24, 24)
    assert not list(out.glob(".*.tmp"))
    assert main(["demo", "--size", "24", "--views", "24", "--out", str(out)]) == 1
    assert "not empty" in capsys.readouterr().err


def test_cli_usage_errors():
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--size", "4"])
    assert exc.value.code == 2
    with pytest.raises(SystemExit) as exc:
        main([])
    assert exc.value.code == 2
