"""Helpers of the simulate tests: random geometries and closed-form chords."""

from __future__ import annotations

import numpy as np

from pdvc.geometry import VectorGeometry


def _unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def random_geometry(rng, kind, n_views=4, det_shape=(23, 19), *, sod=8.0, odd=6.0, pixel=0.25):
    """A vector geometry with random orientation per view: source anywhere on
    a sphere, detector tilted by up to ~15 degrees and slightly skewed
    (u not orthogonal to v), unequal row/column pitch, detector centre off
    the central ray. Covers a phantom of radius ~2 at the origin."""
    rows = []
    for _ in range(n_views):
        e = _unit(rng.normal(size=3))  # source -> detector direction
        a = _unit(np.cross(e, rng.normal(size=3)))
        b = np.cross(e, a)
        tilt = rng.uniform(-0.25, 0.25, 2)
        u = _unit(a + tilt[0] * e) * pixel
        v = _unit(b + tilt[1] * e + 0.05 * a) * pixel * 1.2
        d = odd * e + rng.uniform(-1, 1, 3) * pixel * 2
        if kind == "cone":
            first = -sod * e + rng.uniform(-0.2, 0.2, 3)
        else:
            first = e + rng.uniform(-0.1, 0.1, 3)  # ray direction, not normal to the detector
        rows.append(np.concatenate([first, d, u, v]))
    return VectorGeometry(np.array(rows), det_shape, kind)


def ray_lines(geom, offsets=(0.0, 0.0)):
    """Origins and unit directions of the rays through the pixel points
    ``(i + offsets[0], j + offsets[1])``, computed from the vectors directly.

    Returns (origin, direction, is_half_line) with arrays (n_views, n_rows, n_cols, 3).
    """
    nr, nc = geom.det_shape
    vec = geom.vectors
    ii = np.arange(nr)[:, None] - (nr - 1) / 2 + offsets[0]
    jj = np.arange(nc)[None, :] - (nc - 1) / 2 + offsets[1]
    pix = (
        vec[:, None, None, 3:6]
        + jj[None, :, :, None] * vec[:, None, None, 6:9]
        + ii[None, :, :, None] * vec[:, None, None, 9:12]
    )
    if geom.kind == "cone":
        origin = np.broadcast_to(vec[:, None, None, 0:3], pix.shape)
        direction = _unit(pix - origin)
        return origin, direction, True
    direction = np.broadcast_to(_unit(vec[:, None, None, 0:3]), pix.shape)
    return pix, direction, False


def sphere_chord(origin, direction, center, radius, half_line):
    """Closed-form chord of a line (or half-line from origin) through a ball."""
    oc = center - origin
    tc = np.einsum("...k,...k->...", oc, direction)
    b2 = np.einsum("...k,...k->...", oc, oc) - tc**2  # squared distance centre - line
    h = np.sqrt(np.maximum(radius**2 - b2, 0.0))
    if not half_line:
        return 2 * h
    return np.maximum(tc + h - np.maximum(tc - h, 0.0), 0.0) * (radius**2 > b2)
