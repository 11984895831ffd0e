"""Zingers, hot and dead pixels found on the residual against a reprojection (pdvc.io.remove_zingers)."""

from __future__ import annotations

import numpy as np
import pytest

import pdvc
from pdvc.calibration import reconstruct
from pdvc.errors import ShapeError
from pdvc.io import remove_zingers
from pdvc.io._zingers import isolated_outliers, outlier_blobs
from pdvc.projectors import forward

from ..correlation.cases import make_case


def _zingers(p, fraction, seed=1):
    """Bright zingers: the line integral of a random fraction of the pixels drops by 0.5 to 3."""
    rng = np.random.default_rng(seed)
    hit = rng.random(p.shape) < fraction
    return np.where(hit, p - rng.uniform(0.5, 3.0, p.shape), p).astype(np.float32), hit


def _blobs(p, count, seed=2):
    """Zingers whose light spread: ``count`` spots, each a core whose line integral drops by 1 to 3 and its right,
    lower and lower-right neighbours by 0.5 to 1 times that (2 x 2 px)."""
    rng = np.random.default_rng(seed)
    n, nr, nc = p.shape
    v, r, c = rng.integers(0, n, count), rng.integers(0, nr - 1, count), rng.integers(0, nc - 1, count)
    drop = np.zeros(p.shape, np.float32)
    core = rng.uniform(1.0, 3.0, count)
    for dr, dc in ((0, 0), (0, 1), (1, 0), (1, 1)):
        f = 1.0 if dr == dc == 0 else rng.uniform(0.5, 1.0, count)
        np.maximum.at(drop, (v, r + dr, c + dc), (core * f).astype(np.float32))
    return (p - drop).astype(np.float32), drop > 0


@pytest.fixture(scope="module")
def case():
    c = make_case("tilted_axis", n=24, n_views=48)  # misaligned: the nominal reprojection misses the edges
    return c


def test_isolated_pixels_are_outliers_lines_and_blobs_are_not():
    z = np.zeros((2, 12, 12), np.float32)
    z[0, 3, 3] = 10.0  # alone
    z[0, 3, 4] = 1.0  # with a neighbour below a quarter of it: still alone (the ramp filter's spread)
    z[0, 8, 2:9] = 10.0  # a line: the edge of a misplaced sample
    z[1, 5:7, 5:7] = 10.0  # a blob
    z[1, 1, 10] = -10.0  # a dead pixel reads high: the sign does not matter
    out = isolated_outliers(z, sigma=1.0)
    assert set(zip(*np.nonzero(out))) == {(0, 3, 3), (1, 1, 10)}
    z[0, 3, 2] = 4.0  # a neighbour above a quarter of it: not alone any more
    assert not isolated_outliers(z, sigma=1.0)[0, 3, 3]
    z[0, 3, 3] = 40.0  # but a quarter of a stronger one
    assert isolated_outliers(z, sigma=1.0)[0, 3, 3]
    # the residual diagnosis's stricter rule: no neighbour beyond 3 sigma at all
    assert not isolated_outliers(z, 1.0, ratio=np.inf)[0, 3, 3]


def test_bright_groups_of_a_few_pixels_are_blobs_lines_and_dark_groups_are_not():
    z = np.zeros((3, 14, 14), np.float32)
    z[0, 2:4, 2:4] = -10.0  # a 2 x 2 spot of light
    z[0, 3, 3] = -20.0
    z[0, 8, 2:10] = -10.0  # a line: the edge of a misplaced sample
    z[0, 11:13, 11:13] = 10.0  # a group that reads dark (a detector defect, or a zinger's streak in the volume)
    z[1, 5:8, 5:8] = -8.0  # a 3 x 3 spot
    z[1, 1, 10:12] = -10.0  # a bright pair next to a dark pair: a misplaced small feature, or a spot next to an edge
    z[1, 2, 10:12] = 10.0
    z[2, 6, 6], z[2, 6, 7] = -20.0, -4.0  # one pixel and the ramp filter's spread: a single zinger, not a blob
    z[2, 10:12, 2:6] = -10.0  # 2 x 4: wider than a spot
    z[2, 1:3, 1:3], z[2, 1, 3] = -30.0, -4.0  # a spot with a faint rim pixel (below a fifth of its peak: left)
    z[2, 3, 1] = -8.0  # and one above a fifth: the spot's edge
    labels, peaks = outlier_blobs(z, sigma=1.0)
    assert np.unique(labels).size == 5
    spot = {(0, 2, 2), (0, 2, 3), (0, 3, 2), (0, 3, 3)} | {(1, r, c) for r in range(5, 8) for c in range(5, 8)} \
        | {(2, 1, 1), (2, 1, 2), (2, 2, 1), (2, 2, 2), (2, 3, 1)}
    assert set(zip(*np.nonzero(labels))) == spot | {(1, 1, 10), (1, 1, 11)}
    assert set(zip(*np.nonzero(peaks))) == {(0, 3, 3), (1, 1, 10), (1, 1, 11)} \
        | {(1, r, c) for r in range(5, 8) for c in range(5, 8)} | {(2, r, c) for r in (1, 2) for c in (1, 2)}
    # quiet: nothing beyond 3 sigma and 1/2.5 of the peak around the core (no check on the next views to tell)
    assert set(zip(*np.nonzero(outlier_blobs(z, sigma=1.0, quiet=True)[0]))) == spot
    assert isolated_outliers(z, sigma=1.0)[2, 6, 6]
    assert not (outlier_blobs(z, sigma=1.0, k=35.0)[0] > 0).any()  # peaks below k sigma


