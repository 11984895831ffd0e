"""Calibration: the pipeline (:func:`calibrate`), what moved (axis, precession, drift, jolts) and coarse initialisation.

* :func:`describe_motion` reads the rotation axis (tilt, offset), its
  precession, the drift and jolts of the set-up off the per-view poses,
  in the lab frame, with the detector displacements of the sample's axis
  points (paper Figs 6 and 14);
* :func:`estimate_axis_offset` finds a large centre-of-rotation offset by
  cross-correlating opposite views, and :func:`offset_poses` turns it into
  per-view poses for the engine to start from.
"""

from ._axis import MotionSummary, describe_motion
from ._pipeline import GAUGE, CalibrationError, CalibrationResult, auto_scales, calibrate, per_view_snr, reconstruct
from ._init import AxisOffsetEstimate, InitError, estimate_axis_offset, offset_poses
from ._outer import OUTER_STATUS, RECONSTRUCTORS, OuterError, OuterResult, drift_basis, self_calibrate

__all__ = [
    "self_calibrate",
    "OuterResult",
    "OuterError",
    "OUTER_STATUS",
    "RECONSTRUCTORS",
    "drift_basis",
    "calibrate",
    "CalibrationResult",
    "CalibrationError",
    "GAUGE",
    "auto_scales",
    "per_view_snr",
    "reconstruct",
    "MotionSummary",
    "describe_motion",
    "AxisOffsetEstimate",
    "InitError",
    "estimate_axis_offset",
    "offset_poses",
]
