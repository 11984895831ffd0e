"""Foam and granular phantoms (pdvc.simulate.foam_phantom, granular_phantom)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from scipy.spatial.transform import Rotation

from pdvc.errors import GeometryError, PdvcError
from pdvc.simulate import EllipsoidPhantom, SimulationError, foam_phantom, granular_phantom


def _same(a: EllipsoidPhantom, b: EllipsoidPhantom) -> bool:
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("density", "center", "semi_axes", "rotvec"))


def _inside(points, axes) -> np.ndarray:
    return np.sum((points / np.asarray(axes)) ** 2, axis=-1) < 1


def _surfaces(ph: EllipsoidPhantom, n_per: int = 200) -> np.ndarray:
    s = np.random.default_rng(0).normal(size=(n_per, 3))
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    R = Rotation.from_rotvec(np.array(ph.rotvec)).as_matrix()
    return (ph.center[:, None, :] + np.einsum("nij,npj->npi", R, s[None] * ph.semi_axes[:, None, :])).reshape(-1, 3)


def _apart(ph: EllipsoidPhantom) -> bool:
    cen, rad = ph.center, ph.bounding_radius
    dist = np.linalg.norm(cen[:, None] - cen[None], axis=2)
    np.fill_diagonal(dist, np.inf)
    return bool(np.all(dist >= rad[:, None] + rad[None, :]))


def test_foam_is_deterministic_pores_inside_and_empty():
    r, h = 2.0, 4.0
    ph = foam_phantom(r, h, seed=3)
    assert _same(ph, foam_phantom(r, h, seed=3))
    assert not _same(ph, foam_phantom(r, h, seed=4))
    rho = 1.0 / r
    assert_allclose(ph.semi_axes[0], [r, r, h / 2])
    assert ph.density[0] == pytest.approx(rho)
    pores = ph[1:]
    assert pores.n_ellipsoids > 50
    assert_allclose(pores.density, -rho)  # a pore is empty: attenuation 0
    assert_array_equal(pores.semi_axes[:, 0], pores.semi_axes[:, 1])  # spheres
    assert_array_equal(pores.semi_axes[:, 0], pores.semi_axes[:, 2])
    assert np.all((pores.semi_axes[:, 0] >= 0.08 * r) & (pores.semi_axes[:, 0] <= 0.18 * r))
    assert np.all(np.diff(pores.semi_axes[:, 0]) <= 0)  # largest first
    assert np.all(_inside(_surfaces(pores), ph.semi_axes[0]))
    assert _apart(pores)
    # the default porosity is reached (within one pore)
    phi = pores.volumes().sum() / ph.volumes()[0]
    assert 0.3 <= phi <= 0.3 + pores.volumes().max() / ph.volumes()[0]
    # attenuation: solid or air, nothing else
    x = np.random.default_rng(1).uniform(-1, 1, (20000, 3)) * ph.semi_axes[0]
    x = x[_inside(x, ph.semi_axes[0])]
    v = ph.density_at(x)
    assert np.all(np.isclose(v, rho) | np.isclose(v, 0.0, atol=1e-12))
    assert np.mean(np.isclose(v, 0.0, atol=1e-12)) == pytest.approx(phi, abs=0.03)
    assert ph.density_at(pores.center[:5]) == pytest.approx(np.zeros(5), abs=1e-12)


def test_foam_options():
    ph = foam_phantom(1.0, 3.0, n_cells=40, cell_size=(0.1, 0.15), density=2.0, seed=0, center=(1.0, -2.0, 0.5))
    assert ph.n_ellipsoids == 41
    assert_allclose(ph.density, [2.0] + [-2.0] * 40)
    assert_allclose(ph.center[0], [1.0, -2.0, 0.5])
    assert np.all(_inside(_surfaces(ph[1:]) - ph.center[0], ph.semi_axes[0]))
    with pytest.raises(GeometryError, match="porosity"):
        foam_phantom(1.0, 2.0, porosity=0.6)
    with pytest.raises(GeometryError, match="cell_size"):
        foam_phantom(1.0, 2.0, cell_size=(0.2, 0.1))
    with pytest.raises(PdvcError, match="n_cells"):
        foam_phantom(1.0, 2.0, n_cells=-1)
    with pytest.raises(SimulationError, match="pores"):
        foam_phantom(1.0, 2.0, n_cells=400, cell_size=(0.3, 0.3))


def test_granular_is_deterministic_grains_inside_the_container():
    r, h = 2.0, 4.0
    ph = granular_phantom(r, h, seed=5)
    assert _same(ph, granular_phantom(r, h, seed=5))
    assert not _same(ph, granular_phantom(r, h, seed=6))
    rho, wt = 1.0 / r, 0.05 * r
    inner = np.array([r - wt, r - wt, h / 2 - wt])
    assert_allclose(ph.semi_axes[0], [r, r, h / 2])
    assert_allclose(ph.semi_axes[1], inner)
    assert_allclose(ph.density[:2], [0.3 * rho, -0.3 * rho])  # a wall, air inside
    grains = ph[2:]
    assert grains.n_ellipsoids > 30
    assert_allclose(grains.density, rho)
    big = grains.semi_axes.max(axis=1)
    assert np.all((big >= 0.1 * r) & (big <= 0.2 * r))
    ratio = np.sort(grains.semi_axes, axis=1)[:, :2] / big[:, None]
    assert np.all((ratio >= 0.6 - 1e-12) & (ratio <= 1.0))
    assert np.all(_inside(_surfaces(grains), inner))
    assert _apart(grains)
    # attenuation: air, grain, or wall
    x = np.random.default_rng(2).uniform(-1, 1, (20000, 3)) * ph.semi_axes[0]
    x = x[_inside(x, ph.semi_axes[0])]
    v = ph.density_at(x)
    levels = np.array([0.0, rho, 0.3 * rho])
    assert np.all(np.min(np.abs(v[:, None] - levels[None]), axis=1) < 1e-12)
    in_wall = ~_inside(x, inner)
    assert_allclose(v[in_wall], 0.3 * rho)
    assert np.mean(np.isclose(v[~in_wall], rho)) == pytest.approx(0.2, abs=0.04)  # default packing
    assert ph.density_at(grains.center[:5]) == pytest.approx(np.full(5, rho))


def test_granular_options():
    ph = granular_phantom(1.0, 2.0, n_grains=20, aspect=(1.0, 1.0), wall=0.1, wall_contrast=1.0, density=3.0, seed=1)
    assert ph.n_ellipsoids == 22
    assert_allclose(ph.density, [3.0, -3.0] + [3.0] * 20)
    assert_allclose(ph.semi_axes[1], [0.9, 0.9, 0.9])
    with pytest.raises(GeometryError, match="aspect"):
        granular_phantom(1.0, 2.0, aspect=(0.5, 1.5))
    with pytest.raises(GeometryError, match="wall"):
        granular_phantom(1.0, 2.0, wall=0.5)
    with pytest.raises(GeometryError, match="packing"):
        granular_phantom(1.0, 2.0, packing=0.0)
    with pytest.raises(SimulationError, match="grains"):
        granular_phantom(1.0, 2.0, n_grains=300, grain_size=(0.3, 0.3))
