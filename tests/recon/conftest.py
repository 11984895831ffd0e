"""Analytic phantoms for the reconstruction tests.

Exact line integrals of uniform ellipsoids (balls included) along every
detector ray of a vector geometry, independent of any voxel projector (no
inverse crime, DESIGN.md §4): the chord of a line through the unit ball at
distance ``r`` from its centre is ``2 sqrt(1 - r^2)``; an ellipsoid is the
unit ball under ``x = c + R diag(axes) y``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pdvc.geometry import VectorGeometry, VolumeGeometry, circular_cone, parallel


@dataclass(frozen=True)
class Ellipsoid:
    """Uniform ellipsoid: centre (x, y, z), semi-axes (a, b, c), rotation vector, density (1/length)."""

    center: tuple
    axes: tuple
    density: float = 1.0
    rotvec: tuple = (0.0, 0.0, 0.0)

    @property
    def rotation(self) -> np.ndarray:
        return Rotation.from_rotvec(np.asarray(self.rotvec, float)).as_matrix()


def ball(center, radius, density=1.0) -> Ellipsoid:
    return Ellipsoid(tuple(center), (radius, radius, radius), density)


def moved(e: Ellipsoid, rotvec, translation) -> Ellipsoid:
    """The ellipsoid after the rigid map ``x -> R x + t`` of the volume frame."""
    R = Rotation.from_rotvec(np.asarray(rotvec, float))
    c = R.apply(np.asarray(e.center, float)) + np.asarray(translation, float)
    rot = (R * Rotation.from_rotvec(np.asarray(e.rotvec, float))).as_rotvec()
    return Ellipsoid(tuple(c), e.axes, e.density, tuple(rot))


def _chords(origin, direction, e: Ellipsoid) -> np.ndarray:
    """Length of ``origin + t direction`` inside ``e`` (arrays ``(..., 3)``)."""
    R = e.rotation
    inv_axes = 1.0 / np.asarray(e.axes, float)
    o = ((origin - np.asarray(e.center, float)) @ R) * inv_axes
    d = (direction @ R) * inv_axes
    A = np.einsum("...k,...k->...", d, d)
    B = np.einsum("...k,...k->...", o, d)
    C = np.einsum("...k,...k->...", o, o) - 1.0
    disc = np.maximum(B * B - A * C, 0.0)
    return 2.0 * np.sqrt(disc) / A * np.linalg.norm(direction, axis=-1)


def project(phantom, geom: VectorGeometry, *, supersample: int = 1) -> np.ndarray:
    """Exact line integrals ``(n_views, n_rows, n_cols)`` float32 of a list of ellipsoids.

    ``supersample`` > 1 averages ``s x s`` point rays per pixel (the detector
    pixel's area integral, needed when comparing with a binned detector).
    """
    nr, nc = geom.det_shape
    s = supersample
    off = (np.arange(s) + 0.5) / s - 0.5
    rows = (np.arange(nr)[:, None] + off[None, :]).ravel()
    cols = (np.arange(nc)[:, None] + off[None, :]).ravel()
    out = np.zeros((geom.n_views, nr, nc), np.float64)
    for k in range(geom.n_views):
        pix = geom.pixel_centers(k, rows, cols)  # (nr*s, nc*s, 3)
        if geom.kind == "cone":
            origin = np.broadcast_to(geom.src[k], pix.shape)
            direction = pix - geom.src[k]
        else:
            origin = pix
            direction = np.broadcast_to(geom.ray[k], pix.shape)
        acc = np.zeros(pix.shape[:2])
        for e in phantom:
            acc += e.density * _chords(origin, direction, e)
        out[k] = acc.reshape(nr, s, nc, s).mean(axis=(1, 3))
    return out.astype(np.float32)


def voxelize(phantom, vol_geom: VolumeGeometry, *, supersample: int = 3) -> np.ndarray:
    """Partial-volume image of the phantom on the grid (mean of ``s^3`` sub-voxel samples)."""
    nz, ny, nx = vol_geom.shape
    s = supersample
    off = (np.arange(s) + 0.5) / s - 0.5
    zc, yc, xc = vol_geom.coordinates()
    sz, sy, sx = vol_geom.voxel_size
    z = (zc[:, None] + off * sz).ravel()
    y = (yc[:, None] + off * sy).ravel()
    x = (xc[:, None] + off * sx).ravel()
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    pts = np.stack([X, Y, Z], axis=-1)
    img = np.zeros(Z.shape)
    for e in phantom:
        q = ((pts - np.asarray(e.center, float)) @ e.rotation) / np.asarray(e.axes, float)
        img += e.density * (np.einsum("...k,...k->...", q, q) <= 1.0)
    return img.reshape(nz, s, ny, s, nx, s).mean(axis=(1, 3, 5)).astype(np.float32)


def central_mask(vol_geom: VolumeGeometry, *, half_height: int, radius_frac: float = 0.85) -> np.ndarray:
    """Central slices ``|iz - mid| <= half_height`` inside a cylinder of ``radius_frac`` x half width."""
    nz, ny, nx = vol_geom.shape
    iz = np.abs(np.arange(nz) - (nz - 1) / 2)[:, None, None]
    iy = (np.arange(ny) - (ny - 1) / 2)[None, :, None]
    ix = (np.arange(nx) - (nx - 1) / 2)[None, None, :]
    r = np.sqrt(iy**2 + ix**2)
    return (iz <= half_height) & (r <= radius_frac * min(nx, ny) / 2)


def edge_free(ref: np.ndarray, width: int = 2) -> np.ndarray:
    """Voxels farther than ``width`` voxels from any edge of the phantom image."""
    from scipy import ndimage

    size = 2 * width + 1
    return (ndimage.maximum_filter(ref, size) - ndimage.minimum_filter(ref, size)) <= 1e-6


def rel_rmse(rec, ref, mask) -> float:
    """RMS error in ``mask`` relative to the RMS of the reference there."""
    d = (rec - ref)[mask]
    return float(np.sqrt(np.mean(d * d)) / np.sqrt(np.mean(ref[mask] ** 2)))


# -- the standard small problem ---------------------------------------------
N = 48  #: volume side (voxels of size 1)
SOD, ODD = 150.0, 75.0  #: magnification 1.5
PIXEL = 1.5  #: detector pitch: 1 voxel at the rotation axis
DET = (64, 80)  #: rows x cols: the whole 48^3 box projects inside
N_VIEWS = 144


@pytest.fixture(scope="session")
def vol_geom():
    return VolumeGeometry((N, N, N), 1.0)


@pytest.fixture(scope="session")
def cone_geom():
    angles = np.linspace(0, 2 * np.pi, N_VIEWS, endpoint=False)
    return circular_cone(angles, sod=SOD, odd=ODD, det_shape=DET, pixel=PIXEL)


@pytest.fixture(scope="session")
def par_geom():
    angles = np.linspace(0, np.pi, N_VIEWS // 2, endpoint=False)
    return parallel(angles, det_shape=DET, pixel=1.0)


@pytest.fixture(scope="session")
def uniform_ball():
    return [ball((0.0, 0.0, 0.0), 16.0, 1.0)]


@pytest.fixture(scope="session")
def phantom():
    """A few balls and ellipsoids, overlapping (densities add), within radius 20 of the origin."""
    return [
        Ellipsoid((0.0, 0.0, 0.0), (18.0, 15.0, 12.0), 1.0, (0.0, 0.0, 0.3)),
        ball((6.0, -4.0, 2.0), 5.0, 0.5),
        ball((-7.0, 5.0, -3.0), 4.0, -0.4),
        Ellipsoid((-2.0, -8.0, 5.0), (6.0, 3.0, 3.0), 0.8, (0.2, 0.5, 0.0)),
        ball((9.0, 8.0, 0.0), 3.0, 1.5),
    ]
