"""Vector geometry, nominal builders and rigid poses (``DESIGN.md`` §1)."""

from ._compare import ReprojectionError, reprojection_error, sample_points
from ._nominal import circular_cone, parallel
from ._frames import lab_frames
from ._poses import (
    Poses,
    compose_poses,
    fix_gauge,
    invert_poses,
    magnification_mode,
    matrix_to_rotvec,
    remove_mean_pose,
    rotvec_to_matrix,
)
from ._vector import VectorGeometry, check_det_shape
from ._volume import VolumeGeometry

__all__ = [
    "VectorGeometry",
    "Poses",
    "lab_frames",
    "check_det_shape",
    "VolumeGeometry",
    "circular_cone",
    "parallel",
    "rotvec_to_matrix",
    "matrix_to_rotvec",
    "compose_poses",
    "invert_poses",
    "remove_mean_pose",
    "fix_gauge",
    "magnification_mode",
    "reprojection_error",
    "ReprojectionError",
    "sample_points",
]
