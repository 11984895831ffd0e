"""Reading projection data: TIFF folders and stacks, HDF5 (Data Exchange, NXtomo), ``.npy``.

Every reader returns one :class:`RawScan` (:func:`read_projections`), or a
:class:`ProjectionSource` that reads the views a chunk at a time
(:func:`open_projections`, for scans too large for memory as float32;
:mod:`pdvc.io._chunked` normalises and bins them): the projections as float32
``(n_views, n_rows, n_cols)`` (``DESIGN.md`` §1), the flat and dark frames
when there are any, the rotation angles in **radians** and a few facts about
where it all came from. Nothing is normalised here; that is
:func:`pdvc.io.normalize`'s job.

Units of angles
---------------
Angles are in degrees wherever a person or a file format writes them and in
radians in the returned object:

* ``angles=`` given to :func:`read_projections` (array or text file, one
  value per line) are **degrees**;
* Data Exchange ``exchange/theta`` is in degrees (the spec, and the
  ``units`` attribute written by dxchange); a ``units`` attribute that says
  radians is honoured;
* NeXus NXtomo ``sample/rotation_angle`` is an ``NX_ANGLE`` with a
  ``units`` attribute; degrees when the attribute is missing.

Flat positions
--------------
``RawScan.flat_positions`` says *when* each flat was taken, in view units
on the acquisition time line: ``-0.5`` for a flat taken before the first
projection, ``n_views - 0.5`` after the last one, ``k - 0.5`` between
projections ``k - 1`` and ``k``. NXtomo files give it through the order of
``image_key``; for other formats it is unknown (``None``) unless passed as
``flat_positions=``.

What the values are
-------------------
``RawScan.kind`` says what the numbers are: ``"counts"`` (detector counts:
:func:`pdvc.io.normalize` takes ``-log((I - D) / (F - D))`` and needs flats),
``"transmission"`` (flat-field-corrected intensities ``I/I0``: ``-log`` is
taken, no flats needed) or ``"line_integrals"`` (used as they are). With
``is_raw=None`` (``"auto"``) the reader decides: counts when there are flats,
when the file says so or when the values are integers; otherwise
:func:`classify_values` looks at the values (robust percentiles and the most
common level, never min/max: dead pixels and zingers exist). The decision and
its reason are logged and kept in ``metadata["is_raw_reason"]``.

Bad pixels
----------
``bad_pixels=`` (a detector-shaped boolean or 0/1 image, or a TIFF/.npy file
holding one) and ``dead_columns=`` mark detector pixels whose values are not
to be trusted (NaN, Inf, stuck); before any check they are replaced in the
projections, flats and darks by linear interpolation along their row from the
nearest good pixels (:func:`pdvc.io.fill_bad_pixels`). NaN/Inf anywhere else
is an error that names the views, pixels, and the dead rows/columns they form.
"""

from __future__ import annotations

import glob
import logging
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputTypeError, PdvcError, ShapeError

__all__ = [
    "RawScan",
    "read_projections",
    "ProjectionSource",
    "open_projections",
    "sample_view_indices",
    "classify_values",
    "DataError",
    "InputFileError",
    "FormatError",
]

log = logging.getLogger("pdvc.io")

_FORMATS = ("tiff-folder", "tiff", "dxchange", "nxtomo", "npy")
_SCAN_FORMATS = _FORMATS + ("memory",)  # "memory": built in code, not read from a file
_TIFF_EXTS = (".tif", ".tiff")
_HDF5_EXTS = (".h5", ".hdf5", ".hdf", ".he5", ".nxs", ".nx", ".nx5", ".cxi")
_GLOB_MAGIC = re.compile(r"[*?\[]")

# NXtomo image_key values (NXtomo application definition).
_KEY_PROJECTION, _KEY_FLAT, _KEY_DARK, _KEY_INVALID = 0, 1, 2, 3
# ``image_key_control`` (ESRF nxtomo) also uses -1 for alignment frames.
_KEY_ALIGNMENT = -1

_KINDS = ("counts", "transmission", "line_integrals")
_KIND_WORDS = {"counts": "raw counts", "transmission": "transmission (I/I0)", "line_integrals": "line integrals"}

_DEGREE_UNITS = {"deg", "degree", "degrees", "°"}
_RADIAN_UNITS = {"rad", "radian", "radians"}


class DataError(PdvcError, ValueError):
    """Data that cannot be used as read: NaN/Inf, non-positive flats, inconsistent counts."""


class InputFileError(PdvcError, FileNotFoundError):
    """An input file or folder that is missing or cannot be read."""


class FormatError(PdvcError, ValueError):
    """A file whose format is not supported or not recognised, or an option that does not apply to it."""


# --------------------------------------------------------------------------- RawScan


def _first_bad(arr: np.ndarray) -> tuple[int, int]:
    """Number of non-finite values and the index (along axis 0) of the first one."""
    bad = ~np.isfinite(arr)
    n_bad = int(np.count_nonzero(bad))
    first = int(np.argmax(bad.reshape(bad.shape[0], -1).any(axis=1))) if n_bad else -1
    return n_bad, first


def _listed(values, n_max: int = 8) -> str:
    vals = [str(int(v)) for v in values]
    return ", ".join(vals[:n_max]) + (f", ... ({len(vals)} in all)" if len(vals) > n_max else "")


class _NonfiniteTally:
    """NaN/Inf of a ``(n, n_rows, n_cols)`` stack, counted block by block (views in order).

    :func:`_nonfinite_error` is one block; the chunked reader adds its chunks
    one after the other and gets the same message as for the whole stack.
    """

    def __init__(self, det_shape: tuple[int, int]):
        nr, nc = det_shape
        self.n = 0
        self.n_bad = 0
        self.frames: list[np.ndarray] = []
        self.pixels: list[str] = []
        self.per_col = np.zeros(nc, dtype=np.int64)
        self.per_row = np.zeros(nr, dtype=np.int64)
        self.always = np.ones((nr, nc), dtype=bool)

    def add(self, block: np.ndarray) -> int:
        """Count the non-finite values of the next ``block`` of frames; returns how many it held."""
        bad = ~np.isfinite(block)
        n_bad = int(np.count_nonzero(bad))
        start = self.n
        self.n += int(block.shape[0])
        if not n_bad:
            self.always[...] = False
            return 0
        self.n_bad += n_bad
        frames = np.flatnonzero(bad.reshape(bad.shape[0], -1).any(axis=1))
        self.frames.append(frames + start)
        for k in frames:
            if len(self.pixels) >= 5:
                break
            for r, c in np.argwhere(bad[k])[: 5 - len(self.pixels)]:
                self.pixels.append(f"({int(k) + start}, {int(r)}, {int(c)})")
        self.per_col += bad.sum(axis=(0, 1))
        self.per_row += bad.sum(axis=(0, 2))
        self.always &= bad.all(axis=0)
        return n_bad

    def error(self, name: str, unit: str) -> DataError | None:
        """The DataError for what was counted (see :func:`_nonfinite_error`), or None when all finite."""
        if not self.n_bad:
            return None
        n, (nr, nc) = self.n, self.always.shape
        frames = np.concatenate(self.frames)
        per_col, per_row = self.per_col, self.per_row
        dead_cols = np.flatnonzero(per_col >= 0.5 * n * nr)
        dead_rows = np.flatnonzero(per_row >= 0.5 * n * nc) if nc > 1 else np.array([], dtype=int)
        always = int(np.count_nonzero(self.always))
        parts = [
            f"{name} must be finite; it holds {self.n_bad} NaN/Inf values, the first in {unit} {int(frames[0])}",
            f"{len(frames)} of {n} {unit}s hold some ({_listed(frames)})",
            f"first at ({unit}, row, col) {', '.join(self.pixels)}",
        ]
        if dead_cols.size:
            counts = ", ".join(f"{int(c)} ({int(per_col[c])} of {n * nr})" for c in dead_cols[:8])
            parts.append(f"dead columns (non-finite in at least half of their pixels over all {unit}s): {counts}"
                         + (f", ... ({dead_cols.size} in all)" if dead_cols.size > 8 else ""))
        if dead_rows.size:
            counts = ", ".join(f"{int(r)} ({int(per_row[r])} of {n * nc})" for r in dead_rows[:8])
            parts.append(f"dead rows: {counts}" + (f", ... ({dead_rows.size} in all)" if dead_rows.size > 8 else ""))
        if always:
            parts.append(f"{always} detector pixels are non-finite in every {unit}")
        hint = (
            "mark the bad pixels (read_projections(bad_pixels=..., dead_columns=...), or in the config "
            '[preprocess] mask = "mask.npy" (a detector-shaped 0/1 image, 1 = bad)'
            + (f" or dead_columns = [{_listed(dead_cols, 20)}]" if dead_cols.size else " or dead_columns = [...]")
            + "): they are then interpolated along the row from good neighbours"
        )
        return DataError("; ".join(parts) + ". To use the rest, " + hint)


