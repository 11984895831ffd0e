"""Noise variance: Immerkær's estimator and the Poisson (delta-method) model."""

import numpy as np
import pytest

import pdvc
from pdvc.correlation._noise import NoiseEstimateError, estimate_noise_variance, poisson_variance
from pdvc.geometry import circular_cone
from pdvc.simulate import cast_iron_phantom, project_analytic, simulate_scan


def _smooth_images(n_views=4, shape=(256, 256)):
    """Smooth line-integral-like images: a wide Gaussian bump, a ramp and a slow wave, per view."""
    r, c = np.mgrid[0 : shape[0], 0 : shape[1]] / max(shape)
    out = []
    for k in range(n_views):
        img = 1.5 * np.exp(-((r - 0.5) ** 2 + (c - 0.4 - 0.05 * k) ** 2) / (2 * 0.15**2))
        img += 0.3 * r + 0.1 * np.sin(2 * np.pi * (c + k / n_views))
        out.append(img)
    return np.array(out, dtype=np.float32)


@pytest.fixture(scope="module")
def cone_scan_setup():
    angles = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    geom = circular_cone(angles, sod=10, odd=10, det_shape=(96, 96), pixel=0.05)
    phantom = cast_iron_phantom(1.0, 1.8, n_nodules=40, nodule_size=(0.1, 0.2), seed=3)
    return geom, phantom


def test_smooth_image_plus_white_noise():
    clean = _smooth_images()
    rng = np.random.default_rng(0)
    # noise-free smooth signal barely registers: the mask cancels what is locally linear along an axis
    assert np.sqrt(estimate_noise_variance(clean)) < 1e-5  # signal range ~1.8; measured 2e-8
    for sigma in (0.002, 0.01, 0.05):
        noisy = clean + rng.normal(0, sigma, clean.shape).astype(np.float32)
        before = noisy.copy()
        est = estimate_noise_variance(noisy)
        np.testing.assert_array_equal(noisy, before)  # input untouched
        # 254² pixels per view: the estimate's statistical scatter is < 1 % in σ; 3 % leaves room
        assert np.sqrt(est) / sigma == pytest.approx(1.0, abs=0.03)
    # the naive estimate (std of the image) is dominated by the signal
    assert noisy.std() > 5 * sigma


def test_single_image_and_pure_noise():
    rng = np.random.default_rng(1)
    img = rng.normal(0, 2.0, (300, 300))
    assert estimate_noise_variance(img) == pytest.approx(4.0, rel=0.03)  # 2D input = one view


def test_analytic_cast_iron_projections_plus_white_noise(cone_scan_setup):
    geom, phantom = cone_scan_setup
    clean = project_analytic(phantom, geom, supersampling=2)
    rng = np.random.default_rng(2)
    for sigma in (0.02, 0.04):
        noisy = clean + rng.normal(0, sigma, clean.shape).astype(np.float32)
        ratio = np.sqrt(estimate_noise_variance(noisy)) / sigma
        # the silhouettes of the rod and of ~4-px nodules are sharp (sqrt-like profiles):
        # they leak into the Laplacian and bias σ upward, measured +10 % at σ = 0.02, +3 % at 0.04
        assert 0.98 < ratio < 1.12


def test_simulated_scan_poisson_noise(cone_scan_setup):
    geom, phantom = cone_scan_setup
    scan = simulate_scan(phantom, geom, i0=2e3, seed=4)
    est = estimate_noise_variance(scan.projections)
    expected = float(np.mean(scan.noise_variance()))
    # two biases of opposite sign: Poisson noise is heteroscedastic (the estimator
    # gives ~(mean σ)², below the mean variance) and sharp edges leak in (above);
    # measured ratio 1.00; 15 % covers both
    assert est / expected == pytest.approx(1.0, rel=0.15)


def test_mask_excludes_edges():
    rng = np.random.default_rng(5)
    r, c = np.mgrid[0:200, 0:200]
    disc = ((r - 100) ** 2 + (c - 50) ** 2 < 40**2).astype(np.float64)  # sharp curved edge, left half
    noisy = disc + rng.normal(0, 0.01, disc.shape)
    mask = np.zeros(disc.shape, bool)
    mask[:, 100:] = True
    biased = np.sqrt(estimate_noise_variance(noisy))
    masked = np.sqrt(estimate_noise_variance(noisy, mask=mask))
    assert biased > 1.2 * 0.01  # the edge of the disc leaks in (measured +37 %)
    assert masked == pytest.approx(0.01, rel=0.04)  # 200x98 pixels: scatter ~1 %
    # NaNs outside the mask are fine
    holed = noisy.copy()
    holed[:, :90] = np.nan
    assert np.sqrt(estimate_noise_variance(holed, mask=mask)) == pytest.approx(masked)
    with pytest.raises(NoiseEstimateError, match="NaN"):
        estimate_noise_variance(holed)


def test_views_selection_and_median():
    rng = np.random.default_rng(6)
    sig = np.array([0.01] * 6 + [1.0])  # one broken view
    stack = rng.normal(0, 1, (7, 120, 120)) * sig[:, None, None]
    # the median over views ignores the outlier view
    assert np.sqrt(estimate_noise_variance(stack)) == pytest.approx(0.01, rel=0.05)
    assert np.sqrt(estimate_noise_variance(stack, views=[6])) == pytest.approx(1.0, rel=0.05)
    assert np.sqrt(estimate_noise_variance(stack, views=slice(0, 2))) == pytest.approx(0.01, rel=0.05)
    sel = np.zeros(7, bool)
    sel[6] = True
    assert np.sqrt(estimate_noise_variance(stack, views=sel)) == pytest.approx(1.0, rel=0.05)


