"""Shared fixtures: small random geometries and analytic objects."""

from __future__ import annotations

import importlib.util
import sys
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

import pdvc


BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@contextmanager
def benchmark_module(name: str):
    """``benchmarks/<name>.py`` imported as a module (skips the test where the checkout has no benchmarks)."""
    path = BENCHMARKS / f"{name}.py"
    if not path.exists():
        pytest.skip(f"benchmarks/{name}.py not in this checkout")
    spec = importlib.util.spec_from_file_location(f"pdvc_bench_{name}", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses look their module up
    try:
        spec.loader.exec_module(mod)
        yield mod
    finally:
        sys.modules.pop(spec.name, None)


def gaussian_blob_volume(vol_geom, mean, sigma, amplitude=1.0):
    """Samples of A exp(-|x - m|² / 2σ²) at the voxel centres (float32)."""
    zc, yc, xc = vol_geom.coordinates()
    Z, Y, X = np.meshgrid(zc, yc, xc, indexing="ij")
    r2 = (X - mean[0]) ** 2 + (Y - mean[1]) ** 2 + (Z - mean[2]) ** 2
    return (amplitude * np.exp(-r2 / (2 * sigma**2))).astype(np.float32)


def gaussian_blob_line_integrals(geom, mean, sigma, amplitude=1.0):
    """Exact line integrals of the Gaussian blob: A σ √(2π) exp(-d² / 2σ²), d the ray-to-mean distance."""
    out = np.empty((geom.n_views,) + geom.det_shape)
    m = np.asarray(mean, np.float64)
    for k in range(geom.n_views):
        pc = geom.pixel_centers(k)
        if geom.kind == "cone":
            origin, direction = geom.src[k], pc - geom.src[k]
        else:
            origin, direction = pc, np.broadcast_to(geom.ray[k], pc.shape)
        dn = direction / np.linalg.norm(direction, axis=-1, keepdims=True)
        w = m - origin
        dist2 = np.sum(w * w, -1) - np.sum(w * dn, -1) ** 2
        out[k] = amplitude * sigma * np.sqrt(2 * np.pi) * np.exp(-dist2 / (2 * sigma**2))
    return out


def random_geometry(kind, rng, n_views=5, det_shape=(40, 52), *, tilt=0.2, shift=2.0):
    """A nominal scan at random angles, each view then moved by a random rigid pose.

    Views are therefore not a circular orbit: detectors are tilted and
    shifted independently, as after calibration.
    """
    angles = rng.uniform(0, 2 * np.pi, n_views)
    if kind == "cone":
        g = pdvc.circular_cone(angles, sod=110, odd=70, det_shape=det_shape, pixel=(1.3, 1.2))
    else:
        g = pdvc.parallel(angles, det_shape=det_shape, pixel=(0.9, 1.0))
    return g.apply_poses(rng.normal(0, tilt, (n_views, 3)), rng.normal(0, shift, (n_views, 3)))


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
