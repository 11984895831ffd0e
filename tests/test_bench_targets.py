"""bench_accuracy.py states issue #10's targets from its rows: each verdict follows its figure."""

from __future__ import annotations

from .conftest import benchmark_module


def _row(seed, motion, err, best=0.1, worse=False):
    return dict(seed=seed, motion=motion, err_pdvc=err, err_best_offset_tilt=best, worse=worse)


def test_the_targets_follow_the_rows():
    with benchmark_module("bench_accuracy") as bench:
        good = [_row(0, "offset", 0.01, best=0.001), _row(1, "prec1", 0.02, best=0.09), _row(2, "jolts", 0.1, best=0.4),
                _row(3, "combo", 0.03, best=0.15)]
        text = "\n".join(bench.targets(good))
        assert "NOT met" not in text
        assert "smooth motions (3 cases): median 0.020 px" in text and "jolts (1 cases): median 0.100 px" in text
        assert "3 of 3 cases (lowest 4.0x, seed 2)" in text  # the offset is not a motion beyond offset + tilt
        # one precession only 2x below the best offset + tilt, one case worse than nominal, jolts above 0.15 px
        bad = good[:1] + [_row(1, "prec1", 0.045, best=0.09), _row(2, "jolts", 0.2, best=0.4, worse=True), good[3]]
        lines = bench.targets(bad)
        assert sum("NOT met" in line for line in lines) == 3
        assert any("lowest 2.0x, seed 1" in line and "NOT met" in line for line in lines)
        assert any("worse than nominal: 1 of 4 cases (seeds [2])" in line for line in lines)
        # a smooth p90 above 0.1 px fails on its own
        wide = [_row(i, "drift", e) for i, e in enumerate([0.01] * 8 + [0.3, 0.3])]
        smooth = [line for line in bench.targets(wide) if "smooth motions" in line][0]
        assert "median 0.010 px (<= 0.05: met)" in smooth and "(<= 0.1: NOT met)" in smooth


def test_the_suite_keeps_each_seeds_case_and_filters_by_motion():
    with benchmark_module("bench_accuracy") as bench:
        every = bench.suite("medium", "tuning", 12, 0)
        some = bench.suite("medium", "tuning", 3, 0, motions=("prec2", "combo"))
        assert len(some) == 3 and all(c.motion in ("prec2", "combo") for c in some)
        assert all(c.seed % 2 == 0 and c.n == 128 for c in some)
        # a seed draws the same case with or without the filter: the filter only skips seeds
        drawn = {c.seed: c for c in every}
        assert all(drawn[c.seed] == c for c in some if c.seed in drawn)
        assert [c.seed for c in every if c.motion in ("prec2", "combo")][:3] == [c.seed for c in some]


def test_an_unknown_motion_is_refused_by_name(capsys):
    import pytest

    with benchmark_module("bench_accuracy") as bench:
        with pytest.raises(SystemExit):
            bench.main(["--tiny", "--motions", "prec1,wobble"])
    assert "--motions takes names among offset, tilt_det" in capsys.readouterr().err


def test_a_supersampling_below_one_is_refused_by_name(capsys):
    import pytest

    with benchmark_module("bench_accuracy") as bench:
        with pytest.raises(SystemExit):
            bench.main(["--tiny", "--supersampling", "0"])
        assert bench.SCAN["supersampling"] == 2  # the default every figure in the docs used
    assert "--supersampling must be a positive integer" in capsys.readouterr().err


def test_a_still_case_has_no_motion_and_counts_only_toward_worse_than_nominal():
    import dataclasses

    import numpy as np

    with benchmark_module("bench_accuracy") as bench:
        c = dataclasses.replace(bench.case(1, "tiny"), motion="none", params={})  # what --still makes of a case
        rv, t = bench.true_poses(c, np.linspace(0.0, 2 * np.pi, 12, endpoint=False))
        assert rv.shape == t.shape == (12, 3) and not rv.any() and not t.any()
        # no smooth-motion, jolt or 3x verdict for scans without motion: only whether pdvc invented one
        lines = bench.targets([_row(0, "none", 0.004, worse=True), _row(1, "none", 0.0)])
        assert lines[1:] == ["  worse than nominal: 1 of 2 cases (seeds [0]): NOT met"]
