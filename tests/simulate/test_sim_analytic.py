"""Exact line integrals of ellipsoid phantoms (pdvc.simulate.analytic)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from scipy.spatial.transform import Rotation

from pdvc.errors import InputTypeError, PdvcError
from pdvc.geometry import VectorGeometry, circular_cone, parallel
from pdvc.simulate import EllipsoidPhantom, cast_iron_phantom, project_analytic

from .simulate_helpers import random_geometry, ray_lines, sphere_chord

# Projections are computed in float64 and rounded once to float32: any two
# exact computations agree to a few float32 ulps of the value.
F32 = dict(rtol=2e-6, atol=2e-6)


def test_sphere_through_centre_parallel():
    R, rho = 1.3, 0.7
    ball = EllipsoidPhantom(rho, (0, 0, 0), (R, R, R))
    geom = parallel([0.0, 0.7, 2.0], det_shape=(21, 21), pixel=0.2)
    p = project_analytic(ball, geom)
    assert p.dtype == np.float32 and p.shape == (3, 21, 21)
    # the central pixel's ray passes through the centre
    assert_allclose(p[:, 10, 10], 2 * R * rho, rtol=1e-6)
    # pixel (10, 10 + k) passes at distance b = 0.2 k
    b = 0.2 * np.arange(1, 7)
    assert_allclose(p[:, 10, 11:17], np.broadcast_to(2 * rho * np.sqrt(R**2 - b**2), (3, 6)), rtol=1e-6)
    assert np.all(p[:, 10, 17:] == 0)  # b >= 1.4 > R


def test_sphere_matches_closed_form_any_geometry(rng, kind):
    R, rho, c = 1.1, 0.9, np.array([0.3, -0.2, 0.25])
    ball = EllipsoidPhantom(rho, c, (R, R, R))
    geom = random_geometry(rng, kind, n_views=5)
    origin, direction, half = ray_lines(geom)
    expected = rho * sphere_chord(origin, direction, c, R, half)
    p = project_analytic(ball, geom)
    assert np.count_nonzero(expected) > 100  # the ball is seen
    assert_allclose(p, expected, **F32)


def test_cone_sphere_around_and_behind_the_source(rng):
    geom = random_geometry(rng, "cone", n_views=3)
    src = geom.src[0]
    beam = geom.det_center[0] - src
    beam /= np.linalg.norm(beam)
    side = np.cross(beam, [0.3, 0.1, 0.9])
    side /= np.linalg.norm(side)
    g0 = geom[0]
    origin, direction, _ = ray_lines(g0)
    # around the source: only the part in front of it counts
    around = EllipsoidPhantom(1.0, src + 0.3 * beam + 0.2 * side, (1.0, 1.0, 1.0))
    assert_allclose(
        project_analytic(around, g0), sphere_chord(origin, direction, src + 0.3 * beam + 0.2 * side, 1.0, True), **F32
    )
    # wholly behind the source: invisible
    behind = EllipsoidPhantom(1.0, src - 3 * beam, (1.0, 1.0, 1.0))
    assert np.all(project_analytic(behind, g0) == 0)
    # beside the source, straddling the plane parallel to the detector
    beside = EllipsoidPhantom(1.0, src + 1.5 * side, (1.0, 1.0, 1.0))
    assert_allclose(project_analytic(beside, g0), sphere_chord(origin, direction, src + 1.5 * side, 1.0, True), **F32)


def _random_ellipsoids(rng, n):
    return EllipsoidPhantom(
        density=rng.uniform(-1, 1, n),
        center=rng.uniform(-0.8, 0.8, (n, 3)),
        semi_axes=rng.uniform(0.3, 1.2, (n, 3)),
        rotvec=Rotation.random(n, random_state=rng).as_rotvec(),
    )


def _indicator_integral(phantom, origin, direction, t0, t1, n_steps):
    """Midpoint-rule line integral of the phantom's attenuation, with the
    indicator written out independently of the package (scipy rotations)."""
    h = (t1 - t0) / n_steps
    t = t0 + (np.arange(n_steps) + 0.5) * h
    x = origin[None, :] + t[:, None] * direction[None, :]
    mats = Rotation.from_rotvec(np.array(phantom.rotvec)).as_matrix()
    total = 0.0
    for rho, c, a, m in zip(phantom.density, phantom.center, phantom.semi_axes, mats):
        s = (x - c) @ m / a  # m.T (x - c) as rows, scaled by the semi-axes
        total += rho * h * np.count_nonzero(np.sum(s * s, axis=1) <= 1.0)
    return total


def test_random_ellipsoids_vs_quadrature(rng, kind):
    ph = _random_ellipsoids(rng, 3)
    geom = random_geometry(rng, kind, n_views=2, det_shape=(15, 13))
    p = project_analytic(ph, geom)
    origin, direction, _ = ray_lines(geom)
    pick = np.argwhere(p != 0)
    pick = pick[rng.choice(len(pick), 10, replace=False)]
    n_steps, span = 400_000, 20.0
    # midpoint rule on a step function: each of the <= 6 boundary crossings
    # is off by at most one step h times |density| <= 1
    tol = 6 * span / n_steps
    for k, i, j in pick:
        o, w = origin[k, i, j], direction[k, i, j]
        t0, t1 = (0.0, span) if kind == "cone" else (-span / 2, span / 2)
        ref = _indicator_integral(ph, o, w, t0, t1, n_steps)
        assert abs(p[k, i, j] - ref) <= tol + 1e-6, (k, i, j, p[k, i, j], ref)


def test_density_at_matches_independent_indicator(rng):
    ph = _random_ellipsoids(rng, 4)
    pts = rng.uniform(-1.5, 1.5, (5000, 3))
    mats = Rotation.from_rotvec(np.array(ph.rotvec)).as_matrix()
    ref = np.zeros(len(pts))
    for rho, c, a, m in zip(ph.density, ph.center, ph.semi_axes, mats):
        s = (pts - c) @ m / a
        ref += rho * (np.sum(s * s, axis=1) <= 1.0)
    assert_allclose(ph.density_at(pts), ref, atol=1e-12)


def test_supersampling_is_the_mean_of_sub_rays(rng, kind):
    """s = 2 equals the mean of four s = 1 projections with the detector
    shifted by a quarter pixel in u and v (the definition of the sub-rays)."""
    ph = cast_iron_phantom(1.0, 1.6, n_nodules=30, n_inclusions=2, seed=3)
    geom = random_geometry(rng, kind, n_views=3)
    vec = np.array(geom.vectors)
    mean = np.zeros((3, *geom.det_shape))
    for orow in (-0.25, 0.25):
        for ocol in (-0.25, 0.25):
            shifted = vec.copy()
            shifted[:, 3:6] += ocol * vec[:, 6:9] + orow * vec[:, 9:12]
            mean += project_analytic(ph, VectorGeometry(shifted, geom.det_shape, kind)) / 4
    assert_allclose(project_analytic(ph, geom, supersampling=2), mean, rtol=1e-5, atol=1e-6)


def test_supersampling_converges():
    R, rho, px = 1.0, 1.0, 0.1
    ball = EllipsoidPhantom(rho, (0.013, -0.021, 0.007), (R, R, R))
    geom = parallel([0.3], det_shape=(25, 25), pixel=px)
    p = {s: project_analytic(ball, geom, supersampling=s).astype(np.float64) for s in (1, 2, 4, 16)}
    # smooth region (pixel at least 2 pixels inside the shadow): the pixel
    # mean differs from the centre value by ~ |c''| h²/12 per axis, with
    # c(b) = 2 sqrt(R² - b²), |c''| <= 2 R² / (R² - b²)^1.5
    cols = (np.arange(25) - 12) * px
    b = np.hypot(cols[None, :], cols[:, None])  # detector distance from the axis, about
    inner = b < R - 3 * px
    bmax = R - 2 * px
    bound = 2 * (2 * R**2 / (R**2 - bmax**2) ** 1.5) * px**2 / 12 * rho
    for s in (1, 2, 4):
        assert np.max(np.abs(p[s] - p[16])[0][inner]) <= bound
    # at the edges the error shrinks as s grows
    err = [np.abs(p[s] - p[16]).sum() for s in (1, 2, 4)]
    assert err[0] > err[1] > err[2] > 0


def test_pose_convention_moved_phantom_equals_apply_poses(rng, kind):
    """Projecting phantom.moved(R_k, t_k) with the nominal view k equals
    projecting the phantom with geom.apply_poses (DESIGN.md §1)."""
    ph = cast_iron_phantom(0.9, 1.6, n_nodules=25, n_inclusions=2, seed=1)
    geom = random_geometry(rng, kind, n_views=4)
    rv = rng.normal(scale=0.2, size=(4, 3))
    t = rng.normal(scale=0.2, size=(4, 3))
    posed = project_analytic(ph, geom.apply_poses(rv, t), supersampling=2)
    moved = np.stack([project_analytic(ph.moved(rv[k], t[k]), geom[k], supersampling=2)[0] for k in range(4)])
    assert np.abs(posed).max() > 0.5
    assert_allclose(posed, moved, **F32)


def test_culling_changes_nothing(rng, kind):
    """The per-view culling only skips pixels whose rays miss: the result is
    bit-identical to visiting every pixel, also for ellipsoids around,
    beside and behind the source and beyond the detector."""
    geom = random_geometry(rng, kind, n_views=4, det_shape=(17, 14))
    extra = []
    if kind == "cone":
        src, d = geom.src[0], geom.det_center[0]
        beam = (d - src) / np.linalg.norm(d - src)
        side = np.cross(beam, [0.2, 0.9, 0.1])
        side /= np.linalg.norm(side)
        extra = [src + 0.2 * beam, src + 1.2 * side, src - 1.5 * beam, d + 0.5 * beam, src + 0.05 * side + 0.3 * beam]
    ph = cast_iron_phantom(1.0, 1.8, n_nodules=40, n_inclusions=3, seed=2)
    if extra:
        ph = ph + EllipsoidPhantom(np.ones(len(extra)), np.array(extra), np.full((len(extra), 3), 0.6))
    culled = project_analytic(ph, geom, supersampling=2)
    full = project_analytic(ph, geom, supersampling=2, _cull=False)
    assert np.count_nonzero(full) > 0
    assert_array_equal(culled, full)


def test_circular_cone_rod_axis_ray():
    """A nominal cone scan of the rod: the central ray crosses it along a
    diameter, 2·radius·density."""
    ph = cast_iron_phantom(1.0, 2.0, n_nodules=0, n_inclusions=0)
    geom = circular_cone(np.linspace(0, np.pi, 4), sod=5.0, odd=5.0, det_shape=(31, 31), pixel=0.1)
    p = project_analytic(ph, geom)
    assert_allclose(p[:, 15, 15], 2.0, rtol=1e-6)  # density defaults to 1/radius
    assert_allclose(p, p[:1].repeat(4, axis=0), **F32)  # a rod on the axis looks the same at every angle


def test_empty_phantom_and_bad_inputs():
    geom = parallel([0.0], det_shape=(4, 5), pixel=1.0)
    empty = EllipsoidPhantom(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))
    assert np.all(project_analytic(empty, geom) == 0)
    ball = EllipsoidPhantom(1.0, (0, 0, 0), (1, 1, 1))
    with pytest.raises(InputTypeError, match="phantom"):
        project_analytic(np.ones((4, 4, 4)), geom)
    with pytest.raises(InputTypeError, match="geom"):
        project_analytic(ball, geom.vectors)
    with pytest.raises(PdvcError, match="supersampling"):
        project_analytic(ball, geom, supersampling=0)
    with pytest.raises(InputTypeError, match="supersampling"):
        project_analytic(ball, geom, supersampling=1.5)
