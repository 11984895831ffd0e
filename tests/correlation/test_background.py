"""The smooth background per view, profiled out of the normal equations (pdvc.correlation._background)."""

from __future__ import annotations

import numpy as np
import pytest

import pdvc
from pdvc.correlation import CorrelationError, correlate
from pdvc.correlation._background import background_basis, reduce_views_background
from pdvc.projectors import reduce_views

from .cases import make_case


@pytest.fixture(scope="module")
def case():
    c = make_case("offset", n=24, n_views=48)
    return c, pdvc.fdk(c.scan.projections, c.vol_geom, c.scan.geometry)


def test_basis_is_the_monomials_up_to_the_degree():
    phi = background_basis((5, 7), 2)
    assert phi.shape == (6, 5, 7)
    u, v = np.linspace(-1, 1, 7), np.linspace(-1, 1, 5)
    np.testing.assert_allclose(phi[0], 1.0)
    np.testing.assert_allclose(phi[1], np.broadcast_to(u, (5, 7)))  # u
    np.testing.assert_allclose(phi[2], np.broadcast_to(v[:, None], (5, 7)))  # v
    np.testing.assert_allclose(phi[4], np.outer(v, u))  # u v
    assert background_basis((5, 7), 0).shape == (1, 5, 7)
    with pytest.raises(ValueError, match="degree"):
        background_basis((5, 7), 3)


def test_a_background_in_the_basis_changes_nothing_once_profiled(case):
    """Adding Φ c (random per view) to the data leaves M', b' and χ of the profiled reduction unchanged."""
    c, vol = case
    p, g, vg = c.scan.projections, c.scan.geometry, c.vol_geom
    rng = np.random.default_rng(0)
    phi = background_basis(g.det_shape, 2)
    bg = np.einsum("kq,qrc->krc", rng.normal(0, 0.3, (g.n_views, phi.shape[0])), phi).astype(np.float32)
    a = reduce_views_background(vol, vg, g, p, degree=2, center=vg.offset)
    b = reduce_views_background(vol, vg, g, p + bg, degree=2, center=vg.offset)
    np.testing.assert_allclose(b.M, a.M, rtol=1e-6, atol=1e-9 * np.abs(a.M).max())
    np.testing.assert_allclose(b.b, a.b, atol=1e-5 * np.abs(a.b).max())
    np.testing.assert_allclose(b.rss, a.rss, rtol=1e-4)
    # the plain reduction sees it: its residual grows by the background's energy
    plain, plain_bg = (reduce_views(vol, vg, g, x, center=vg.offset) for x in (p, p + bg))
    assert plain_bg.rss.sum() > plain.rss.sum() + 0.5 * float(np.sum(bg.astype(float) ** 2))
    # and profiling only removes: rss' <= rss, M' <= M (a Schur complement)
    assert np.all(a.rss <= plain.rss * (1 + 1e-6))
    assert np.all(np.linalg.eigvalsh(plain.M - a.M) > -1e-6 * np.abs(a.M).max())


def test_without_a_background_term_the_profiled_reduction_is_the_fused_one_minus_the_mean(case):
    """Degree 0 removes only the weighted mean of the residual per view: M' = M - C Cᵀ / Σw with C = Σ w g."""
    c, vol = case
    p, g, vg = c.scan.projections, c.scan.geometry, c.vol_geom
    plain = reduce_views(vol, vg, g, p, center=vg.offset)
    prof = reduce_views_background(vol, vg, g, p, degree=0, center=vg.offset)
    np.testing.assert_allclose(prof.rss, plain.rss - plain.resid_sum**2 / plain.weight_sum, rtol=1e-4)
    np.testing.assert_allclose(prof.weight_sum, plain.weight_sum)
    np.testing.assert_allclose(prof.meas_sum, plain.meas_sum, rtol=1e-5)


def test_correlate_finds_the_motion_under_a_drifting_air_level(case):
    """Line integrals with an offset per view (an air level drifting from 0 to 0.3) and a known translation:
    with background=0 the motion is found as without the offset; without it the offset steers the poses."""
    c, vol = case
    p, g, vg = c.scan.projections, c.scan.geometry, c.vol_geom
    n = g.n_views
    drift = np.linspace(0.0, 0.3, n, dtype=np.float32)[:, None, None]
    # the translation along the beam (a magnification change) is nearly an offset of the view: held, as the gauge holds it
    kw = dict(basis="constant", frame="lab", fixed=("rx", "ry", "rz", "ty"), max_iter=15,
              noise_variance=float(c.scan.noise_variance().mean()))
    clean = correlate(vol, vg, p, g, **kw)
    with_bg = correlate(vol, vg, p + drift, g, background=0, **kw)
    without = correlate(vol, vg, p + drift, g, **kw)
    d_bg = np.abs(with_bg.params - clean.params).max()
    d_without = np.abs(without.params - clean.params).max()
    assert d_bg < 0.02, d_bg
    assert d_without > 3 * d_bg, (d_without, d_bg)
    with pytest.raises(CorrelationError, match="background"):
        correlate(vol, vg, p, g, background=3, **kw)


