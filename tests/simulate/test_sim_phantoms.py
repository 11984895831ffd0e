"""Ellipsoid phantoms, builders and voxelisation (pdvc.simulate.phantoms)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from scipy.spatial.transform import Rotation

from pdvc.errors import GeometryError, InputTypeError, PdvcError, ShapeError
from pdvc.geometry import VolumeGeometry, compose_poses
from pdvc.simulate import EllipsoidPhantom, SimulationError, cast_iron_phantom, shepp_logan_3d, voxelize


def _surface_points(ph, n_per=400, seed=0):
    """Points on every ellipsoid's surface, (N, n_per, 3)."""
    rng = np.random.default_rng(seed)
    s = rng.normal(size=(n_per, 3))
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    R = Rotation.from_rotvec(np.array(ph.rotvec)).as_matrix()
    return ph.center[:, None, :] + np.einsum("nij,npj->npi", R, s[None] * ph.semi_axes[:, None, :])


# -- the dataclass ---------------------------------------------------------------


def test_single_ellipsoid_and_read_only_copies():
    c = np.array([1.0, 2.0, 3.0])
    ph = EllipsoidPhantom(0.5, c, (1, 2, 3))
    c[0] = 99.0  # the caller's array is copied
    assert ph.n_ellipsoids == len(ph) == 1
    assert_array_equal(ph.center, [[1, 2, 3]])
    assert_array_equal(ph.rotvec, np.zeros((1, 3)))
    with pytest.raises(ValueError):
        ph.density[0] = 1.0
    assert_allclose(ph.volumes(), [4 / 3 * np.pi * 6])
    assert_allclose(ph.integral(), 0.5 * 4 / 3 * np.pi * 6)


@pytest.mark.parametrize(
    "kwargs, error, words",
    [
        (dict(density=[1, 2], center=np.zeros((3, 3)), semi_axes=np.ones((2, 3))), ShapeError, "center"),
        (dict(density=[1], center=[0, 0, 0], semi_axes=[1, -1, 1]), GeometryError, "semi_axes"),
        (dict(density=[np.nan], center=[0, 0, 0], semi_axes=[1, 1, 1]), GeometryError, "density"),
        (dict(density=[1], center=[0, 0], semi_axes=[1, 1, 1]), ShapeError, "center"),
        (dict(density=[1], center=[0, 0, 0], semi_axes=[1, 1, 1], rotvec=np.zeros((2, 3))), ShapeError, "rotvec"),
        (dict(density="dense", center=[0, 0, 0], semi_axes=[1, 1, 1]), InputTypeError, "density"),
    ],
)
def test_validation_names_the_parameter(kwargs, error, words):
    with pytest.raises(error, match=words):
        EllipsoidPhantom(**kwargs)


def test_moved_is_the_rigid_map_of_the_attenuation(rng):
    """moved(R, t) puts at R x + t what was at x (pose convention)."""
    ph = cast_iron_phantom(1.0, 1.5, n_nodules=30, n_inclusions=2, seed=4)
    rv, t = rng.normal(scale=0.5, size=3), rng.normal(scale=0.3, size=3)
    moved = ph.moved(rv, t)
    x = rng.uniform(-1.2, 1.2, (20000, 3))
    y = Rotation.from_rotvec(rv).apply(x) + t
    assert_allclose(moved.density_at(y), ph.density_at(x), atol=1e-12)
    # moving twice is moving by the composed pose
    rv2, t2 = rng.normal(scale=0.5, size=3), rng.normal(scale=0.3, size=3)
    rvc, tc = compose_poses(rv2, t2, rv, t)
    twice, once = ph.moved(rv, t).moved(rv2, t2), ph.moved(rvc, tc)
    assert_allclose(twice.center, once.center, atol=1e-12)
    assert_allclose(twice.unit_maps(), once.unit_maps(), atol=1e-12)
    assert_array_equal(ph.moved().center, ph.center)


