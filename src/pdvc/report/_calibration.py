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


def build_report(out, result, *, projections, angles, params_lab, inputs=()):
    """The HTML report of a CalibrationResult: what was kept, measured at the geometry returned.

    ``inputs``: what was read and assumed about the data (``Scan.notes``), listed after the summary.
    """
    from . import (
        axis_trajectory_figure,
        pose_figure,
        residual_maps_figure,
        slices_figure,
        snr_per_view_figure,
        spatial_modes_figure,
        temporal_modes_figure,
        write_report,
    )

    angles_deg = np.rad2deg(angles)
    n = len(angles)
    figs = {}
    figs["snr_per_view"] = snr_per_view_figure(angles_deg, result.snr_before, result.snr_after)
    asm = result.assessment
    figs["poses_lab"] = pose_figure(np.arange(n), params_lab, None, frame="lab")
    if asm is not None and asm.modes:
        alphas = np.array([m.alpha for m in asm.modes])
        free = np.array([m.alpha_free for m in asm.modes])
        figs["temporal_modes"] = temporal_modes_figure(np.arange(n), alphas, free)
        figs["spatial_modes"] = spatial_modes_figure(np.array([m.spatial for m in asm.modes]))
    # residual maps at two angles, before and after, one colour scale
    views = sorted({0, int(np.argmin(np.abs(np.mod(angles - angles[0], 2 * np.pi) - np.pi / 2))) % n})
    if len(views) < 2:
        views = [0, n // 2]
    p = np.asarray(projections, np.float32)[views]
    before = p - forward(result.volume_initial, result.vol_geom, result.nominal[views])
    after = p - forward(result.volume, result.vol_geom, result.geometry[views])
    figs["residuals"] = residual_maps_figure(before, after, [f"view {v} ({angles_deg[v]:.0f} deg)" for v in views])
    top, centre, bottom = detector_displacements(result.nominal, result.geometry, result.vol_geom)
    figs["axis_trajectory"] = axis_trajectory_figure(angles_deg, top, centre, bottom)
    figs["slices"] = slices_figure(result.volume_initial, result.volume)
    tables = {}
    if result.stage_outcomes:
        tables["stages"] = (
            ("stage", "scale", "rounds", "status", "time (s)"),
            [(o.name, str(o.scale), str(o.rounds), str(o.status), f"{o.elapsed_s:.1f}") for o in result.stage_outcomes],
        )
    if result.history:
        # the row sums' misfit where the half turns' guard read it (docs/method.md §5.31)
        guarded = any("row_sums_misfit" in h for h in result.history)
        tables["rounds"] = (
            ("stage", "scale", "round", "chi before", "chi after", "increment (px)")
            + (("row sums' misfit",) if guarded else ()),
            [
                (str(h.get("stage", "")), str(h.get("scale", "")),
                 str(h.get("round", "")) + (" (extrapolated start)" if h.get("extrapolated") else ""), f"{h.get('chi_before', np.nan):.4g}",
                 f"{h.get('chi_after', np.nan):.4g}", f"{h.get('increment_px', np.nan):.3g}")
                + ((f"{h['row_sums_misfit']:.5g}" if "row_sums_misfit" in h else "",) if guarded else ())
                for h in result.history
            ],
        )
    summary = {
        "views": str(n),
        "detector": f"{result.nominal.det_shape[0]} x {result.nominal.det_shape[1]} ({result.nominal.kind} beam)",
        "status": f"{'success' if result.success else 'NOT A SUCCESS'}: {result.message}",
        "mean SNR before (dB)": float(np.mean(result.snr_before)),
        "mean SNR after (dB)": float(np.mean(result.snr_after)),
        "entropy before (bits)": result.entropy_before,
        "entropy after (bits)": result.entropy_after,
        "gauge": result.gauge,
        "run time (s)": round(result.elapsed_s, 1),
    }
    if result.initial_offset_px is not None:
        summary["coarse axis offset (px)"] = result.initial_offset_px
    if "axis_tilt" in (getattr(result, "options", None) or {}):
        summary["coarse axis tilt (row sums of the views)"] = result.options["axis_tilt"]
    if "axis_lean" in (getattr(result, "options", None) or {}):
        summary["coarse axis lean (views near opposite)"] = result.options["axis_lean"]
    if "vertical_motion" in (getattr(result, "options", None) or {}):
        summary["vertical motion (row sums' registration)"] = result.options["vertical_motion"]
    if "row_sums_guard" in (getattr(result, "options", None) or {}):
        summary["row sums' guard on the rounds"] = result.options["row_sums_guard"]
    fitted = any(h.get("background", -1) >= 0 for h in (getattr(result, "history", None) or ()))
    for when, d in zip(("nominal", "returned"), getattr(result, "residual", ())):
        # the diagnosis is of the data against the volume: a background the correlation fitted is still in it
        summary[f"residual, {when} geometry"] = d.describe() + (" (before the background per view fitted with the motion)"
                                                                 if fitted and when == "returned" else "") + (
            getattr(result, "residual_note", "") if when == "returned" else "")
    if getattr(result, "truncation", None) is not None:
        summary["sample and volume"] = result.truncation.describe()
    options = getattr(result, "options", None) or {}
    if "model" in options:
        summary["motion model"] = options["model"]
    if options.get("reconstruction", "").startswith("a short"):
        summary["reconstruction"] = options["reconstruction"]
    if options.get("scales", "").startswith("scales:"):  # the automatic schedule left out its finest scales
        summary["scales"] = options["scales"]
    if "air" in options:
        summary["air level (what the rays that miss the sample read)"] = options["air"]
    if "detector_pattern" in options:
        summary["pattern fixed on the detector (region of interest, opposite views)"] = options["detector_pattern"]
    if "background" in options:
        summary["background per view"] = options["background"]
    if "zingers" in options:
        summary["zingers, hot and dead pixels"] = options["zingers"]
    if "rings" in options:
        summary["rings (a fixed pattern of the detector)"] = options["rings"]
    if asm is not None:
        summary["modes and uncertainties"] = (
            f"measured at the geometry returned, {asm.frame} frame, basis {', '.join(asm.basis_names)} "
            f"(free history: view by view; constrained: the motion kept)"
        )
    notes = []
    if result.motion is not None and hasattr(result.motion, "describe"):
        notes.extend(result.motion.describe())
    if asm is not None:
        notes.extend(asm.observability.describe())
    return write_report(out, title="pdvc calibration report", summary=summary, figures=figs, tables=tables, notes=notes,
                        inputs=tuple(inputs))
