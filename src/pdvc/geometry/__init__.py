"""Vector geometry, nominal builders and rigid poses (``DESIGN.md`` §1)."""

from ._compare import ReprojectionError, reprojection_error, sample_points
from ._nominal import circular_cone, parallel
from ._poses import (
    compose_poses,
    fix_gauge,
    invert_poses,
    magnification_mode,
    matrix_to_rotvec,
    remove_mean_pose,
    rotvec_to_matrix,
)
from ._vector import VectorGeometry
from ._volume import VolumeGeometry

__all__ = [
    "VectorGeometry",
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
