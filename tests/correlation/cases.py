"""Simulated calibration cases for the engine tests (no inverse crime: the
data come from the analytic ellipsoid projector with Poisson noise, the
engine inverts the voxel projector)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import pdvc
from pdvc.correlation import correlate
from pdvc.geometry import remove_mean_pose, reprojection_error, sample_points
from pdvc.recon import fbp, fdk
from pdvc.simulate import (
    cast_iron_phantom,
    combine_poses,
    drift_poses,
    jolt_poses,
    precession_poses,
    simulate_scan,
    tilted_axis_poses,
    voxelize,
)


@dataclass
class Case:
    name: str
    scan: object
    vol_geom: pdvc.VolumeGeometry
    truth: np.ndarray
    points: np.ndarray


def make_case(
    name: str,
    *,
    n: int = 48,
    n_views: int = 90,
    kind: str = "cone",
    seed: int = 0,
    i0: float = 2e4,
    sod: float = 8.0,
    odd: float = 4.0,
) -> Case:
    vg = pdvc.VolumeGeometry((n, n, n))
    angles = np.linspace(0, 2 * np.pi, n_views, endpoint=False)
    det = (int(1.2 * n), int(1.4 * n))
    if kind == "cone":
        mag = (sod + odd) / sod  # detector pixel = one voxel at the rotation axis
        geom = pdvc.circular_cone(angles, sod=sod * n, odd=odd * n, det_shape=det, pixel=mag)
    else:
        geom = pdvc.parallel(angles, det_shape=det, pixel=1.0)
    phantom = cast_iron_phantom(0.36 * n, 0.8 * n, n_nodules=3 * n, seed=seed)
    times = np.linspace(0, 1, n_views)
    if name == "tilted_axis":
        rv, t = tilted_axis_poses(angles, tilt=np.deg2rad(0.5), tilt_azimuth=0.7, offset=(2.0, 0.0, 0.0))
    elif name == "precession_drift":
        rv, t = combine_poses(
            precession_poses(angles, amplitude=np.deg2rad(0.3)),
            drift_poses(times, angles, velocity=(1.5, -1.0, 1.0), acceleration=(1.0, 0.0, -0.5)),
        )
    elif name == "jolts":
        rv, t = combine_poses(
            tilted_axis_poses(angles, tilt=np.deg2rad(0.2), offset=(1.0, 0.0, 0.0)),
            jolt_poses(angles, at=[n_views // 3, 2 * n_views // 3], translations=[(1.2, 0.0, 0.4), (-0.8, 0.5, -0.6)]),
        )
    elif name == "offset":
        rv, t = tilted_axis_poses(angles, tilt=0.0, offset=(2.0, 0.0, 0.0))
    else:
        raise ValueError(name)
    scan = simulate_scan(phantom, geom, rotvecs=rv, translations=t, i0=i0, seed=seed, supersampling=2)
    return Case(name, scan, vg, voxelize(phantom, vg, supersampling=2), sample_points(vg, 5, fraction=0.6))


def reconstruct(case: Case, geom):
    return (fdk if geom.kind == "cone" else fbp)(case.scan.projections, case.vol_geom, geom)


def self_calibrate(case: Case, *, n_outer: int = 3, **options):
    """Reconstruct, correlate, rewrite the geometry, repeat (the outer loop of issue #4)."""
    geom = case.scan.geometry
    rv = np.zeros((geom.n_views, 3))
    t = np.zeros((geom.n_views, 3))
    results = []
    for _ in range(n_outer):
        vol = reconstruct(case, geom.apply_poses(rv, t))
        res = correlate(vol, case.vol_geom, case.scan.projections, geom, initial_rotvecs=rv, initial_translations=t, **options)
        rv, t = remove_mean_pose(res.rotvecs, res.translations, center=case.vol_geom.offset)
        results.append(res)
    return results


def error_px(case: Case, geom) -> float:
    return reprojection_error(geom, case.scan.true_geometry, case.points).rms


def best_at_second_call(calls: list):
    """A reconstruction (FDK scaled) that fits best at its second call, then worse at every call.

    Each geometry it is called with is appended to ``calls``: the consistency guard must keep the
    poses of the second call.
    """

    def rec(p, vg, g):
        calls.append(g)
        k = len(calls) - 1
        return fdk(p, vg, g) * (1.0 + (0.3 if k == 0 else 0.5 * (k - 1)))

    return rec
