"""Tabular and HDF5 outputs: ``motion.csv`` (one row per view) and ``result.h5``."""

from __future__ import annotations

import csv
import dataclasses
import numbers
from pathlib import Path
from typing import Mapping

import h5py
import numpy as np

from ..errors import InputTypeError, ShapeError
from ..io import atomic_path

__all__ = [
    "MOTION_COLUMNS",
    "write_motion_csv",
    "read_motion_csv",
    "write_result_h5",
    "read_result_h5",
]

_T = ("tx", "ty", "tz")
_R = ("rx", "ry", "rz")


def _param_columns(suffix: str) -> tuple[str, ...]:
    return tuple(f"{n}{suffix}" for n in _T) + tuple(f"{n}{suffix}_deg" for n in _R)


#: Columns of ``motion.csv``, in order.  Translations (``tx_*``, ``ty_*``,
#: ``tz_*``, ``std_t*``) are in volume units, angles and rotations in degrees,
#: SNR in dB; ``time`` is in the unit of the scan's time stamps.
MOTION_COLUMNS = (
    ("index", "angle_deg", "time")
    + _param_columns("_sample")
    + _param_columns("_lab")
    + tuple(f"std_{n}" for n in _T)
    + tuple(f"std_{n}_deg" for n in _R)
    + ("snr_before_db", "snr_after_db")
)

_STD_COLUMNS = MOTION_COLUMNS[15:21]


# --------------------------------------------------------------------------- motion.csv


def _column(name: str, a, n: int | None) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 1 or (n is not None and arr.shape[0] != n):
        raise ShapeError(f"{name} must have shape ({'n_views' if n is None else n},), got {arr.shape}")
    return arr


def _params(name: str, a, n: int) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.shape != (n, 6):
        raise ShapeError(f"{name} must have shape ({n}, 6) = (n_views, (tx, ty, tz, rx, ry, rz)), got {arr.shape}")
    out = arr.copy()
    out[:, 3:] = np.degrees(out[:, 3:])
    return out


def _fmt(v: float) -> str:
    # repr of a Python float is the shortest string that reads back to the same double
    return repr(float(v))


def write_motion_csv(
    path,
    *,
    angles_deg,
    times,
    params_sample,
    params_lab,
    std=None,
    snr_before=None,
    snr_after=None,
) -> Path:
    """Write the per-view motion table ``motion.csv`` atomically.

    Parameters
    ----------
    path : path-like
        Output file.
    angles_deg : array_like, shape (n_views,), degrees
        Nominal projection angle of each view.
    times : array_like, shape (n_views,) or None
        Time stamp of each view (the scan's unit, e.g. seconds); ``None``
        writes NaN.
    params_sample, params_lab : array_like, shape (n_views, 6)
        Pose ``(tx, ty, tz, rx, ry, rz)`` of each view in the sample and in
        the lab frame; translations in volume units, rotations in radians
        (written in degrees).
    std : array_like, shape (n_views, 6), optional
        Standard deviation of the sample-frame parameters, same units
        (rotations in radians, written in degrees); NaN when absent.
    snr_before, snr_after : array_like, shape (n_views,), dB, optional
        SNR of each view with the nominal and calibrated geometry; NaN when
        absent.

    Returns
    -------
    Path
        ``path``.

    Notes
    -----
    The columns are :data:`MOTION_COLUMNS`, always all of them, one row per
    view.  Floats are written with ``repr`` so that they read back to the
    same double.

    Examples
    --------
    >>> import numpy as np, tempfile, os
    >>> p = os.path.join(tempfile.mkdtemp(), "motion.csv")
    >>> z = np.zeros((3, 6))
    >>> _ = write_motion_csv(p, angles_deg=[0, 120, 240], times=None, params_sample=z, params_lab=z)
    >>> read_motion_csv(p)["angle_deg"]
    array([  0., 120., 240.])
    """
    ang = _column("angles_deg", angles_deg, None)
    n = ang.size
    t = np.full(n, np.nan) if times is None else _column("times", times, n)
    ps = _params("params_sample", params_sample, n)
    pl = _params("params_lab", params_lab, n)
    sd = np.full((n, 6), np.nan) if std is None else _params("std", std, n)
    sb = np.full(n, np.nan) if snr_before is None else _column("snr_before", snr_before, n)
    sa = np.full(n, np.nan) if snr_after is None else _column("snr_after", snr_after, n)
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(MOTION_COLUMNS)
            for k in range(n):
                row = [str(k), _fmt(ang[k]), _fmt(t[k])]
                row += [_fmt(v) for v in ps[k]]
                row += [_fmt(v) for v in pl[k]]
                row += [_fmt(v) for v in sd[k]]
                row += [_fmt(sb[k]), _fmt(sa[k])]
                w.writerow(row)
    return Path(path)


def read_motion_csv(path) -> dict[str, np.ndarray]:
    """Read a ``motion.csv`` (or any CSV of numbers with a header row).

    Returns
    -------
    dict of str to ndarray, each of shape (n_views,)
        One array per column, in file order; ``index`` as int64, the others
        as float64 (rotations in degrees, as written).
    """
    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.reader(fh)
        try:
            header = next(reader)
        except StopIteration:
            raise ShapeError(f"{str(path)!r} is empty; expected a header row") from None
        rows = [r for r in reader if r]
    for i, r in enumerate(rows):
        if len(r) != len(header):
            raise ShapeError(f"{str(path)!r} row {i + 2} has {len(r)} cells, the header {len(header)}")
    out: dict[str, np.ndarray] = {}
    for j, name in enumerate(header):
        cells = [r[j] for r in rows]
        if name == "index":
            out[name] = np.array([int(c) for c in cells], dtype=np.int64)
        else:
            out[name] = np.array([float(c) if c != "" else np.nan for c in cells], dtype=np.float64)
    return out


