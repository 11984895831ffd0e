"""Phantoms and scans with known per-view motion, for tests, demos and benchmarks.

* :mod:`~pdvc.simulate.phantoms`: :class:`EllipsoidPhantom`, the 3D
  Shepp–Logan head, a nodular cast-iron rod, voxelisation;
* :mod:`~pdvc.simulate.analytic`: exact line integrals of ellipsoid phantoms
  for any cone / parallel vector geometry;
* :mod:`~pdvc.simulate.motion`: per-view poses of a tilted or precessing
  axis, drift, jolts, and their exact composition;
* :mod:`~pdvc.simulate.scan`: Beer–Lambert counts with Poisson, flat and dark
  noise, and the user's normalised projections.

Examples
--------
>>> import numpy as np
>>> from pdvc.geometry import circular_cone
>>> from pdvc.simulate import cast_iron_phantom, tilted_axis_poses, simulate_scan
>>> angles = np.linspace(0, 2 * np.pi, 60, endpoint=False)
>>> geom = circular_cone(angles, sod=10, odd=10, det_shape=(48, 48), pixel=0.1)
>>> rv, t = tilted_axis_poses(angles, tilt=0.01, offset=(0.05, 0, 0))
>>> scan = simulate_scan(cast_iron_phantom(1.0, 1.8, n_nodules=40), geom, rotvecs=rv, translations=t)
>>> scan.projections.dtype
dtype('float32')
"""

from ._checks import SimulationError
from .analytic import project_analytic
from .motion import (
    combine_poses,
    drift_poses,
    jolt_poses,
    lab_motion_to_poses,
    poses_to_lab_motion,
    precession_poses,
    tilted_axis_poses,
)
from .phantoms import EllipsoidPhantom, cast_iron_phantom, foam_phantom, granular_phantom, shepp_logan_3d, voxelize
from .scan import SimulatedScan, add_poisson_noise, simulate_scan

__all__ = [
    "EllipsoidPhantom",
    "shepp_logan_3d",
    "cast_iron_phantom",
    "foam_phantom",
    "granular_phantom",
    "voxelize",
    "project_analytic",
    "tilted_axis_poses",
    "precession_poses",
    "drift_poses",
    "jolt_poses",
    "combine_poses",
    "lab_motion_to_poses",
    "poses_to_lab_motion",
    "SimulatedScan",
    "simulate_scan",
    "add_poisson_noise",
    "SimulationError",
]
