"""The built-in demonstration: a drifting, precessing scan of a cast-iron rod,
simulated with the analytic ellipsoid projector (not the voxel projector the
engine inverts), calibrated from its own projections, and judged against the
known true geometry."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .geometry import ReprojectionError, VolumeGeometry, circular_cone, reprojection_error, sample_points
from .simulate import (
    SimulatedScan,
    cast_iron_phantom,
    combine_poses,
    drift_poses,
    precession_poses,
    simulate_scan,
    tilted_axis_poses,
)

__all__ = ["run_demo", "demo_scan", "DemoResult"]


@dataclass(frozen=True)
class DemoResult:
    scan: SimulatedScan
    vol_geom: VolumeGeometry
    calibration: object  # CalibrationResult
    nominal_error: ReprojectionError
    recovered_error: ReprojectionError
    t_simulate: float
    t_calibrate: float


def demo_scan(*, size: int = 64, n_views: int = 150, seed: int = 0, i0: float = 2e4):
    """The demo's scan: 0.5° tilted, offset, precessing and drifting axis; Poisson noise.

    Returns ``(scan, vol_geom)``; ``scan.true_geometry`` is the answer.
    """
    n = int(size)
    vg = VolumeGeometry((n, n, n), voxel_size=1.0)
    det_shape = (int(1.2 * n), int(1.4 * n))
    angles = np.linspace(0, 2 * np.pi, n_views, endpoint=False)
    # magnification 1.5, pixel pitch 1.5: one voxel per detector pixel at the axis
    geom = circular_cone(angles, sod=8.0 * n, odd=4.0 * n, det_shape=det_shape, pixel=1.5)
    phantom = cast_iron_phantom(0.36 * n, 0.8 * n, n_nodules=3 * n, seed=seed)
    times = np.linspace(0.0, 1.0, n_views)
    rotvecs, translations = combine_poses(
        tilted_axis_poses(angles, tilt=np.deg2rad(0.5), tilt_azimuth=0.7, offset=(0.04 * n, 0.0, 0.0)),
        precession_poses(angles, amplitude=np.deg2rad(0.15)),
        drift_poses(times, angles, velocity=(0.02 * n, 0.0, 0.015 * n)),
    )
    scan = simulate_scan(phantom, geom, rotvecs=rotvecs, translations=translations, i0=i0, seed=seed, supersampling=2)
    return scan, vg


def run_demo(*, size: int = 64, n_views: int = 150, seed: int = 0, out_dir=None, overwrite: bool = False, progress=None, **options) -> DemoResult:
    """Simulate the demo scan, calibrate it with :func:`pdvc.calibrate`, measure."""
    from ._calibrate import calibrate

    t0 = time.perf_counter()
    scan, vg = demo_scan(size=size, n_views=n_views, seed=seed)
    t_sim = time.perf_counter() - t0
    points = sample_points(vg, 5, fraction=0.6)
    t0 = time.perf_counter()
    res = calibrate(scan.projections, scan.geometry, vg, out_dir=out_dir, overwrite=overwrite, progress=progress, **options)
    t_cal = time.perf_counter() - t0
    return DemoResult(
        scan=scan,
        vol_geom=vg,
        calibration=res,
        nominal_error=reprojection_error(scan.geometry, scan.true_geometry, points),
        recovered_error=reprojection_error(res.geometry, scan.true_geometry, points),
        t_simulate=t_sim,
        t_calibrate=t_cal,
    )
