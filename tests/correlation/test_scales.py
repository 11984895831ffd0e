"""Coarse graining of projections and volumes, scale schedules."""

import numpy as np
import pytest

import pdvc
from pdvc.correlation._scales import coarse_grain, coarse_noise_factor, coarse_volume, scale_schedule
from pdvc.geometry import VolumeGeometry, circular_cone, parallel

from ..conftest import gaussian_blob_line_integrals, gaussian_blob_volume

ANGLES = np.linspace(0, np.pi, 5, endpoint=False)


def _effective_sigma_px(s, sigma=None):
    """Std (fine pixels) of the Gaussian blur followed by the s-pixel block mean."""
    g = s / 2 if sigma is None else sigma
    return np.sqrt(g**2 + (s**2 - 1) / 12)


@pytest.mark.parametrize("scale", [2, 3, 4])
def test_shapes_and_geometry(scale, rng):
    g = circular_cone(ANGLES, sod=50, odd=30, det_shape=(37, 50), pixel=(0.2, 0.3))
    proj = rng.normal(size=(5, 37, 50)).astype(np.float32)
    before = proj.copy()
    ps, gs = coarse_grain(proj, g, scale)
    np.testing.assert_array_equal(proj, before)  # input untouched
    assert ps.dtype == np.float32 and ps.shape == (5, 37 // scale, 50 // scale)
    assert gs.det_shape == ps.shape[1:] and gs.n_views == 5
    np.testing.assert_allclose(np.linalg.norm(gs.u, axis=1), 0.3 * scale)
    np.testing.assert_allclose(np.linalg.norm(gs.v, axis=1), 0.2 * scale)
    # each coarse pixel centre is the centre of its block of fine pixels
    fine = g.pixel_centers(2)
    nr, nc = gs.det_shape
    blocks = fine[: nr * scale, : nc * scale].reshape(nr, scale, nc, scale, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(gs.pixel_centers(2), blocks, atol=1e-12)


@pytest.mark.parametrize("shape, scale, sigma", [((3, 37, 50), 2, None), ((2, 31, 47), 3, None), ((2, 64, 80), 4, None),
                                                 ((2, 9, 11), 4, 3.0), ((2, 20, 20), 2, 0.3)])
def test_blur_and_bin_at_the_coarse_pixels_only_is_the_blur_then_the_block_mean(shape, scale, sigma, rng):
    # the definition (scipy's Gaussian with mirror edges over every fine pixel, then the block mean), against the
    # one linear map per axis evaluated at the coarse pixels; sigma 3 at 9 rows: the kernel reflects more than once
    from scipy.ndimage import gaussian_filter

    g = parallel(np.linspace(0, np.pi, shape[0], endpoint=False), det_shape=shape[1:], pixel=1.0)
    proj = rng.normal(size=shape).astype(np.float32) + 2.0
    sig = scale / 2 if sigma is None else sigma
    want = pdvc.projectors.bin_projections(gaussian_filter(proj, sigma=(0, sig, sig), mode="reflect"), scale)
    got, _ = coarse_grain(proj, g, scale, sigma=sigma)
    assert got.dtype == np.float32 and got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5)


def test_scale_one_is_an_unchanged_copy(rng):
    g = parallel(ANGLES, det_shape=(8, 9), pixel=1.0)
    proj = rng.normal(size=(5, 8, 9))
    ps, gs = coarse_grain(proj, g, 1)
    assert gs == g and ps.dtype == np.float32
    np.testing.assert_array_equal(ps, proj.astype(np.float32))
    ps[0, 0, 0] = 99.0
    assert proj[0, 0, 0] != 99.0
    # an explicit blur is honoured at scale 1
    blurred, _ = coarse_grain(proj, g, 1, sigma=1.0)
    assert blurred.std() < 0.7 * proj.std()


def test_no_mixing_across_views_and_plain_binning():
    g = parallel(ANGLES, det_shape=(32, 32), pixel=1.0)
    proj = np.zeros((5, 32, 32), np.float32)
    proj[2] = np.arange(32 * 32.0).reshape(32, 32)
    ps, _ = coarse_grain(proj, g, 2)
    assert np.all(ps[[0, 1, 3, 4]] == 0)  # blur is along rows and columns only
    plain, _ = coarse_grain(proj, g, 2, sigma=0)
    np.testing.assert_array_equal(plain, pdvc.projectors.bin_projections(proj, 2))
    # a ramp is kept by the (symmetric) blur away from the edges (kernel radius 4 fine pixels)
    np.testing.assert_allclose(ps[2, 3:-3, 3:-3], plain[2, 3:-3, 3:-3], atol=1e-3)


@pytest.mark.parametrize("scale", [2, 4])
def test_coarse_grained_exact_projection_is_a_wider_blob(scale):
    """Parallel beam, exact line integrals: the coarse image is the blob blurred by ≈ 0.58 s pixels."""
    px = 0.5
    g = parallel(ANGLES, det_shape=(96, 96), pixel=px)
    mean, sig, amp = (1.2, -0.7, 0.9), 4.0, 1.0
    fine = gaussian_blob_line_integrals(g, mean, sig, amp)
    ps, gs = coarse_grain(fine, g, scale)
    # blurring a Gaussian of width sig by a Gaussian of width b gives width √(sig² + b²), area kept
    b = _effective_sigma_px(scale) * px
    wide = np.sqrt(sig**2 + b**2)
    expected = gaussian_blob_line_integrals(gs, mean, wide, amp * sig**3 / wide**3)
    peak = expected.max()
    # the block mean is a box, not a Gaussian: only its variance is matched; the rest is
    # of order (b / sig)⁴ of the peak (b/sig = 0.14 at s = 2, 0.29 at s = 4) with a small
    # factor (the box's excess kurtosis); measured 6e-6 and 1e-4 of the peak
    assert np.abs(ps - expected).max() < 0.1 * (b / sig) ** 4 * peak + 1e-6
    # sampling the unblurred blob at the coarse pixel centres misses by the blur, ~(b/sig)² of the peak
    naive = gaussian_blob_line_integrals(gs, mean, sig, amp)
    assert np.abs(ps - naive).max() > 0.5 * (b / sig) ** 2 * peak


@pytest.mark.parametrize("scale", [2, 4])
def test_coarse_geometry_projects_like_coarse_grained_fine(scale):
    """pdvc.forward at the coarse geometry ≈ coarse_grain(forward at the fine geometry)."""
    g = circular_cone(np.linspace(0, 2 * np.pi, 4, endpoint=False), sod=40, odd=40, det_shape=(64, 72), pixel=0.25)
    vg = VolumeGeometry((32, 32, 32), voxel_size=0.25)
    sig = 1.0  # world units; magnification 2 -> 8 fine pixels on the detector
    vol = gaussian_blob_volume(vg, (0.4, -0.3, 0.2), sig)
    fine = pdvc.forward(vol, vg, g)
    ps, gs = coarse_grain(fine, g, scale)
    coarse = pdvc.forward(vol, vg, gs)
    assert ps.shape == coarse.shape
    # The difference is the blur: peak drop 1 - sig_d² / (sig_d² + b²), sig_d = 8 fine pixels
    # (magnification 2), b the effective blur; plus the voxel projector's own error, which
    # differs between the fine and the coarse rays (measured against exact line integrals).
    proj_err = np.abs(fine - gaussian_blob_line_integrals(g, (0.4, -0.3, 0.2), sig)).max() / fine.max()
    b = _effective_sigma_px(scale)
    drop = 1 - 64 / (64 + b**2)  # 0.019 at s = 2, 0.076 at s = 4
    err = np.abs(ps - coarse).max() / coarse.max()  # measured 0.029 and 0.073
    assert err < drop + 2 * proj_err  # proj_err ~0.012
    assert err > 0.5 * drop


def test_coarse_noise_factor_matches_empirical():
    rng = np.random.default_rng(3)
    noise = rng.normal(size=(1, 512, 512)).astype(np.float32)
    g = parallel([0.0], det_shape=(512, 512), pixel=1.0)
    assert coarse_noise_factor(1) == 1.0
    assert coarse_noise_factor(2, sigma=0) == pytest.approx(0.25)
    for s in (2, 4):
        ps, _ = coarse_grain(noise, g, s)
        inner = ps[0, 3:-3, 3:-3]  # away from the mirrored edges
        # ~(512/s)² correlated samples: the variance is known to ~2 % (s = 2) and ~4 % (s = 4)
        assert inner.var() == pytest.approx(coarse_noise_factor(s), rel=0.08)
    # more blur, less noise
    assert coarse_noise_factor(2, sigma=2.0) < coarse_noise_factor(2) < coarse_noise_factor(2, sigma=0)


def test_coarse_grain_errors():
    g = parallel(ANGLES, det_shape=(8, 8), pixel=1.0)
    with pytest.raises(pdvc.ShapeError, match="scale must be a positive int"):
        coarse_grain(np.zeros((5, 8, 8)), g, 0)
    with pytest.raises(pdvc.ShapeError, match="scale must be a positive int"):
        coarse_grain(np.zeros((5, 8, 8)), g, 2.0)
    with pytest.raises(pdvc.ShapeError, match=r"\(5, 8, 8\)"):
        coarse_grain(np.zeros((5, 8, 9)), g, 2)
    with pytest.raises(pdvc.ShapeError, match="larger than the detector"):
        coarse_grain(np.zeros((5, 8, 8)), g, 9)
    with pytest.raises(pdvc.ShapeError, match="sigma"):
        coarse_grain(np.zeros((5, 8, 8)), g, 2, sigma=-1)
    with pytest.raises(pdvc.InputTypeError, match="geom"):
        coarse_grain(np.zeros((5, 8, 8)), np.zeros((5, 12)), 2)


def _linear_field(vg, a=(0.3, -1.1, 2.0), c0=5.0):
    zc, yc, xc = vg.coordinates()
    Z, Y, X = np.meshgrid(zc, yc, xc, indexing="ij")
    return a[0] * X + a[1] * Y + a[2] * Z + c0


@pytest.mark.parametrize(
    "shape, scale", [((12, 16, 8), 2), ((12, 16, 8), 4), ((11, 10, 13), 2), ((14, 17, 12), 3)]
)
def test_coarse_volume_centres_are_block_centres(shape, scale):
    vg = VolumeGeometry(shape, voxel_size=(0.5, 0.4, 0.3), offset=(1.0, -2.0, 0.5))
    f = _linear_field(vg)
    before = f.copy()
    vs, vgs = coarse_volume(f, vg, scale)
    np.testing.assert_array_equal(f, before)
    assert vs.dtype == np.float32 and vs.shape == tuple(n // scale for n in shape) == vgs.shape
    np.testing.assert_allclose(vgs.voxel_size, np.array([0.5, 0.4, 0.3]) * scale)
    # the block mean of a linear field is its value at the block centre: the coarse grid's centres
    np.testing.assert_allclose(vs, _linear_field(vgs), atol=2e-5 * np.abs(f).max())
    rem = np.array(shape) % scale
    if np.all(rem % 2 == 0):
        assert vgs == vg.binned(scale)
    else:  # odd remainders: the offset moves by half a fine voxel on those axes
        shift = (np.asarray(vgs.offset) - np.asarray(vg.offset))[::-1]  # (z, y, x)
        np.testing.assert_allclose(shift, -(rem % 2) / 2 * np.array(vg.voxel_size), atol=1e-12)


def test_coarse_volume_preserves_mean(rng):
    vg = VolumeGeometry((16, 12, 20), voxel_size=1.0)
    f = rng.random((16, 12, 20)).astype(np.float32)
    for s in (1, 2, 4):
        vs, _ = coarse_volume(f, vg, s)
        assert vs.mean(dtype=np.float64) == pytest.approx(f.mean(dtype=np.float64), rel=1e-6)
    vs1, vg1 = coarse_volume(f, vg, 1)
    assert vg1 == vg and vs1 is not f
    np.testing.assert_array_equal(vs1, f)
    with pytest.raises(pdvc.ShapeError, match="fewer than 2 voxels"):
        coarse_volume(f, vg, 7)
    with pytest.raises(pdvc.ShapeError, match="shape"):
        coarse_volume(f[:-1], vg, 2)


def test_scale_schedule():
    assert scale_schedule(4) == (4, 2, 1)
    assert scale_schedule(8) == (8, 4, 2, 1)
    assert scale_schedule(1) == (1,)
    assert scale_schedule(6) == (6, 3, 1)
    assert scale_schedule(8, 2) == (8, 4, 2)
    assert scale_schedule(3, 2) == (3, 2)
    assert scale_schedule(5) == (5, 2, 1)
    with pytest.raises(pdvc.ShapeError, match="start must be >= stop"):
        scale_schedule(2, 4)
    with pytest.raises(pdvc.ShapeError, match="scale must be a positive int"):
        scale_schedule(0)