def _nonfinite_error(arr: np.ndarray, name: str, unit: str) -> DataError | None:
    """A DataError naming where the NaN/Inf of a ``(n, n_rows, n_cols)`` stack are, or None when all finite.

    The message keeps the historical head (``"<name> must be finite; it holds N NaN/Inf values, the first
    in <unit> K"``) and adds the frames, the first pixels ``(frame, row, col)``, the dead columns and rows
    (non-finite in at least half of their pixels over all frames) and how to mask them.
    """
    if 0 in arr.strides and arr.size:  # a broadcast (e.g. flats_from_columns): check its distinct values only
        arr = arr[tuple(slice(0, 1) if st == 0 else slice(None) for st in arr.strides)]
    tally = _NonfiniteTally(arr.shape[1:])
    tally.add(arr)
    return tally.error(name, unit)


def _check_frames(arr, name: str, det_shape: tuple[int, int], what: str) -> np.ndarray:
    arr = np.asarray(arr, dtype=np.float32)
    if arr.ndim != 3 or arr.shape[0] < 1 or tuple(arr.shape[1:]) != det_shape:
        raise ShapeError(
            f"{name} must have shape (n_{what}, {det_shape[0]}, {det_shape[1]}) with n_{what} >= 1 "
            f"to match the detector of data, got {arr.shape}"
        )
    err = _nonfinite_error(arr, name, "frame")
    if err is not None:
        raise err
    return arr


# --------------------------------------------------------------------------- what the values are


_SAMPLE_VIEWS = 64  # views that classify_values looks at (evenly spaced)


def _strided(n: int, m: int) -> np.ndarray:
    """``min(n, m)`` indices evenly spaced over ``0 .. n - 1`` (rounded, unique)."""
    return np.unique(np.linspace(0, n - 1, min(n, m)).round().astype(np.int64))


def sample_view_indices(n_views: int) -> np.ndarray:
    """The views :func:`classify_values` looks at in a stack of ``n_views``: it gives the same answer
    on those views alone (what the chunked reader reads instead of the whole scan)."""
    return _strided(int(n_views), _SAMPLE_VIEWS)


