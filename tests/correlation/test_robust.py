"""Huber's M-estimator in the Jacobian pass (iteratively reweighted least squares): ``reduce_views(robust=)``,
``correlate(robust=)`` and the calibration's ``robust`` (docs/method.md §5.19)."""

from __future__ import annotations

import numpy as np
import pytest

import pdvc
from pdvc.correlation import CorrelationError, correlate, residual_scale
from pdvc.correlation._background import _by_images, reduce_views_background
from pdvc.errors import ShapeError
from pdvc.projectors import jacobian, reduce_views

from .cases import make_case


@pytest.fixture(scope="module")
def case():
    c = make_case("offset", n=24, n_views=48)
    return c, pdvc.fdk(c.scan.projections, c.vol_geom, c.scan.geometry)


def _zingers(p, fraction=0.01, seed=3):
    """Pixels read brighter (a cosmic ray): the line integral drops by 0.5 to 3."""
    rng = np.random.default_rng(seed)
    hit = rng.random(p.shape) < fraction
    return np.where(hit, p - rng.uniform(0.5, 3.0, p.shape), p).astype(np.float32)


def test_the_fused_robust_pass_equals_huber_weights_computed_from_the_images(case):
    """Known answer by another path: the projection and sensitivity images, Huber's weights and loss in NumPy."""
    c, vol = case
    p, g, vg = _zingers(c.scan.projections), c.scan.geometry, c.vol_geom
    w = np.random.default_rng(1).uniform(0.2, 1.0, g.det_shape).astype(np.float32)
    shift = np.random.default_rng(2).normal(0, 0.02, g.n_views)
    cut = 0.05
    red = reduce_views(vol, vg, g, p, weights=w, center=vg.offset, robust=(cut, shift))
    proj, sens = jacobian(vol, vg, g, center=vg.offset)
    e = (p.astype(np.float64) - proj) - shift[:, None, None]
    a = np.abs(e)
    assert 0.01 < np.mean(a > cut) < 0.5  # the cut is reached, but not everywhere
    wr = w * np.minimum(1.0, cut / a)
    G = sens.astype(np.float64)  # (n, 6, rows, cols)
    M = np.einsum("kirc,kjrc,krc->kij", G, G, wr)
    np.testing.assert_allclose(red.M, M, rtol=1e-5, atol=1e-6 * np.abs(M).max())
    np.testing.assert_allclose(red.b, np.einsum("kirc,krc->ki", G, wr * e), rtol=1e-4, atol=1e-5 * np.abs(red.b).max())
    loss = np.where(a > cut, 2 * cut * a - cut**2, e**2)
    np.testing.assert_allclose(red.rss, np.einsum("krc,rc->k", loss, w), rtol=1e-5)
    np.testing.assert_allclose(red.weight_sum, wr.sum(axis=(1, 2)), rtol=1e-5)
    np.testing.assert_allclose(red.resid_sum, (wr * e).sum(axis=(1, 2)), rtol=1e-4, atol=1e-6 * np.abs(red.resid_sum).max())
    np.testing.assert_allclose(red.meas_sum, np.einsum("krc,rc->k", p.astype(np.float64), w), rtol=1e-5)  # the data's: w


def test_with_no_pixel_beyond_the_cut_the_robust_pass_is_least_squares(case):
    c, vol = case
    p, g, vg = c.scan.projections, c.scan.geometry, c.vol_geom
    plain = reduce_views(vol, vg, g, p, center=vg.offset)
    wide = reduce_views(vol, vg, g, p, center=vg.offset, robust=(1e6, np.zeros(g.n_views)))
    for name in ("M", "b", "rss", "weight_sum", "meas_sum", "resid_sum"):
        np.testing.assert_allclose(getattr(wide, name), getattr(plain, name), rtol=1e-9, err_msg=name)


def test_the_robust_background_paths_agree(case):
    """Degree 0 on the fused pass and on the images give the same profiled reduction under Huber weights."""
    c, vol = case
    p, g, vg = _zingers(c.scan.projections), c.scan.geometry, c.vol_geom
    rob = (0.05, np.linspace(-0.02, 0.02, g.n_views))
    fused = reduce_views_background(vol, vg, g, p, degree=0, center=vg.offset, robust=rob)
    images = _by_images(vol, vg, g, p, degree=0, center=vg.offset, robust=rob)
    np.testing.assert_allclose(fused.M, images.M, rtol=1e-5, atol=1e-6 * np.abs(images.M).max())
    np.testing.assert_allclose(fused.b, images.b, atol=1e-5 * np.abs(images.b).max())
    np.testing.assert_allclose(fused.rss, images.rss, rtol=1e-5)


