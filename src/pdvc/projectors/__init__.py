"""Projectors over per-view vector geometry, behind one backend registry.

Functions: :func:`forward`, its exact adjoint :func:`backproject`, the fused
Jacobian pass as images (:func:`jacobian`) or reduced per view
(:func:`reduce_views`). The CPU backend (numba) is always available.
"""

from ._api import (
    POSE_PARAMETERS,
    ViewReduction,
    backproject,
    bin_projections,
    forward,
    jacobian,
    reduce_views,
)
from ._numba import NumbaBackend, geometry_table
from ._registry import available_backends, get_backend, register_backend

register_backend("cpu", NumbaBackend)

__all__ = [
    "forward",
    "backproject",
    "jacobian",
    "reduce_views",
    "ViewReduction",
    "bin_projections",
    "POSE_PARAMETERS",
    "available_backends",
    "get_backend",
    "register_backend",
    "NumbaBackend",
    "geometry_table",
]
