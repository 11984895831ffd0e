"""Reading, normalising and binning a large scan a chunk of views at a time (issue #11, item 3).

A 2048 x 2048 x 1440 uint16 scan is 12 GB as read and 24 GB as float32:
:func:`preprocess_chunked` never holds it whole. It reads a chunk of views
(:class:`pdvc.io._projections.ProjectionSource`: TIFF files one by one,
multi-page TIFF page by page, HDF5 by slices, ``.npy`` through a memory map;
the next chunk is read in a thread while this one is processed), fills the
bad pixels, normalises it (:class:`pdvc.io._preprocess.Normalizer`: the flat
of each view follows the flat groups on the time line of the whole scan),
crops the detector ROI and coarse-grains it
(:func:`pdvc.correlation.coarse_grain`, the function the in-memory path
uses: the Gaussian is 2-D per view, so chunks give what the whole gives)
into a preallocated binned float32 array. Peak memory is about two raw
chunks and their float32 intermediates plus the binned array.

What needs the whole scan is accumulated chunk by chunk, with the same
result as the in-memory path up to float rounding:

* NaN/Inf: counted per chunk (the error names views and pixels as
  :class:`pdvc.io.RawScan` does), raised after the pass;
* the clipping of :func:`pdvc.io.normalize`: counted per chunk;
* the air level: :func:`pdvc.io.estimate_air` only looks at a few detector
  rows (:func:`pdvc.io._preprocess.air_rows`); those rows of every view are
  kept and the estimate is made from them after the pass. With
  ``[preprocess] air = "auto"`` the fitted background ``o_k + P(c)`` is then
  subtracted from the *binned* projections, binned the same way (binning is
  linear); with a beam-hardening polynomial as well (not linear) a second
  pass reads the scan again and subtracts it before the polynomial;
* the beam-hardening check (the polynomial must increase over the range of
  the line integrals): made on the range of the views read so far, at every
  chunk;
* the noise variance from the counts: the mean of the per-pixel Poisson
  variance, summed chunk by chunk;
* open-beam columns as flats (``[data] open_beam_columns``): their mean is
  read in a first pass (the flats of all views are needed before any view
  is normalised when they are averaged).

The value classification (counts, transmission or line integrals) looks at
64 evenly spaced views in both paths (:func:`classify_values` subsamples).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..errors import ShapeError
from ..geometry import VectorGeometry
from ._preprocess import (
    AirEstimate,
    Normalizer,
    PreprocessReport,
    _apply_bh,
    _bh_coefficients,
    _check_bh,
    air_rows,
    estimate_air,
    open_beam_columns,
    open_beam_means,
    roi_ranges,
    subtract_background,
)
from ._projections import DataError, ProjectionSource, _NonfiniteTally

__all__ = ["ChunkedResult", "preprocess_chunked", "DEFAULT_MEMORY_BUDGET", "DEFAULT_CHUNK_BYTES", "chunk_views"]

log = logging.getLogger("pdvc.io")

DEFAULT_MEMORY_BUDGET = 2 * 2**30
"""Bytes: a scan whose float32 projections (full detector) would exceed this is read in chunks even without binning."""

DEFAULT_CHUNK_BYTES = 128 * 2**20
"""Bytes of float32 views per chunk (8 views of 2048 x 2048)."""

_PROGRESS_EVERY_S = 5.0
_WORKERS = 2  # chunks normalised and binned at once (plus the one being read)


@dataclass(frozen=True, eq=False)
class ChunkedResult:
    """What :func:`preprocess_chunked` made.

    Attributes
    ----------
    projections : (n_views, n_rows // s, n_cols // s) float32 array
        Line integrals of the ROI, coarse-grained at scale ``s`` (air
        subtracted when asked, beam hardening applied).
    geometry : VectorGeometry
        Their geometry (the ROI geometry binned ``s``).
    geometry_roi : VectorGeometry
        The geometry of the full-resolution ROI (what the calibrated geometry
        is written for).
    report : PreprocessReport
        The normalisation over all views (clipping counted per chunk).
    air : AirEstimate
        The air level of the full-resolution line integrals (before any subtraction).
    air_subtracted : bool
    noise_variance : float or None
        Mean per-pixel Poisson variance of the full-resolution line
        integrals (``noise_i0`` given), before binning.
    n_passes : int
        Passes over the data (1, or 2 with open-beam columns or air
        subtraction before a beam-hardening polynomial).
    chunk_views : int
    seconds : float
        Wall-clock time of the passes.
    bytes_read : int
        Bytes of projections read (file dtype), all passes.
    """

    projections: np.ndarray
    geometry: VectorGeometry
    geometry_roi: VectorGeometry
    report: PreprocessReport
    air: AirEstimate
    air_subtracted: bool
    noise_variance: float | None
    n_passes: int
    chunk_views: int
    seconds: float
    bytes_read: int

    @property
    def mb_per_s(self) -> float:
        return self.bytes_read / 1e6 / max(self.seconds, 1e-9)


def chunk_views(det_shape, chunk_bytes: int = DEFAULT_CHUNK_BYTES) -> int:
    """Views per chunk: as many float32 views of ``det_shape`` as fit in ``chunk_bytes`` (at least 1)."""
    if not (isinstance(chunk_bytes, (int, np.integer)) and chunk_bytes > 0):
        raise ShapeError(f"chunk_bytes must be a positive int, got {chunk_bytes!r}")
    return max(1, int(chunk_bytes) // (4 * int(det_shape[0]) * int(det_shape[1])))


class _Reader:
    """Chunks of a source in order, the next one read in a thread; logs progress (views, MB/s, time left)."""

    def __init__(self, src: ProjectionSource, chunk: int, what: str):
        self.src, self.chunk, self.what = src, chunk, what
        self.view_bytes = src.raw_itemsize * src.det_shape[0] * src.det_shape[1]
        self.bytes_read = 0
        self.seconds = 0.0

    def __iter__(self):
        n, c = self.src.n_views, self.chunk
        t0 = last = time.perf_counter()
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="pdvc-read") as pool:
            fut = pool.submit(self.src.read, 0, min(c, n))
            for a in range(0, n, c):
                b = min(a + c, n)
                x = fut.result()
                if b < n:
                    fut = pool.submit(self.src.read, b, min(b + c, n))
                yield a, x
                del x
                self.bytes_read += (b - a) * self.view_bytes
                now = time.perf_counter()
                if now - last >= _PROGRESS_EVERY_S or b == n:
                    last = now
                    el = now - t0
                    log.info(
                        "%s: %d/%d views (%.0f%%), %.0f MB/s, %.0f s, ~%.0f s left",
                        self.what, b, n, 100.0 * b / n, (b * self.view_bytes) / 1e6 / max(el, 1e-9), el,
                        el / b * (n - b),
                    )
        self.seconds += time.perf_counter() - t0


def _with_column_flats(src: ProjectionSource, columns: slice, chunk: int) -> tuple[ProjectionSource, float, int]:
    """The source with one flat per view from its open-beam columns (as flats_from_columns), by a first pass."""
    idx = open_beam_columns(src.det_shape[1], columns)
    per_view = np.empty((src.n_views, src.det_shape[0]), dtype=np.float32)
    tally = _NonfiniteTally(src.det_shape)
    reader = _Reader(src, chunk, "reading open-beam columns")
    for a, x in reader:
        tally.add(x)
        per_view[a : a + x.shape[0]] = open_beam_means(x, idx)
    err = tally.error("data", "view")
    if err is not None:
        raise err
    flats = np.broadcast_to(per_view[:, :, None], (src.n_views,) + src.det_shape)
    meta = dict(src.metadata)
    meta["flats_source"] = f"open-beam columns {idx.min()}..{idx.max()} ({idx.size} columns), one flat per view"
    log.info("flats_from_columns: %s", meta["flats_source"])
    out = dataclasses.replace(src, flats=flats, flat_positions=np.arange(src.n_views, dtype=np.float64), metadata=meta)
    return out, reader.seconds, reader.bytes_read


def preprocess_chunked(
    src: ProjectionSource,
    geom: VectorGeometry,
    *,
    scale: int = 1,
    roi_rows=None,
    roi_cols=None,
    flat_interpolation: str = "linear",
    clip_min: float = 1e-6,
    subtract_air: bool = False,
    beam_hardening=None,
    noise_i0: tuple[float, int] | None = None,
    open_beam: tuple[int, int] | None = None,
    chunk_bytes: int = DEFAULT_CHUNK_BYTES,
) -> ChunkedResult:
    """Line integrals of a scan, ROI-cropped and coarse-grained, read a chunk of views at a time.

    The same steps, in the same order and with the same results (to float
    rounding), as ``pdvc calibrate``'s in-memory path: fill bad pixels (done
    by ``src``), flats from open-beam columns, :func:`pdvc.io.normalize`,
    :func:`pdvc.io.estimate_air` (and :func:`pdvc.io.subtract_air`),
    :func:`pdvc.io.beam_hardening`, :func:`pdvc.io.detector_roi`,
    :func:`pdvc.correlation.coarse_grain` (module docstring).

    Parameters
    ----------
    src : ProjectionSource
        From :func:`pdvc.io._projections.open_projections`.
    geom : VectorGeometry
        The geometry of the full detector (``src.n_views`` views of ``src.det_shape``).
    scale : int, >= 1
        Coarse-graining scale (``[preprocess] bin``); 1 keeps full resolution.
    roi_rows, roi_cols : (start, stop) or slice, optional
        Detector window, as :func:`pdvc.io.detector_roi`.
    flat_interpolation, clip_min
        As :func:`pdvc.io.normalize`.
    subtract_air : bool
        Subtract the fitted air background (``[preprocess] air = "auto"``).
    beam_hardening : sequence of float, optional
        Coefficients, as :func:`pdvc.io.beam_hardening`.
    noise_i0 : (i0, n_flats), optional
        Accumulate the mean Poisson variance of the line integrals
        (:func:`pdvc.correlation.poisson_variance`).
    open_beam : (start, stop), optional
        Open-beam columns whose mean serves as each view's flat.
    chunk_bytes : int
        Float32 bytes of views per chunk (:func:`chunk_views`).

    Raises
    ------
    DataError
        NaN/Inf outside the bad pixels (after the pass), and what
        :func:`pdvc.io.normalize` and :func:`pdvc.io.beam_hardening` raise.
    ShapeError
        ``geom`` not the source's views and detector; a bad ROI.
    """
    from ..correlation import coarse_grain, poisson_variance

    if not isinstance(src, ProjectionSource):
        raise DataError(f"src must be a ProjectionSource (see open_projections), got {type(src).__name__}")
    n, det = src.n_views, src.det_shape
    if geom.n_views != n or tuple(geom.det_shape) != tuple(det):
        raise ShapeError(
            f"geom must describe the {n} views of {det} px of src, got {geom.n_views} views of {tuple(geom.det_shape)} px"
        )
    s = int(scale)
    chunk = chunk_views(det, chunk_bytes)
    t_start = time.perf_counter()
    (r0, r1), (c0, c1) = roi_ranges(det, roi_rows, roi_cols)
    geom_roi = geom.cropped((r0, r1), (c0, c1))
    bytes_read = 0
    n_passes = 1
    if open_beam is not None:
        src, _, nb = _with_column_flats(src, slice(*open_beam), chunk)
        bytes_read, n_passes = bytes_read + nb, n_passes + 1
    norm = Normalizer(src, flat_interpolation=flat_interpolation, clip_min=clip_min)
    bh = None if beam_hardening is None else _bh_coefficients(beam_hardening)
    two_pass = subtract_air and bh is not None
    rows = air_rows((n,) + tuple(det))
    air_S = np.empty((n, rows.size, det[1]), dtype=np.float32)
    out_shape = (n, (r1 - r0) // s, (c1 - c0) // s)
    if min(out_shape[1:]) < 1:
        raise ShapeError(f"scale {s} is larger than the detector {(r1 - r0, c1 - c0)}")
    out = np.empty(out_shape, dtype=np.float32)
    tally = _NonfiniteTally(det)
    lohi = [np.inf, -np.inf]

    def coarse(p, a):
        """ROI, beam hardening, coarse graining of normalised views ``a ..`` into ``out``."""
        pr = p[:, r0:r1, c0:c1]
        if bh is not None:
            pr = _apply_bh(pr, bh)
        out[a : a + p.shape[0]] = coarse_grain(pr, geom_roi[a : a + p.shape[0]], s)[0]

    def first(x, a):
        """Pass 1 on views ``a ..`` (a worker thread): normalise, keep the air rows, bin unless two passes."""
        p, clipped = norm.apply(x, a)
        noise = 0.0
        if noise_i0 is not None:
            noise = float(np.sum(poisson_variance(p, i0=noise_i0[0], n_flats=noise_i0[1]), dtype=np.float64))
        air_S[a : a + p.shape[0]] = p[:, rows, :]
        lo, hi = (float(p.min()), float(p.max())) if bh is not None else (0.0, 0.0)
        if not two_pass:
            coarse(p, a)
        return clipped, x.size, noise, lo, hi

    def second(x, a, bg):
        """Pass 2 on views ``a ..``: normalise, subtract the air, beam hardening, bin."""
        p, _ = norm.apply(x, a)
        if bg is not None:
            p = subtract_background(p, bg, a)
        lo, hi = float(p.min()), float(p.max())
        coarse(p, a)
        return [], 0, 0.0, lo, hi

    noise = [0.0, 0]

    def collect(result) -> None:
        """Results in view order: clipping, noise, the beam-hardening range so far (checked)."""
        clipped, size, nsum, lo, hi = result
        if size:
            norm.record(clipped, size)
            noise[0] += nsum
            noise[1] += size
        if bh is not None:
            lohi[0], lohi[1] = min(lohi[0], lo), max(lohi[1], hi)
            _check_bh(bh, lohi[0], lohi[1])

    # chunks are normalised and coarse-grained in worker threads (numpy and scipy.ndimage release the
    # GIL) while the next chunk is read; results are collected in view order
    workers = ThreadPoolExecutor(max_workers=_WORKERS, thread_name_prefix="pdvc-chunk")
    pending: list = []

    def run(pass_reader, fn, *extra) -> None:
        for a, x in pass_reader:
            if fn is first and (tally.add(x) or tally.n_bad):  # NaN/Inf: count them all for the message
                continue
            while len(pending) >= _WORKERS:  # memory: _WORKERS chunks in work, one being read
                collect(pending.pop(0).result())
            pending.append(workers.submit(fn, x, a, *extra))
            del x
        while pending:
            collect(pending.pop(0).result())

    what = f"reading {src.source}"
    try:
        reader = _Reader(src, chunk, what + (" (pass 1 of 2)" if two_pass else ""))
        run(reader, first)
        bytes_read += reader.bytes_read
        err = tally.error("data", "view")
        if err is not None:
            raise err
        report = norm.report()
        air = estimate_air(air_S)
        air_subtracted = bool(subtract_air and air.found)
        if two_pass:
            n_passes += 1
            reader = _Reader(src, chunk, what + " (pass 2 of 2: air subtracted before beam hardening)")
            run(reader, second, air.background() if air_subtracted else None)
            bytes_read += reader.bytes_read
    finally:
        for f in pending:
            f.cancel()
        workers.shutdown(wait=True, cancel_futures=True)
    if air_subtracted and not two_pass:  # binning is linear: subtract the binned background of each view
        bg = air.background()[:, c0:c1].astype(np.float32)
        band = np.broadcast_to(bg[:, None, :], (n, s, c1 - c0))
        gb = VectorGeometry(geom_roi.vectors, (s, c1 - c0), geom_roi.kind)
        out -= coarse_grain(band, gb, s)[0]
    if air_subtracted:
        log.info("subtract_air: %s", air.summary())
    geom_binned = geom_roi if s == 1 else geom_roi.binned(s)
    if tuple(geom_binned.det_shape) != out.shape[1:]:  # pragma: no cover - coarse_grain and binned agree
        raise ShapeError(f"binned geometry {geom_binned.det_shape} does not match the binned views {out.shape[1:]}")
    return ChunkedResult(
        projections=out,
        geometry=geom_binned,
        geometry_roi=geom_roi,
        report=report,
        air=air,
        air_subtracted=air_subtracted,
        noise_variance=None if noise_i0 is None else noise[0] / max(noise[1], 1),
        n_passes=n_passes,
        chunk_views=chunk,
        seconds=time.perf_counter() - t_start,
        bytes_read=bytes_read,
    )
