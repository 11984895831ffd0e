"""Calibration: stages and recipes, the driver, the pipeline, what moved, coarse initialisation.

* :class:`Stage` is one part of a calibration as data; :func:`recipe_stages`
  gives the named recipes (``default``, ``precession``, ``jolts``,
  ``axis``); :func:`run_stages` runs a list of stages;
* :func:`calibrate` is the pipeline (coarse initialisation, stages, final
  volume on the user's grid, the check against nominal, metrics);
  :func:`self_calibrate` runs a recipe at the data's own scale;
* :func:`describe_motion` reads the rotation axis (tilt, offset), its
  precession, the drift and jolts of the set-up off the per-view poses;
* :func:`estimate_axis_offset` finds a large centre-of-rotation offset by
  cross-correlating opposite views, and :func:`offset_poses` turns it into
  per-view poses; :func:`compare_offsets` ranks two offsets by how well
  each view matches its mirrored opposite; in parallel beam
  :func:`estimate_axis_roll` finds the projected axis as a leaning line by
  reflecting each view about it (:func:`compare_axes` ranks two such
  lines); :func:`estimate_axis_lean` finds it as the line through the
  offsets of the detector's top and bottom halves of rows (180° scans
  too); :func:`estimate_detector_pattern` fits a pattern fixed on the
  detector that opposite views see mirrored (a flat field tilted across the
  columns) with the axis offset; :func:`estimate_axis_tilt` measures the
  axis's tilt, along the beam too, from the row sums of the views (no
  reconstruction), and :func:`tilt_poses` turns it into poses;
  :class:`RowSumConsistency` scores any per-view poses against those row
  sums (the half turns' guard of :func:`run_stages`) and measures the
  vertical motion of the views from their registration
  (:meth:`RowSumConsistency.vertical_motion`, :class:`VerticalMotion`);
* :func:`compare_models` scores motion models (:data:`MODELS`) on views
  they were not fitted to: the default recipe's automatic model choice;
  :func:`cross_validated_misfit` compares finished calibrations by how well
  each geometry's reconstruction predicts the views it was not made from
  (a study tool, not in the pipeline);
* :func:`epipolar_refine` measures modes of the set-up by the epipolar
  consistency of cone-beam view pairs, a criterion that does not go
  through a reconstruction (a study tool: ``benchmarks/bench_modes.py --ecc``).

The method and the reasons behind each default: ``docs/method.md``.
"""

from ..correlation import drift_basis
from ._axis import MotionSummary, describe_motion
from ._driver import (DriverResult, StageOutcome, correlation_volume, jolt_steps, jolt_views, reconstruct, refined_grid,
                      run_stages)
from ._init import (AxisLeanEstimate, AxisOffsetEstimate, AxisRollEstimate, DetectorPatternEstimate, InitError,
                    MirrorComparison, compare_axes, compare_offsets, estimate_axis_lean, estimate_axis_offset,
                    estimate_axis_roll, estimate_detector_pattern, offset_poses)
from ._rowsums import AxisTiltEstimate, RowSumConsistency, VerticalMotion, estimate_axis_tilt, tilt_poses
from ._outer import OuterError, OuterResult, gauge_text, self_calibrate
from ._diagnose import ResidualDiagnosis, diagnose_residual, sample_outline
from ._epipolar import EpipolarFit, EpipolarViews, epipolar_refine, epipolar_residuals, epipolar_views, view_pairs
from ._truncation import (
    Truncation,
    air_columns_span,
    air_to_subtract,
    cylinder_window,
    detect_scan_truncation,
    detect_truncation,
    field_cover,
    field_radius,
    outside_pattern,
    truncation_weights,
)
from ._pipeline import CalibrationError, CalibrationResult, calibrate, per_view_snr, resolve_stages, short_scan_reconstruction
from ._select import MIN_MODEL_GAIN, MODELS, OWN_MODEL_GAIN, ModelChoice, compare_models, cross_validated_misfit
from ._stages import (
    GUARDS,
    RECIPES,
    RECONSTRUCTIONS,
    OVERSAMPLE_BY,
    Stage,
    StageError,
    auto_scales,
    capped_oversample,
    recipe_stages,
    stages_from_dicts,
    stages_to_dicts,
    warmup_stage,
    jolt_stage,
    refine_stage,
)

__all__ = [
    "Stage",
    "StageError",
    "RECIPES",
    "RECONSTRUCTIONS",
    "OVERSAMPLE_BY",
    "GUARDS",
    "recipe_stages",
    "warmup_stage",
    "stages_from_dicts",
    "stages_to_dicts",
    "auto_scales",
    "capped_oversample",
    "resolve_stages",
    "short_scan_reconstruction",
    "run_stages",
    "jolt_views",
    "jolt_steps",
    "jolt_stage",
    "refine_stage",
    "DriverResult",
    "StageOutcome",
    "refined_grid",
    "reconstruct",
    "correlation_volume",
    "self_calibrate",
    "OuterResult",
    "OuterError",
    "gauge_text",
    "drift_basis",
    "calibrate",
    "CalibrationResult",
    "CalibrationError",
    "per_view_snr",
    "MotionSummary",
    "describe_motion",
    "AxisOffsetEstimate",
    "InitError",
    "estimate_axis_offset",
    "compare_offsets",
    "MirrorComparison",
    "estimate_axis_roll",
    "AxisRollEstimate",
    "estimate_axis_lean",
    "AxisLeanEstimate",
    "compare_axes",
    "estimate_detector_pattern",
    "DetectorPatternEstimate",
    "offset_poses",
    "AxisTiltEstimate",
    "RowSumConsistency",
    "VerticalMotion",
    "estimate_axis_tilt",
    "tilt_poses",
    "truncation_weights",
    "air_to_subtract",
    "air_columns_span",
    "detect_scan_truncation",
    "detect_truncation",
    "outside_pattern",
    "cylinder_window",
    "field_radius",
    "field_cover",
    "Truncation",
    "diagnose_residual",
    "sample_outline",
    "ResidualDiagnosis",
    "compare_models",
    "cross_validated_misfit",
    "ModelChoice",
    "MODELS",
    "MIN_MODEL_GAIN",
    "OWN_MODEL_GAIN",
    "EpipolarFit",
    "EpipolarViews",
    "epipolar_refine",
    "epipolar_residuals",
    "epipolar_views",
    "view_pairs",
]