def test_the_result_reports_the_per_view_offset_its_poses_leave(case):
    """offset_sigma: the weighted RMS per-view offset of the residual at the poses returned, in noise std; near 0 on
    clean data, the drift's RMS (less what the reconstruction absorbs) with one, 0 once a background is fitted."""
    from pdvc.correlation._background import AUTO_OFFSET_SIGMA, auto_background, view_offset

    c, vol = case
    p, g, vg = c.scan.projections, c.scan.geometry, c.vol_geom
    gamma2 = float(c.scan.noise_variance().mean())
    kw = dict(basis="constant", frame="lab", fixed=("rx", "ry", "rz", "ty"), max_iter=5, noise_variance=gamma2)
    clean = correlate(vol, vg, p, g, **kw)
    assert clean.offset_sigma < AUTO_OFFSET_SIGMA / 2 and auto_background(clean.offset_sigma) is None
    drift = np.linspace(-1.0, 1.0, g.n_views, dtype=np.float32)[:, None, None] * np.sqrt(gamma2)  # RMS 0.58 σ
    found = correlate(vol, vg, p + drift, g, **kw)
    assert 0.4 < found.offset_sigma < 0.8, found.offset_sigma
    assert auto_background(found.offset_sigma) == 1
    # the number is the one view_offset reads off the reduction at the poses returned
    red = reduce_views(vol, vg, found.geometry, p + drift, center=vg.offset)
    assert view_offset(red, gamma2) == pytest.approx(found.offset_sigma, rel=1e-6)
    fitted = correlate(vol, vg, p + drift, g, background=1, **kw)
    assert fitted.background == 1 and fitted.offset_sigma < 1e-6
    assert found.background is None
    with pytest.raises(CorrelationError, match="background"):
        correlate(vol, vg, p, g, background="auto", **kw)


def test_the_images_pass_by_chunks_of_views_gives_the_same_reduction(case, monkeypatch):
    from pdvc.correlation import _background

    c, vol = case
    p, g, vg = c.scan.projections, c.scan.geometry, c.vol_geom
    whole = reduce_views_background(vol, vg, g, p, degree=1, center=vg.offset)
    monkeypatch.setattr(_background, "_CHUNK_BYTES", 7 * 4 * 5 * p.shape[1] * p.shape[2])  # 5 views a chunk
    chunked = reduce_views_background(vol, vg, g, p, degree=1, center=vg.offset)
    np.testing.assert_array_equal(chunked.M, whole.M)
    np.testing.assert_array_equal(chunked.rss, whole.rss)


def test_an_offset_profiled_from_the_fused_pass_equals_the_one_from_the_images(case):
    """Degree 0 runs on the fused pass (Σ w g, Σ w ρ, Σ w); the images path computes the same thing another way."""
    from pdvc.correlation._background import _by_images

    c, vol = case
    p, g, vg = c.scan.projections, c.scan.geometry, c.vol_geom
    w = np.random.default_rng(1).uniform(0.2, 1.0, g.det_shape).astype(np.float32)
    fused = reduce_views_background(vol, vg, g, p, degree=0, weights=w, center=vg.offset)
    images = _by_images(vol, vg, g, p, degree=0, weights=w, center=vg.offset)
    # both sum float32 products over the pixels, in different orders: an element that cancels to a small value keeps
    # the rounding of its large terms (a full run saw 4.0e-4 against a largest element of 42, 0.9e-5 of it, where the
    # test alone matches to 1e-7): the absolute tolerance is float32's, a wrong term would be off by its whole size
    np.testing.assert_allclose(fused.M, images.M, rtol=1e-6, atol=3e-5 * np.abs(images.M).max())
    np.testing.assert_allclose(fused.b, images.b, atol=1e-6 * np.abs(images.b).max())
    np.testing.assert_allclose(fused.rss, images.rss, rtol=1e-6)