def test_scaled_concatenate_and_select():
    ph = shepp_logan_3d(2.0)
    big = ph.scaled(3.0)
    assert_allclose(big.volumes(), 27 * ph.volumes())
    assert_allclose(big.center, 3 * ph.center)
    assert_array_equal(big.density, ph.density)
    assert_allclose(ph.scaled(3.0, preserve_line_integrals=True).density, ph.density / 3)
    both = ph + big
    assert both.n_ellipsoids == 20
    assert_array_equal(both[10:].semi_axes, big.semi_axes)
    assert_array_equal(EllipsoidPhantom.concatenate(ph).density, ph.density)
    assert both[3].n_ellipsoids == 1
    assert_allclose(ph.with_density(2.0).density, np.full(10, 2.0))
    with pytest.raises(InputTypeError, match=r"phantoms\[1\]"):
        EllipsoidPhantom.concatenate(ph, "not a phantom")
    with pytest.raises(GeometryError, match="factor"):
        ph.scaled(-1.0)


# -- builders ------------------------------------------------------------------------


def test_shepp_logan_scale_and_values():
    r, c = 10.0, np.array([1.0, -2.0, 0.5])
    ph = shepp_logan_3d(r, c)
    assert ph.n_ellipsoids == 10
    assert ph.semi_axes[0].max() == pytest.approx(r)
    assert_allclose(ph.center[0], c)
    rho = 1.0 / r  # default density scale
    assert_allclose(ph.density[:2], [rho, -0.8 * rho])
    # at the centre: skull + brain = 0.2; inside the small ball 0.046 at (0, 0.1, -0.25): + 0.2
    s = r / 0.92
    assert ph.density_at(c) == pytest.approx(0.2 * rho)
    assert ph.density_at(c + s * np.array([0.0, 0.1, -0.25])) == pytest.approx((0.2 + 0.2 + 0.2) * rho)
    # every inner ellipsoid lies inside the brain ellipsoid
    pts = _surface_points(ph[2:]).reshape(-1, 3)
    q = (pts - ph.center[1]) / ph.semi_axes[1]
    assert np.all(np.sum(q * q, axis=1) < 1)
    # explicit density scale
    assert shepp_logan_3d(1.0, density=3.0).density[0] == 3.0
    with pytest.raises(GeometryError, match="radius"):
        shepp_logan_3d(0.0)


def test_cast_iron_is_deterministic_inside_and_non_overlapping():
    r, h = 2.0, 5.0
    ph = cast_iron_phantom(r, h, n_nodules=120, n_inclusions=5, seed=7)
    again = cast_iron_phantom(r, h, n_nodules=120, n_inclusions=5, seed=7)
    other = cast_iron_phantom(r, h, n_nodules=120, n_inclusions=5, seed=8)
    assert ph.n_ellipsoids == 126
    for name in ("density", "center", "semi_axes", "rotvec"):
        assert_array_equal(getattr(ph, name), getattr(again, name))
    assert not np.array_equal(ph.center, other.center)
    rho = 1.0 / r
    assert_allclose(ph.semi_axes[0], [r, r, h / 2])
    assert_allclose(ph.density[0], rho)
    inc, nod = ph[1:6], ph[6:]
    assert np.all(inc.density > 0) and np.all(nod.density < 0)
    assert_allclose(nod.density, -0.9 * rho)
    big = nod.semi_axes.max(axis=1)
    assert np.all((big >= 0.02 * r) & (big <= 0.06 * r))
    # everything inside the rod: points on every particle's surface
    pts = _surface_points(ph[1:], n_per=300).reshape(-1, 3)
    q = pts / ph.semi_axes[0]
    assert np.all(np.sum(q * q, axis=1) < 1)
    # bounding spheres apart
    cen, rad = ph.center[1:], ph.bounding_radius[1:]
    dist = np.linalg.norm(cen[:, None] - cen[None], axis=2)
    np.fill_diagonal(dist, np.inf)
    assert np.all(dist >= rad[:, None] + rad[None, :])
    # attenuation: matrix, nodule, inclusion
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (20000, 3)) * ph.semi_axes[0]
    x = x[np.sum((x / ph.semi_axes[0]) ** 2, axis=1) < 1]
    values = ph.density_at(x)
    levels = np.array([rho, 0.1 * rho, 2.0 * rho])  # matrix, in a nodule, in an inclusion
    assert np.all(np.min(np.abs(values[:, None] - levels[None, :]), axis=1) < 1e-12)
    assert np.mean(values == rho) > 0.9
    assert ph.density_at(nod.center[:5]) == pytest.approx(np.full(5, 0.1 * rho))
    assert ph.density_at(inc.center[:2]) == pytest.approx(np.full(2, 2.0 * rho))


