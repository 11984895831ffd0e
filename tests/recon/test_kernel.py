"""The back-projection kernel and projection matrices against slow, obviously-correct references."""

from __future__ import annotations

import numpy as np
import pytest

from pdvc.geometry import VolumeGeometry, circular_cone, parallel
from pdvc.recon._fbp import _z_invariant, projection_matrices
from pdvc.recon._kernels import backproject_block


def _bilinear_zero_outside(img, row, col):
    """Bilinear sample of ``img`` at (row, col); 0 outside the detector's area.

    The detector covers -1/2 <= row <= nr - 1/2 (pixels are squares around
    their centres): within the outer half of an edge pixel its value is used.
    """
    nr, nc = img.shape
    out = np.zeros(row.shape)
    ok = (row >= -0.5) & (row <= nr - 0.5) & (col >= -0.5) & (col <= nc - 0.5)
    r, c = np.clip(row[ok], 0, nr - 1), np.clip(col[ok], 0, nc - 1)
    i = np.minimum(np.floor(r).astype(int), nr - 2)
    j = np.minimum(np.floor(c).astype(int), nc - 2)
    fr, fc = r - i, c - j
    out[ok] = (
        (1 - fr) * (1 - fc) * img[i, j]
        + (1 - fr) * fc * img[i, j + 1]
        + fr * (1 - fc) * img[i + 1, j]
        + fr * fc * img[i + 1, j + 1]
    )
    return out


def _reference_backprojection(q, vol_geom, geom, center):
    """sum_k (SOD_k / depth_k)^2 bilinear(q_k, project(x)) with geometry's own point projection."""
    nz, ny, nx = vol_geom.shape
    iz, iy, ix = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    pts = vol_geom.voxel_center(iz, iy, ix).reshape(-1, 3)
    rc = geom.project_points(pts)  # independent implementation (plane intersection)
    out = np.zeros(pts.shape[0])
    for k in range(geom.n_views):
        if geom.kind == "cone":
            n = geom.det_normal[k]
            n = n if (geom.det_center[k] - geom.src[k]) @ n > 0 else -n
            wgt = (((center - geom.src[k]) @ n) / ((pts - geom.src[k]) @ n)) ** 2
        else:
            wgt = 1.0
        out += wgt * _bilinear_zero_outside(q[k], rc[k, :, 0], rc[k, :, 1])
    return out.reshape(nz, ny, nx)


def _geometries():
    rng = np.random.default_rng(7)
    angles = np.linspace(0, 2 * np.pi, 5, endpoint=False) + 0.1
    cone = circular_cone(angles, sod=40.0, odd=25.0, det_shape=(17, 23), pixel=(1.3, 1.1), det_offset=(0.7, -1.9))
    posed = cone.apply_poses(rng.normal(0, 0.05, (5, 3)), rng.normal(0, 0.8, (5, 3)))
    par = parallel(angles, det_shape=(17, 23), pixel=(1.2, 0.9), det_offset=(0.4, 1.3))
    par_posed = par.apply_poses(rng.normal(0, 0.05, (5, 3)), rng.normal(0, 0.8, (5, 3)))
    return {"cone": cone, "cone-posed": posed, "parallel": par, "parallel-posed": par_posed}


@pytest.mark.parametrize("name", ["cone", "cone-posed", "parallel", "parallel-posed"])
def test_kernel_matches_reference(name):
    # Non-cubic grid, anisotropic voxels and an offset catch any axis mix-up.
    geom = _geometries()[name]
    vg = VolumeGeometry((9, 11, 13), (1.1, 0.9, 1.0), offset=(0.5, -0.3, 0.2))
    rng = np.random.default_rng(3)
    q = rng.random((geom.n_views,) + geom.det_shape).astype(np.float32)
    center = np.array([0.2, -0.1, 0.3])
    P, _, _ = projection_matrices(vg, geom, center=center)
    zinv = _z_invariant(P, vg)
    # the fast path is taken exactly for the untilted scans about z
    assert zinv.all() == (not name.endswith("posed"))
    P[zinv, 0, 2] = 0.0
    P[zinv, 2, 2] = 0.0
    vol = np.zeros(vg.shape, np.float32)
    backproject_block(vol, np.ascontiguousarray(q.transpose(0, 2, 1)), P, zinv)
    ref = _reference_backprojection(q, vg, geom, center)
    assert np.count_nonzero(ref) > 0.5 * ref.size  # most voxels see the detector
    # float32 interpolation of values in [0, 1]: agreement to ~1e-6 relative;
    # voxels exactly on the detector edge may differ by rounding: compare away from them
    np.testing.assert_allclose(vol, ref, rtol=2e-5, atol=2e-5 * np.abs(ref).max())


