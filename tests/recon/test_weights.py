"""Scan analysis: axis, centre, angular widths and Parker weights from the vectors."""

from __future__ import annotations

import numpy as np
import pytest

from pdvc.geometry import circular_cone, parallel
from pdvc.recon._weights import parker_weights, scan_weights

from .conftest import DET, ODD, PIXEL, SOD


def _cone(angles, **kw):
    return circular_cone(angles, sod=SOD, odd=ODD, det_shape=DET, pixel=PIXEL, **kw)


def test_full_scan_nominal():
    n = 90
    w = scan_weights(_cone(np.linspace(0, 2 * np.pi, n, endpoint=False)))
    assert w.kind == "full" and w.full
    np.testing.assert_allclose(np.abs(w.axis), [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(w.center, 0, atol=1e-9)
    np.testing.assert_allclose(w.dtheta, 2 * np.pi / n, rtol=1e-12)
    np.testing.assert_allclose(w.redundancy, 0.5)


def test_center_and_axis_follow_the_scanner():
    """A scanner tilted and shifted: the estimated axis and centre move with it."""
    from scipy.spatial.transform import Rotation

    rv, t = np.array([0.1, -0.05, 0.3]), np.array([5.0, -2.0, 7.0])
    g = _cone(np.linspace(0, 2 * np.pi, 60, endpoint=False)).transformed(rv, t)
    w = scan_weights(g)
    axis = Rotation.from_rotvec(rv).apply([0, 0, 1])
    assert abs(abs(w.axis @ axis) - 1) < 1e-12
    np.testing.assert_allclose(w.center, t, atol=1e-9)
    np.testing.assert_allclose(w.dtheta, 2 * np.pi / 60, rtol=1e-9)


def test_irregular_widths_sum_to_the_period():
    rng = np.random.default_rng(0)
    step = 2 * np.pi / 50
    angles = (np.arange(50) + rng.uniform(-0.3, 0.3, 50)) * step
    angles = np.concatenate([angles, 1.0 + np.linspace(0, step, 10)])  # a dense cluster
    w = scan_weights(_cone(rng.permutation(angles)))  # any view order
    assert w.kind == "full"
    assert np.isclose(w.dtheta.sum(), 2 * np.pi)
    assert np.all(w.dtheta > 0)
    # the clustered views share the width of the region they sample
    order = np.argsort(np.mod(angles, 2 * np.pi))
    assert w.dtheta[order].max() < 1.7 * step


def test_several_turns():
    g = _cone(np.linspace(0, 3 * 2 * np.pi, 3 * 40, endpoint=False) + 0.01 * np.arange(120) / 120)
    w = scan_weights(g)
    assert w.kind == "full"
    np.testing.assert_allclose(w.dtheta.sum(), 2 * np.pi)  # each turn gets a third
    np.testing.assert_allclose(w.dtheta, 2 * np.pi / 120, rtol=0.05)


def test_short_scan_detected_and_parker_sums_to_one():
    g = _cone(np.linspace(0, np.pi + 0.8, 120))
    w = scan_weights(g)
    assert w.kind == "short"
    assert np.all((w.redundancy >= 0) & (w.redundancy <= 1))
    # end views weigh zero, the middle of the arc one
    assert np.all(w.redundancy[[0, -1]] < 1e-12)
    np.testing.assert_allclose(w.redundancy[60, 30:50], 1.0)


@pytest.mark.parametrize("delta", [0.2, 0.5, 1.2])
def test_parker_pairs_sum_to_one(delta):
    rng = np.random.default_rng(1)
    gamma = rng.uniform(-0.95 * delta, 0.95 * delta, 300)
    # rays whose conjugate (beta + pi + 2 gamma, -gamma) is also in the arc [0, pi + 2 delta]
    beta = rng.uniform(0, 1, 300) * (2 * delta - 2 * gamma)
    w1 = parker_weights(beta[:, None], gamma[:, None], delta)
    w2 = parker_weights((beta + np.pi + 2 * gamma)[:, None], -gamma[:, None], delta)
    np.testing.assert_allclose(w1 + w2, 1.0, atol=1e-12)
    # rays measured once: weight one
    mid = 2 * delta - 2 * gamma + rng.uniform(0, 1, 300) * (np.pi - 2 * delta)
    np.testing.assert_allclose(parker_weights(mid[:, None], gamma[:, None], delta), 1.0)


def test_parker_orientation_matches_conjugate_rays():
    """With the fan angles measured from the vectors, conjugate rays get weights summing to 1."""
    from pdvc.recon._weights import fan_angles

    span = np.pi + 0.8
    angles = np.linspace(0, span, 721) + 0.4  # start anywhere
    g = _cone(angles)
    w = scan_weights(g)
    gam = fan_angles(g, w.axis, w.center)
    step = span / 720
    checked = 0
    for k in (10, 60, 300, 660, 710):
        for j in range(0, 80, 7):
            kc = int(round((angles[k] - 0.4 + np.pi + 2 * gam[k, j]) / step))
            if kc > 720:  # conjugate beyond the arc (or before it): this ray is measured once
                kb = int(round((angles[k] - 0.4 - np.pi + 2 * gam[k, j]) / step))
                if kb < 0:
                    assert w.redundancy[k, j] > 0.98, (k, j)
                    continue
                kc = kb
            jc = int(np.argmin(np.abs(gam[kc] + gam[k, j])))
            # nearest-neighbour pairing on the (beta, gamma) grid: 2 % rounding
            assert abs(w.redundancy[k, j] + w.redundancy[kc, jc] - 1) < 0.02, (k, j)
            checked += 1
    assert checked > 20


def test_parallel_mod_pi():
    n = 60
    w = scan_weights(parallel(np.linspace(0, 2 * np.pi, n, endpoint=False), det_shape=DET, pixel=1.0))
    assert w.kind == "full"
    np.testing.assert_allclose(w.dtheta.sum(), np.pi)
    np.testing.assert_allclose(w.redundancy, 1.0)
    w2 = scan_weights(parallel(np.linspace(0, np.pi, n, endpoint=False), det_shape=DET, pixel=1.0))
    np.testing.assert_allclose(w2.dtheta, np.pi / n)


def test_parallel_limited_angle_warns(caplog):
    g = parallel(np.linspace(0, 2.0, 40), det_shape=DET, pixel=1.0)
    with caplog.at_level("WARNING", logger="pdvc.recon._weights"):
        w = scan_weights(g)
    assert w.kind == "partial"
    assert "limited-angle" in caplog.text
