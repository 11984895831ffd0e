"""Small argument checks shared by the simulate modules (private)."""

from __future__ import annotations

import numpy as np

from ..errors import GeometryError, InputTypeError, PdvcError, ShapeError

__all__ = ["SimulationError", "as_vec3", "as_positive", "as_int", "as_finite"]


class SimulationError(PdvcError, ValueError):
    """An invalid simulation parameter (noise level, counts, numbers of frames, ...)."""


def as_vec3(value, name: str) -> np.ndarray:
    """A finite float64 3-vector (x, y, z)."""
    arr = np.asarray(value, dtype=np.float64) if _numeric(value) else None
    if arr is None or arr.shape != (3,):
        raise ShapeError(f"{name} must be a 3-vector (x, y, z), got {value!r}")
    if not np.all(np.isfinite(arr)):
        raise GeometryError(f"{name} must be finite, got {value!r}")
    return arr.copy()


def as_finite(value, name: str, *, error=SimulationError) -> float:
    """A finite float."""
    if not _numeric(value) or np.ndim(value) != 0 or not np.isfinite(float(value)):
        raise error(f"{name} must be a finite number, got {value!r}")
    return float(value)


def as_positive(value, name: str, *, error=SimulationError, allow_zero: bool = False) -> float:
    """A finite float > 0 (or >= 0 with ``allow_zero``)."""
    x = as_finite(value, name, error=error)
    if x < 0 or (x == 0 and not allow_zero):
        what = "non-negative" if allow_zero else "positive"
        raise error(f"{name} must be a {what} number, got {value!r}")
    return x


def as_int(value, name: str, *, minimum: int = 0) -> int:
    """An int >= ``minimum`` (bools refused)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InputTypeError(f"{name} must be an int >= {minimum}, got {value!r}")
    if value < minimum:
        raise SimulationError(f"{name} must be an int >= {minimum}, got {value!r}")
    return int(value)


def _numeric(value) -> bool:
    try:
        arr = np.asarray(value)
    except Exception:  # noqa: BLE001 - anything numpy cannot read is not numeric
        return False
    return arr.dtype.kind in "iuf"
