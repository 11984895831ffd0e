"""Projector known answers: analytic line integrals, exact adjoint,
finite-difference Jacobian, exact invariances, per-view reduction."""

import numpy as np
import pytest

import pdvc
from pdvc.projectors import backproject, bin_projections, forward, jacobian, reduce_views

from ..conftest import gaussian_blob_line_integrals, gaussian_blob_volume, random_geometry

KINDS = ["cone", "parallel"]


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_forward_matches_analytic_gaussian_line_integrals(kind, seed):
    """Bound from interpolation theory: bilinear interpolation of a Gaussian
    of width σ on a grid of pitch h errs by about h²/(8σ²) of the peak per
    in-plane axis (≈ 2.3 % here for h = 1.2, σ = 4); measured 1.2-1.4 %."""
    rng = np.random.default_rng(seed)
    vg = pdvc.VolumeGeometry((40, 44, 48), voxel_size=(1.0, 0.8, 1.2), offset=(1.0, -2.0, 0.5))
    mean, sigma = np.array([3.0, -1.0, 2.0]), 4.0
    geom = random_geometry(kind, rng, n_views=4, det_shape=(48, 64))
    p = forward(gaussian_blob_volume(vg, mean, sigma), vg, geom)
    a = gaussian_blob_line_integrals(geom, mean, sigma)
    assert np.abs(p - a).max() <= 0.023 * a.max()


@pytest.mark.parametrize("kind", KINDS)
def test_forward_error_is_second_order_in_voxel_size(kind):
    """Halving the voxel pitch for the same analytic blob divides the error by ~4."""
    rng = np.random.default_rng(7)
    geom = random_geometry(kind, rng, n_views=3, det_shape=(40, 40), tilt=0.1, shift=1.0)
    mean, sigma = np.array([1.0, 2.0, -1.5]), 2.5
    a = gaussian_blob_line_integrals(geom, mean, sigma)
    errs = []
    for n, h in [(24, 2.0), (48, 1.0), (96, 0.5)]:
        vg = pdvc.VolumeGeometry((n, n, n), voxel_size=h)
        errs.append(np.sqrt(np.mean((forward(gaussian_blob_volume(vg, mean, sigma), vg, geom) - a) ** 2)))
    assert errs[0] / errs[1] > 3.0 and errs[1] / errs[2] > 3.0, errs


def test_forward_of_a_uniform_ball_matches_chord_lengths():
    """Partial-volume ball (8³ supersampling) against 2 √(R² - d²).

    Sampling a sharp surface on grid planes aliases: each of the two surface
    crossings of a ray can be off by a fraction of a voxel of length depending
    on its phase (measured ≤ 0.27); near the rim the voxel surface also acts
    as a blur, shortening chords by ½ b² |p''(d)| (b² ≈ 1/4 voxel²)."""
    n, R = 48, 17.0
    vg = pdvc.VolumeGeometry((n, n, n))
    sub = (np.arange(8) + 0.5) / 8 - 0.5
    zc, yc, xc = vg.coordinates()
    ball = np.zeros(vg.shape)
    for dz in sub:
        for dy in sub:
            for dx in sub:
                ball += ((xc[None, None, :] + dx) ** 2 + (yc[None, :, None] + dy) ** 2 + (zc[:, None, None] + dz) ** 2) <= R**2
    ball /= 8**3
    geom = pdvc.circular_cone([0.0, 0.9, 2.2], sod=150, odd=100, det_shape=(60, 60), pixel=1.0)
    p = forward(ball, vg, geom)
    for k in range(geom.n_views):
        pc = geom.pixel_centers(k)
        d = pc - geom.src[k]
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        w = -geom.src[k]
        dist = np.sqrt(np.maximum(np.sum(w * w) - (d @ w) ** 2, 0))
        chord = 2 * np.sqrt(np.maximum(R**2 - dist**2, 0))
        inside = dist < R - 4
        np.testing.assert_allclose(p[k][inside], chord[inside], atol=0.35)
        assert np.abs(p[k][inside] - chord[inside]).mean() < 0.1  # aliasing averages out (measured 0.066)
        rim = (dist >= R - 4) & (dist < R - 1.5)
        np.testing.assert_allclose(p[k][rim], chord[rim], atol=0.6)
        assert np.all(p[k][dist > R + 2.5] == 0)  # partial-volume rim + 1 voxel of interpolation support


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("seed", [0, 1])
def test_adjoint_dot_product(kind, seed):
    """<A x, y> = <x, Aᵀ y>: the same weights, gathered and scattered. Float32
    storage of A x and Aᵀ y bounds the agreement at ~1e-6."""
    rng = np.random.default_rng(seed)
    vg = pdvc.VolumeGeometry((23, 26, 29), voxel_size=(1.1, 0.9, 1.0), offset=(0.5, -1.0, 2.0))
    geom = random_geometry(kind, rng, n_views=6, det_shape=(30, 34), tilt=0.6, shift=3.0)
    x = rng.standard_normal(vg.shape).astype(np.float32)
    y = rng.standard_normal((geom.n_views,) + geom.det_shape).astype(np.float32)
    lhs = np.vdot(forward(x, vg, geom).astype(np.float64), y.astype(np.float64))
    rhs = np.vdot(x.astype(np.float64), backproject(y, vg, geom).astype(np.float64))
    assert abs(lhs - rhs) <= 1e-5 * np.sqrt(np.vdot(x, x) * np.vdot(y, y))