def test_kernel_accumulates_into_volume():
    geom = _geometries()["cone"]
    vg = VolumeGeometry((6, 7, 8), 1.0)
    q = np.ones((geom.n_views,) + geom.det_shape[::-1], np.float32)
    P, _, _ = projection_matrices(vg, geom)
    zinv = _z_invariant(P, vg)
    vol = np.full(vg.shape, 2.0, np.float32)
    once = np.zeros(vg.shape, np.float32)
    backproject_block(once, q, P, zinv)
    backproject_block(vol, q, P, zinv)
    np.testing.assert_allclose(vol, once + 2.0, rtol=1e-6)


@pytest.mark.parametrize("name", ["cone", "cone-posed", "parallel", "parallel-posed"])
def test_projection_matrices_match_geometry(name):
    geom = _geometries()[name]
    vg = VolumeGeometry((5, 6, 7), (1.2, 0.8, 1.0), offset=(1.0, 2.0, -0.5))
    P, sod, sdd = projection_matrices(vg, geom, center=np.zeros(3))
    rng = np.random.default_rng(1)
    idx = rng.uniform(0, 5, (50, 3))  # (ix, iy, iz)
    pts = vg.voxel_center(idx[:, 2], idx[:, 1], idx[:, 0])
    w = np.einsum("vij,pj->vpi", P, np.concatenate([idx, np.ones((50, 1))], axis=1))
    rc = geom.project_points(pts)
    np.testing.assert_allclose(w[..., 1] / w[..., 2], rc[..., 0], atol=1e-9)
    np.testing.assert_allclose(w[..., 0] / w[..., 2], rc[..., 1], atol=1e-9)
    if geom.kind == "cone":
        n = geom.det_normal * np.sign(np.einsum("ij,ij->i", geom.det_center - geom.src, geom.det_normal))[:, None]
        depth = np.einsum("vpk,vk->vp", pts[None] - geom.src[:, None], n)
        np.testing.assert_allclose(w[..., 2], depth / sod[:, None], rtol=1e-12)
        np.testing.assert_allclose(sdd, np.einsum("ij,ij->i", geom.det_center - geom.src, n), rtol=1e-12)
    else:
        np.testing.assert_allclose(w[..., 2], 1.0)


def test_thin_detector_keeps_voxels_on_the_edge_rows():
    """Two rows, a two-voxel slab: a detector shifted by 1e-4 px must not drop a layer."""
    from pdvc import forward
    from pdvc.recon import fbp

    ang = np.linspace(0, np.pi, 60, endpoint=False)
    g = parallel(ang, det_shape=(2, 48), pixel=1.0, det_offset=(1e-4, 0.0))
    vg = VolumeGeometry((2, 40, 40))
    f = np.zeros(vg.shape, np.float32)
    f[:, 15:25, 12:20] = 1.0
    r = fbp(forward(f, vg, g), vg, g)
    assert abs(float(r[:, 15:25, 12:20].mean()) - 1.0) < 0.1  # was 0.5 off when the edge rows dropped


def test_detector_above_32_bit_pixel_indices_is_refused():
    """The kernel's pixel indices are 32-bit: a detector of 2**32 pixels gets a clear error, not a wrap-around."""
    from pdvc.errors import GeometryError
    from pdvc.recon import fdk

    g = circular_cone(np.array([0.0, 1.0]), sod=40.0, odd=25.0, det_shape=(2**16, 2**16), pixel=1.0)
    with pytest.raises(GeometryError, match=r"det_shape.*2\*\*32"):
        fdk(np.zeros((2, 2, 2), np.float32), VolumeGeometry((4, 4, 4)), g)
