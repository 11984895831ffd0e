"""Small array helpers shared by every layer (no pdvc imports beyond errors)."""

from __future__ import annotations

import numpy as np

from .errors import GeometryError, ShapeError

__all__ = ["frozen", "per_view_vectors"]


def frozen(arr) -> np.ndarray:
    """``arr`` made read-only in place (for arrays a frozen dataclass owns); returns it."""
    arr.setflags(write=False)
    return arr


def per_view_vectors(value, n: int, name: str) -> np.ndarray:
    """``value`` as a new finite ``(n, 3)`` float64 array: one 3-vector per view, or one for all."""
    arr = np.asarray(value, dtype=np.float64)
    try:
        arr = np.broadcast_to(arr, (n, 3)).copy()
    except ValueError:
        raise ShapeError(f"{name} must have shape ({n}, 3) or (3,) (one row per view), got {np.shape(value)}") from None
    if not np.all(np.isfinite(arr)):
        raise GeometryError(f"{name} must be finite")
    return arr
