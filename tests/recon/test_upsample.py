"""Cubic B-spline upsampling onto a finer grid of the same box (the correlation grid)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from pdvc.errors import PdvcError, ShapeError
from pdvc.geometry import VolumeGeometry
from pdvc.recon import refined_grid, spline_upsample


@pytest.mark.parametrize("factor", [2, 3])
def test_equals_scipy_zoom_with_grid_mode(factor):
    """The same interpolant as scipy's zoom of order 3 over the box (grid_mode), mirror boundary."""
    v = np.random.default_rng(0).random((9, 11, 13)).astype(np.float32)
    ref = ndimage.zoom(v.astype(np.float64), factor, order=3, grid_mode=True, mode="mirror")
    out = spline_upsample(v, factor)
    assert out.shape == ref.shape and out.dtype == np.float32
    np.testing.assert_allclose(out, ref, atol=2e-6)


def test_interpolates_at_the_coarse_centres():
    """With factor 3 the middle fine voxel of each coarse voxel sits on its centre: same value."""
    v = np.random.default_rng(1).random((6, 7, 8)).astype(np.float32)
    out = spline_upsample(v, 3)
    np.testing.assert_allclose(out[1::3, 1::3, 1::3], v, atol=2e-6)


def test_reproduces_a_cubic_in_the_interior():
    """B-spline interpolation of degree 3 is exact on cubic polynomials (away from the boundary)."""
    vg = VolumeGeometry((30, 32, 34), voxel_size=1.0)
    fine = refined_grid(vg, 2)

    def f(z, y, x):
        return 0.01 * x**3 - 0.02 * x * y * z + 0.3 * z**2 - y + 2.0

    coarse = f(*np.meshgrid(*vg.coordinates(), indexing="ij")).astype(np.float32)
    exact = f(*np.meshgrid(*fine.coordinates(), indexing="ij"))
    out = spline_upsample(coarse, 2)
    inner = (slice(24, -24),) * 3  # the mirror boundary's error decays by 0.27 per coarse voxel
    np.testing.assert_allclose(out[inner], exact[inner], atol=1e-3)


def test_refined_grid_is_the_inverse_of_binned():
    vg = VolumeGeometry((10, 12, 14), voxel_size=(0.5, 1.0, 2.0), offset=(1.0, -2.0, 3.0))
    fine = refined_grid(vg, 2)
    assert fine.shape == (20, 24, 28) and fine.binned(2) == vg
    np.testing.assert_allclose(fine.extent_xyz, vg.extent_xyz)


def test_input_kept_and_factor_one_is_a_copy():
    v = np.random.default_rng(2).random((4, 5, 6))
    keep = v.copy()
    out = spline_upsample(v, 1)
    spline_upsample(v, 2)
    np.testing.assert_array_equal(v, keep)
    np.testing.assert_allclose(out, v, rtol=1e-6)
    assert out.dtype == np.float32 and out is not v


@pytest.mark.parametrize("factor", [0, -1, 1.5, True])
def test_bad_factor_is_named(factor):
    with pytest.raises(PdvcError, match="factor"):
        spline_upsample(np.zeros((3, 3, 3)), factor)


def test_bad_shape_is_named():
    with pytest.raises(ShapeError, match="volume"):
        spline_upsample(np.zeros((3, 3)), 2)
