"""Lab frame vs sample frame of the rigid modes."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import pdvc
from pdvc.correlation._frames import lab_frames, lab_to_sample_map, params_to_lab, params_to_sample, to_lab
from pdvc.geometry import VolumeGeometry, circular_cone, parallel
from pdvc.simulate import lab_motion_to_poses

from ..conftest import gaussian_blob_volume, random_geometry

ANGLES = np.concatenate([[0.0], np.random.default_rng(0).uniform(-np.pi, 3 * np.pi, 20)])


def _rz(theta):
    return Rotation.from_rotvec(np.outer(theta, [0, 0, 1])).as_matrix()


@pytest.mark.parametrize("kind", ["cone", "parallel"])
def test_nominal_frames_are_rz(kind):
    if kind == "cone":
        g = circular_cone(ANGLES, sod=100, odd=50, det_shape=(10, 12), pixel=(0.3, 0.2), det_offset=(1.5, -2.0))
    else:
        g = parallel(ANGLES, det_shape=(10, 12), pixel=0.7)
    F = lab_frames(g)
    assert F.shape == (ANGLES.size, 3, 3)
    np.testing.assert_array_equal(F[0], np.eye(3))  # exactly: lab = sample frame at θ = 0
    np.testing.assert_allclose(F, _rz(ANGLES), atol=1e-15)
    if kind == "cone":
        # y_lab points along the beam, source -> detector
        beam = g.det_center - g.src
        assert np.all(np.einsum("ki,ki->k", F[:, :, 1], beam) > 0)


@pytest.mark.parametrize("kind", ["cone", "parallel"])
def test_frames_orthonormal_and_follow_poses(kind, rng):
    g = random_geometry(kind, rng, n_views=8)
    F = lab_frames(g)
    np.testing.assert_allclose(F @ np.swapaxes(F, 1, 2), np.broadcast_to(np.eye(3), F.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(F), 1.0, atol=1e-14)
    np.testing.assert_allclose(F[:, :, 0], g.u / np.linalg.norm(g.u, axis=1, keepdims=True), atol=1e-15)
    # a pose R_k rotates the scanner by R_kᵀ in the volume frame: F'_k = R_kᵀ F_k
    rv = rng.normal(0, 0.3, (8, 3))
    R = Rotation.from_rotvec(rv).as_matrix()
    F2 = lab_frames(g.apply_poses(rv, rng.normal(0, 1, (8, 3))))
    np.testing.assert_allclose(F2, np.swapaxes(R, 1, 2) @ F, atol=1e-13)


def test_constant_lab_motion_matches_simulate():
    g = circular_cone(ANGLES, sod=100, odd=50, det_shape=(10, 12), pixel=0.2)
    T = lab_to_sample_map(g)
    np.testing.assert_allclose(T[:, 3:, :3], 0)
    np.testing.assert_allclose(T[:, :3, 3:], 0)  # centre on the axis: block diagonal
    l = np.array([0.4, -0.25, 0.1])
    _, t = lab_motion_to_poses(ANGLES, np.zeros(3), l)
    p = params_to_sample(np.r_[l, 0, 0, 0], T)
    np.testing.assert_allclose(p[:, :3], t, atol=1e-14)
    np.testing.assert_allclose(p[:, 3:], 0)
    # a fixed lab rotation about the origin is the conjugated rotation: rotvec F_k ω, exactly
    w = np.array([0.02, -0.03, 0.01])
    rv, t = lab_motion_to_poses(ANGLES, w, np.zeros(3))
    p = params_to_sample(np.r_[0, 0, 0, w], T)
    np.testing.assert_allclose(p[:, 3:], rv, atol=1e-15)
    np.testing.assert_allclose(t, 0, atol=1e-15)
    # and back
    np.testing.assert_allclose(params_to_lab(p, T), np.broadcast_to(np.r_[0, 0, 0, w], p.shape), atol=1e-15)


def test_lab_rotation_about_pivot_off_axis():
    g = parallel(ANGLES, det_shape=(10, 12), pixel=0.5)
    c = np.array([1.0, -2.0, 0.5])  # engine's rotation centre, off the axis
    q = np.array([3.0, 1.0, -4.0])  # lab pivot, e.g. the table bearing
    T = lab_to_sample_map(g, center=c, pivot=q)
    w = np.array([2e-6, -1e-6, 3e-6])
    L = Rotation.from_rotvec(w)
    rv, t = lab_motion_to_poses(ANGLES, w, q - L.apply(q))  # about q in the lab
    # the same pose read about c: x -> R (x - c) + c + τ, τ = t + R c - c
    tau = t + Rotation.from_rotvec(rv).apply(c) - c
    p = params_to_sample(np.r_[0, 0, 0, w], T)
    # first order in |ω| ~ 4e-6: error O(|ω|² · |q|) ~ 1e-10
    np.testing.assert_allclose(p[:, :3], tau, atol=1e-10)
    np.testing.assert_allclose(p[:, 3:], rv, atol=1e-15)
    # not block diagonal any more, and the inverse still undoes it
    assert np.abs(T[:, :3, 3:]).max() > 1
    pl = np.random.default_rng(1).normal(size=(ANGLES.size, 6))
    np.testing.assert_allclose(params_to_lab(params_to_sample(pl, T), T), pl, atol=1e-12)


@pytest.mark.parametrize("kind", ["cone", "parallel"])
def test_an_increment_on_tilted_poses_moves_the_sample_along_the_lab_axes(kind, rng):
    # the engine composes an increment before the current pose: read with rotvecs, a lab translation moves the sample
    # by exactly that lab vector in the volume frame, whatever the pose; with the nominal axes it is tilted with it
    from pdvc.geometry import Poses

    g = circular_cone(ANGLES, sod=100, odd=50, det_shape=(10, 12), pixel=0.3) if kind == "cone" else \
        parallel(ANGLES, det_shape=(10, 12), pixel=0.3)
    n = ANGLES.size
    pose = Poses(rng.normal(0, 0.05, (n, 3)), rng.normal(0, 1.0, (n, 3)))  # tilts of ~3°
    F = lab_frames(g)
    l = np.array([0.0, 1.0, 0.0])  # along the beam
    for T, exact in ((lab_to_sample_map(g, rotvecs=pose.rotvecs), True), (lab_to_sample_map(g), False)):
        d = params_to_sample(np.broadcast_to(np.r_[l, 0, 0, 0], (n, 6)), T)
        moved = pose.compose(Poses.from_params(d, (0.0, 0.0, 0.0)))
        shift = moved.translations - pose.translations  # the volume-frame motion of every point (no rotation added)
        err = np.abs(shift - F @ l).max()
        assert (err < 1e-12) if exact else (err > 1e-2)
    # identity poses: the nominal map
    np.testing.assert_allclose(lab_to_sample_map(g, rotvecs=np.zeros((n, 3))), lab_to_sample_map(g), atol=1e-15)
    with pytest.raises(pdvc.ShapeError, match="rotvecs"):
        lab_to_sample_map(g, rotvecs=np.zeros((n + 1, 3)))


def test_to_lab_quadratic_form_invariance(rng):
    g = random_geometry("cone", rng, n_views=6)
    T = lab_to_sample_map(g, center=(0.5, 0.2, -1.0))
    G = rng.normal(size=(6, 50, 6))
    M = np.swapaxes(G, 1, 2) @ G
    b = rng.normal(size=(6, 6))
    M0, b0, T0 = M.copy(), b.copy(), T.copy()
    Ml, bl = to_lab(M, b, T)
    np.testing.assert_array_equal(M, M0)
    np.testing.assert_array_equal(b, b0)
    np.testing.assert_array_equal(T, T0)
    pl = rng.normal(size=(6, 6))
    ps = params_to_sample(pl, T)
    np.testing.assert_allclose(np.einsum("ki,kij,kj->k", pl, Ml, pl), np.einsum("ki,kij,kj->k", ps, M, ps), rtol=1e-12)
    np.testing.assert_allclose(np.einsum("ki,ki->k", pl, bl), np.einsum("ki,ki->k", ps, b), rtol=1e-12)
    # Gauss-Newton steps agree: the lab step mapped to the sample frame is the sample step
    step_lab = np.linalg.solve(Ml, bl[..., None])[..., 0]
    step_s = np.linalg.solve(M, b[..., None])[..., 0]
    np.testing.assert_allclose(params_to_sample(step_lab, T), step_s, rtol=1e-9, atol=1e-12)
    # single view
    M1, b1 = to_lab(M[2], b[2], T[2])
    np.testing.assert_allclose(M1, Ml[2])
    np.testing.assert_allclose(b1, bl[2])


@pytest.mark.parametrize("l", [(0.08, 0.0, 0.06), (0.0, -0.3, 0.0)], ids=["detector-plane", "along-beam"])
def test_constant_lab_translation_is_one_mode(l):
    """A fixed lab shift, seen through the projector, is found as one constant lab-frame mode."""
    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    g = circular_cone(angles, sod=60, odd=40, det_shape=(36, 40), pixel=1.0)
    vg = VolumeGeometry((24, 24, 24), voxel_size=0.6)
    vol = gaussian_blob_volume(vg, (1.5, -1.0, 0.5), 2.0) + gaussian_blob_volume(vg, (-2.0, 1.5, -1.0), 1.6)
    l = np.array(l)
    T = lab_to_sample_map(g, center=vg.offset)
    t_sample = params_to_sample(np.r_[l, 0, 0, 0], T)[:, :3]
    measured = pdvc.forward(vol, vg, g.apply_poses(np.zeros(3), t_sample))
    p_lab = np.zeros(6)
    for it in range(3):  # Gauss-Newton on the one constant lab mode (exact poses each pass)
        p_s = params_to_sample(p_lab, T)
        red = pdvc.reduce_views(vol, vg, g.apply_poses(p_s[:, 3:], p_s[:, :3], center=vg.offset), measured)
        Ml, bl = to_lab(red.M, red.b, T)
        step = np.linalg.solve(Ml.sum(0), bl.sum(0))
        p_lab = p_lab + step
        if it == 0:
            first = step
    # After one step the error is second order in the shift (~0.1 voxel against blobs
    # ~3 voxels wide), but a shift along the beam is seen only through the magnification
    # (H's smallest eigenvalue, cond ~300), so an in-plane shift's second-order terms leak
    # into ty, amplified (measured 0.025 for l = (0.08, 0, 0.06)); the passes remove it.
    assert np.abs(first[:3] - l).max() < 0.4 * np.abs(l).max()
    # three passes: measured error ~1e-8 (noise-free data, same projector); 1e-5 allows float32 rounding
    np.testing.assert_allclose(p_lab[:3], l, atol=1e-5)
    np.testing.assert_allclose(p_lab[3:], 0, atol=1e-5)
    # the same constant in the sample frame does not describe it
    red = pdvc.reduce_views(vol, vg, g, measured)
    # the same constant in the sample frame does not describe it
    p_s = np.linalg.solve(red.M.sum(0), red.b.sum(0))
    assert np.abs(p_s[:3] - l).max() > 0.3 * np.abs(l).max()


def test_errors():
    g = parallel([0.0, 1.0], det_shape=(4, 4), pixel=1.0)
    with pytest.raises(pdvc.InputTypeError, match="VectorGeometry"):
        lab_frames(np.zeros((2, 12)))
    with pytest.raises(pdvc.ShapeError, match="center"):
        lab_to_sample_map(g, center=(1, 2))
    T = lab_to_sample_map(g)
    with pytest.raises(pdvc.ShapeError, match="b must have shape"):
        to_lab(np.zeros((2, 6, 6)), np.zeros((3, 6)), T)
    with pytest.raises(pdvc.ShapeError, match="2 views but the other argument has 3"):
        to_lab(np.zeros((3, 6, 6)), np.zeros((3, 6)), T)
    with pytest.raises(pdvc.ShapeError, match="p_lab"):
        params_to_sample(np.zeros((2, 3)), T)
