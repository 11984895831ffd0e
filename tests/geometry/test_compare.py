import numpy as np
import pytest

import pdvc
from pdvc.geometry import reprojection_error, sample_points


def test_parallel_shift_gives_known_pixel_error():
    vg = pdvc.VolumeGeometry((20, 20, 20))
    g = pdvc.parallel(np.linspace(0, np.pi, 6, endpoint=False), det_shape=(30, 30), pixel=0.5)
    t = np.zeros((6, 3))
    t[2] = [0.0, 0.0, 0.3]  # along v at every angle: 0.3 / 0.5 = 0.6 px
    err = reprojection_error(g.apply_poses(np.zeros(3), t), g, sample_points(vg), remove_gauge=False)
    np.testing.assert_allclose(err.per_view, [0, 0, 0.6, 0, 0, 0], atol=1e-9)
    assert err.max == pytest.approx(0.6)


@pytest.mark.parametrize("kind", ["cone", "parallel"])
def test_global_rigid_motion_is_removed_as_gauge(kind, rng):
    vg = pdvc.VolumeGeometry((32, 32, 32))
    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    g = (pdvc.circular_cone(angles, sod=200, odd=100, det_shape=(48, 48), pixel=1.0) if kind == "cone"
         else pdvc.parallel(angles, det_shape=(48, 48), pixel=1.0))
    moved = g.apply_poses([0.05, -0.03, 0.2], [1.5, -2.0, 0.7])  # same pose for every view
    pts = sample_points(vg)
    assert reprojection_error(moved, g, pts, remove_gauge=False).rms > 1.0
    err = reprojection_error(moved, g, pts)
    assert err.rms < 1e-6
    # per-view motion is not a gauge
    wobble = g.apply_poses(np.zeros(3), rng.normal(0, 0.5, (12, 3)) * [1, 1, 1])
    assert reprojection_error(wobble, g, pts).rms > 0.1


def test_mismatched_geometries_are_rejected():
    g = pdvc.parallel([0.0, 1.0], det_shape=(8, 8), pixel=1.0)
    with pytest.raises(pdvc.GeometryError, match="same scan"):
        reprojection_error(g, g[:1], np.zeros((4, 3)))
