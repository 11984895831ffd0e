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


def _proc_umask():
    """The process umask from ``/proc/self/status`` (Linux), or None."""
    try:
        with open("/proc/self/status", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    return None


def _import_umask() -> int:
    # os.umask can only be read by setting it; done once, at import, and only
    # where /proc does not tell (setting it later would race other threads)
    mask = _proc_umask()
    if mask is None:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


_UMASK_AT_IMPORT = _import_umask()


def _file_mode() -> int:
    """Permissions of a new file, as ``open(path, "w")`` gives them: ``0o666 & ~umask``."""
    mask = _proc_umask()  # the current umask where /proc tells, else the one at import
    return 0o666 & ~(_UMASK_AT_IMPORT if mask is None else mask)


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    For writers that want a file name (h5py, tifffile, matplotlib).  If the
    block raises (Ctrl-C included) the temporary file is removed and ``path``
    keeps whatever it held before.  The file gets the permissions of a plain
    ``open(path, "w")`` (``0o666 & ~umask``), not mkstemp's 0600.
    """
    dest = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent)
    try:
        try:
            # mkstemp makes the file 0600 and the rename keeps it: give it the usual
            # mode (best effort: a file system without permissions may refuse)
            with contextlib.suppress(OSError):
                if hasattr(os, "fchmod"):
                    os.fchmod(fd, _file_mode())
                else:  # pragma: no cover - Windows
                    os.chmod(tmp, _file_mode())
        finally:
            os.close(fd)
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
