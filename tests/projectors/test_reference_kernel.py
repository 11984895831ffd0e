"""The benchmarks' yardstick (benchmarks/_reference.py) computes the same line
integrals as pdvc.forward: a different discretisation (trilinear ray-marching
against Joseph plane sampling), so they agree to a loose tolerance only."""

import numpy as np
import pytest

import pdvc
from pdvc.projectors import forward

from ..conftest import benchmark_module, gaussian_blob_line_integrals, gaussian_blob_volume, random_geometry


@pytest.fixture(scope="module")
def reference():
    with benchmark_module("_reference") as mod:
        yield mod


def _rel_l2(a, b):
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


@pytest.mark.parametrize("seed", [0, 1])
def test_reference_matches_pdvc_forward_on_posed_views(reference, seed):
    """Per-view vectors (tilted, shifted detectors), anisotropic voxels, off-centre grid."""
    rng = np.random.default_rng(seed)
    vg = pdvc.VolumeGeometry((30, 34, 38), voxel_size=(1.0, 0.8, 1.2), offset=(1.0, -2.0, 0.5))
    f = gaussian_blob_volume(vg, [3.0, -1.0, 2.0], 4.0) + gaussian_blob_volume(vg, [-6.0, 5.0, -3.0], 3.0, 0.6)
    geom = random_geometry("cone", rng, n_views=5, det_shape=(36, 44))
    p = forward(f, vg, geom)
    q = reference.reference_forward(f, vg, geom)
    assert q.shape == p.shape and q.dtype == np.float32
    assert _rel_l2(q, p) < 0.01  # measured 0.15 %
    # and both are close to the analytic line integrals of the (truncated) blobs
    a = gaussian_blob_line_integrals(geom, [3.0, -1.0, 2.0], 4.0) + gaussian_blob_line_integrals(geom, [-6.0, 5.0, -3.0], 3.0, 0.6)
    assert _rel_l2(q, a) < 0.03  # measured 1.0 % (as pdvc.forward)


def test_reference_matches_pdvc_forward_on_a_textured_cylinder(reference):
    """The benchmark object (random texture in a cylinder filling the grid, a
    non-empty border) on a circular orbit."""
    rng = np.random.default_rng(3)
    n = 32
    vg = pdvc.VolumeGeometry((n, n, n))
    f = rng.random(vg.shape, dtype=np.float32)
    zc, yc, xc = vg.coordinates()
    f *= (xc[None, None, :] ** 2 + yc[None, :, None] ** 2 < (0.45 * n) ** 2).astype(np.float32)
    geom = pdvc.circular_cone(np.linspace(0, 2 * np.pi, 12, endpoint=False), sod=120, odd=60, det_shape=(40, 56), pixel=1.2)
    p = forward(f, vg, geom)
    q = reference.reference_forward(f, vg, geom)
    assert _rel_l2(q, p) < 0.05  # measured 1.1 %; the volume transposed in x, y gives 11 %


def test_reference_rejects_parallel_beam(reference):
    rng = np.random.default_rng(0)
    vg = pdvc.VolumeGeometry((8, 8, 8))
    with pytest.raises(ValueError, match="cone"):
        reference.reference_forward(np.zeros(vg.shape), vg, random_geometry("parallel", rng, 2, (8, 8)))
