"""The operators on a Dask cluster: what is sent where, once, and what comes back.

A :class:`DaskSession` is made by :func:`pdvc.compute.use_scheduler` and
lives as long as its ``with`` block. It holds what it has sent to the
workers, so that it is sent once:

* a **volume** is broadcast to every worker once and reused for every call
  with the same array (same object, same content): the correlation engine
  makes tens of Jacobian passes per round with one volume;
* **projections** (and per-view weights) are split into chunks of views,
  each chunk sent to one worker once per projections array (once per
  scale in a calibration); when the array is a view of a file opened with
  ``mmap_mode`` (``.npy``) and the workers see that file, they read their
  chunk from it and nothing is sent;
* FDK/FBP sends to each slab of z the band of detector rows it projects
  onto (kept and reused while it covers the band asked for).

"Same content" is checked on every call by a CRC-32 of the array (of a
regular sample of 2**28 elements for arrays over ``FULL_CHECKSUM_BYTES``), so an
array changed in place is sent again. What comes back: the per-view 6 x 6
blocks, right-hand sides and residual sums (38 numbers per view), the
projections of :func:`forward`, the slabs of an FDK.

Faults: every task is pure and submitted with ``retries``; a task whose
worker dies is run again elsewhere by Dask. Data that lived only on a lost
worker (a chunk of projections) is sent again and the call re-run, at most
``RERUNS`` times; the result is the same.
"""

from __future__ import annotations

import concurrent.futures
import logging
import math
import mmap
import uuid
import zlib
from collections import OrderedDict
from typing import Optional

import numpy as np

from ..errors import PdvcError
from . import _tasks

__all__ = ["DaskSession", "ComputeError", "FULL_CHECKSUM_BYTES", "TASKS_PER_THREAD", "RETRIES", "RERUNS"]

log = logging.getLogger("pdvc.compute")

#: Arrays up to this size are checksummed whole on every call; larger ones by a regular sample.
FULL_CHECKSUM_BYTES = 1 << 30
#: Chunks of views per worker thread (load balance; a lost chunk costs little to redo).
TASKS_PER_THREAD = 2
#: Dask retries of a task that failed (e.g. its worker died while running it).
RETRIES = 2
#: Whole-call re-runs when data sent to a lost worker is gone with it.
RERUNS = 2
#: Fraction of a worker's memory limit that one chunk of projections may take.
CHUNK_MEMORY_FRACTION = 1 / 8


class ComputeError(PdvcError, RuntimeError):
    """The cluster could not finish a computation (workers lost more often than ``RERUNS``)."""


def _fingerprint(arr: np.ndarray) -> tuple:
    flat = arr.reshape(-1)
    if arr.nbytes <= FULL_CHECKSUM_BYTES:
        crc = zlib.crc32(np.ascontiguousarray(flat).view(np.uint8))
    else:
        step = math.ceil(flat.size / (1 << 28))
        crc = zlib.crc32(np.ascontiguousarray(flat[::step]).view(np.uint8))
    return (arr.shape, arr.dtype.str, arr.__array_interface__["data"][0], crc)


def _file_source(arr: np.ndarray):
    """(path, offset, dtype, shape) when ``arr`` is (a whole-array view of) a file mapped by ``np.memmap``, else None."""
    a = arr
    for _ in range(4):
        if isinstance(a, np.memmap) and isinstance(a.base, mmap.mmap):
            break
        a = getattr(a, "base", None)
        if not isinstance(a, np.ndarray):
            return None
    else:
        return None
    if (
        a.filename is None
        or a.shape != arr.shape
        or a.dtype != arr.dtype
        or not a.flags.c_contiguous
        or not arr.flags.c_contiguous
        or a.__array_interface__["data"][0] != arr.__array_interface__["data"][0]
        or not a.dtype.isnative
    ):
        return None
    return str(a.filename), int(a.offset), a.dtype.str, tuple(a.shape)


class _Entry:
    __slots__ = ("ref", "fp", "payload")

    def __init__(self, ref, fp, payload):
        self.ref, self.fp, self.payload = ref, fp, payload


