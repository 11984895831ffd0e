"""pdvc: self-calibration of lab micro-CT scans by projection-based DVC."""

from .errors import BackendError, GeometryError, PdvcError, ShapeError
from .geometry import VectorGeometry, VolumeGeometry, circular_cone, parallel

__version__ = "0.1.0"

__all__ = [
    "PdvcError",
    "GeometryError",
    "ShapeError",
    "BackendError",
    "VectorGeometry",
    "VolumeGeometry",
    "circular_cone",
    "parallel",
]