def test_estimate_errors():
    with pytest.raises(pdvc.ShapeError, match="n_views, n_rows, n_cols"):
        estimate_noise_variance(np.zeros(10))
    with pytest.raises(pdvc.ShapeError, match="at least 3 columns"):
        estimate_noise_variance(np.zeros((2, 10, 2)))
    with pytest.raises(pdvc.ShapeError, match="mask must have shape"):
        estimate_noise_variance(np.zeros((2, 10, 10)), mask=np.ones((5, 5)))
    with pytest.raises(NoiseEstimateError, match="3x3 neighbourhood"):
        estimate_noise_variance(np.zeros((2, 10, 10)), mask=np.eye(10))
    with pytest.raises(pdvc.ShapeError, match=r"indices in \[0, 2\)"):
        estimate_noise_variance(np.zeros((2, 10, 10)), views=[5])
    with pytest.raises(NoiseEstimateError, match="selects no view"):
        estimate_noise_variance(np.zeros((2, 10, 10)), views=[])
    with pytest.raises(pdvc.InputTypeError, match="views must be"):
        estimate_noise_variance(np.zeros((2, 10, 10)), views=[0.5])


def test_poisson_variance_formula():
    np.testing.assert_allclose(poisson_variance(0.0, i0=100.0), 0.01, rtol=1e-6)
    np.testing.assert_allclose(poisson_variance(np.log(4.0), i0=100.0), 0.04, rtol=1e-6)  # e^p / i0
    np.testing.assert_allclose(poisson_variance(0.0, i0=100.0, n_flats=4), 0.01 + 1 / 400, rtol=1e-6)
    # read noise: (N + σ²)/N²
    np.testing.assert_allclose(poisson_variance(0.0, i0=100.0, dark_noise=10.0), 200 / 100**2, rtol=1e-6)
    per_pixel = poisson_variance(np.zeros((3, 2, 2)), i0=np.array([[100.0, 200.0], [400.0, 800.0]]))
    assert per_pixel.shape == (3, 2, 2) and per_pixel.dtype == np.float32
    np.testing.assert_allclose(per_pixel[1], [[0.01, 0.005], [0.0025, 0.00125]], rtol=1e-6)
    with pytest.raises(pdvc.ShapeError, match="i0 must be positive"):
        poisson_variance(0.0, i0=0.0)
    with pytest.raises(pdvc.ShapeError, match="n_flats"):
        poisson_variance(0.0, i0=10.0, n_flats=0)
    with pytest.raises(pdvc.ShapeError, match="broadcast"):
        poisson_variance(np.zeros((2, 3)), i0=np.ones(4))
    with pytest.raises(pdvc.ShapeError, match="finite"):
        poisson_variance([np.nan], i0=10.0)


def test_poisson_variance_matches_simulated_scan(cone_scan_setup):
    geom, phantom = cone_scan_setup
    scan = simulate_scan(phantom, geom, i0=2e4, n_flats=10, dark_noise=2.0, seed=7)
    var = poisson_variance(scan.clean, i0=scan.i0, n_flats=10, dark_noise=scan.dark_noise).astype(np.float64)
    z2 = (scan.projections.astype(np.float64) - scan.clean) ** 2 / var
    # 16 x 96² = 147k pixels: std of mean(z²) is √(2/N) ≈ 0.4 %; the flat noise is
    # shared by the views of a pixel (9216 draws, ~10 % of the variance): +0.15 %.
    # The delta method's next order is O(1/N) ~ 1e-3 at N >= 2700 counts. 2 % is > 4σ.
    assert z2.mean() == pytest.approx(1.0, abs=0.02)
    # the exp(p) dependence holds across attenuation levels: quartiles of p, 37k pixels each (~1 %)
    edges = np.quantile(scan.clean, [0, 0.25, 0.5, 0.75, 1.0])
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (scan.clean >= lo) & (scan.clean <= hi)
        assert z2[sel].mean() == pytest.approx(1.0, abs=0.04)
    # leaving out the flat noise underestimates the open-beam pixels by ~1/n_flats
    no_flat = poisson_variance(scan.clean, i0=scan.i0, dark_noise=scan.dark_noise).astype(np.float64)
    open_beam = scan.clean < 1e-3
    ratio = np.mean((scan.projections[open_beam] - scan.clean[open_beam]) ** 2 / no_flat[open_beam])
    assert ratio == pytest.approx(1.1, abs=0.03)


def test_thin_detectors_use_the_row_estimate():
    """One- or two-row detectors (sinograms): the 1-D second difference, same known answer."""
    rng = np.random.default_rng(3)
    x = np.linspace(0, 1, 4000)
    signal = 5 * x[None, None, :] + 2 * x[None, None, :] ** 2  # locally linear: cancelled
    for rows in (1, 2):
        stack = signal + rng.normal(0, 0.02, (8, rows, 4000))
        assert np.sqrt(estimate_noise_variance(stack)) == pytest.approx(0.02, rel=0.03)
