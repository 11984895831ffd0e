"""The HTML report of a calibration run (the paper's figures, from a CalibrationResult)."""

from __future__ import annotations

import logging

import numpy as np

from ..projectors import forward

log = logging.getLogger("pdvc.report")

__all__ = ["build_report", "detector_displacements"]


def detector_displacements(nominal, calibrated, vol_geom):
    """Displacement (row, col) px of the top, centre and bottom of the sample on the axis.

    Points on the rotation axis (x = y = 0 of the volume frame, shifted by
    its offset) at z = +0.9, 0 and −0.9 of the half height, projected with
    the calibrated minus the nominal geometry (paper Figs 6, 14).
    """
    c = np.asarray(vol_geom.offset, float)
    half = 0.5 * float(vol_geom.extent_xyz[2])
    pts = np.array([c + [0, 0, 0.9 * half], c, c - [0, 0, 0.9 * half]])
    d = calibrated.project_points(pts) - nominal.project_points(pts)  # (n_views, 3, 2)
    return d[:, 0, :], d[:, 1, :], d[:, 2, :]


def build_report(out, result, *, projections, geom_fine, angles, params_lab):
    from . import (
        axis_trajectory_figure,
        pose_figure,
        residual_maps_figure,
        slices_figure,
        snr_modes_table,
        snr_per_view_figure,
        spatial_modes_figure,
        temporal_modes_figure,
        write_report,
    )

    angles_deg = np.rad2deg(angles)
    figs = {}
    figs["snr_per_view"] = snr_per_view_figure(angles_deg, result.snr_before, result.snr_after)
    eng = result.engine
    figs["poses_lab"] = pose_figure(np.arange(len(angles)), params_lab, None, frame="lab")
    if eng is not None and eng.modes:
        alphas = np.array([m.alpha for m in eng.modes])
        free = np.array([m.alpha_free if m.alpha_free is not None else np.full(len(angles), np.nan) for m in eng.modes])
        figs["temporal_modes"] = temporal_modes_figure(np.arange(len(angles)), alphas, free)
        figs["spatial_modes"] = spatial_modes_figure(np.array([m.spatial for m in eng.modes]))
    # residual maps at two angles, before and after, one colour scale
    n = len(angles)
    views = sorted({0, int(np.argmin(np.abs(np.mod(angles - angles[0], 2 * np.pi) - np.pi / 2))) % n})
    if len(views) < 2:
        views = [0, n // 2]
    p = np.asarray(projections, np.float32)[views]
    s = int(result.scales[-1])
    g_cal = result.geometry if s == 1 else result.geometry.binned(s)
    before = p - forward(result.volume_initial, result.vol_geom, geom_fine[views])
    after = p - forward(result.volume, result.vol_geom, g_cal[views])
    figs["residuals"] = residual_maps_figure(before, after, [f"view {v} ({angles_deg[v]:.0f} deg)" for v in views])
    top, centre, bottom = detector_displacements(result.nominal, result.geometry, result.vol_geom)
    figs["axis_trajectory"] = axis_trajectory_figure(angles_deg, top, centre, bottom)
    figs["slices"] = slices_figure(result.volume_initial, result.volume)
    tables = {}
    if eng is not None and eng.mode_table:
        tables["snr_vs_modes"] = snr_modes_table(eng.mode_table)
    hist = result.history
    if hist:
        tables["outer_iterations"] = (
            ("scale", "iteration", "chi before", "chi after", "increment (px)"),
            [
                (str(h.get("scale", "")), str(h.get("iteration", "")), f"{h.get('chi_before', np.nan):.4g}", f"{h.get('chi_after', np.nan):.4g}", f"{h.get('increment_px', np.nan):.3g}")
                for h in hist
            ],
        )
    summary = {
        "views": str(n),
        "detector": f"{result.nominal.det_shape[0]} x {result.nominal.det_shape[1]} ({result.nominal.kind} beam)",
        "scales": " -> ".join(map(str, result.scales)),
        "mean SNR before (dB)": float(np.mean(result.snr_before)),
        "mean SNR after (dB)": float(np.mean(result.snr_after)),
        "entropy before (bits)": result.entropy_before,
        "entropy after (bits)": result.entropy_after,
        "status": result.message,
        "gauge": result.gauge,
        "run time (s)": round(result.elapsed_s, 1),
    }
    if result.initial_offset_px is not None:
        summary["coarse axis offset (px)"] = result.initial_offset_px
    notes = []
    if result.motion is not None and hasattr(result.motion, "describe"):
        notes.extend(result.motion.describe())
    if eng is not None and hasattr(eng.observability, "describe"):
        notes.extend(eng.observability.describe())
    return write_report(out, title="pdvc calibration report", summary=summary, figures=figs, tables=tables, notes=notes)