# --------------------------------------------------------------------------- result.h5

_LIST_ATTR = "__pdvc_type__"
_LEN_ATTR = "__pdvc_length__"
_RESERVED = (_LIST_ATTR, _LEN_ATTR)
_GZIP_ABOVE = 1000  # elements: compress larger arrays
_ATTR_MAX_CHARS = 32_000  # longer strings go to a string dataset (attributes are limited to 64 KiB)


def _check_key(key, where: str) -> str:
    if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
        key = str(int(key))
    if not isinstance(key, str):
        raise InputTypeError(f"keys of the result tree must be str, got {key!r} at {where or '/'}")
    if not key or "/" in key or key in (".", "..") or key in _RESERVED:
        raise InputTypeError(f"invalid key {key!r} at {where or '/'}: empty, '/', '.', '..' or reserved")
    return key


def _numeric_array(value) -> np.ndarray | None:
    """``value`` as a numeric or unicode array, or None if it is not one."""
    try:
        arr = np.asarray(value)
    except (ValueError, TypeError):  # ragged
        return None
    if arr.dtype.kind in "biufcU":
        return arr
    return None


def _write_array(group: h5py.Group, key: str, arr: np.ndarray) -> None:
    if arr.dtype.kind == "U":
        group.create_dataset(key, data=arr.astype(object), dtype=h5py.string_dtype())
        return
    kwargs = {}
    if arr.ndim and arr.size > _GZIP_ABOVE:
        kwargs = dict(compression="gzip", compression_opts=4, shuffle=True)
    group.create_dataset(key, data=arr, **kwargs)


def _write_node(group: h5py.Group, key: str, value, where: str) -> None:
    here = f"{where}/{key}"
    if value is None:
        return
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    if isinstance(value, Path):
        value = str(value)
    if isinstance(value, Mapping):
        sub = group.create_group(key)
        for k, v in value.items():
            _write_node(sub, _check_key(k, here), v, here)
        return
    if isinstance(value, str):
        if len(value) <= _ATTR_MAX_CHARS:
            group.attrs[key] = value
        else:
            group.create_dataset(key, data=value, dtype=h5py.string_dtype())
        return
    if isinstance(value, (np.ndarray, np.generic, numbers.Number)):
        arr = np.asarray(value)
        if arr.dtype.kind not in "biufcU":
            raise InputTypeError(f"{here}: arrays of dtype {arr.dtype} cannot be stored; use numbers or str")
        _write_array(group, key, arr)
        return
    if isinstance(value, (list, tuple)):
        arr = _numeric_array(value) if len(value) else None
        if arr is not None:
            _write_array(group, key, arr)
            return
        sub = group.create_group(key)
        sub.attrs[_LIST_ATTR] = "list"
        sub.attrs[_LEN_ATTR] = len(value)
        for i, v in enumerate(value):
            _write_node(sub, str(i), v, here)
        return
    raise InputTypeError(
        f"{here}: cannot store a {type(value).__name__} in HDF5; "
        "use dict, list, str, number, ndarray, dataclass or None"
    )


def write_result_h5(path, tree: Mapping) -> Path:
    """Write a nested result tree to an HDF5 file, atomically.

    Values map to HDF5 as follows:

    * dict (any mapping) or dataclass instance -> group;
    * ndarray, NumPy scalar, int/float/bool/complex -> dataset (gzip-compressed
      when it has more than 1000 elements); unicode arrays -> string datasets;
    * str -> attribute of the enclosing group (a string dataset when longer
      than 32 000 characters); ``pathlib.Path`` -> str;
    * list/tuple of numbers (or of equal-length lists of numbers, or of str)
      -> array dataset;
    * other lists (of dicts, of ragged arrays, empty) -> group with members
      ``"0"``, ``"1"``, ... read back as a list;
    * None -> skipped (read back as absent; a None inside a list reads back as
      None).

    Parameters
    ----------
    path : path-like
        Output file (replaced atomically; never left half-written).
    tree : mapping
        Keys are str (ints are converted), without ``/``.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    InputTypeError
        A key or a value that cannot be stored; nothing is written.
    """
    if not isinstance(tree, Mapping):
        raise InputTypeError(f"tree must be a mapping (dict), got {type(tree).__name__}")
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as fh:
            for k, v in tree.items():
                _write_node(fh, _check_key(k, ""), v, "")
    return Path(path)


def _read_dataset(ds: h5py.Dataset):
    if h5py.check_string_dtype(ds.dtype) is not None:
        data = ds.asstr()[()]
        if isinstance(data, np.ndarray):
            return np.array(data.tolist(), dtype=str)
        return data
    data = ds[()]
    if isinstance(data, np.generic):
        return data.item()
    return data


def _read_group(group: h5py.Group):
    if group.attrs.get(_LIST_ATTR) == "list":
        out = [None] * int(group.attrs[_LEN_ATTR])
        for k, item in group.items():
            out[int(k)] = _read_item(item)
        return out
    d: dict = {}
    for k, v in group.attrs.items():
        if k not in _RESERVED:
            d[k] = v if not isinstance(v, bytes) else v.decode("utf-8")
    for k, item in group.items():
        d[k] = _read_item(item)
    return d


def _read_item(item):
    if isinstance(item, h5py.Group):
        return _read_group(item)
    return _read_dataset(item)


def read_result_h5(path) -> dict:
    """Read a file written by :func:`write_result_h5` back into a nested dict.

    Groups become dicts (lists where they were written from lists), datasets
    NumPy arrays (0-d ones Python scalars), string attributes and string
    datasets str.  Member order is HDF5's (alphabetical), not the writer's.
    """
    with h5py.File(path, "r") as fh:
        return _read_group(fh)
