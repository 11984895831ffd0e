"""Fingerprint of a calibration run: which data, geometry and settings it used.

Written into ``run.json`` so that ``--resume`` can refuse to continue a
checkpoint with other projections, another geometry or other settings.
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import numpy as np

__all__ = ["run_fingerprint"]

_DIGEST_SIZE = 16
#: bytes hashed per chunk of views (so a large or memory-mapped stack is never copied whole)
_CHUNK_BYTES = 64 * 1024 * 1024
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")


def _hasher():
    return hashlib.blake2b(digest_size=_DIGEST_SIZE)


def _array_digest(a) -> str:
    """Digest of an array-like's shape, dtype and values, hashed chunk by chunk along axis 0."""
    if not hasattr(a, "shape") or not hasattr(a, "dtype"):
        a = np.asarray(a)
    shape = tuple(int(s) for s in a.shape)
    dtype = np.dtype(a.dtype)
    h = _hasher()
    h.update(repr((shape, dtype.str)).encode())
    if len(shape) == 0:
        h.update(np.ascontiguousarray(np.asarray(a)).tobytes())
        return h.hexdigest()
    row_bytes = max(1, int(np.prod(shape[1:], dtype=np.int64)) * dtype.itemsize)
    step = max(1, _CHUNK_BYTES // row_bytes)
    for i in range(0, shape[0], step):
        chunk = np.ascontiguousarray(a[i : i + step])
        h.update(memoryview(chunk).cast("B"))
    return h.hexdigest()


def _canonical(x):
    """A JSON-ready, process-independent form of a settings value."""
    if isinstance(x, dict):
        return {str(k): _canonical(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_canonical(v) for v in x]
    if x is None or isinstance(x, (bool, int, str)):
        return x
    if isinstance(x, float):
        return repr(x)  # exact, and NaN/inf stay valid JSON
    if isinstance(x, np.generic):
        return _canonical(x.item())
    if isinstance(x, np.ndarray):
        return {"__array__": _array_digest(x)}
    if isinstance(x, Path):
        return str(x)
    if hasattr(x, "vectors") and hasattr(x, "det_shape"):  # a VectorGeometry (e.g. an initial geometry)
        return {"__geometry__": _geometry_digest(x, None)}
    # anything else by its text, without memory addresses (stable across processes)
    return _ADDRESS.sub("", repr(x))


def _geometry_digest(geometry, vol_geom) -> str:
    h = _hasher()
    h.update(repr((str(geometry.kind), tuple(int(s) for s in geometry.det_shape))).encode())
    h.update(_array_digest(np.asarray(geometry.vectors, np.float64)).encode())
    if vol_geom is not None:
        grid = (
            tuple(int(s) for s in vol_geom.shape),
            tuple(float(v) for v in np.ravel(vol_geom.voxel_size)),
            tuple(float(v) for v in np.ravel(vol_geom.offset)),
        )
        h.update(repr(grid).encode())
    return h.hexdigest()


def run_fingerprint(projections, geometry, vol_geom, settings: dict) -> dict:
    """Fingerprint of a calibration run, for ``run.json`` and ``--resume``.

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) array-like
        The projections the calibration sees. Hashed view chunk by view
        chunk (``np.ascontiguousarray`` per chunk), so a large or
        memory-mapped stack is never copied whole; a non-contiguous view
        hashes like its contiguous copy.
    geometry : VectorGeometry
        Nominal geometry: ``vectors`` (as float64), ``det_shape`` and ``kind``.
    vol_geom : VolumeGeometry
        Reconstruction grid: ``shape``, ``voxel_size`` and ``offset``.
    settings : dict
        Calibration options and configuration. Hashed as canonical JSON
        (sorted keys); arrays by their digest, floats exactly, other
        objects by their text without memory addresses. Leave callables
        (progress, checkpoint) out: they are not settings.

    Returns
    -------
    dict
        ``{"data": hex, "geometry": hex, "settings": hex}``, BLAKE2b digests
        of 16 bytes. Equal fingerprints mean the same inputs (up to hash
        collisions); compare key by key to tell what changed.

    Examples
    --------
    >>> import numpy as np
    >>> from pdvc.geometry import VolumeGeometry, parallel
    >>> g = parallel(np.linspace(0, np.pi, 8, endpoint=False), det_shape=(4, 6), pixel=1.0)
    >>> fp = run_fingerprint(np.zeros((8, 4, 6)), g, VolumeGeometry((4, 6, 6)), {"n_outer": 3})
    >>> sorted(fp)
    ['data', 'geometry', 'settings']
    >>> fp == run_fingerprint(np.zeros((8, 4, 6)), g, VolumeGeometry((4, 6, 6)), {"n_outer": 4})
    False
    """
    text = json.dumps(_canonical(dict(settings)), sort_keys=True, separators=(",", ":"), default=str)
    s = _hasher()
    s.update(text.encode("utf-8"))
    return {
        "data": _array_digest(projections),
        "geometry": _geometry_digest(geometry, vol_geom),
        "settings": s.hexdigest(),
    }
