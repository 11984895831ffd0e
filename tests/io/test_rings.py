"""Rings: the detector's fixed pattern estimated from the mean of the views (pdvc.io.remove_rings) and removed by
pdvc.calibrate when the residual at the calibrated geometry shows it (rings = "auto")."""

from __future__ import annotations

import numpy as np
import pytest

import pdvc
from pdvc.errors import PdvcError, ShapeError
from pdvc.io import ring_pattern, remove_rings
from pdvc.io._config import ConfigError, load_config

from ..correlation.cases import make_case


def _turning_sample(n_views=120, n_rows=6, n_cols=80, seed=0):
    """Line integrals of a disc off the axis turning with the scan (parallel beam), the same in every row, and noise."""
    rng = np.random.default_rng(seed)
    u = np.arange(n_cols) - (n_cols - 1) / 2
    th = np.linspace(0, 2 * np.pi, n_views, endpoint=False)
    c = 15.0 * np.cos(th)[:, None]  # the disc's centre sweeps across the columns
    chord = 2 * np.sqrt(np.clip(8.0**2 - (u[None] - c) ** 2, 0, None)) * 0.05
    p = np.repeat(chord[:, None, :], n_rows, axis=1) + rng.normal(0, 0.01, (n_views, n_rows, n_cols))
    return p.astype(np.float32)


@pytest.mark.parametrize("slope", [0.0, 1e-3])
def test_sparse_stripes_are_found_to_the_slope_of_the_views(slope):
    """Known answer: the running median of a flat profile with fewer stripes than half the window is the profile,
    so the estimate is the stripes; across a ramp each stripe in the window shifts the median by at most one
    column's step."""
    rng = np.random.default_rng(1)
    n_views, n_rows, n_cols = 30, 4, 90
    u = np.arange(n_cols, dtype=np.float64)
    views = rng.uniform(0.5, 2.0, (n_views, n_rows, 1)) + slope * u
    stripes = np.zeros(n_cols)
    stripes[[20, 21, 45, 60, 67]] = [0.2, 0.1, -0.3, 0.05, 0.15]
    est = ring_pattern((views + stripes).astype(np.float32))
    inner = slice(10, n_cols - 10)  # the reflected border bends a ramp
    np.testing.assert_allclose(est[:, inner], np.broadcast_to(stripes, est.shape)[:, inner], atol=2 * slope + 2e-5)


def test_a_white_pattern_on_a_turning_sample_is_found_in_part():
    """What the estimate cannot tell from a pattern of every column: the running median of the pattern itself
    (about a quarter of its RMS over 21 columns) and the sample's trace in the mean of the views (here about 1 % of
    its largest line integral): it finds most of the pattern, not all of it (docs/method.md §5.13)."""
    p = _turning_sample()
    stripes = (0.03 * np.random.default_rng(1).standard_normal(p.shape[2])).astype(np.float32)
    est = ring_pattern(p + stripes)
    assert np.corrcoef(est.mean(axis=0), stripes)[0, 1] > 0.6
    trace = ring_pattern(p)
    assert np.sqrt(np.mean(trace**2)) < 0.04 * p.max()


def test_remove_rings_subtracts_from_a_copy_and_reports():
    p = _turning_sample()
    stripes = np.zeros(p.shape[2], np.float32)
    stripes[[10, 40, 41, 70]] = [0.2, -0.15, -0.15, 0.1]
    dirty = p + stripes
    before = dirty.copy()
    out, rep = remove_rings(dirty, noise_variance=1e-4)
    np.testing.assert_array_equal(dirty, before)  # input not modified
    assert out.dtype == np.float32 and out.shape == dirty.shape
    # the stripes are gone: the result is what the same filter makes of the scan without them (which takes the
    # sample's trace in the mean of the views), to within the median's shift by a stripe in its window
    without = p - ring_pattern(p)[None]
    assert np.abs((out - without).mean(axis=0)[:, [10, 40, 41, 70]]).max() < 0.01
    assert rep.peak > 0.1 and rep.amplitude > 3 * rep.noise
    assert rep.noise == pytest.approx(np.sqrt(1e-4 / p.shape[0]))
    assert "subtracted from every view" in rep.describe()


@pytest.mark.parametrize("kw, match", [
    (dict(width=4), "width must be an odd int"),
    (dict(width=1), "width must be an odd int"),
    (dict(noise_variance=-1.0), "noise_variance"),
    (dict(noise_variance=float("nan")), "noise_variance"),
])
def test_bad_parameters_are_named(kw, match):
    with pytest.raises(PdvcError, match=match):
        remove_rings(_turning_sample(n_views=8), **kw)


def test_bad_shapes_are_named():
    with pytest.raises(ShapeError, match="n_views, n_rows, n_cols"):
        ring_pattern(np.zeros((8, 30), np.float32))
    with pytest.raises(ShapeError, match="fewer than the ring filter's width"):
        ring_pattern(np.zeros((8, 3, 15), np.float32))


def test_config_key_and_calibrate_argument_are_checked(tmp_path):
    base = {"data": {"path": "scan"}, "geometry": {"type": "cone", "sod": 100.0, "odd": 300.0, "pixel": 0.2}}
    assert load_config(dict(base, calibration={"rings": "on"}), base_dir=tmp_path).calibration.rings == "on"
    assert load_config(base, base_dir=tmp_path).calibration.rings == "auto"
    with pytest.raises(ConfigError, match="calibration.rings"):
        load_config(dict(base, calibration={"rings": "yes"}), base_dir=tmp_path)
    c = make_case("offset", n=24, n_views=32)
    with pytest.raises(pdvc.calibration.CalibrationError, match="rings must be"):
        pdvc.calibrate(c.scan.projections, c.scan.geometry, c.vol_geom, rings="maybe")


def test_calibrate_says_what_it_did_with_rings():
    c = make_case("tilted_axis", n=24, n_views=48)
    p, g, vg = c.scan.projections, c.scan.geometry, c.vol_geom
    auto = pdvc.calibrate(p, g, vg, max_outer=2)
    assert auto.options["rings"].startswith("not removed: no fixed pattern")
    assert "first_pass" not in auto.timings
    on = pdvc.calibrate(p, g, vg, max_outer=2, rings="on")
    assert on.options["rings"].startswith("a fixed pattern of the detector of RMS")
    assert "rings" in on.timings
    off = pdvc.calibrate(p, g, vg, max_outer=2, rings="off")
    assert off.options["rings"] == "not removed (rings = 'off')"
