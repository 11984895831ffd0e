"""Vector geometry: builders against DESIGN.md formulas, poses, binning, errors."""

import numpy as np
import pytest

import pdvc
from pdvc.geometry import compose_poses, invert_poses, rotvec_to_matrix


def test_circular_cone_matches_design_formulas():
    th = np.array([0.0, 0.7, 2.0])
    g = pdvc.circular_cone(th, sod=500.0, odd=250.0, det_shape=(10, 20), pixel=(0.2, 0.1))
    s, c = np.sin(th), np.cos(th)
    np.testing.assert_allclose(g.src, np.stack([500 * s, -500 * c, 0 * s], 1))
    np.testing.assert_allclose(g.det_center, np.stack([-250 * s, 250 * c, 0 * s], 1))
    np.testing.assert_allclose(g.u, np.stack([0.1 * c, 0.1 * s, 0 * s], 1))
    np.testing.assert_allclose(g.v, np.tile([0, 0, 0.2], (3, 1)))
    assert g.kind == "cone" and g.det_shape == (10, 20) and g.n_views == 3


def test_parallel_matches_astra_parallel3d_vec():
    th = np.array([0.0, 1.1])
    g = pdvc.parallel(th, det_shape=(4, 6), pixel=2.0)
    np.testing.assert_allclose(g.ray, np.stack([np.sin(th), -np.cos(th), 0 * th], 1))
    np.testing.assert_allclose(g.det_center, 0)
    np.testing.assert_allclose(g.u, np.stack([2 * np.cos(th), 2 * np.sin(th), 0 * th], 1))


def test_detector_offset_moves_centre_along_u_and_v():
    g0 = pdvc.circular_cone([0.3], sod=100, odd=50, det_shape=(8, 8), pixel=1.0)
    g1 = pdvc.circular_cone([0.3], sod=100, odd=50, det_shape=(8, 8), pixel=1.0, det_offset=(2.0, -3.0))
    np.testing.assert_allclose(g1.det_center - g0.det_center, -3 * g0.u + 2 * g0.v)


def test_magnified_point_projection():
    # a point at x = 2 seen at θ = 0 lands 2 * SDD/SOD / px columns right of centre
    g = pdvc.circular_cone([0.0], sod=100.0, odd=50.0, det_shape=(9, 11), pixel=0.5)
    rc = g.project_points([[2.0, 0.0, 0.0], [0.0, 0.0, 0.0]])[0]
    np.testing.assert_allclose(rc[1], [4.0, 5.0])
    np.testing.assert_allclose(rc[0], [4.0 + 0.0, 5.0 + 2 * 1.5 / 0.5])


def test_geometry_is_immutable_and_transforms_return_new_objects(rng):
    g = pdvc.circular_cone(np.linspace(0, 1, 4), sod=100, odd=50, det_shape=(8, 8), pixel=1.0)
    before = g.vectors.copy()
    with pytest.raises(ValueError):
        g.vectors[0, 0] = 1.0
    rv, t = rng.normal(0, 0.1, (4, 3)), rng.normal(0, 1, (4, 3))
    rv0, t0 = rv.copy(), t.copy()
    g2 = g.apply_poses(rv, t)
    assert g2 is not g
    np.testing.assert_array_equal(g.vectors, before)
    np.testing.assert_array_equal(rv, rv0)
    np.testing.assert_array_equal(t, t0)
    with pytest.raises(AttributeError):
        g.kind = "parallel"


@pytest.mark.parametrize("kind", ["cone", "parallel"])
def test_apply_poses_sees_the_sample_at_its_pose(kind, rng):
    """The posed geometry projects sample point x where the nominal one projects R x + t."""
    angles = np.linspace(0, 2 * np.pi, 6, endpoint=False)
    if kind == "cone":
        g = pdvc.circular_cone(angles, sod=200, odd=100, det_shape=(30, 40), pixel=1.0)
    else:
        g = pdvc.parallel(angles, det_shape=(30, 40), pixel=1.0)
    rv, t = rng.normal(0, 0.2, (6, 3)), rng.normal(0, 3, (6, 3))
    x = rng.normal(0, 10, (7, 3))
    posed = g.apply_poses(rv, t).project_points(x)
    R = rotvec_to_matrix(rv)
    for k in range(6):
        moved = x @ R[k].T + t[k]
        np.testing.assert_allclose(posed[k], g[k].project_points(moved)[0], atol=1e-9)