def _value_sample(arr: np.ndarray, max_views: int = _SAMPLE_VIEWS, max_rows: int = 64, max_cols: int = 512) -> np.ndarray:
    """Finite values of an evenly strided subset of a (n_views, n_rows, n_cols) stack, float64, flat."""
    a = np.asarray(arr)
    if a.ndim == 3:
        idx = [_strided(n, m) for n, m in zip(a.shape, (max_views, max_rows, max_cols))]
        a = a[np.ix_(*idx)]
    s = np.asarray(a, dtype=np.float64).reshape(-1)
    if s.size > 2_000_000:
        s = s[:: s.size // 2_000_000 + 1]
    return s[np.isfinite(s)]


def _most_common(s: np.ndarray, lo: float, hi: float, bins: int = 64) -> float:
    """The most common value of ``s`` within [lo, hi]: peak of a lightly smoothed histogram."""
    if not hi > lo:
        return float(lo)
    h, edges = np.histogram(s, bins=bins, range=(lo, hi))
    hs = np.convolve(h.astype(np.float64), np.array([1.0, 2.0, 3.0, 2.0, 1.0]) / 9.0, mode="same")
    m = int(np.argmax(hs))
    return float(0.5 * (edges[m] + edges[m + 1]))


# Thresholds of classify_values (see its docstring).
_COUNTS_P99 = 20.0          # a line integral of 20 is a transmission of 2e-9: nothing measures that
_TRANSMISSION_LO = -0.05    # 0.5th percentile of a transmission: >= 0 up to noise in opaque parts
_TRANSMISSION_HI = 1.15     # 99.5th percentile: the air level (<= 1) plus a few noise std


def classify_values(values) -> tuple[str, str]:
    """What a stack of projection values looks like: raw counts, transmission or line integrals.

    Parameters
    ----------
    values : array
        The projections as read, ``(n_views, n_rows, n_cols)`` (any shape is
        accepted). NaN/Inf are ignored. Large stacks are subsampled (at most
        64 views x 64 rows x 512 columns, evenly spaced).

    Returns
    -------
    kind : {"counts", "transmission", "line_integrals"}
    reason : str
        One sentence with the figures that decided.

    Notes
    -----
    Only percentiles and the most common level are used, never the minimum
    or maximum (dead pixels, zingers and clipped values exist). With ``lo``,
    ``hi`` the 0.5th and 99.5th percentiles and ``air`` the most common
    value in ``[lo, hi]`` (the peak of a 64-bin histogram; in a scan the
    rays that miss the sample are the most common level):

    * **counts**: an integer dtype, or a 99th percentile above 20 (values
      much larger than 1; a line integral of 20 is a transmission of 2e-9);
    * **transmission** (``I/I0``): ``lo >= -0.05``, ``hi <= 1.15`` (values
      in (0, ~1.05] up to noise), ``air > 0.05`` and ``air`` at the top of
      the range (``hi - air <= (hi - lo) / 4``): most of the image sits at
      one air level <= 1 and the sample is darker;
    * **line integrals** otherwise: air near 0 at the bottom of the range,
      the sample larger.

    The case it cannot tell apart is a scan without air whose projections
    are weak line integrals, all in (0, 1], with their most common value at
    the top of their range; set ``is_raw`` explicitly there.

    Examples
    --------
    >>> classify_values(np.full((2, 4, 4), 0.7))[0]          # doctest: +SKIP
    'transmission'
    """
    arr = np.asarray(values)
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise InputTypeError(f"values must be a real numeric array, got dtype {arr.dtype}")
    if np.issubdtype(arr.dtype, np.integer) or arr.dtype == np.bool_:
        return "counts", f"integer data ({arr.dtype})"
    s = _value_sample(arr)
    if s.size == 0:
        raise DataError("values hold no finite number: cannot tell what they are")
    lo, p1, med, p99, hi = (float(v) for v in np.percentile(s, [0.5, 1.0, 50.0, 99.0, 99.5]))
    if p99 > _COUNTS_P99:
        return "counts", (
            f"values much larger than 1 (median {med:.4g}, 99th percentile {p99:.4g}): detector counts"
        )
    air = _most_common(s, lo, hi)
    span = f"0.5-99.5th percentiles {lo:.3g} .. {hi:.3g}, most common level {air:.3g}"
    if lo >= _TRANSMISSION_LO and hi <= _TRANSMISSION_HI and air > 0.05 and (hi - air) <= 0.25 * (hi - lo):
        return "transmission", (
            f"values within (0, ~1.05] ({span}, at the top: the air, with the sample darker): "
            f"flat-field-corrected transmission I/I0"
        )
    where = "at the bottom" if (air - lo) <= 0.25 * max(hi - lo, 1e-12) else "not at the bottom"
    extra = "" if abs(air) <= 0.05 else f"; the most common level {air:.3g} is not near 0: check the air level"
    return "line_integrals", f"values not those of counts or transmission ({span}, {where}){extra}: line integrals"


def _check_parts(det_shape, n_views, flats, darks, angles, flat_positions):
    """Flats, darks (float32, finite, detector-shaped), angles (float64, one per view) and flat positions, checked."""
    if flats is not None:
        flats = _check_frames(flats, "flats", det_shape, "flats")
    if darks is not None:
        darks = _check_frames(darks, "darks", det_shape, "darks")
    if angles is not None:
        ang = np.asarray(angles, dtype=np.float64)
        if ang.shape != (n_views,):
            raise ShapeError(
                f"angles must have shape (n_views,) = ({n_views},), one per view of data, got {ang.shape}"
            )
        if not np.all(np.isfinite(ang)):
            raise DataError(f"angles must be finite; {int(np.sum(~np.isfinite(ang)))} are NaN/Inf")
        angles = ang
    if flat_positions is not None:
        if flats is None:
            raise ShapeError("flat_positions were given but there are no flats")
        pos = np.asarray(flat_positions, dtype=np.float64)
        if pos.shape != (flats.shape[0],):
            raise ShapeError(
                f"flat_positions must have shape (n_flats,) = ({flats.shape[0]},), "
                f"one per flat, got {pos.shape}"
            )
        if not np.all(np.isfinite(pos)):
            raise DataError("flat_positions must be finite")
        flat_positions = pos
    return flats, darks, angles, flat_positions


@dataclass(frozen=True, eq=False)
class RawScan:
    """Projections as read from disk, before any normalisation.

    Parameters
    ----------
    data : (n_views, n_rows, n_cols) float32 array
        Projections as ``kind`` says: raw detector counts, transmission
        ``I/I0`` or line integrals. Finite.
    flats : (n_flats, n_rows, n_cols) float32 array or None
        Open-beam (flat-field, "white") frames, counts.
    darks : (n_darks, n_rows, n_cols) float32 array or None
        Dark frames (beam off), counts.
    angles : (n_views,) float64 array or None
        Rotation angle of each view, **radians**.
    flat_positions : (n_flats,) float64 array or None
        When each flat was taken, in view units on the acquisition time line
        (``-0.5`` before the first view, ``n_views - 0.5`` after the last);
        ``None`` when unknown.
    is_raw : bool
        True when :func:`pdvc.io.normalize` must still take the logarithm
        (counts or transmission), False for data that are already line
        integrals. Default: from ``kind``, else True.
    source : str
        The path that was read (or a description for in-memory data).
    format : str
        One of ``"tiff-folder"``, ``"tiff"``, ``"dxchange"``, ``"nxtomo"``,
        ``"npy"``, or ``"memory"`` for a scan built in code.
    metadata : dict
        What else was learnt while reading (file list, dtypes, units, ...).
    kind : {"counts", "transmission", "line_integrals"}
        What the values are. Default: ``"counts"`` when ``is_raw`` (or
        ``is_raw`` not given), else ``"line_integrals"``. A ``kind`` given
        with an ``is_raw`` that contradicts it (``is_raw`` must be False
        exactly for line integrals) is an error.

    Notes
    -----
    The arrays are converted to float32 / float64 without a copy when they
    already have that type; nothing in pdvc writes to them. Use
    :func:`dataclasses.replace` to change a field: the checks run again.
    """

    data: np.ndarray
    flats: np.ndarray | None = None
    darks: np.ndarray | None = None
    angles: np.ndarray | None = None
    flat_positions: np.ndarray | None = None
    is_raw: bool | None = None
    source: str = "<memory>"
    format: str = "memory"
    metadata: dict = field(default_factory=dict)
    kind: str | None = None

    def __post_init__(self) -> None:
        data = np.asarray(self.data)
        if not np.issubdtype(data.dtype, np.number) or np.issubdtype(data.dtype, np.complexfloating):
            raise InputTypeError(f"data must be a real numeric array, got dtype {data.dtype}")
        data = data.astype(np.float32, copy=False)
        if data.ndim != 3 or min(data.shape) < 1:
            raise ShapeError(
                f"data must have shape (n_views, n_rows, n_cols) with every size >= 1, got {data.shape}"
            )
        err = _nonfinite_error(data, "data", "view")
        if err is not None:
            raise err
        det_shape = (int(data.shape[1]), int(data.shape[2]))
        object.__setattr__(self, "data", data)
        parts = _check_parts(det_shape, data.shape[0], self.flats, self.darks, self.angles, self.flat_positions)
        for name, value in zip(("flats", "darks", "angles", "flat_positions"), parts):
            object.__setattr__(self, name, value)
        if self.is_raw is not None and not isinstance(self.is_raw, (bool, np.bool_)):
            raise InputTypeError(f"is_raw must be a bool, got {self.is_raw!r}")
        kind = self.kind
        if kind is None:
            kind = "line_integrals" if self.is_raw is not None and not self.is_raw else "counts"
        elif kind not in _KINDS:
            raise InputTypeError(f"kind must be one of {_KINDS}, got {kind!r}")
        needs_log = kind != "line_integrals"
        if self.is_raw is not None and bool(self.is_raw) != needs_log:
            raise InputTypeError(
                f"is_raw={bool(self.is_raw)} contradicts kind={kind!r} (is_raw is False exactly for line "
                f"integrals); give one of them, or both consistently"
            )
        object.__setattr__(self, "is_raw", needs_log)
        object.__setattr__(self, "kind", kind)
        if self.format not in _SCAN_FORMATS:
            raise FormatError(f"format must be one of {_SCAN_FORMATS}, got {self.format!r}")

    @property
    def n_views(self) -> int:
        """Number of projections."""
        return int(self.data.shape[0])

    @property
    def det_shape(self) -> tuple[int, int]:
        """Detector shape ``(n_rows, n_cols)``."""
        return int(self.data.shape[1]), int(self.data.shape[2])


# --------------------------------------------------------------------------- small helpers


def _natural_key(path: Path):
    """Sort key that orders ``proj_2`` before ``proj_10`` (digits compare as numbers)."""
    parts = re.split(r"(\d+)", path.name)
    return [int(p) if i % 2 else p.lower() for i, p in enumerate(parts)]


def _decode(value) -> str:
    """An HDF5 string (bytes, str, 0-d or 1-element array) as ``str``."""
    if isinstance(value, np.ndarray):
        value = value.reshape(-1)[0] if value.size else ""
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    return str(value)


def _nx_class(obj) -> str:
    return _decode(obj.attrs.get("NX_class", ""))


def _angles_to_radians(values: np.ndarray, units: str | None, name: str) -> tuple[np.ndarray, str]:
    """Convert angles to radians given a units string (``None`` = degrees)."""
    u = (units or "").strip().lower()
    if u in ("",) or u in _DEGREE_UNITS:
        return np.deg2rad(values), "degrees" if u else "degrees (no units attribute)"
    if u in _RADIAN_UNITS:
        return np.asarray(values, np.float64), "radians"
    raise DataError(f"{name} has units {units!r}; expected degrees or radians")


def _check_path_exists(path: Path, name: str) -> None:
    if not path.exists():
        what = name if name.endswith("path") else f"{name} path"  # never "path path"
        raise InputFileError(f"{what} {str(path)!r} does not exist")


def _read_tiff_file(path: Path, name: str) -> np.ndarray:
    """One TIFF file as an array: its first series, or all its 2D series stacked."""
    import tifffile

    try:
        with tifffile.TiffFile(path) as tf:
            series = tf.series
            if len(series) > 1:
                shapes = {tuple(s.shape) for s in series}
                if len(shapes) == 1 and len(next(iter(shapes))) == 2:
                    return np.stack([s.asarray() for s in series])
                raise ShapeError(
                    f"{name} file {str(path)!r} holds {len(series)} image series of shapes "
                    f"{sorted(shapes)}; expected one stack or 2D pages of one shape"
                )
            return series[0].asarray()
    except PdvcError:
        raise
    except Exception as exc:  # tifffile raises several types for damaged files
        raise InputFileError(f"{name} file {str(path)!r} could not be read as TIFF: {exc}") from exc


def _list_tiffs(folder: Path, pattern: str | None, name: str) -> list[Path]:
    if pattern is None:
        files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _TIFF_EXTS]
        where = f"folder {str(folder)!r}"
    else:
        files = [Path(p) for p in glob.glob(str(folder / pattern)) if Path(p).is_file()]
        where = f"pattern {str(folder / pattern)!r}"
    if not files:
        raise InputFileError(f"{name}: no TIFF files (*.tif, *.tiff) found in {where}")
    return sorted(files, key=_natural_key)


