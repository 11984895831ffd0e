"""The Poses value type: exact algebra on SO(3), parameter conversions, frames, gauge, immutability."""

import numpy as np
import pytest

import pdvc
from pdvc.errors import GeometryError
from pdvc.geometry import Poses, compose_poses, fix_gauge, lab_frames


@pytest.fixture
def poses():
    rng = np.random.default_rng(3)
    return Poses(rng.normal(0, 0.2, (12, 3)), rng.normal(0, 2.0, (12, 3)))


@pytest.fixture
def geom():
    return pdvc.circular_cone(np.linspace(0, 2 * np.pi, 12, endpoint=False), sod=100.0, odd=50.0, det_shape=(10, 12), pixel=1.0)


def _apply(p: Poses, x):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.array(p.rotvecs)).apply(x) + p.translations  # scipy wants a writable array


def test_compose_is_the_map_composition_and_inverse_undoes_it(poses):
    rng = np.random.default_rng(1)
    other = Poses(rng.normal(0, 0.3, (12, 3)), rng.normal(0, 1.0, (12, 3)))
    x = rng.normal(0, 5.0, (12, 3))
    np.testing.assert_allclose(_apply(poses @ other, x), _apply(poses, _apply(other, x)), atol=1e-12)
    ident = poses.compose(poses.inverse())
    np.testing.assert_allclose(ident.rotvecs, 0, atol=1e-12)
    np.testing.assert_allclose(ident.translations, 0, atol=1e-12)
    assert (poses @ other) == Poses(*compose_poses(*poses, *other))


def test_params_about_a_centre_round_trip_and_mean_what_they_say(poses):
    c = np.array([1.0, -2.0, 0.5])
    q = poses.to_params(c)
    back = Poses.from_params(q, c)
    np.testing.assert_allclose(back.rotvecs, poses.rotvecs, atol=1e-14)
    np.testing.assert_allclose(back.translations, poses.translations, atol=1e-12)
    # tau is where the centre goes
    np.testing.assert_allclose(q[:, :3], _apply(poses, np.tile(c, (12, 1))) - c, atol=1e-12)


def test_lab_parameters_of_a_nominal_scan_are_the_sample_ones_turned_back(poses, geom):
    c = np.zeros(3)
    lab = poses.lab_params(geom, c)
    F = lab_frames(geom)
    q = poses.to_params(c)
    np.testing.assert_allclose(np.einsum("kij,kj->ki", F, lab[:, :3]), q[:, :3], atol=1e-12)
    np.testing.assert_allclose(np.einsum("kij,kj->ki", F, lab[:, 3:]), q[:, 3:], atol=1e-12)
    # a constant lab translation along x_lab (across the beam) is what it is at every view
    th = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    t = np.stack([np.cos(th), np.sin(th), np.zeros(12)], 1) * 0.7  # x_lab of view k in the sample frame
    lab = Poses(np.zeros((12, 3)), t).lab_params(geom, c)
    np.testing.assert_allclose(lab[:, 0], 0.7, atol=1e-12)
    np.testing.assert_allclose(lab[:, 1:3], 0.0, atol=1e-12)


def test_lab_parameters_go_back_to_the_same_poses(poses, geom):
    c = np.array([0.3, -1.2, 2.0])
    back = Poses.from_lab_params(poses.lab_params(geom, c), geom, c)
    np.testing.assert_allclose(back.rotvecs, poses.rotvecs, atol=1e-12)
    np.testing.assert_allclose(back.translations, poses.translations, atol=1e-12)
    # a vertical lab translation is a vertical translation of the sample at every view
    q = np.zeros((12, 6))
    q[:, 2] = np.linspace(-0.5, 0.5, 12)
    up = Poses.from_lab_params(q, geom, c)
    np.testing.assert_allclose(up.translations[:, 2], q[:, 2], atol=1e-12)
    np.testing.assert_allclose(up.translations[:, :2], 0.0, atol=1e-12)
    with pytest.raises(GeometryError, match=r"params must have shape \(12, 6\)"):
        Poses.from_lab_params(q[:5], geom, c)


def test_gauge_and_application_agree_with_the_functions(poses, geom):
    c = (0.0, 0.0, 0.0)
    g = poses.gauge_fixed(geom, center=c)
    rv, t = fix_gauge(poses.rotvecs, poses.translations, geom, center=c)
    np.testing.assert_array_equal(g.rotvecs, rv)
    np.testing.assert_array_equal(g.translations, t)
    assert geom.apply(poses) == geom.apply_poses(poses.rotvecs, poses.translations)
    assert geom.apply(Poses.identity(12)) == geom


def test_poses_are_frozen_and_checked(poses, geom):
    with pytest.raises(AttributeError):
        poses.rotvecs = np.zeros((12, 3))
    with pytest.raises(ValueError):
        poses.translations[0, 0] = 1.0
    src = np.zeros((3, 3))
    p = Poses(src, src)
    src[0, 0] = 1.0  # the caller's array is copied
    assert p.rotvecs[0, 0] == 0.0
    with pytest.raises(GeometryError, match="shape"):
        Poses(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(GeometryError, match="finite"):
        Poses(np.full((2, 3), np.nan), np.zeros((2, 3)))
    with pytest.raises(GeometryError, match="views"):
        geom.apply(Poses.identity(5))
    with pytest.raises(GeometryError, match="Poses"):
        geom.apply((np.zeros((12, 3)), np.zeros((12, 3))))
    assert len(poses[2:5]) == 3 and "n_views=12" in repr(poses)
