"""Simulated scans: counts, noise and normalisation (pdvc.simulate.scan)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from pdvc.errors import GeometryError, InputTypeError, ShapeError
from pdvc.geometry import circular_cone, parallel
from pdvc.simulate import (
    EllipsoidPhantom,
    SimulationError,
    add_poisson_noise,
    cast_iron_phantom,
    drift_poses,
    project_analytic,
    simulate_scan,
)


@pytest.fixture(scope="module")
def small_scan_inputs():
    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    geom = circular_cone(angles, sod=8.0, odd=4.0, det_shape=(20, 24), pixel=0.15)
    phantom = cast_iron_phantom(1.0, 1.6, n_nodules=30, n_inclusions=2, seed=5)
    rv, t = drift_poses(np.arange(12.0), angles, velocity=(0.01, -0.005, 0.002), rot_rate=(0, 0, 1e-3))
    return angles, geom, phantom, rv, t


def test_clean_is_the_analytic_projection_with_the_true_geometry(small_scan_inputs):
    angles, geom, phantom, rv, t = small_scan_inputs
    scan = simulate_scan(phantom, geom, rotvecs=rv, translations=t, angles=angles, supersampling=2)
    assert scan.true_geometry == geom.apply_poses(rv, t)
    assert scan.geometry is geom
    assert_array_equal(scan.clean, project_analytic(phantom, geom.apply_poses(rv, t), supersampling=2))
    # moving the sample == moving the scanner: view by view with the moved phantom
    for k in (0, 7):
        moved = project_analytic(phantom.moved(rv[k], t[k]), geom[k], supersampling=2)[0]
        assert_allclose(scan.clean[k], moved, rtol=2e-6, atol=2e-6)
    for name in ("projections", "clean", "counts"):
        arr = getattr(scan, name)
        assert arr.dtype == np.float32 and arr.shape == (12, 20, 24)
        assert not arr.flags.writeable
    assert scan.flats.shape == (10, 20, 24) and scan.darks.shape == (10, 20, 24)
    assert_array_equal(scan.angles, angles)
    assert scan.n_clipped == 0
    # motion is visible in the data
    still = simulate_scan(phantom, geom, supersampling=2)
    assert np.abs(still.clean - scan.clean).max() > 0.1


def test_same_seed_same_data_and_inputs_untouched(small_scan_inputs):
    angles, geom, phantom, rv, t = small_scan_inputs
    rv0, t0, vec0, c0 = rv.copy(), t.copy(), geom.vectors.copy(), phantom.center.copy()
    a = simulate_scan(phantom, geom, rotvecs=rv, translations=t, seed=11, supersampling=1)
    b = simulate_scan(phantom, geom, rotvecs=rv, translations=t, seed=11, supersampling=1)
    c = simulate_scan(phantom, geom, rotvecs=rv, translations=t, seed=12, supersampling=1)
    for name in ("projections", "counts", "flats", "darks"):
        assert_array_equal(getattr(a, name), getattr(b, name))
        assert not np.array_equal(getattr(a, name), getattr(c, name))
    assert_array_equal(rv, rv0)
    assert_array_equal(t, t0)
    assert_array_equal(geom.vectors, vec0)
    assert_array_equal(phantom.center, c0)


def test_noise_statistics_match_poisson():
    """400 identical views of a ball: per pixel, the mean over views equals
    the clean value within its standard error, and the variance over views
    is the delta-method one, (N + σ²)/N² with N = i0·e^{-p}."""
    n_views, i0, sigma, n_flats = 400, 2e4, 2.0, 10
    geom = parallel(np.zeros(n_views), det_shape=(8, 8), pixel=0.25)
    ball = EllipsoidPhantom(1.0, (0.1, 0.0, -0.05), (1.0, 1.0, 1.0))
    scan = simulate_scan(ball, geom, i0=i0, dark_noise=sigma, n_flats=n_flats, seed=3, supersampling=1)
    p = scan.clean[0].astype(np.float64)
    assert p.max() > 1.5 and p.min() < 0.5  # a useful spread of attenuations
    s = scan.projections.astype(np.float64)
    N = i0 * np.exp(-p)
    var_view = (N + sigma**2) / N**2
    # the mean carries the view noise / n_views plus the shared flat noise
    se = np.sqrt(var_view / n_views + (i0 + sigma**2) / (n_flats * i0**2))
    z = (s.mean(axis=0) - p) / se
    assert np.max(np.abs(z)) < 4.5  # 64 pixels: P(any |z| > 4.5) ~ 4e-4
    # variance over views: each pixel's estimate has relative s.d. sqrt(2/399) = 7 %
    ratio = s.var(axis=0, ddof=1) / var_view
    assert np.all(np.abs(ratio - 1) < 0.35)  # 5 sigma per pixel
    assert abs(ratio.mean() - 1) < 0.05  # 64 pixels: s.d. 0.9 %, 5 sigma
    assert_allclose(scan.noise_variance()[0] - (i0 + sigma**2) / (n_flats * i0**2), var_view, rtol=1e-5)
    # flats and darks: means of 10 frames x 64 pixels, within 5 standard errors
    n_samples = n_flats * 64
    assert abs(scan.flat.mean() - i0 - scan.dark_level) < 5 * np.sqrt((i0 + sigma**2) / n_samples)
    assert abs(scan.dark.mean() - scan.dark_level) < 5 * sigma / np.sqrt(n_samples)
    assert scan.darks.std() == pytest.approx(sigma, rel=0.25)


def test_clipping_of_starved_pixels():
    geom = parallel([0.0], det_shape=(6, 6), pixel=0.3)
    dense = EllipsoidPhantom(20.0, (0, 0, 0), (1.0, 1.0, 1.0))  # p up to 40: no photons
    scan = simulate_scan(dense, geom, i0=50.0, dark_noise=3.0, seed=0)
    assert scan.n_clipped > 0
    assert np.all(np.isfinite(scan.projections))
    assert scan.projections.max() <= np.float32(np.log(2 * 50.0)) + 1e-6


def test_add_poisson_noise():
    p = np.full((200, 500), 1.0)
    p0 = p.copy()
    i0 = 1e4
    noisy = add_poisson_noise(p, i0, seed=1)
    assert noisy.dtype == np.float32 and noisy.shape == p.shape
    assert_array_equal(p, p0)
    assert_array_equal(noisy, add_poisson_noise(p, i0, seed=1))
    var = np.e / i0  # delta method
    # 1e5 samples: the mean's s.e. is sqrt(var / 1e5); the variance's relative s.e. sqrt(2 / 1e5)
    assert abs(noisy.mean() - 1.0 - var / 2) < 5 * np.sqrt(var / p.size)
    assert noisy.var() / var == pytest.approx(1.0, abs=5 * np.sqrt(2 / p.size) + 0.01)
    assert add_poisson_noise(np.array([30.0]), 10.0).max() <= np.log(20.0) + 1e-6


def test_bad_inputs_name_the_parameter(small_scan_inputs):
    angles, geom, phantom, rv, t = small_scan_inputs
    with pytest.raises(SimulationError, match="i0"):
        simulate_scan(phantom, geom, i0=0)
    with pytest.raises(SimulationError, match="n_flats"):
        simulate_scan(phantom, geom, n_flats=0)
    with pytest.raises(SimulationError, match="dark_noise"):
        simulate_scan(phantom, geom, dark_noise=-1.0)
    with pytest.raises(GeometryError, match="rotvecs"):
        simulate_scan(phantom, geom, rotvecs=np.zeros((5, 3)))
    with pytest.raises(ShapeError, match="angles"):
        simulate_scan(phantom, geom, angles=angles[:5])
    with pytest.raises(InputTypeError, match="phantom"):
        simulate_scan(np.zeros((8, 8, 8)), geom)
    with pytest.raises(InputTypeError, match="geom"):
        simulate_scan(phantom, "cone")
    with pytest.raises(SimulationError, match="i0"):
        add_poisson_noise(np.zeros(3), -5)