class _Views:
    """Views of a stack read on demand: ``shape`` ``(n_views, n_rows, n_cols)``, the file ``dtype``, and
    ``take(indices)`` -> float32 ``(len(indices), n_rows, n_cols)``. Subclasses read one format."""

    shape: tuple
    dtype: np.dtype

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def take(self, indices) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError


def _runs(indices: np.ndarray):
    """``(position in indices, first, stop)`` of each run of consecutive indices."""
    i = 0
    while i < indices.size:
        j = i + 1
        while j < indices.size and indices[j] == indices[j - 1] + 1:
            j += 1
        yield i, int(indices[i]), int(indices[j - 1]) + 1
        i = j


class _ArrayViews(_Views):
    """Views of an array (in memory or ``np.load(mmap_mode="r")``): contiguous runs are sliced."""

    def __init__(self, arr: np.ndarray):
        self.arr, self.shape, self.dtype = arr, tuple(arr.shape), arr.dtype

    def take(self, indices) -> np.ndarray:
        idx = np.asarray(indices, dtype=np.int64)
        out = np.empty((idx.size,) + self.shape[1:], dtype=np.float32)
        for i, a, b in _runs(idx):
            out[i : i + b - a] = self.arr[a:b]
        return out


class _TiffFolderViews(_Views):
    """One 2D TIFF file per view, read file by file."""

    def __init__(self, files: list, name: str):
        self.files, self.name = files, name
        first = _read_tiff_file(files[0], name)
        if first.ndim != 2:
            raise ShapeError(
                f"{name}: each file of a TIFF folder must hold one 2D image, but {files[0].name!r} "
                f"has shape {first.shape}; pass the file path itself to read a multi-page stack"
            )
        self.shape, self.dtype = (len(files),) + first.shape, first.dtype

    def take(self, indices) -> np.ndarray:
        idx = np.asarray(indices, dtype=np.int64)
        out = np.empty((idx.size,) + self.shape[1:], dtype=np.float32)
        for j, k in enumerate(idx):
            f = self.files[k]
            img = _read_tiff_file(f, self.name)
            if img.shape != self.shape[1:]:
                raise ShapeError(
                    f"{self.name}: every image of a TIFF folder must have the shape of the first "
                    f"({self.files[0].name!r}: {self.shape[1:]}); {f.name!r} has shape {img.shape}"
                )
            out[j] = img
        return out


class _TiffPageViews(_Views):
    """A multi-page TIFF whose pages are the views, read page by page."""

    def __init__(self, path: Path, n_pages: int, page_shape: tuple, dtype, name: str):
        self.path, self.name = path, name
        self.shape, self.dtype = (n_pages,) + tuple(page_shape), np.dtype(dtype)

    def take(self, indices) -> np.ndarray:
        import tifffile

        idx = np.asarray(indices, dtype=np.int64)
        out = np.empty((idx.size,) + self.shape[1:], dtype=np.float32)
        try:
            with tifffile.TiffFile(self.path) as tf:
                for j, k in enumerate(idx):
                    out[j] = tf.pages[int(k)].asarray()
        except Exception as exc:
            raise InputFileError(f"{self.name} file {str(self.path)!r} could not be read as TIFF: {exc}") from exc
        return out


class _H5Views(_Views):
    """Frames of an HDF5 dataset (the projections among them), read by slices of views."""

    def __init__(self, path: Path, dataset: str, frames: np.ndarray, frame_shape: tuple, dtype):
        self.path, self.dataset, self.frames = path, dataset, np.asarray(frames, dtype=np.int64)
        self.shape, self.dtype = (self.frames.size,) + tuple(frame_shape), np.dtype(dtype)

    def take(self, indices) -> np.ndarray:
        import h5py

        idx = self.frames[np.asarray(indices, dtype=np.int64)]
        out = np.empty((idx.size,) + self.shape[1:], dtype=np.float32)
        with h5py.File(self.path, "r") as h5:
            ds = h5[self.dataset]
            for i, a, b in _runs(idx):
                out[i : i + b - a] = ds[a:b]
        return out


def _tiff_pages(path: Path, name: str) -> _TiffPageViews | None:
    """Page-by-page views of a multi-page TIFF whose pages are 2D images of one shape, else None."""
    import tifffile

    try:
        with tifffile.TiffFile(path) as tf:
            pages = tf.pages
            n = len(pages)
            first = pages[0]
            if n < 2 or len(first.shape) != 2:
                return None
            return _TiffPageViews(path, n, first.shape, first.dtype, name)
    except Exception as exc:
        raise InputFileError(f"{name} file {str(path)!r} could not be read as TIFF: {exc}") from exc


def _read_tiff_folder(folder: Path, pattern: str | None, name: str) -> tuple[np.ndarray, list[Path], np.dtype]:
    """Every TIFF of a folder (natural order) stacked (float32) along a new first axis, and the files' dtype."""
    views = _TiffFolderViews(_list_tiffs(folder, pattern, name), name)
    return views.take(np.arange(views.shape[0])), views.files, views.dtype


def _read_npy(path: Path, name: str) -> np.ndarray:
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except Exception as exc:
        raise InputFileError(f"{name} file {str(path)!r} could not be read as .npy: {exc}") from exc


def _split_glob(path_str: str) -> tuple[Path, str | None]:
    """``"dir/proj_*.tif"`` -> (``dir``, ``"proj_*.tif"``); no glob characters -> (path, None)."""
    if _GLOB_MAGIC.search(path_str):
        p = Path(path_str)
        if _GLOB_MAGIC.search(str(p.parent)):
            raise FormatError(f"only the file name may hold glob characters, got {path_str!r}")
        return p.parent, p.name
    return Path(path_str), None


def _read_array_file(value, name: str) -> tuple[np.ndarray, str]:
    """A flats/darks (or data) file or folder as a raw array, with a description of the source."""
    folder, pattern = _split_glob(os.fspath(value))
    if pattern is not None:
        _check_path_exists(folder, name)
        arr, files, _ = _read_tiff_folder(folder, pattern, name)
        return arr, f"{len(files)} TIFF files {str(folder / pattern)!r}"
    path = folder
    _check_path_exists(path, name)
    if path.is_dir():
        arr, files, _ = _read_tiff_folder(path, None, name)
        return arr, f"{len(files)} TIFF files in {str(path)!r}"
    ext = path.suffix.lower()
    if ext in _TIFF_EXTS:
        return _read_tiff_file(path, name), str(path)
    if ext == ".npy":
        return _read_npy(path, name), str(path)
    raise FormatError(
        f"{name} file {str(path)!r} must be a TIFF (.tif, .tiff), a folder of TIFFs or a .npy file, "
        f"got extension {ext or '(none)'!r}; load other files yourself and pass an array"
    )


def _frames_from(value, name: str, det_shape: tuple[int, int]) -> tuple[np.ndarray | None, str | None]:
    """User flats/darks (path or array) as a float32 ``(n, n_rows, n_cols)`` copy."""
    if value is None:
        return None, None
    if isinstance(value, (str, os.PathLike)):
        arr, desc = _read_array_file(value, name)
    else:
        arr, desc = np.asarray(value), "array"
        if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
            raise InputTypeError(f"{name} must be a path or a real numeric array, got {type(value).__name__}")
    r, c = det_shape
    if arr.ndim == 2:
        if arr.shape == det_shape:
            arr = arr[None]
        elif r == 1 and arr.shape[1] == c:
            arr = arr[:, None, :]
    if arr.ndim != 3 or tuple(arr.shape[1:]) != det_shape or arr.shape[0] < 1:
        extra = f" or (n_{name}, {c}) for a one-row detector" if r == 1 else ""
        raise ShapeError(
            f"{name} must have shape (n_{name}, {r}, {c}) or ({r}, {c}){extra} to match the detector "
            f"of data, got {arr.shape}"
        )
    return np.array(arr, dtype=np.float32, copy=True), desc


