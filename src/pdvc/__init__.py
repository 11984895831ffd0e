"""pdvc: self-calibration of lab micro-CT scans by projection-based DVC."""

from .errors import BackendError, GeometryError, InputTypeError, PdvcError, ShapeError
from .status import Status
from .geometry import Poses, VectorGeometry, VolumeGeometry, circular_cone, parallel
from .projectors import backproject, forward, jacobian, reduce_views
from .recon import fbp, fdk
from .correlation import correlate
from ._calibrate import calibrate
from .calibration import CalibrationResult
from .compute import use_scheduler

__version__ = "0.1.0"

__all__ = [
    "PdvcError",
    "GeometryError",
    "ShapeError",
    "BackendError",
    "InputTypeError",
    "Status",
    "Poses",
    "VectorGeometry",
    "VolumeGeometry",
    "circular_cone",
    "parallel",
    "forward",
    "backproject",
    "jacobian",
    "reduce_views",
    "fdk",
    "fbp",
    "correlate",
    "calibrate",
    "CalibrationResult",
    "use_scheduler",
]
