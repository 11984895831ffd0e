"""What the Dask workers run: pure functions of (volume, geometry chunk, data chunk).

Every task is a plain module-level function, so that a worker imports it
(``pdvc`` must be installed where the workers run) and Dask may run it
again after a worker is lost: the same inputs give the same output.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Optional

import numpy as np

__all__ = ["FileSlice", "forward_chunk", "reduce_chunk", "per_view_chunk", "reconstruct_slab", "set_task_threads"]


@dataclass(frozen=True)
class FileSlice:
    """Views ``[v0, v1)`` and rows ``[r0, r1)`` of a raw C-order array in a file (e.g. a ``.npy`` opened with ``mmap_mode``).

    The worker reads its part itself instead of receiving it from the client.
    """

    path: str
    offset: int
    dtype: str
    shape: tuple
    views: tuple
    rows: Optional[tuple] = None

    def load(self) -> np.ndarray:
        mm = np.memmap(self.path, dtype=np.dtype(self.dtype), mode="r", offset=self.offset, shape=tuple(self.shape))
        v0, v1 = self.views
        part = mm[v0:v1] if self.rows is None else mm[v0:v1, self.rows[0]:self.rows[1]]
        return np.ascontiguousarray(part, dtype=np.float32)


def _data(x):
    return x.load() if isinstance(x, FileSlice) else x


def set_task_threads() -> int:
    """numba threads for this task: the worker's ``NUMBA_NUM_THREADS``.

    The kernels are compiled without ``nogil``: the Dask threads of one
    worker take turns, so each task may use every numba thread the worker
    was given (``local:NxT`` gives each worker T; for a remote cluster,
    start the workers with ``--nthreads 1`` and ``NUMBA_NUM_THREADS`` set to
    their cores).
    """
    import numba

    try:
        allowed = int(os.environ.get("NUMBA_NUM_THREADS", numba.config.NUMBA_NUM_THREADS))
    except ValueError:
        allowed = numba.config.NUMBA_NUM_THREADS
    n = max(1, min(allowed, int(numba.config.NUMBA_NUM_THREADS)))
    numba.set_num_threads(n)
    return n


def forward_chunk(volume, vol_geom, geom, backend) -> np.ndarray:
    """Line integrals of one chunk of views, ``(n_chunk, n_rows, n_cols)`` float32."""
    from ..projectors import get_backend

    set_task_threads()
    out = np.empty((geom.n_views,) + tuple(geom.det_shape), np.float32)
    return get_backend(backend).forward(volume, vol_geom, geom, out)


def reduce_chunk(volume, vol_geom, geom, measured, weights, center, backend, robust=None) -> np.ndarray:
    """The backend's per-view reduction of one chunk of views, ``(n_chunk, 38)`` float64 (see ``reduce_views``;
    ``robust``: its ``(cut, shift)`` for this chunk's views)."""
    from ..projectors import get_backend

    set_task_threads()
    meas = _data(measured)
    w = _data(weights)
    extra = {} if robust is None else dict(robust=robust)
    return get_backend(backend).reduce(volume, vol_geom, geom, np.asarray(center, np.float64), meas, w, **extra)


def per_view_chunk(fn, volume, vol_geom, geom, projections, weights) -> np.ndarray:
    """``fn(volume, vol_geom, geom, projections, weights)`` on one chunk of views (one value per view)."""
    set_task_threads()
    return np.asarray(fn(volume, vol_geom, geom, _data(projections), _data(weights)))


def reconstruct_slab(band, slab_geom, band_geom, weights, filter, cutoff, views_per_block, padding="zero") -> np.ndarray:
    """FDK/FBP of one slab of z from the detector rows it projects onto, ``(nz_slab, ny, nx)`` float32."""
    from ..recon._fbp import _reconstruct
    from ._scheduler import use_scheduler

    set_task_threads()
    arr = _data(band)
    with use_scheduler("threads"):  # also when the worker shares this process: never dispatch again
        return _reconstruct(
            arr, slab_geom, band_geom, weights, filter=filter, cutoff=cutoff, out=None, views_per_block=views_per_block,
            padding=padding,
        )


def file_visible(path: str, size: int) -> bool:
    """Whether this worker sees ``path`` with at least ``size`` bytes (a shared file system)."""
    try:
        return os.path.getsize(path) >= size
    except OSError:
        return False
