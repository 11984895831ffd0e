"""Atomic output files: a reader never sees a half-written file."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from ..errors import PdvcError

__all__ = ["atomic_write_npy", "prepare_output_dir", "OutputExistsError"]


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


def atomic_write_npy(path, array) -> Path:
    """Write ``array`` to ``path`` (.npy) via a temporary file and an atomic rename."""
    dest = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.save(fh, np.asarray(array))
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, dest)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return dest
