"""Zingers, hot and dead pixels found on the residual against a reprojection (pdvc.io.remove_zingers)."""

from __future__ import annotations

import numpy as np
import pytest

import pdvc
from pdvc.calibration import reconstruct
from pdvc.errors import ShapeError
from pdvc.io import remove_zingers
from pdvc.io._zingers import isolated_outliers
from pdvc.projectors import forward

from ..correlation.cases import make_case


def _zingers(p, fraction, seed=1):
    """Bright zingers: the line integral of a random fraction of the pixels drops by 0.5 to 3."""
    rng = np.random.default_rng(seed)
    hit = rng.random(p.shape) < fraction
    return np.where(hit, p - rng.uniform(0.5, 3.0, p.shape), p).astype(np.float32), hit


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
    assert "isolated pixel" in rep.describe()


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