def _angles_from(value, n_views: int) -> tuple[np.ndarray | None, str | None]:
    """User angles in **degrees** (array or text file, one per line) as radians."""
    if value is None:
        return None, None
    if isinstance(value, (str, os.PathLike)):
        path = Path(value)
        _check_path_exists(path, "angles")
        try:
            deg = np.loadtxt(path, dtype=np.float64, ndmin=1)
        except Exception as exc:
            raise InputFileError(
                f"angles file {str(path)!r} could not be read as numbers, one angle in degrees per line: {exc}"
            ) from exc
        desc = f"file {str(path)!r} (degrees)"
    else:
        try:
            deg = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputTypeError(f"angles must be a path or an array of numbers (degrees), got {value!r}") from exc
        desc = "array (degrees)"
    if deg.ndim != 1:
        raise ShapeError(f"angles must be one value per view, shape ({n_views},), in degrees; got shape {deg.shape}")
    if deg.shape[0] != n_views:
        raise ShapeError(f"angles must hold one value per view: expected {n_views} angles, got {deg.shape[0]}")
    if not np.all(np.isfinite(deg)):
        raise DataError(f"angles must be finite; {int(np.sum(~np.isfinite(deg)))} of {n_views} are NaN/Inf")
    return np.deg2rad(deg), desc


def _shape_data(arr: np.ndarray, *, sinogram: bool, allow_single_2d: bool, source: str) -> np.ndarray:
    """Raw array -> ``(n_views, n_rows, n_cols)``, following ``sinogram``."""
    if arr.ndim == 3:
        return arr.transpose(1, 0, 2) if sinogram else arr
    if arr.ndim == 2:
        if sinogram:
            return arr[:, None, :]
        if allow_single_2d:
            return arr[None]
        raise ShapeError(
            f"data from {source} must be 3D (n_views, n_rows, n_cols), or 2D (n_views, n_cols) with "
            f"sinogram=True; got 2D shape {arr.shape}"
        )
    hint = "2D (n_views, n_cols)" if sinogram else "3D (n_views, n_rows, n_cols)"
    raise ShapeError(f"data from {source} must be {hint}, got {arr.ndim}D shape {arr.shape}")


# --------------------------------------------------------------------------- HDF5


def _find_nxtomo(h5) -> list[str]:
    """Paths of the NXtomo entries of a file (root children and one level below)."""
    found = []

    def is_tomo(g) -> bool:
        if _nx_class(g) == "NXtomo":
            return True
        if _nx_class(g) in ("NXentry", "NXsubentry", "") and "definition" in g:
            try:
                return _decode(g["definition"][()]).strip() == "NXtomo"
            except Exception:
                return False
        return False

    import h5py

    for name, obj in h5.items():
        if isinstance(obj, h5py.Group):
            if is_tomo(obj):
                found.append(obj.name)
                continue
            for sub in obj.values():
                if isinstance(sub, h5py.Group) and is_tomo(sub):
                    found.append(sub.name)
    return found


def _nx_get(group, candidates):
    """The first existing member among ``candidates`` (paths relative to ``group``), or None."""
    for c in candidates:
        if c in group:
            return group[c], c
    return None, None


def _read_nxtomo(h5, entry_path: str, path: Path, lazy: bool = False) -> dict:
    import h5py

    entry = h5[entry_path]
    det_paths = ["instrument/detector"]
    if "instrument" in entry:
        det_paths += [
            f"instrument/{k}"
            for k, v in entry["instrument"].items()
            if isinstance(v, h5py.Group) and _nx_class(v) == "NXdetector" and k != "detector"
        ]
    data_ds, data_at = _nx_get(entry, [f"{d}/data" for d in det_paths] + ["data/data"])
    if data_ds is None or not isinstance(data_ds, h5py.Dataset):
        raise FormatError(
            f"NXtomo entry {entry_path!r} of {str(path)!r} has no frames: expected instrument/detector/data "
            f"or data/data"
        )
    frames = data_ds if lazy else np.asarray(data_ds[()])
    if frames.ndim != 3:
        raise ShapeError(
            f"NXtomo {entry_path}/{data_at} must be 3D (n_frames, n_rows, n_cols), got shape {frames.shape}"
        )
    n_frames = frames.shape[0]
    key_ds, key_at = _nx_get(
        entry,
        [f"{d}/image_key" for d in det_paths]
        + ["data/image_key"]
        + [f"{d}/image_key_control" for d in det_paths],
    )
    meta: dict = {"hdf5_entry": entry_path, "hdf5_data": f"{entry_path}/{data_at}", "raw_dtype": str(frames.dtype)}
    if key_ds is None:
        log.warning("NXtomo %s: no image_key; every one of the %d frames is taken as a projection", path, n_frames)
        keys = np.zeros(n_frames, dtype=np.int64)
        meta["image_key"] = "absent (all frames projections)"
    else:
        keys = np.asarray(key_ds[()]).astype(np.int64).reshape(-1)
        meta["image_key"] = f"{entry_path}/{key_at}"
        if keys.shape[0] != n_frames:
            raise ShapeError(
                f"NXtomo {entry_path}/{key_at} must hold one key per frame: expected {n_frames}, got {keys.shape[0]}"
            )
        allowed = {_KEY_PROJECTION, _KEY_FLAT, _KEY_DARK, _KEY_INVALID, _KEY_ALIGNMENT}
        unknown = sorted(set(np.unique(keys).tolist()) - allowed)
        if unknown:
            raise DataError(
                f"NXtomo {entry_path}/{key_at} must hold 0 (projection), 1 (flat), 2 (dark) or 3 (invalid), "
                f"got also {unknown}"
            )
    proj = keys == _KEY_PROJECTION
    flat = keys == _KEY_FLAT
    dark = keys == _KEY_DARK
    meta["n_invalid_frames"] = int(np.sum(keys == _KEY_INVALID))
    meta["n_alignment_frames"] = int(np.sum(keys == _KEY_ALIGNMENT))
    if not np.any(proj):
        raise DataError(f"NXtomo entry {entry_path!r} of {str(path)!r} has no projection frames (image_key 0)")
    # position of each flat on the time line, in view units: -0.5 before the first projection, ...
    n_before = np.cumsum(proj) - proj  # projections acquired before each frame
    flat_positions = n_before[flat].astype(np.float64) - 0.5 if np.any(flat) else None

    angles = None
    ang_ds, ang_at = _nx_get(entry, ["sample/rotation_angle", "data/rotation_angle"])
    if ang_ds is not None:
        values = np.asarray(ang_ds[()], dtype=np.float64).reshape(-1)
        if values.shape[0] != n_frames:
            raise ShapeError(
                f"NXtomo {entry_path}/{ang_at} must hold one angle per frame: expected {n_frames}, "
                f"got {values.shape[0]}"
            )
        units = _decode(ang_ds.attrs["units"]) if "units" in ang_ds.attrs else None
        angles, units_read = _angles_to_radians(values[proj], units, f"NXtomo {entry_path}/{ang_at}")
        meta["angle_units"] = units_read
    def take(sel):  # h5py reads an increasing index list; an array takes a boolean mask
        return np.asarray(frames[np.flatnonzero(sel)]) if lazy else frames[sel]

    data = _H5Views(path, data_ds.name, np.flatnonzero(proj), frames.shape[1:], frames.dtype) if lazy else frames[proj]
    return {
        "data": data,
        "flats": take(flat) if np.any(flat) else None,
        "darks": take(dark) if np.any(dark) else None,
        "angles": angles,
        "flat_positions": flat_positions,
        "counts": True if np.any(flat) else None,
        "metadata": meta,
    }