def test_apply_poses_about_a_center_and_composition(rng):
    g = pdvc.circular_cone(np.linspace(0, 3, 5), sod=200, odd=100, det_shape=(20, 20), pixel=1.0)
    c = np.array([1.0, -2.0, 3.0])
    rv, tau = rng.normal(0, 0.2, (5, 3)), rng.normal(0, 1, (5, 3))
    R = rotvec_to_matrix(rv)
    t = tau + c - np.einsum("nij,j->ni", R, c)
    np.testing.assert_allclose(g.apply_poses(rv, tau, center=c).vectors, g.apply_poses(rv, t).vectors, atol=1e-12)
    # posing by b then by a equals posing by a ∘ b ... seen from the sample: geometry(a∘b)
    rv2, t2 = rng.normal(0, 0.2, (5, 3)), rng.normal(0, 1, (5, 3))
    rv_ab, t_ab = compose_poses(rv2, t2, rv, t)
    x = rng.normal(0, 5, (4, 3))
    lhs = g.apply_poses(rv_ab, t_ab).project_points(x)
    R2 = rotvec_to_matrix(rv2)
    for k in range(5):
        moved = (x @ R[k].T + t[k]) @ R2[k].T + t2[k]
        np.testing.assert_allclose(lhs[k], g[k].project_points(moved)[0], atol=1e-9)
    rvi, ti = invert_poses(rv, t)
    rv_id, t_id = compose_poses(rv, t, rvi, ti)
    np.testing.assert_allclose(rv_id, 0, atol=1e-12)
    np.testing.assert_allclose(t_id, 0, atol=1e-12)


@pytest.mark.parametrize("shape,factor", [((8, 12), 2), ((9, 13), 2), ((12, 12), 3)])
def test_binned_pixel_centres_are_block_means(shape, factor):
    g = pdvc.circular_cone([0.4, 1.3], sod=100, odd=50, det_shape=shape, pixel=(0.7, 0.5), det_offset=(0.3, -1.2))
    gb = g.binned(factor)
    nr, nc = gb.det_shape
    assert (nr, nc) == (shape[0] // factor, shape[1] // factor)
    for k in range(2):
        fine = g.pixel_centers(k)[: nr * factor, : nc * factor]
        means = fine.reshape(nr, factor, nc, factor, 3).mean(axis=(1, 3))
        np.testing.assert_allclose(gb.pixel_centers(k), means, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(gb.u, axis=1), 0.5 * factor)


def test_cropped_window_keeps_pixel_positions():
    g = pdvc.parallel([0.2], det_shape=(10, 12), pixel=1.0)
    gc = g.cropped((2, 7), (3, 11))
    np.testing.assert_allclose(gc.pixel_centers(0), g.pixel_centers(0)[2:7, 3:11], atol=1e-12)


def test_view_selection_and_astra_roundtrip():
    g = pdvc.circular_cone(np.arange(6.0), sod=100, odd=50, det_shape=(4, 5), pixel=1.0)
    assert g[2:4].n_views == 2 and g[3].n_views == 1
    np.testing.assert_array_equal(g[[0, 5]].vectors, g.vectors[[0, 5]])
    d = g.to_astra()
    assert d["type"] == "cone_vec" and d["DetectorRowCount"] == 4 and d["DetectorColCount"] == 5
    assert pdvc.VectorGeometry.from_astra(d) == g
    gp = pdvc.parallel([0.1], det_shape=(4, 5), pixel=1.0)
    assert pdvc.VectorGeometry.from_astra(gp.to_astra()) == gp
    assert pdvc.VectorGeometry.from_vectors(g.vectors, (4, 5), "cone") == g


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(det_shape=(0, 512)), "det_shape"),
        (dict(det_shape=(4,)), "det_shape"),
        (dict(pixel=0.0), "pixel"),
        (dict(sod=-1.0), "sod"),
        (dict(odd=-200.0), "odd"),
        (dict(angles=[]), "angles"),
        (dict(angles=[np.nan]), "angles"),
        (dict(det_offset=(1.0,)), "det_offset"),
    ],
)
def test_circular_cone_rejects_bad_input(kwargs, match):
    args = dict(angles=[0.0, 1.0], sod=100.0, odd=50.0, det_shape=(4, 4), pixel=1.0)
    args.update(kwargs)
    angles = args.pop("angles")
    with pytest.raises(pdvc.GeometryError, match=match):
        pdvc.circular_cone(angles, **args)