@pytest.mark.parametrize("aligned", [True, False])
def test_zinger_blobs_are_found_and_filled_from_their_rim(case, aligned):
    p, g, vg = case.scan.projections, case.scan.geometry, case.vol_geom
    pz, hit = _blobs(p, 60)
    g_rec = case.scan.true_geometry if aligned else g
    q = forward(reconstruct(pz, vg, g_rec), vg, g_rec)
    clean, rep = remove_zingers(pz, q)
    found = clean != pz
    assert rep.blobs >= (50 if aligned else 40), rep.blobs
    assert found[hit].mean() > (0.85 if aligned else 0.7), found[hit].mean()
    assert (found & ~hit).sum() < 0.2 * hit.sum()
    assert np.abs(clean - p)[hit].mean() < 0.2 * np.abs(pz - p)[hit].mean()
    assert "spot(s) of 2-9 px" in rep.describe()


@pytest.mark.parametrize("aligned", [True, False])
def test_zingers_are_found_on_the_residual_and_replaced_by_their_neighbours(case, aligned):
    p, g, vg = case.scan.projections, case.scan.geometry, case.vol_geom
    pz, hit = _zingers(p, 0.003)
    before = pz.copy()
    g_rec = case.scan.true_geometry if aligned else g
    q = forward(reconstruct(pz, vg, g_rec), vg, g_rec)
    clean, rep = remove_zingers(pz, q)
    np.testing.assert_array_equal(pz, before)  # the input is not modified
    found = clean != pz
    assert rep.count == int(found.sum()) and rep.views == int(found.any(axis=(1, 2)).sum())
    # nearly every zinger, few others (spikes of the zingers' own streaks in the 48-view FDK, edges); at the nominal
    # geometry of a tilted axis (edges 2 px off everywhere on this small detector) those on an edge are partly hidden
    assert found[hit].mean() > (0.9 if aligned else 0.75), found[hit].mean()
    assert (found & ~hit).sum() < 0.3 * hit.sum()
    # what replaced them is the sample's own value to within its local variation, not the zinger's 0.5-3
    assert np.abs(clean - p)[found].max() < 0.3
    assert np.abs(clean - p)[hit].mean() < 0.3 * np.abs(pz - p)[hit].mean()
    assert "isolated" in rep.describe()


def test_a_hot_pixel_is_replaced_in_every_view(case):
    p, g, vg = case.scan.projections, case.scan.geometry, case.vol_geom
    ph = p.copy()
    ph[:, 5, 7] += 2.0  # a dead pixel (no counts): its line integral reads high in every view
    q = forward(reconstruct(ph, vg, g), vg, g)
    clean, rep = remove_zingers(ph, q)
    assert np.all(clean[:, 5, 7] != ph[:, 5, 7])
    assert np.abs(clean[:, 5, 7] - p[:, 5, 7]).max() < 0.3


def test_a_scan_without_zingers_is_returned_as_it_is(case):
    p, g, vg = case.scan.projections, case.scan.geometry, case.vol_geom
    q = forward(reconstruct(p, vg, g), vg, g)  # at the nominal geometry of a tilted axis: edges everywhere
    clean, rep = remove_zingers(p, q)
    assert rep.count <= 2e-4 * p.size, rep.count
    if rep.count == 0:
        assert clean is p and rep.describe().startswith("none found")
    with pytest.raises(ShapeError, match="reprojection"):
        remove_zingers(p, q[:-1])
    with pytest.raises(ShapeError, match="projections"):
        remove_zingers(p[0], q[0])
    with pytest.raises(ValueError, match="k must be"):
        remove_zingers(p, q, k=2.0)


def test_calibrate_takes_zingers_out_and_says_so(case):
    p, g, vg = case.scan.projections, case.scan.geometry, case.vol_geom
    pz, hit = _zingers(p, 0.003)
    res = pdvc.calibrate(pz, g, vg, max_outer=2)
    n_found = int(res.options["zingers"].split()[0])
    assert 0.75 * hit.sum() < n_found < 1.5 * hit.sum()
    assert pdvc.calibrate(pz, g, vg, max_outer=2, zingers="off").options["zingers"] == "not checked"
    with pytest.raises(pdvc.calibration.CalibrationError, match="zingers"):
        pdvc.calibrate(p, g, vg, zingers="on")


def test_a_long_scan_is_checked_on_every_eighth_view_first():
    """64 views or more: a scan without zingers costs the forward projection of every 8th view; with zingers the
    probe finds them and all views are checked."""
    c = make_case("offset", n=24, n_views=72)
    p, g, vg = c.scan.projections, c.scan.geometry, c.vol_geom
    clean = pdvc.calibrate(p, g, vg, max_outer=1)
    assert clean.options["zingers"].startswith("none found on every 8th view")
    assert clean.timings["zingers"] < clean.timings["final"]
    pz, hit = _zingers(p, 0.003)
    found = pdvc.calibrate(pz, g, vg, max_outer=1)
    n_found = int(found.options["zingers"].split()[0])
    assert 0.75 * hit.sum() < n_found < 1.5 * hit.sum()