def _read_dxchange(h5, path: Path, dataset: str | None, lazy: bool = False) -> dict:
    import h5py

    if dataset is None:
        group_path, data_name = "exchange", "data"
    elif isinstance(h5.get(dataset), h5py.Dataset):
        group_path, data_name = h5[dataset].parent.name, dataset.rsplit("/", 1)[-1]
    else:
        group_path, data_name = dataset, "data"
    if group_path not in h5 or data_name not in h5[group_path]:
        raise FormatError(
            f"{str(path)!r} has no Data Exchange projections {group_path.strip('/')}/{data_name}; "
            f"pass dataset= with the HDF5 path of the projections"
        )
    grp = h5[group_path]
    ds = grp[data_name]
    if lazy and ds.ndim == 3:
        frames = _H5Views(path, ds.name, np.arange(ds.shape[0]), ds.shape[1:], ds.dtype)
    else:
        frames = np.asarray(ds[()])
    meta: dict = {"hdf5_data": ds.name, "raw_dtype": str(frames.dtype)}
    units = _decode(ds.attrs["units"]).strip().lower() if "units" in ds.attrs else ""
    if units:
        meta["data_units"] = units
    flats = np.asarray(grp["data_white"][()]) if "data_white" in grp else None
    darks = np.asarray(grp["data_dark"][()]) if "data_dark" in grp else None
    angles = None
    if "theta" in grp:
        th = grp["theta"]
        t_units = _decode(th.attrs["units"]) if "units" in th.attrs else None
        angles, meta["angle_units"] = _angles_to_radians(
            np.asarray(th[()], dtype=np.float64).reshape(-1), t_units, f"{grp.name}/theta"
        )
    for extra in ("theta_white", "theta_dark"):
        if extra in grp:  # kept for the record; not turned into flat_positions (see module notes)
            meta[extra] = np.asarray(grp[extra][()]).tolist()
    counts = True if (units == "counts" or flats is not None) else None
    return {
        "data": frames,
        "flats": flats,
        "darks": darks,
        "angles": angles,
        "flat_positions": None,
        "counts": counts,
        "metadata": meta,
    }


def _read_hdf5(path: Path, fmt: str, dataset: str | None, lazy: bool = False) -> tuple[dict, str]:
    import h5py

    try:
        h5 = h5py.File(path, "r")
    except Exception as exc:
        raise InputFileError(f"path {str(path)!r} could not be opened as HDF5: {exc}") from exc
    with h5:
        entries = _find_nxtomo(h5)
        if dataset is not None:
            obj = h5.get(dataset)
            if obj is None:
                raise FormatError(
                    f"dataset {dataset!r} is not in {str(path)!r}; top-level members are {sorted(h5.keys())}"
                )
            if fmt == "nxtomo" or (fmt == "auto" and isinstance(obj, h5py.Group) and obj.name in entries):
                if not isinstance(obj, h5py.Group):
                    raise FormatError(f"dataset must name the NXtomo entry group with fmt='nxtomo', got {dataset!r}")
                return _read_nxtomo(h5, obj.name, path, lazy), "nxtomo"
            return _read_dxchange(h5, path, dataset, lazy), "dxchange"
        if fmt in ("auto", "nxtomo"):
            if len(entries) > 1:
                raise FormatError(
                    f"{str(path)!r} holds {len(entries)} NXtomo entries {entries}; choose one with dataset="
                )
            if len(entries) == 1:
                return _read_nxtomo(h5, entries[0], path, lazy), "nxtomo"
            if fmt == "nxtomo":
                raise FormatError(
                    f"{str(path)!r} has no NXtomo entry (an NXentry whose definition is 'NXtomo'); "
                    f"pass dataset= with the entry path"
                )
        if fmt == "dxchange" or "exchange" in h5:
            return _read_dxchange(h5, path, None, lazy), "dxchange"
        raise FormatError(
            f"{str(path)!r} is HDF5 but neither Data Exchange (exchange/data) nor NeXus NXtomo; "
            f"top-level members are {sorted(h5.keys())}; pass dataset= with the path of the projections"
        )


# --------------------------------------------------------------------------- public


def _detect_format(path_str: str) -> str:
    folder, pattern = _split_glob(path_str)
    if pattern is not None:
        return "tiff-folder"
    path = folder
    _check_path_exists(path, "path")
    if path.is_dir():
        return "tiff-folder"
    ext = path.suffix.lower()
    if ext in _TIFF_EXTS:
        return "tiff"
    if ext == ".npy":
        return "npy"
    import h5py

    if ext in _HDF5_EXTS or h5py.is_hdf5(path):
        return "hdf5"
    raise FormatError(
        f"path {str(path)!r} is not a supported projection format: expected a folder of TIFFs, a .tif/.tiff "
        f"file, a .npy file or HDF5 (Data Exchange or NXtomo); got extension {ext or '(none)'!r}"
    )


def read_projections(
    path,
    *,
    fmt: str = "auto",
    flats=None,
    darks=None,
    angles=None,
    sinogram: bool = False,
    is_raw: bool | str | None = None,
    dataset: str | None = None,
    flat_positions=None,
    bad_pixels=None,
    dead_columns=None,
) -> RawScan:
    """Read projections (and flats, darks, angles) from a folder or a file.

    Parameters
    ----------
    path : str or os.PathLike
        * a folder: every ``*.tif``/``*.tiff`` in it, in natural order
          (``proj_2`` before ``proj_10``), one 2D image per file;
        * a glob such as ``"scan/proj_*.tif"``: the matching files, natural order;
        * a ``.tif``/``.tiff`` file: a multi-page stack, or one 2D image (one view);
        * a ``.npy`` file: a 3D array (or 2D with ``sinogram=True``);
        * an HDF5 file: NeXus NXtomo (frames split by ``image_key``) or Data
          Exchange (``exchange/data``, ``data_white``, ``data_dark``, ``theta``).
    fmt : {"auto", "tiff-folder", "tiff", "dxchange", "nxtomo", "npy"}
        ``"auto"`` decides from the path: folder or glob, extension, then the
        contents of an HDF5 file (NXtomo entry first, then ``exchange``).
    flats, darks : str, os.PathLike or array, optional
        Flat (open beam) and dark frames, counts: ``(n, n_rows, n_cols)`` or
        one ``(n_rows, n_cols)`` image (for a one-row detector also
        ``(n, n_cols)``); a path is read as TIFF, TIFF folder/glob or
        ``.npy``. They replace the frames found in an HDF5 file.
    angles : str, os.PathLike or array of float, optional
        Rotation angles in **degrees**, one per view: an array or a text file
        with one value per line. They replace the angles found in the file.
        Returned in radians.
    sinogram : bool
        The array is sinogram-major: 2D ``(n_views, n_cols)`` becomes
        ``(n_views, 1, n_cols)``, 3D ``(n_rows, n_views, n_cols)`` becomes
        ``(n_views, n_rows, n_cols)``. TIFF and ``.npy`` only; flats and darks
        are always given view-major.
    is_raw : bool, "transmission" or "auto", optional
        True if the values are counts, False if already line integrals,
        ``"transmission"`` if they are flat-field-corrected intensities
        ``I/I0`` (``-log`` is taken, no flats needed). Default (None or
        ``"auto"``): inferred -- counts when the file has flats, the values
        are integers, or Data Exchange says ``units="counts"``; else what
        :func:`classify_values` makes of the values (transmission, line
        integrals or counts) -- and logged at INFO; the kind is
        ``RawScan.kind``, the reason ``metadata["is_raw_reason"]``.
    dataset : str, optional
        HDF5 only: the NXtomo entry group (when a file holds several), or the
        Data Exchange group / projection dataset path (e.g.
        ``"exchange_1/data"``; its siblings ``data_white``, ``data_dark``,
        ``theta`` are read too).
    flat_positions : array of float, optional
        When each flat was taken, in view units (``-0.5`` before the first
        view, ``n_views - 0.5`` after the last); lets
        :func:`pdvc.io.normalize` interpolate between flats taken before and
        after. Overrides positions from an NXtomo ``image_key``.
    bad_pixels : str, os.PathLike or array, optional
        Bad detector pixels: a ``(n_rows, n_cols)`` boolean or 0/1 image
        (nonzero = bad; ``(n_cols,)`` for a one-row detector), or a TIFF /
        ``.npy`` file holding one, in the detector layout of the returned
        views. They are replaced in the projections, flats and darks by
        linear interpolation along the row from the nearest good pixels
        (:func:`pdvc.io.fill_bad_pixels`) before any check, so NaN/Inf
        there are no error. ``metadata["bad_pixels"]`` counts them.
    dead_columns : sequence of int, optional
        Detector columns that are bad as a whole; added to ``bad_pixels``.

    Returns
    -------
    RawScan
        ``data`` float32 ``(n_views, n_rows, n_cols)``; angles in radians.

    Raises
    ------
    InputFileError
        A missing or unreadable file (also a ``FileNotFoundError``).
    FormatError
        An unsupported or unrecognised format, or an option that does not apply.
    ShapeError
        Wrong dimensions; flats/darks that do not match the detector; a
        number of angles that is not the number of views.
    DataError
        NaN/Inf in the data outside ``bad_pixels`` (the message names the
        views, the first pixels and the dead rows/columns they form).

    Examples
    --------
    >>> raw = read_projections("scan/", flats="flats/", darks="darks/",
    ...                        angles=np.arange(360) * 0.5)    # doctest: +SKIP
    >>> p, report = normalize(raw)                              # doctest: +SKIP
    """
    views, head = _open(
        path, fmt=fmt, flats=flats, darks=darks, angles=angles, sinogram=sinogram, is_raw=is_raw,
        dataset=dataset, flat_positions=flat_positions, bad_pixels=bad_pixels, dead_columns=dead_columns, lazy=False,
    )
    data = np.array(views, dtype=np.float32, copy=True)
    mask = head.pop("mask")
    if mask is not None:
        from ._preprocess import fill_bad_pixels

        data = fill_bad_pixels(data, mask)
    scan = RawScan(data=data, **head)
    _log_read(scan.source, scan.format, scan.n_views, scan.det_shape, scan.kind, scan.flats, scan.darks,
              scan.metadata["angles_source"])
    return scan