@pytest.mark.parametrize("kind", KINDS)
def test_adjoint_dot_product_long_rays(kind):
    """Rays with more interior samples than several scatter chunks (the
    adjoint computes a chunk's targets, then adds them): the chunk
    boundaries lose or repeat no sample."""
    from pdvc.projectors._kernels import SCATTER_CHUNK

    rng = np.random.default_rng(7)
    n = 3 * SCATTER_CHUNK + 5
    vg = pdvc.VolumeGeometry((8, n, n + 3))
    geom = random_geometry(kind, rng, n_views=4, det_shape=(8, n + 20), tilt=0.01, shift=0.5)
    x = rng.standard_normal(vg.shape).astype(np.float32)
    y = rng.standard_normal((geom.n_views,) + geom.det_shape).astype(np.float32)
    lhs = np.vdot(forward(x, vg, geom).astype(np.float64), y.astype(np.float64))
    rhs = np.vdot(x.astype(np.float64), backproject(y, vg, geom).astype(np.float64))
    assert abs(lhs - rhs) <= 1e-5 * np.sqrt(np.vdot(x, x) * np.vdot(y, y))
    # a ray through the middle of every view crosses all the planes of its axis
    p = forward(np.ones(vg.shape, np.float32), vg, geom)
    assert p[:, 4, (n + 20) // 2].min() > 2.5 * SCATTER_CHUNK


def test_adjoint_dot_product_z_dominant_rays():
    """Rays mostly along z (a laminography-like tilt) take the other branch of the slab adjoint."""
    rng = np.random.default_rng(3)
    vg = pdvc.VolumeGeometry((20, 22, 24))
    th = np.linspace(0, 3, 5)
    ray = np.stack([0.4 * np.sin(th), -0.4 * np.cos(th), np.ones_like(th)], 1)
    u = np.stack([np.cos(th), np.sin(th), 0 * th], 1)
    v = np.cross(ray / np.linalg.norm(ray, axis=1, keepdims=True), u)
    g = pdvc.VectorGeometry(np.hstack([ray, np.zeros((5, 3)), u, v]), (26, 28), "parallel")
    assert np.all(np.abs(g.ray[:, 2]) > np.abs(g.ray[:, :2]).max(axis=1))
    x = rng.standard_normal(vg.shape).astype(np.float32)
    y = rng.standard_normal((5, 26, 28)).astype(np.float32)
    lhs = np.vdot(forward(x, vg, g).astype(np.float64), y)
    rhs = np.vdot(x.astype(np.float64), backproject(y, vg, g))
    assert abs(lhs - rhs) <= 1e-5 * np.sqrt(np.vdot(x, x) * np.vdot(y, y))


@pytest.mark.parametrize("kind", KINDS)
def test_adjoint_independent_of_slabs(kind, monkeypatch):
    """Any cut of the volume into slabs (one, thin ones of 2 rows, an odd
    count, uneven ones) gives the same back-projection: every sample belongs
    to exactly one slab, including those on a slab boundary (a cut at the
    height of a ray that runs along it)."""
    from pdvc.projectors import _numba

    rng = np.random.default_rng(5)
    vg = pdvc.VolumeGeometry((24, 21, 25), voxel_size=(1.0, 1.1, 0.9))
    geom = random_geometry(kind, rng, n_views=5, det_shape=(28, 30), tilt=0.3, shift=2.0)
    y = rng.standard_normal((geom.n_views,) + geom.det_shape).astype(np.float32)
    x = rng.standard_normal(vg.shape).astype(np.float32)
    lhs = np.vdot(forward(x, vg, geom).astype(np.float64), y.astype(np.float64))
    results = []
    for edges in ([0, 24], [0, 12, 24], [0, 7, 15, 24], list(range(0, 25, 2)), [0, 2, 4, 13, 21, 24]):
        monkeypatch.setattr(_numba, "_slab_edges", lambda shape, e=edges: np.asarray(e, np.int64))
        b = backproject(y, vg, geom)
        rhs = np.vdot(x.astype(np.float64), b.astype(np.float64))
        assert abs(lhs - rhs) <= 1e-5 * np.sqrt(np.vdot(x, x) * np.vdot(y, y))
        results.append(b)
    for b in results[1:]:
        np.testing.assert_allclose(b, results[0], rtol=0, atol=1e-5 * np.abs(results[0]).max())


def test_adjoint_slab_boundary_on_a_ray(monkeypatch):
    """Rays that run exactly along a slab boundary (horizontal rays of a
    parallel beam at integer heights) are scattered once, not twice."""
    from pdvc.projectors import _numba

    vg = pdvc.VolumeGeometry((16, 12, 12))
    geom = pdvc.parallel(np.linspace(0, np.pi, 7, endpoint=False), det_shape=(16, 14), pixel=1.0)
    y = np.ones((geom.n_views,) + geom.det_shape, np.float32)
    x = np.random.default_rng(0).random(vg.shape).astype(np.float32)
    lhs = np.vdot(forward(x, vg, geom).astype(np.float64), y.astype(np.float64))
    monkeypatch.setattr(_numba, "_slab_edges", lambda shape: np.asarray([0, 16], np.int64))
    one = backproject(y, vg, geom)
    monkeypatch.setattr(_numba, "_slab_edges", lambda shape: np.arange(0, 17, 2, dtype=np.int64))
    many = backproject(y, vg, geom)
    for b in (one, many):
        assert abs(lhs - np.vdot(x.astype(np.float64), b.astype(np.float64))) <= 1e-5 * abs(lhs)
    np.testing.assert_allclose(many, one, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("kind", KINDS)
def test_jacobian_matches_finite_differences(kind):
    """Central differences of the forward projector under apply_poses.

    The bilinear interpolant has kinks, so the difference error is O(ε), not
    O(ε²), and float32 projections add ulp(P)/2ε: the best attainable
    agreement is ~0.1 % for translations (ε = 1e-3 voxel) and ~0.5-1 % for
    rotations (ε = 1e-3 rad moves the outer samples by ~0.02 voxel). Bounds:
    0.5 % and 1.5 %; a wrong sensitivity is off by ~100 %. The error must
    also shrink from ε = 1e-2 to 1e-3. Rays whose two largest direction
    components are within 1 % are left out: a rotation can swap their
    dominant axis, where plane sampling (any Joseph projector) jumps by
    O(h² f'')."""
    rng = np.random.default_rng(11)
    vg = pdvc.VolumeGeometry((32, 32, 32), voxel_size=1.0)
    f = gaussian_blob_volume(vg, [2.0, -3.0, 1.0], 4.0) + gaussian_blob_volume(vg, [-5.0, 4.0, -4.0], 2.5, 0.7)
    geom = random_geometry(kind, rng, n_views=3, det_shape=(36, 40), tilt=0.1, shift=1.0)
    center = np.array([1.0, -0.5, 2.0])
    proj, sens = jacobian(f, vg, geom, center=center)
    np.testing.assert_allclose(proj, forward(f, vg, geom), rtol=1e-5, atol=1e-6)  # same model, summed in another order
    keep = np.empty(proj.shape, bool)
    for k in range(geom.n_views):
        pc = geom.pixel_centers(k)
        d = np.abs(pc - geom.src[k] if kind == "cone" else np.broadcast_to(geom.ray[k], pc.shape))
        d = np.sort(d / np.asarray(vg.spacing_xyz), axis=-1)
        keep[k] = d[..., 2] - d[..., 1] > 0.01 * d[..., 2]
    assert keep.mean() > 0.9
    sens = sens * keep[:, None]
    for j in range(6):
        errs = []
        for eps in (1e-2, 1e-3):
            step = np.zeros(6)
            step[j] = eps
            plus = forward(f, vg, geom.apply_poses(step[3:], step[:3], center=center)).astype(np.float64)
            minus = forward(f, vg, geom.apply_poses(-step[3:], -step[:3], center=center))
            fd = (plus - minus) / (2 * eps) * keep
            errs.append(np.linalg.norm(fd - sens[:, j]) / np.linalg.norm(sens[:, j]))
        assert errs[1] < (5e-3 if j < 3 else 1.5e-2), (j, errs)
        assert errs[1] < errs[0] or errs[0] < 1e-3, (j, errs)


def test_integer_translation_of_volume_equals_translated_geometry():
    """Joseph sampling is exactly shift-covariant for whole-voxel shifts."""
    rng = np.random.default_rng(5)
    vg = pdvc.VolumeGeometry((24, 26, 28))
    f = np.zeros(vg.shape, np.float32)
    f[6:18, 7:19, 8:20] = rng.random((12, 12, 12))
    shift = (3, -2, 1)  # voxels along x, y, z
    moved = np.roll(f, (shift[2], shift[1], shift[0]), axis=(0, 1, 2))
    for geom in (random_geometry("cone", rng, 4, (30, 30), tilt=0.3), random_geometry("parallel", rng, 4, (30, 30), tilt=0.3)):
        a = forward(moved, vg, geom)
        b = forward(f, vg, geom.apply_poses(np.zeros(3), np.array(shift, float)))
        np.testing.assert_allclose(a, b, atol=2e-5 * np.abs(a).max())


def test_quarter_turn_of_volume_equals_rotated_geometry():
    """np.rot90 of the volume about z is an exact rigid motion of the grid."""
    rng = np.random.default_rng(6)
    vg = pdvc.VolumeGeometry((20, 24, 24))
    f = rng.random(vg.shape).astype(np.float32)
    # rot90 in (y, x) plane: new[z, y, x] = f[z, x, n-1-y] -> x' = -y ... a +90° turn about z
    turned = np.ascontiguousarray(np.rot90(f, k=1, axes=(1, 2)))
    geom = pdvc.circular_cone([0.37, 1.9], sod=100, odd=60, det_shape=(28, 30), pixel=1.1)
    for rv in ([0, 0, np.pi / 2], [0, 0, -np.pi / 2]):
        b = forward(f, vg, geom.apply_poses(rv, np.zeros(3)))
        a = forward(turned, vg, geom)
        if np.allclose(a, b, atol=1e-4 * a.max()):
            break
    else:
        pytest.fail("no quarter-turn sign convention matched")


@pytest.mark.parametrize("kind", KINDS)
def test_reduce_views_equals_image_reduction(kind):
    rng = np.random.default_rng(8)
    vg = pdvc.VolumeGeometry((24, 24, 24))
    f = gaussian_blob_volume(vg, [1.0, 0.0, -1.0], 3.0)
    geom = random_geometry(kind, rng, n_views=4, det_shape=(28, 30), tilt=0.1, shift=1.0)
    measured = forward(f, vg, geom.apply_poses([0.01, -0.02, 0.03], [0.3, -0.2, 0.1])) + rng.normal(0, 0.01, (4, 28, 30)).astype(np.float32)
    weights = (rng.random((4, 28, 30)) > 0.3).astype(np.float32) * rng.random((4, 28, 30)).astype(np.float32)
    proj, sens = jacobian(f, vg, geom)
    red = reduce_views(f, vg, geom, measured, weights=weights)
    G = sens.reshape(4, 6, -1).astype(np.float64)
    W = weights.reshape(4, -1).astype(np.float64)
    rho = (measured - proj).reshape(4, -1).astype(np.float64)
    np.testing.assert_allclose(red.M, np.einsum("kin,kn,kjn->kij", G, W, G), rtol=1e-5, atol=1e-6 * np.abs(red.M).max())
    np.testing.assert_allclose(red.b, np.einsum("kin,kn,kn->ki", G, W, rho), rtol=1e-4, atol=1e-5 * np.abs(red.b).max())
    np.testing.assert_allclose(red.rss, np.einsum("kn,kn->k", W, rho**2), rtol=1e-4)
    np.testing.assert_allclose(red.weight_sum, W.sum(1), rtol=1e-6)
    np.testing.assert_allclose(red.meas_sum, np.einsum("kn,kn->k", W, measured.reshape(4, -1)), rtol=1e-5)
    np.testing.assert_allclose(red.resid_sum, np.einsum("kn,kn->k", W, rho), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(red.M, red.M.transpose(0, 2, 1))
    # a 2D mask is shared by all views
    mask = np.zeros((28, 30), np.float32)
    mask[5:20, 3:25] = 1
    red2 = reduce_views(f, vg, geom, measured, weights=mask)
    red3 = reduce_views(f, vg, geom, measured, weights=np.broadcast_to(mask, (4, 28, 30)))
    np.testing.assert_allclose(red2.M, red3.M)


def test_one_gauss_newton_step_recovers_a_small_translation():
    """Known injected motion, linear regime: M⁻¹ b of each view ≈ the pose."""
    rng = np.random.default_rng(9)
    vg = pdvc.VolumeGeometry((32, 32, 32))
    f = gaussian_blob_volume(vg, [3, -2, 1], 3.0) + gaussian_blob_volume(vg, [-6, 5, -4], 2.5, 0.8) + gaussian_blob_volume(vg, [4, 6, -7], 2.0, 0.6)
    geom = pdvc.circular_cone(np.linspace(0, 2 * np.pi, 4, endpoint=False), sod=120, odd=80, det_shape=(40, 40), pixel=1.2)
    rv = rng.normal(0, 0.01, (4, 3))
    t = rng.normal(0, 0.15, (4, 3))
    measured = forward(f, vg, geom.apply_poses(rv, t, center=vg.offset))
    red = reduce_views(f, vg, geom, measured)
    step = np.linalg.solve(red.M, red.b[..., None])[..., 0]
    # across the beam a translation moves the image directly: tight; along the
    # beam it is seen only through magnification (a few % of the signal): loose
    beam = geom.ray / np.linalg.norm(geom.ray, axis=1, keepdims=True)
    err = step[:, :3] - t
    along = np.einsum("ki,ki->k", err, beam)
    across = err - along[:, None] * beam
    assert np.abs(across).max() < 0.01, across
    assert np.abs(along).max() < 0.1, along
    # 5e-3 rad is 0.05 voxel at the blobs' radius (~10 voxels)
    np.testing.assert_allclose(step[:, 3:], rv, atol=5e-3)


def test_binned_geometry_projects_like_binned_projections():
    vg = pdvc.VolumeGeometry((32, 32, 32))
    f = gaussian_blob_volume(vg, [1, 2, 0], 4.0)
    geom = pdvc.circular_cone([0.3, 1.2], sod=100, odd=60, det_shape=(41, 50), pixel=0.6)
    fine = bin_projections(forward(f, vg, geom), 2)
    coarse = forward(f, vg, geom.binned(2))
    assert coarse.shape == fine.shape == (2, 20, 25)
    # the mean over a 2x2 block differs from the centre value by the curvature term (~h²/(8σ²))
    assert np.abs(coarse - fine).max() < 0.02 * fine.max()


def test_inputs_are_not_modified_and_out_is_used(rng):
    vg = pdvc.VolumeGeometry((16, 16, 16))
    geom = random_geometry("cone", rng, 2, (20, 20))
    f = rng.random(vg.shape).astype(np.float32)
    f0 = f.copy()
    out = np.empty((2, 20, 20), np.float32)
    res = forward(f, vg, geom, out=out)
    assert res is out
    np.testing.assert_array_equal(f, f0)
    y = out.copy()
    backproject(out, vg, geom)
    np.testing.assert_array_equal(out, y)


def test_bad_inputs_raise_clear_errors(rng):
    vg = pdvc.VolumeGeometry((16, 16, 16))
    geom = random_geometry("cone", rng, 2, (20, 20))
    f = np.zeros(vg.shape, np.float32)
    with pytest.raises(pdvc.ShapeError, match=r"volume must have shape \(16, 16, 16\)"):
        forward(np.zeros((16, 16)), vg, geom)
    with pytest.raises(pdvc.ShapeError, match=r"projections must have shape \(2, 20, 20\)"):
        backproject(np.zeros((3, 20, 20)), vg, geom)
    with pytest.raises(pdvc.ShapeError, match="out must be"):
        forward(f, vg, geom, out=np.empty((2, 20, 20)))
    with pytest.raises(pdvc.InputTypeError, match="geom must be a pdvc.VectorGeometry"):
        forward(f, vg, geom.vectors)
    with pytest.raises(pdvc.InputTypeError, match="vol_geom"):
        forward(f, (16, 16, 16), geom)
    with pytest.raises(pdvc.ShapeError, match="weights must have shape"):
        reduce_views(f, vg, geom, np.zeros((2, 20, 20)), weights=np.ones((5, 5)))
    with pytest.raises(pdvc.ShapeError, match="non-negative"):
        reduce_views(f, vg, geom, np.zeros((2, 20, 20)), weights=-np.ones((20, 20)))
    with pytest.raises(pdvc.ShapeError, match="finite"):
        reduce_views(f, vg, geom, np.full((2, 20, 20), np.nan))
    with pytest.raises(pdvc.ShapeError, match="center"):
        jacobian(f, vg, geom, center=(1, 2))
    with pytest.raises(pdvc.BackendError, match=r"backend must be one of \['auto', 'cpu'\]|backend must be one of"):
        forward(f, vg, geom, backend="cuda-nope")
