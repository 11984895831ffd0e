"""Atomic output files: a reader never sees a half-written file."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

import numpy as np

from ..errors import PdvcError

__all__ = [
    "atomic_path",
    "atomic_write_bytes",
    "atomic_write_npy",
    "atomic_write_text",
    "prepare_output_dir",
    "OutputExistsError",
]


class OutputExistsError(PdvcError, FileExistsError):
    """The output folder holds files and overwriting was not asked for."""


def prepare_output_dir(path, *, overwrite: bool = False) -> Path:
    """Create ``path`` (and parents); refuse a non-empty folder unless ``overwrite``."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise OutputExistsError(f"output folder {str(out)!r} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise OutputExistsError(
            f"output folder {str(out)!r} is not empty; choose another or pass --overwrite"
        )
    out.mkdir(parents=True, exist_ok=True)
    return out


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    For writers that want a file name (h5py, tifffile, matplotlib).  If the
    block raises (Ctrl-C included) the temporary file is removed and ``path``
    keeps whatever it held before.
    """
    dest = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, dest)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` via a temporary file and an atomic rename."""
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(data)
    return Path(path)


def atomic_write_text(path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_npy(path, array) -> Path:
    """Write ``array`` to ``path`` (.npy) via a temporary file and an atomic rename."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, np.asarray(array))
    return Path(path)