def _log_read(source, fmt, n_views, det_shape, kind, fl, dk, ang_desc) -> None:
    log.info(
        "read %s (%s): %d views of %d x %d, %s, %s flats, %s darks, angles %s",
        source,
        fmt,
        n_views,
        det_shape[0],
        det_shape[1],
        _KIND_WORDS[kind],
        0 if fl is None else fl.shape[0],
        0 if dk is None else dk.shape[0],
        ang_desc or "none",
    )


def _open(path, *, fmt, flats, darks, angles, sinogram, is_raw, dataset, flat_positions, bad_pixels, dead_columns,
          lazy: bool):
    """Everything :func:`read_projections` reads but the projections: ``(views, header)``.

    ``views``: the projections as read (an array, or with ``lazy`` a :class:`_Views` that reads them on
    demand where the format allows it); ``header``: the other :class:`RawScan` fields and ``mask``, the bad
    pixels to fill in the projections (None when none). Flats and darks are read and filled; the kind is
    decided (from the views :func:`sample_view_indices` names when the values must tell).
    """
    if fmt != "auto" and fmt not in _FORMATS:
        raise FormatError(f"fmt must be 'auto' or one of {_FORMATS}, got {fmt!r}")
    if not isinstance(path, (str, os.PathLike)):
        raise InputTypeError(f"path must be a str or os.PathLike, got {type(path).__name__}")
    if not isinstance(sinogram, (bool, np.bool_)):
        raise InputTypeError(f"sinogram must be a bool, got {sinogram!r}")
    if not (is_raw is None or isinstance(is_raw, (bool, np.bool_)) or (isinstance(is_raw, str) and is_raw in ("auto",) + _KINDS)):
        raise InputTypeError(
            f"is_raw must be None, \"auto\", a bool or one of {_KINDS} (\"transmission\": I/I0), got {is_raw!r}"
        )
    path_str = os.fspath(path)
    detected = _detect_format(path_str) if fmt == "auto" else fmt
    if fmt in ("dxchange", "nxtomo"):
        _check_path_exists(Path(path_str), "path")
    if dataset is not None and detected not in ("hdf5", "dxchange", "nxtomo"):
        raise FormatError(f"dataset applies to HDF5 files only, but {path_str!r} is read as {detected!r}")
    if sinogram and detected in ("hdf5", "dxchange", "nxtomo"):
        raise FormatError("sinogram=True applies to TIFF and .npy inputs only, not to HDF5 files")

    parts: dict = {"flats": None, "darks": None, "angles": None, "flat_positions": None, "counts": None}
    meta: dict = {}
    if detected in ("hdf5", "dxchange", "nxtomo"):
        hparts, out_fmt = _read_hdf5(Path(path_str), "auto" if detected == "hdf5" else detected, dataset, lazy)
        parts.update(hparts)
        meta.update(hparts["metadata"])
        raw_arr = parts["data"]
        if raw_arr.ndim != 3:
            raise ShapeError(f"data in {path_str!r} must be 3D (n_views, n_rows, n_cols), got shape {raw_arr.shape}")
    elif detected == "tiff-folder":
        folder, pattern = _split_glob(path_str)
        _check_path_exists(folder, "path")
        if not folder.is_dir():
            raise FormatError(f"fmt='tiff-folder' needs a folder or a glob, got the file {path_str!r}")
        if lazy and not sinogram:
            raw_arr = _TiffFolderViews(_list_tiffs(folder, pattern, "path"), "path")
            files, file_dtype = raw_arr.files, raw_arr.dtype
        else:
            raw_arr, files, file_dtype = _read_tiff_folder(folder, pattern, "path")
        meta.update(n_files=len(files), first_file=files[0].name, last_file=files[-1].name)
        meta["raw_dtype"] = str(file_dtype)
        # a folder of 2D images: each file is one view, or one sinogram (row) with sinogram=True
        raw_arr = _shape_data(raw_arr, sinogram=sinogram, allow_single_2d=False, source=path_str)
        out_fmt = "tiff-folder"
    elif detected == "tiff":
        p = Path(path_str)
        _check_path_exists(p, "path")
        raw_arr = (_tiff_pages(p, "path") if lazy and not sinogram else None) or _read_tiff_file(p, "path")
        meta["raw_dtype"] = str(raw_arr.dtype)
        raw_arr = _shape_data(raw_arr, sinogram=sinogram, allow_single_2d=True, source=path_str)
        out_fmt = "tiff"
    else:  # npy
        p = Path(path_str)
        _check_path_exists(p, "path")
        raw_arr = _read_npy(p, "path")
        meta["raw_dtype"] = str(raw_arr.dtype)
        raw_arr = _shape_data(raw_arr, sinogram=sinogram, allow_single_2d=False, source=path_str)
        out_fmt = "npy"
    meta.setdefault("raw_dtype", str(raw_arr.dtype))
    integer_input = np.issubdtype(np.dtype(meta["raw_dtype"]), np.integer)
    det_shape = (int(raw_arr.shape[1]), int(raw_arr.shape[2]))
    n_views = int(raw_arr.shape[0])

    fl, fl_desc = _frames_from(flats, "flats", det_shape)
    if fl is None and parts["flats"] is not None:
        fl, fl_desc = _frames_from(parts["flats"], "flats", det_shape)
        fl_desc = "file"
        positions = parts["flat_positions"]
    else:
        if fl is not None and parts["flats"] is not None:
            log.info("flats given by the caller replace the %d flats of %s", len(parts["flats"]), path_str)
        positions = None
    dk, dk_desc = _frames_from(darks, "darks", det_shape)
    if dk is None and parts["darks"] is not None:
        dk, dk_desc = _frames_from(parts["darks"], "darks", det_shape)
        dk_desc = "file"
    elif dk is not None and parts["darks"] is not None:
        log.info("darks given by the caller replace the %d darks of %s", len(parts["darks"]), path_str)

    ang, ang_desc = _angles_from(angles, n_views)
    if ang is None and parts["angles"] is not None:
        ang = parts["angles"]
        ang_desc = f"file ({meta.get('angle_units', 'degrees')})"
        if ang.shape != (n_views,):
            raise ShapeError(
                f"angles in {path_str!r} must hold one value per view: expected {n_views}, got {ang.shape[0]}"
            )
    if flat_positions is not None:
        if fl is None:
            raise ShapeError("flat_positions were given but there are no flats; pass flats= too")
        positions = np.asarray(flat_positions, dtype=np.float64)
        if positions.shape != (fl.shape[0],):
            raise ShapeError(
                f"flat_positions must hold one value per flat: expected shape ({fl.shape[0]},), got {positions.shape}"
            )

    mask = None
    if bad_pixels is not None or dead_columns is not None:
        from ._preprocess import bad_pixel_mask, fill_bad_pixels

        mask, mask_desc = bad_pixel_mask(det_shape, bad_pixels, dead_columns)
        n_masked = int(np.count_nonzero(mask))
        if not n_masked:
            mask = None
        if n_masked:
            fl = None if fl is None else fill_bad_pixels(fl, mask)
            dk = None if dk is None else fill_bad_pixels(dk, mask)
        meta["bad_pixels"] = n_masked
        meta["bad_pixels_source"] = mask_desc
        log.info("%d bad detector pixels (%s) interpolated along their rows", n_masked, mask_desc)

    if is_raw is None or (isinstance(is_raw, str) and is_raw == "auto"):
        if fl is not None:
            kind, reason = "counts", "flats present"
        elif parts["counts"]:
            kind, reason = "counts", "file says counts"
        elif integer_input:
            kind, reason = "counts", f"integer data ({meta['raw_dtype']})"
        else:
            kind, why = classify_values(_filled_views(raw_arr, sample_view_indices(n_views), mask))
            reason = f"float data without flats: {why}"
        log.info("data taken as %s (%s); pass is_raw= to override", _KIND_WORDS[kind], reason)
    else:
        if isinstance(is_raw, str):
            kind = is_raw
        else:
            kind = "counts" if is_raw else "line_integrals"
        reason = f"given (is_raw={is_raw!r})"
    meta["is_raw_reason"] = reason
    meta["data_kind"] = kind
    meta["angles_source"] = ang_desc
    meta["flats_source"] = fl_desc
    meta["darks_source"] = dk_desc

    head = dict(
        flats=fl,
        darks=dk,
        angles=ang,
        flat_positions=positions,
        source=path_str,
        format=out_fmt,
        metadata=meta,
        kind=kind,
        mask=mask,
    )
    return raw_arr, head