def test_residual_scale_reads_the_noise_and_the_offset_per_view(case):
    c, vol = case
    g, vg = c.scan.geometry, c.vol_geom
    exact = pdvc.forward(vol, vg, g)
    rng = np.random.default_rng(5)
    offsets = rng.uniform(-0.3, 0.3, g.n_views)
    noisy = (exact + offsets[:, None, None] + rng.normal(0, 0.01, exact.shape)).astype(np.float32)
    noisy = _zingers(noisy, 0.02)  # outliers move neither the median nor the MAD much
    sigma, shift = residual_scale(vol, vg, noisy, g, noise_variance=1e-8)
    assert sigma == pytest.approx(0.01, rel=0.1)
    np.testing.assert_allclose(shift, offsets, atol=2e-3)
    # the noise std is the floor: exact data have no spread
    sigma0, _ = residual_scale(vol, vg, exact, g, noise_variance=0.02**2)
    assert sigma0 == pytest.approx(0.02)


def test_zingers_do_not_steer_the_poses_under_huber_weights(case):
    """Known motion (an axis offset of 2 voxels) under 1 % zingers: least squares is pulled off, Huber is not."""
    c, _ = case
    p, g, vg = c.scan.projections, c.scan.geometry, c.vol_geom
    gamma2 = float(c.scan.noise_variance().mean())
    kw = dict(basis="constant", frame="lab", fixed=("rx", "ry", "rz", "ty"), max_iter=15, noise_variance=gamma2)
    ref = correlate(pdvc.fdk(p, vg, g), vg, p, g, **kw).params[0, :3]
    assert abs(ref[0] - 2.0) < 0.01  # the offset injected
    pz = _zingers(p)
    vol = pdvc.fdk(pz, vg, g)
    d_plain = np.abs(correlate(vol, vg, pz, g, **kw).params[0, :3] - ref).max()
    huber = correlate(vol, vg, pz, g, robust=4.0, **kw)
    d_huber = np.abs(huber.params[0, :3] - ref).max()
    assert d_huber < 0.06 and d_plain > 2 * d_huber, (d_plain, d_huber)
    # on clean data Huber's estimate is least squares' within a hundredth of a voxel
    clean = correlate(pdvc.fdk(p, vg, g), vg, p, g, robust=4.0, **kw)
    assert np.abs(clean.params[0, :3] - ref).max() < 0.01


def test_the_offset_per_view_is_reported_with_huber_weights_as_without(case):
    """offset_sigma feeds background = "auto": the shift the Huber weights take out is put back."""
    c, vol = case
    p, g, vg = c.scan.projections, c.scan.geometry, c.vol_geom
    gamma2 = float(c.scan.noise_variance().mean())
    drift = np.linspace(-1.0, 1.0, g.n_views, dtype=np.float32)[:, None, None] * np.sqrt(gamma2)
    kw = dict(basis="constant", frame="lab", fixed=("rx", "ry", "rz", "ty"), max_iter=5, noise_variance=gamma2)
    plain = correlate(vol, vg, p + drift, g, **kw)
    huber = correlate(vol, vg, p + drift, g, robust=4.0, **kw)
    assert huber.offset_sigma == pytest.approx(plain.offset_sigma, rel=0.15)
    assert 0.4 < huber.offset_sigma < 0.8


def test_bad_robust_options_are_named(case):
    c, vol = case
    p, g, vg = c.scan.projections, c.scan.geometry, c.vol_geom
    for bad in (-1.0, 0.0, float("inf"), "4", True):
        with pytest.raises(CorrelationError, match="robust"):
            correlate(vol, vg, p, g, robust=bad, max_iter=1)
    with pytest.raises(ShapeError, match="robust"):
        reduce_views(vol, vg, g, p, robust=(0.0, np.zeros(g.n_views)))
    with pytest.raises(ShapeError, match="robust"):
        reduce_views(vol, vg, g, p, robust=(0.1, np.zeros(g.n_views - 1)))
    before = p.copy()
    correlate(vol, vg, p, g, robust=4.0, max_iter=1)
    np.testing.assert_array_equal(p, before)  # inputs are never modified