def test_vector_geometry_rejects_degenerate_rows():
    good = pdvc.circular_cone([0.0], sod=100, odd=50, det_shape=(4, 4), pixel=1.0).vectors[0]
    with pytest.raises(pdvc.GeometryError, match=r"shape \(n_views, 12\)"):
        pdvc.VectorGeometry(np.zeros((2, 11)), (4, 4))
    bad = good.copy(); bad[6:9] = 0
    with pytest.raises(pdvc.GeometryError, match="zero pixel pitch"):
        pdvc.VectorGeometry(bad, (4, 4))
    bad = good.copy(); bad[9:12] = bad[6:9]
    with pytest.raises(pdvc.GeometryError, match="parallel"):
        pdvc.VectorGeometry(bad, (4, 4))
    bad = good.copy(); bad[0:3] = bad[3:6] + 2 * bad[6:9]
    with pytest.raises(pdvc.GeometryError, match="source on the detector"):
        pdvc.VectorGeometry(bad, (4, 4))
    bad = good.copy(); bad[4] = np.inf
    with pytest.raises(pdvc.GeometryError, match="finite"):
        pdvc.VectorGeometry(bad, (4, 4))
    par = pdvc.parallel([0.0], det_shape=(4, 4), pixel=1.0).vectors[0].copy()
    par[0:3] = par[6:9]
    with pytest.raises(pdvc.GeometryError, match="parallel to the detector"):
        pdvc.VectorGeometry(par, (4, 4), "parallel")
    with pytest.raises(pdvc.GeometryError, match="kind"):
        pdvc.VectorGeometry(good, (4, 4), "fan")
    with pytest.raises(pdvc.GeometryError, match="factor"):
        pdvc.VectorGeometry(good, (4, 4)).binned(0)


def test_volume_geometry_centres_and_errors():
    vg = pdvc.VolumeGeometry((4, 6, 8), voxel_size=(0.5, 1.0, 2.0), offset=(10.0, 20.0, 30.0))
    np.testing.assert_allclose(vg.voxel_center(0, 0, 0), [10 - 3.5 * 2, 20 - 2.5, 30 - 1.5 * 0.5])
    np.testing.assert_allclose(vg.voxel_center(3, 5, 7), [10 + 7, 20 + 2.5, 30 + 0.75])
    p = vg.voxel_center(1.5, 2.0, 6.25)
    np.testing.assert_allclose(vg.world_to_index(p), [1.5, 2.0, 6.25])
    assert vg.binned(2).shape == (2, 3, 4) and vg.binned(2).voxel_size == (1.0, 2.0, 4.0)
    for bad, match in [(dict(shape=(4, 4)), "shape"), (dict(shape=(1, 4, 4)), "shape"),
                       (dict(shape=(4, 4, 4), voxel_size=0), "voxel_size"),
                       (dict(shape=(4, 4, 4), offset=(1, 2)), "offset")]:
        with pytest.raises(pdvc.GeometryError, match=match):
            pdvc.VolumeGeometry(**bad)


def test_pose_helpers_accept_read_only_arrays():
    rv = np.array([[0.1, 0.2, 0.3]])
    t = np.array([[1.0, 2.0, 3.0]])
    rv.setflags(write=False)
    t.setflags(write=False)
    compose_poses(rv, t, rv, t)
    invert_poses(rv, t)


def test_remove_mean_pose_is_a_gauge(rng):
    """Re-gauged poses describe the same scan up to one rigid motion, and average to the identity."""
    from pdvc.geometry import remove_mean_pose, reprojection_error

    g = pdvc.circular_cone(np.linspace(0, 2 * np.pi, 10, endpoint=False), sod=200, odd=100, det_shape=(40, 40), pixel=1.0)
    rv = rng.normal(0, 0.05, (10, 3)) + [0.1, -0.2, 0.3]
    t = rng.normal(0, 1.0, (10, 3)) + [3.0, -2.0, 5.0]
    c = np.array([1.0, 2.0, -1.0])
    rv2, t2 = remove_mean_pose(rv, t, center=c)
    from scipy.spatial.transform import Rotation

    np.testing.assert_allclose(Rotation.from_rotvec(rv2).mean().as_rotvec(), 0, atol=1e-12)
    moved_c = Rotation.from_rotvec(rv2).apply(c) + t2
    np.testing.assert_allclose(moved_c.mean(axis=0), c, atol=1e-9)
    pts = rng.normal(0, 8, (20, 3))
    assert reprojection_error(g.apply_poses(rv2, t2), g.apply_poses(rv, t), pts).rms < 1e-6