def _filled_views(views, indices, mask) -> np.ndarray:
    """Views ``indices`` of an array or :class:`_Views`, float32, bad pixels filled."""
    sub = views.take(indices) if isinstance(views, _Views) else np.asarray(views[np.asarray(indices)], dtype=np.float32)
    if mask is None:
        return sub
    from ._preprocess import fill_bad_pixels

    return fill_bad_pixels(sub, mask)


@dataclass(frozen=True, eq=False)
class ProjectionSource:
    """A scan opened for reading its views a chunk at a time (:func:`open_projections`).

    Everything :class:`RawScan` holds except the projections: flats and darks
    (read, bad pixels filled, checked), angles (radians), flat positions,
    ``kind``, ``source``, ``format``, ``metadata``; and ``read(start, stop)``,
    which reads views ``start .. stop - 1`` as float32 with the bad pixels
    filled. The values are not checked for NaN/Inf here (the chunked reader
    counts them chunk by chunk and raises :class:`RawScan`'s error at the end).

    Attributes
    ----------
    views : object
        The reader: TIFF files one by one, the pages of a multi-page TIFF, an
        HDF5 dataset by slices, or an array (``.npy`` memory-mapped, or data
        that had to be read whole: sinogram-major TIFF).
    mask : (n_rows, n_cols) bool array or None
        Bad pixels filled in every view read.
    """

    views: object
    flats: np.ndarray | None = None
    darks: np.ndarray | None = None
    angles: np.ndarray | None = None
    flat_positions: np.ndarray | None = None
    kind: str = "counts"
    source: str = "<memory>"
    format: str = "memory"
    metadata: dict = field(default_factory=dict)
    mask: np.ndarray | None = None

    def __post_init__(self) -> None:
        views = self.views
        if not isinstance(views, _Views):
            views = np.asarray(views) if not isinstance(views, np.ndarray) else views
            if views.ndim != 3 or min(views.shape) < 1:
                raise ShapeError(f"views must have shape (n_views, n_rows, n_cols) with every size >= 1, got {views.shape}")
            views = _ArrayViews(views)
            object.__setattr__(self, "views", views)
        if self.kind not in _KINDS:
            raise InputTypeError(f"kind must be one of {_KINDS}, got {self.kind!r}")
        parts = _check_parts(self.det_shape, self.n_views, self.flats, self.darks, self.angles, self.flat_positions)
        for name, value in zip(("flats", "darks", "angles", "flat_positions"), parts):
            object.__setattr__(self, name, value)

    @property
    def n_views(self) -> int:
        return int(self.views.shape[0])

    @property
    def det_shape(self) -> tuple[int, int]:
        return int(self.views.shape[1]), int(self.views.shape[2])

    @property
    def is_raw(self) -> bool:
        """As :attr:`RawScan.is_raw`: False exactly for line integrals."""
        return self.kind != "line_integrals"

    @property
    def raw_itemsize(self) -> int:
        """Bytes per value in the file (2 for uint16)."""
        return int(np.dtype(self.metadata.get("raw_dtype", "float32")).itemsize)

    def read_views(self, indices) -> np.ndarray:
        """Views ``indices`` (increasing), float32 ``(len(indices), n_rows, n_cols)``, bad pixels filled."""
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        if idx.size and (idx.min() < 0 or idx.max() >= self.n_views):
            raise ShapeError(f"indices must lie in 0 .. {self.n_views - 1}, got {idx.min()} .. {idx.max()}")
        return _filled_views(self.views, idx, self.mask)

    def read(self, start: int, stop: int) -> np.ndarray:
        """Views ``start .. stop - 1``, float32, bad pixels filled."""
        if not 0 <= start < stop <= self.n_views:
            raise ShapeError(f"start, stop must satisfy 0 <= start < stop <= {self.n_views}, got {start}, {stop}")
        return self.read_views(np.arange(start, stop))

    def to_raw(self) -> RawScan:
        """Every view read: the :class:`RawScan` :func:`read_projections` gives for the same arguments."""
        return RawScan(
            data=self.read(0, self.n_views), flats=self.flats, darks=self.darks, angles=self.angles,
            flat_positions=self.flat_positions, source=self.source, format=self.format, metadata=self.metadata,
            kind=self.kind,
        )


def open_projections(
    path,
    *,
    fmt: str = "auto",
    flats=None,
    darks=None,
    angles=None,
    sinogram: bool = False,
    is_raw: bool | str | None = None,
    dataset: str | None = None,
    flat_positions=None,
    bad_pixels=None,
    dead_columns=None,
) -> ProjectionSource:
    """Open projections for reading a chunk of views at a time; parameters as :func:`read_projections`.

    Reads the flats, darks, angles and what the file says about itself, and
    decides what the values are exactly as :func:`read_projections` does
    (from the views :func:`sample_view_indices` names, when the values must
    tell), but not the projections: TIFF folders are then read file by file,
    multi-page TIFFs page by page, HDF5 (NXtomo, Data Exchange) by slices of
    views, ``.npy`` through a memory map. Sinogram-major TIFFs are read whole.

    Returns
    -------
    ProjectionSource
        ``read(start, stop)`` gives views as float32 with bad pixels filled.
    """
    views, head = _open(
        path, fmt=fmt, flats=flats, darks=darks, angles=angles, sinogram=sinogram, is_raw=is_raw,
        dataset=dataset, flat_positions=flat_positions, bad_pixels=bad_pixels, dead_columns=dead_columns, lazy=True,
    )
    src = ProjectionSource(views=views, **head)
    _log_read(src.source, src.format, src.n_views, src.det_shape, src.kind, src.flats, src.darks,
              src.metadata["angles_source"])
    return src