def test_cast_iron_bad_inputs():
    with pytest.raises(GeometryError, match="height"):
        cast_iron_phantom(1.0, -2.0)
    with pytest.raises(GeometryError, match="nodule_size"):
        cast_iron_phantom(1.0, 2.0, nodule_size=(0.1, 0.05))
    with pytest.raises(PdvcError, match="n_nodules"):
        cast_iron_phantom(1.0, 2.0, n_nodules=-1)
    with pytest.raises(GeometryError, match="does not fit"):
        cast_iron_phantom(1.0, 0.8, nodule_size=(0.45, 0.49))
    assert issubclass(SimulationError, ValueError)


# -- voxelisation ----------------------------------------------------------------------


def test_voxelize_integral_and_values():
    vg = VolumeGeometry((40, 44, 48), voxel_size=(0.06, 0.055, 0.05), offset=(0.1, -0.05, 0.02))
    ph = shepp_logan_3d(1.0, (0.1, -0.05, 0.0), density=1.0)
    f = voxelize(ph, vg, supersampling=3)
    assert f.dtype == np.float32 and f.shape == vg.shape
    voxel_volume = np.prod(vg.voxel_size)
    # Counting sub-samples inside a smooth body errs by a fraction of the
    # sub-cells cut by the surfaces, errors that largely cancel (observed
    # ~1e-4 here); 3e-3 is still 10x below the ~5 % that one missing
    # boundary layer of sub-cells would cost.
    assert f.sum(dtype=np.float64) * voxel_volume == pytest.approx(ph.integral(), rel=3e-3)
    # supersampling 1 is point sampling at the voxel centres
    f1 = voxelize(ph, vg, supersampling=1)
    zz, yy, xx = np.meshgrid(*vg.coordinates(), indexing="ij")
    centres = np.stack([xx, yy, zz], axis=-1)
    assert_allclose(f1, ph.density_at(centres).astype(np.float32), atol=1e-7)


def test_voxelize_ball_volume_and_orientation():
    vg = VolumeGeometry((30, 30, 30), voxel_size=1.0)
    ball = EllipsoidPhantom(2.0, (4.3, -2.2, 1.1), (8.0, 8.0, 8.0))
    f = voxelize(ball, vg, supersampling=4)
    assert f.sum(dtype=np.float64) == pytest.approx(ball.integral(), rel=3e-3)
    # interior voxels are exactly the density, far voxels exactly 0
    iz, iy, ix = np.round(vg.world_to_index([4.3, -2.2, 1.1])).astype(int)
    assert f[iz, iy, ix] == 2.0
    assert f[0, 0, 0] == 0.0
    # the ball sits at +x: higher ix (f[z, y, x] convention)
    assert f[:, :, 20:].sum() > f[:, :, :10].sum()
    # partial-volume voxels take fractional values
    assert np.any((f > 0) & (f < 2.0))


def test_voxelize_bad_inputs():
    vg = VolumeGeometry((4, 4, 4))
    ball = EllipsoidPhantom(1.0, (0, 0, 0), (1, 1, 1))
    with pytest.raises(InputTypeError, match="vol_geom"):
        voxelize(ball, (4, 4, 4))
    with pytest.raises(InputTypeError, match="phantom"):
        voxelize(None, vg)
    with pytest.raises(PdvcError, match="supersampling"):
        voxelize(ball, vg, supersampling=0)