class DaskSession:
    """A Dask client current for a run, with what it has sent to the workers.

    Made by :func:`pdvc.compute.use_scheduler`; not constructed by users.

    Attributes
    ----------
    client : distributed.Client
    spec : SchedulerSpec
    stats : dict
        Counters since the start (or :meth:`reset_stats`): ``sent_bytes``
        (client -> workers, a broadcast counted once per worker),
        ``file_bytes`` (read by the workers from the input file),
        ``received_bytes`` (results back), ``tasks``, ``calls``,
        ``volume_sends``, ``projection_sends``, ``reruns``.
    """

    def __init__(self, client, spec):
        self.client = client
        self.spec = spec
        self._volumes: "OrderedDict[int, _Entry]" = OrderedDict()
        self._data: "OrderedDict[tuple, _Entry]" = OrderedDict()
        self._bands: "OrderedDict[int, _Entry]" = OrderedDict()
        self._masks: "OrderedDict[tuple, object]" = OrderedDict()
        self._memory: Optional[int] = None
        self._file_ok: dict = {}
        self.reset_stats()

    # -- cluster facts ---------------------------------------------------------
    @property
    def n_workers(self) -> int:
        return max(1, len(self.client.nthreads()))

    @property
    def n_threads(self) -> int:
        """Tasks the cluster runs at once (Dask threads over all workers)."""
        return max(1, sum(self.client.nthreads().values()))

    def _worker_memory(self) -> int:
        """The smallest memory limit of a worker, bytes (0: unknown); asked once."""
        if self._memory is None:
            try:
                workers = self.client.scheduler_info(n_workers=-1)["workers"]
                lims = [int(w.get("memory_limit") or 0) for w in workers.values()]
                lims = [m for m in lims if m > 0]
                self._memory = min(lims) if lims else 0
            except Exception:  # noqa: BLE001 - a fact for sizing only
                self._memory = 0
        return self._memory

    def reset_stats(self) -> None:
        self.stats = dict(
            sent_bytes=0, file_bytes=0, received_bytes=0, tasks=0, calls=0, volume_sends=0, projection_sends=0, reruns=0
        )

    def release(self) -> None:
        """Drop everything sent (the workers free it)."""
        futs = list(self._masks.values())
        self._masks.clear()
        for cache in (self._volumes, self._data, self._bands):
            for e in cache.values():
                futs.extend(_futures_in(e.payload))
            cache.clear()
        if futs:
            try:
                self.client.cancel(futs)
            except Exception:  # noqa: BLE001 - the cluster may be gone already
                pass

    # -- what is sent once -----------------------------------------------------
    @staticmethod
    def _lookup(cache, key, arr):
        e = cache.get(key)
        if e is None or e.ref is not arr:
            return None
        if not all(f.status == "finished" for f in _futures_in(e.payload)):
            del cache[key]
            return None
        if e.fp != _fingerprint(arr):
            del cache[key]
            return None
        cache.move_to_end(key)
        return e

    @staticmethod
    def _store(cache, key, arr, payload, keep: int):
        cache[key] = _Entry(arr, _fingerprint(arr), payload)
        cache.move_to_end(key)
        while len(cache) > keep:
            cache.popitem(last=False)

    def _scatter(self, data, broadcast: bool = False):
        """Send to the workers: a broadcast goes to one worker, which the others copy from (a tree).

        A local cluster is sent to directly (not through the scheduler); a
        remote one through its scheduler, the one address known to reach.
        """
        direct = True if self.spec.kind == "local" else None
        return self.client.scatter(data, broadcast=broadcast, hash=False, direct=direct)

    def _volume(self, vol: np.ndarray):
        """The future of ``vol`` on every worker (broadcast once)."""
        e = self._lookup(self._volumes, id(vol), vol)
        if e is not None:
            return e.payload
        fut = self._scatter(vol, broadcast=True)
        self.stats["sent_bytes"] += vol.nbytes * self.n_workers
        self.stats["volume_sends"] += 1
        self._store(self._volumes, id(vol), vol, fut, keep=2)
        return fut

    def _view_bounds(self, n_views: int, bytes_per_view: int) -> list:
        n = self.n_threads * TASKS_PER_THREAD
        mem = self._worker_memory()
        if mem > 0 and bytes_per_view > 0:
            n = max(n, math.ceil(n_views * bytes_per_view / (mem * CHUNK_MEMORY_FRACTION)))
        n = max(1, min(n, n_views))
        edges = np.linspace(0, n_views, n + 1).round().astype(int)
        return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]

    def _sees_file(self, path: str, size: int) -> bool:
        if (path, size) not in self._file_ok:
            try:
                seen = self.client.run(_tasks.file_visible, path, size)
                self._file_ok[(path, size)] = bool(seen) and all(seen.values())
            except Exception:  # noqa: BLE001 - then the data are sent
                self._file_ok[(path, size)] = False
        return self._file_ok[(path, size)]

    def _chunks(self, arr: np.ndarray, role: str, bounds: Optional[list] = None):
        """(bounds, per-chunk futures or file slices) of a view-major array, sent once."""
        key = (role, id(arr))
        e = self._lookup(self._data, key, arr)
        if e is not None and (bounds is None or e.payload[0] == bounds):
            return e.payload
        if bounds is None:
            bounds = self._view_bounds(arr.shape[0], int(np.prod(arr.shape[1:])) * 4)
        src = _file_source(arr)
        if src is not None and self._sees_file(src[0], src[1] + arr.nbytes):
            parts = [_tasks.FileSlice(*src, views=(a, b)) for a, b in bounds]
            self.stats["file_bytes"] += arr.nbytes
        else:
            parts = self._scatter([arr[a:b] for a, b in bounds])
            self.stats["sent_bytes"] += arr.nbytes
            self.stats["projection_sends"] += 1
        payload = (bounds, parts)
        self._store(self._data, key, arr, payload, keep=4)
        return payload

    def _weights(self, w: np.ndarray, bounds: list):
        """Per-chunk weights: one mask shared by all views (``(n_rows, n_cols)`` or ``(1, n_rows, n_cols)``),
        broadcast once, or one per view, in chunks like the projections."""
        if w.ndim == 2 or w.shape[0] == 1:
            # a mask is small and often made afresh per call (reduce_views' default ones): known by its content
            key = ("mask", w.shape, w.dtype.str, zlib.crc32(np.ascontiguousarray(w).view(np.uint8)))
            fut = self._masks.get(key)
            if fut is None or fut.status != "finished":
                fut = self._scatter(w, broadcast=True)
                self.stats["sent_bytes"] += w.nbytes * self.n_workers
                self._masks[key] = fut
                while len(self._masks) > 4:
                    self._masks.popitem(last=False)
            return [fut] * len(bounds)
        return self._chunks(w, "weights", bounds)[1]

    # -- running ---------------------------------------------------------------
    def _run(self, name: str, submit_all):
        """Submit (``submit_all(tag) -> futures``), gather; send again and re-run when data were lost."""
        from distributed.comm.core import CommClosedError
        from distributed.scheduler import KilledWorker

        # lost data or workers; an error raised by a task itself (e.g. a GeometryError) is re-raised as it is
        lost = (concurrent.futures.CancelledError, KilledWorker, CommClosedError)
        self.stats["calls"] += 1
        for attempt in range(RERUNS + 1):
            futs = submit_all(f"pdvc-{name}-{uuid.uuid4().hex[:12]}")
            self.stats["tasks"] += len(futs)
            try:
                out = self.client.gather(futs)
            except lost as exc:
                if attempt == RERUNS:
                    raise ComputeError(
                        f"{name}: the cluster lost data or workers {RERUNS + 1} times in a row ({type(exc).__name__}: {exc}); "
                        "check the workers' logs and memory"
                    ) from exc
                log.warning("%s: %s (%s); sending the data again and re-running", name, type(exc).__name__, exc)
                self.stats["reruns"] += 1
                self.release()
                continue
            finally:
                del futs
            self.stats["received_bytes"] += sum(int(getattr(r, "nbytes", 0)) for r in out)
            return out
        raise AssertionError("unreachable")  # pragma: no cover

    def forward(self, vol, vol_geom, geom, out, backend):
        """:func:`pdvc.forward` on the cluster, into ``out``."""
        bounds = self._view_bounds(geom.n_views, 0)

        def submit(tag):
            vf = self._volume(vol)
            return [
                self.client.submit(_tasks.forward_chunk, vf, vol_geom, geom[a:b], backend, key=f"{tag}-{i}", retries=RETRIES)
                for i, (a, b) in enumerate(bounds)
            ]

        for (a, b), part in zip(bounds, self._run("forward", submit)):
            out[a:b] = part
        return out

    def reduce(self, vol, vol_geom, geom, center, measured, weights, backend, robust=None) -> np.ndarray:
        """The backend's ``reduce`` on the cluster: ``(n_views, 38)`` float64."""

        def submit(tag):
            vf = self._volume(vol)
            bounds, parts = self._chunks(measured, "projections")
            wparts = self._weights(np.asarray(weights), bounds)
            return [
                self.client.submit(
                    _tasks.reduce_chunk, vf, vol_geom, geom[a:b], parts[i], wparts[i], center, backend,
                    None if robust is None else (robust[0], robust[1][a:b]), key=f"{tag}-{i}", retries=RETRIES,
                )
                for i, (a, b) in enumerate(bounds)
            ]

        return np.concatenate(self._run("reduce", submit), axis=0)

    def per_view(self, fn, vol, vol_geom, geom, projections, weights=None) -> np.ndarray:
        """``fn(volume, vol_geom, geom_chunk, projections_chunk, weights_chunk)`` per chunk of views, concatenated.

        ``fn`` must be a module-level function (the workers import it) that
        returns one value per view of its chunk; ``weights`` None, one
        ``(n_rows, n_cols)`` mask or one per view (an array kept for the
        run, like the projections).
        """

        vol = np.ascontiguousarray(vol, dtype=np.float32)

        def submit(tag):
            vf = self._volume(vol)
            bounds, parts = self._chunks(projections, "projections")
            wparts = [None] * len(bounds) if weights is None else self._weights(np.asarray(weights), bounds)
            return [
                self.client.submit(
                    _tasks.per_view_chunk, fn, vf, vol_geom, geom[a:b], parts[i], wparts[i], key=f"{tag}-{i}",
                    retries=RETRIES,
                )
                for i, (a, b) in enumerate(bounds)
            ]

        return np.concatenate([np.atleast_1d(r) for r in self._run("per-view", submit)], axis=0)

    # -- FDK / FBP by slabs of z -----------------------------------------------
    def _slabs(self, vol_geom, P, det_rows: int, proj_bytes: int):
        """Slabs ``(z0, z1)`` and the detector rows ``[r0, r1)`` each projects onto (all views)."""
        nz, ny, nx = vol_geom.shape
        n = self.n_threads
        mem = self._worker_memory()
        while mem > 0 and n < nz // 2 and proj_bytes / n > 2 * mem * CHUNK_MEMORY_FRACTION:
            n *= 2
        n = max(1, min(n, nz // 2))
        edges = np.linspace(0, nz, n + 1).round().astype(int)
        out = []
        for z0, z1 in zip(edges[:-1], edges[1:]):
            corners = np.array(
                [[ix, iy, iz, 1.0] for ix in (0, nx - 1) for iy in (0, ny - 1) for iz in (z0, z1 - 1)]
            )
            w = P @ corners.T  # (n_views, 3, 8)
            if np.any(w[:, 2] <= 0):
                r0, r1 = 0, det_rows
            else:
                rows = w[:, 1] / w[:, 2]
                r0 = int(np.clip(np.floor(rows.min()) - 1, 0, det_rows))
                r1 = int(np.clip(np.floor(rows.max()) + 3, 0, det_rows))
            r0 = min(r0, det_rows - 2)
            r1 = max(r1, r0 + 2)
            out.append(((int(z0), int(z1)), (r0, r1)))
        return out

    def _band(self, arr: np.ndarray, rows: tuple):
        """A band of rows ``[R0, R1) ⊇ rows`` of every view on the cluster (future or file slice), sent once."""
        e = self._lookup(self._bands, id(arr), arr)
        bands = e.payload if e is not None else []
        for (b0, b1), part in bands:
            if b0 <= rows[0] and b1 >= rows[1]:
                return (b0, b1), part
        nr = arr.shape[1]
        margin = max(2, nr // 32)  # a later call with a slightly moved geometry still fits
        b0, b1 = max(0, rows[0] - margin), min(nr, rows[1] + margin)
        src = _file_source(arr)
        if src is not None and self._sees_file(src[0], src[1] + arr.nbytes):
            part = _tasks.FileSlice(*src, views=(0, arr.shape[0]), rows=(b0, b1))
            self.stats["file_bytes"] += arr[:, b0:b1].nbytes
        else:
            block = np.ascontiguousarray(arr[:, b0:b1], dtype=np.float32)
            part = self._scatter(block)
            self.stats["sent_bytes"] += block.nbytes
            self.stats["projection_sends"] += 1
        bands = bands + [((b0, b1), part)]
        self._store(self._bands, id(arr), arr, bands, keep=2)
        return (b0, b1), part

    def reconstruct(self, arr, vol_geom, geom, weights, *, filter, cutoff, out, views_per_block, padding="zero"):
        """FDK/FBP (``pdvc.recon._fbp._reconstruct``) by slabs of z, each from its band of detector rows."""
        from ..geometry import VolumeGeometry
        from ..recon._fbp import _reconstruct, _w2_min, projection_matrices

        arr = np.asarray(arr)
        if arr.dtype != np.float32 or not arr.flags.c_contiguous:
            arr = np.ascontiguousarray(arr, dtype=np.float32)
        cone = geom.kind == "cone"
        P, _, _ = projection_matrices(vol_geom, geom, center=weights.center if cone else None)
        if cone and np.any(_w2_min(P, vol_geom) <= 0):  # voxels behind the source: the local path says so
            from ._scheduler import use_scheduler

            with use_scheduler("threads"):
                return _reconstruct(
                    arr, vol_geom, geom, weights, filter=filter, cutoff=cutoff, out=out, views_per_block=views_per_block,
                    padding=padding,
                )
        nz, ny, nx = vol_geom.shape
        nr, nc = geom.det_shape
        slabs = self._slabs(vol_geom, P, nr, arr.nbytes)
        sz = vol_geom.voxel_size[0]
        ox, oy, oz = vol_geom.offset

        def submit(tag):
            futs = []
            for i, ((z0, z1), rows) in enumerate(slabs):
                (b0, b1), part = self._band(arr, rows)
                slab_vg = VolumeGeometry(
                    (z1 - z0, ny, nx), vol_geom.voxel_size, (ox, oy, oz + ((z0 + z1 - 1) / 2 - (nz - 1) / 2) * sz)
                )
                band_geom = geom.cropped((b0, b1), (0, nc))
                futs.append(
                    self.client.submit(
                        _tasks.reconstruct_slab, part, slab_vg, band_geom, weights, filter, cutoff, views_per_block, padding,
                        key=f"{tag}-{i}", retries=RETRIES,
                    )
                )
            return futs

        parts = self._run("fdk", submit)
        if out is None:
            out = np.empty(vol_geom.shape, np.float32)
        for ((z0, z1), _), part in zip(slabs, parts):
            out[z0:z1] = part
        return out


def _futures_in(payload) -> list:
    """The Dask futures in a cache payload (a future, lists and tuples of them, file slices)."""
    if hasattr(payload, "key") and hasattr(payload, "status"):
        return [payload]
    if isinstance(payload, (list, tuple)):
        out = []
        for p in payload:
            out.extend(_futures_in(p))
        return out
    return []
