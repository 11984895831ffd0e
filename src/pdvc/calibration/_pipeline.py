"""The calibration a user runs: scales, coarse initialisation, outer loop,
final reconstruction, metrics and (optionally) the output folder.

This is the only module that knows the order of the stages::

    projections + nominal geometry
      -> coarse initialisation (axis offset from opposite views, when the scan has them)
      -> for each scale s (coarse to fine): coarse-grained projections, binned grid,
         outer loop reconstruct -> correlate -> gauge (``self_calibrate``)
      -> final reconstruction at the finest scale with the calibrated geometry
      -> metrics (per-view SNR, entropy before/after), what moved (``describe_motion``)

Writing files is not done here (the calibration layer imports no io or
report code): ``checkpoint`` is called after every outer iteration with the
state that ``resume`` takes back; :func:`pdvc.calibrate` wires both to an
output folder.

Gauge: the poses are relative to the nominal geometry and fixed by
:func:`pdvc.geometry.fix_gauge` — zero mean rigid pose over the views about
the volume centre, and, in cone beam, zero mean magnification change (the
nominal source–object distance is the mean one, i.e. the voxel size stays
the nominal one). Every output states it.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from ..correlation import coarse_grain, coarse_noise_factor, estimate_noise_variance, shannon_entropy, snr_db
from ..correlation._engine import CorrelationResult
from ..errors import PdvcError, ShapeError
from ..geometry import VectorGeometry, VolumeGeometry, fix_gauge
from ..projectors import forward
from ..recon import fbp, fdk

log = logging.getLogger("pdvc.calibration")

__all__ = ["calibrate", "CalibrationResult", "CalibrationError", "GAUGE", "reconstruct", "auto_scales", "per_view_snr"]

GAUGE = (
    "poses relative to the nominal geometry; gauge: zero mean rigid pose over the views "
    "(mean rotation = identity, mean position of the volume centre unchanged) and, in cone beam, "
    "zero mean magnification change (the nominal source-object distance is the mean one)"
)


class CalibrationError(PdvcError, ValueError):
    """The calibration cannot run or did not converge in a usable way."""


@dataclass(frozen=True)
class CalibrationResult:
    """Outcome of :func:`calibrate`.

    Attributes
    ----------
    geometry : VectorGeometry
        The calibrated per-view geometry at full detector resolution.
    nominal : VectorGeometry
        The geometry given.
    rotvecs, translations : (n_views, 3)
        Poses of the sample relative to ``nominal`` (``apply_poses``
        convention), gauge fixed as stated in ``gauge``.
    engine : CorrelationResult
        The last P-DVC result (finest scale, last outer iteration).
    history : tuple of dict
        One entry per outer iteration over all scales: scale, iteration,
        chi before/after, SNR, increment (px, full-resolution pixels).
    volume, volume_initial : (nz, ny, nx) float32
        Reconstructions with the calibrated and with the nominal geometry on
        ``vol_geom`` (the finest scale requested).
    vol_geom : VolumeGeometry
    snr_before, snr_after : (n_views,) float
        Per-view SNR (dB) of the projections against the re-projection of
        ``volume_initial`` (nominal geometry) and of ``volume`` (calibrated).
    entropy_before, entropy_after : float
        Shannon entropy (bits) of the two volumes on a common gray range.
    motion : object
        What moved (``describe_motion``), or None when unavailable.
    initial_offset_px : float or None
        The coarse axis-offset estimate used to start, in detector pixels.
    gauge : str
    scales : tuple of int
    status : int
        > 0 converged; 0 stopped at the iteration cap; < 0 failed.
    message : str
    elapsed_s : float
    """

    geometry: VectorGeometry
    nominal: VectorGeometry
    rotvecs: np.ndarray
    translations: np.ndarray
    engine: CorrelationResult
    history: tuple
    volume: np.ndarray
    volume_initial: np.ndarray
    vol_geom: VolumeGeometry
    snr_before: np.ndarray
    snr_after: np.ndarray
    entropy_before: float
    entropy_after: float
    motion: object
    initial_offset_px: Optional[float]
    gauge: str
    scales: tuple
    status: int
    message: str
    elapsed_s: float
    options: dict = field(default_factory=dict)
    projections_fine: Optional[np.ndarray] = None  # the coarse-grained data of the last scale, when s > 1


def reconstruct(projections, vol_geom: VolumeGeometry, geom: VectorGeometry, **kw) -> np.ndarray:
    """FDK for cone beam, FBP for parallel beam (the pipeline's reconstruction)."""
    return (fdk if geom.kind == "cone" else fbp)(projections, vol_geom, geom, **kw)


def auto_scales(det_shape) -> tuple:
    """Default coarse-to-fine schedule: coarse enough for ~64+ px, down to 1.

    Large detectors start at 4 and stop at 2 (the paper's 4 -> 2); small
    ones (under 256 columns) run 2 -> 1, tiny ones (under 128) 1 only.
    """
    n = min(det_shape[1], max(det_shape[0], 1) * 4)  # thin detectors (a few rows) count by columns
    if n >= 512:
        return (4, 2)
    if n >= 128:
        return (2, 1)
    return (1,)


def per_view_snr(projections, volume, vol_geom, geom, *, weights=None) -> np.ndarray:
    """SNR (dB) of each view: ``20 log10(std(s_k) / std(s_k - Π_k f))``."""
    p = np.asarray(projections, np.float32)
    res = p - forward(volume, vol_geom, geom)
    if weights is not None:
        w = np.broadcast_to(np.asarray(weights, np.float32), p.shape) > 0
        out = np.empty(p.shape[0])
        for k in range(p.shape[0]):
            out[k] = snr_db(p[k][w[k]], res[k][w[k]])
        return out
    return np.asarray(snr_db(p, res, axis=(1, 2)), float)


def _validate(projections, geom, vol_geom):
    if not isinstance(geom, VectorGeometry):
        raise CalibrationError(f"geom must be a VectorGeometry, got {type(geom).__name__}")
    if not isinstance(vol_geom, VolumeGeometry):
        raise CalibrationError(f"vol_geom must be a VolumeGeometry, got {type(vol_geom).__name__}")
    p = np.asarray(projections)
    if p.ndim != 3 or p.shape != (geom.n_views,) + tuple(geom.det_shape):
        raise ShapeError(
            f"projections must have shape (n_views, n_rows, n_cols) = {(geom.n_views,) + tuple(geom.det_shape)} "
            f"to match the geometry, got {p.shape}"
        )
    if not np.issubdtype(p.dtype, np.floating):
        p = p.astype(np.float32)
    bad = ~np.isfinite(p)
    if bad.any():
        views = np.nonzero(bad.any(axis=(1, 2)))[0]
        raise CalibrationError(
            f"projections contain {int(bad.sum())} NaN/Inf values (first in view {int(views[0])}); "
            "expected finite line integrals: check the flat/dark normalisation"
        )
    return p


def calibrate(
    projections,
    geom: VectorGeometry,
    vol_geom: VolumeGeometry,
    *,
    basis="fourier:1",
    method: str = "full",
    frame: str = "sample",
    fixed=("rz",),
    scales="auto",
    oversample: int = 2,
    n_outer: int = 10,
    tol_px: float = 0.01,
    init: str = "auto",
    fix_scale: bool = True,
    weights=None,
    noise_variance: Optional[float] = None,
    times=None,
    initial_rotvecs=None,
    initial_translations=None,
    checkpoint: Optional[Callable[[dict], None]] = None,
    resume: Optional[dict] = None,
    progress: Optional[Callable[[dict], None]] = None,
    **correlate_options,
) -> CalibrationResult:
    """Calibrate a scan from its own projections.

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) array
        Line integrals (flat/dark normalised, −log); not modified.
    geom : VectorGeometry
        Nominal per-view geometry.
    vol_geom : VolumeGeometry
        Reconstruction grid at full resolution.
    basis, method, frame, fixed
        P-DVC model (see :func:`pdvc.correlate`). ``fixed=("rz",)`` trusts
        the rotation stage's angles: with FDK in the loop a per-view
        rotation about the axis is nearly absorbed by the reconstruction.
    scales : "auto" or sequence of int
        Coarse-to-fine schedule of the outer loop (see :func:`auto_scales`).
        The final reconstruction is at the last (finest) scale.
    oversample : int
        The volume used for correlation has ``oversample`` x finer voxels
        than the reconstruction grid at that scale, so the interpolating
        projector's own blur does not bias the poses.
    n_outer : int
        Outer iterations (reconstruct, correlate) per scale at most.
    tol_px : float
        Stop a scale when an outer iteration moves no sample point by more
        than this on the detector (full-resolution pixels).
    init : {"auto", "axis", "none"}
        Coarse initialisation: the axis offset from opposite views by
        cross-correlation (needs views ~180° apart), so that offsets of tens
        of pixels converge. "auto" uses it when such pairs exist.
    fix_scale : bool
        Cone beam: also fix the magnification gauge (mean source-object
        distance = nominal); see :func:`pdvc.geometry.fix_gauge`.
    weights : (n_rows, n_cols) array, optional
        Detector ROI / weights at full resolution.
    checkpoint : callable, optional
        Called after every outer iteration and every scale with a dict
        (rotvecs, translations, history, scale_index, rounds_done,
        offset_px) — the state ``resume`` accepts.
    resume : dict, optional
        A state given to ``checkpoint`` by an interrupted run: continue it.
    progress : callable, optional
        Called with a dict ``{"stage", "scale", "iteration", ...}``.
    **correlate_options
        Passed to the engine (e.g. ``max_iter``, ``max_modes``).

    Returns
    -------
    CalibrationResult
    """
    from ._outer import self_calibrate

    t_start = time.perf_counter()
    p = _validate(projections, geom, vol_geom)
    sched = auto_scales(geom.det_shape) if scales == "auto" else tuple(int(s) for s in scales)
    if not sched or any(s < 1 for s in sched):
        raise CalibrationError(f"scales must be 'auto' or positive ints coarse to fine, got {scales!r}")
    if init not in ("auto", "axis", "none"):
        raise CalibrationError(f"init must be 'auto', 'axis' or 'none', got {init!r}")
    if not (isinstance(n_outer, (int, np.integer)) and n_outer >= 1):
        raise CalibrationError(f"n_outer must be a positive int, got {n_outer!r}")
    if not (isinstance(oversample, (int, np.integer)) and oversample >= 1):
        raise CalibrationError(f"oversample must be a positive int, got {oversample!r}")
    if weights is not None:
        w = np.asarray(weights, np.float32)
        if w.shape[-2:] != tuple(geom.det_shape):
            raise ShapeError(f"weights must have the detector shape {tuple(geom.det_shape)}, got {w.shape}")
        if not (w > 0).any():
            raise CalibrationError("weights (detector ROI) select no pixel; expected a non-empty region")
    options = dict(
        basis=basis if isinstance(basis, str) else "custom", method=method, frame=frame, fixed=list(fixed),
        scales=list(sched), oversample=int(oversample), n_outer=int(n_outer), tol_px=float(tol_px), init=init,
    )

    def emit(**info):
        if progress is not None:
            progress(info)

    c = np.asarray(vol_geom.offset, float)
    n = geom.n_views
    rv = np.zeros((n, 3)) if initial_rotvecs is None else np.array(initial_rotvecs, float).reshape(n, 3)
    t = np.zeros((n, 3)) if initial_translations is None else np.array(initial_translations, float).reshape(n, 3)
    history: list = []
    start_scale_index = 0
    rounds_done = 0  # outer rounds already done at start_scale_index (resume)
    offset_px = None
    if resume is not None:
        ck = resume
        if ck:
            rv = np.array(ck["rotvecs"], float).reshape(n, 3)
            t = np.array(ck["translations"], float).reshape(n, 3)
            history, start_scale_index, offset_px = list(ck["history"]), int(ck["scale_index"]), ck["offset_px"]
            rounds_done = int(ck.get("rounds_done", 0))
            log.info("resuming from checkpoint: scale index %d, %d outer iterations done", start_scale_index, len(history))
            emit(stage="resume", scale=sched[min(start_scale_index, len(sched) - 1)], iteration=len(history))

    if start_scale_index == 0 and not history and init != "none" and initial_rotvecs is None and initial_translations is None:
        from ._init import InitError, estimate_axis_offset, offset_poses

        emit(stage="init")
        try:
            est = estimate_axis_offset(p, geom)
            offset_px = float(est.offset_px)
            rv, t = offset_poses(geom, offset_px)
            log.info("coarse initialisation: axis offset %.2f px from %d opposite view pairs", offset_px, est.n_pairs)
        except InitError as exc:
            if init == "axis":
                raise
            log.info("coarse initialisation skipped: %s", exc)

    # γ² on the full-resolution data (Immerkær's estimator needs white noise), carried to each scale
    gamma2 = float(noise_variance) if noise_variance is not None else estimate_noise_variance(p)

    # reconstruction with the nominal geometry at the finest scale (the "before")
    fine = sched[-1]
    p_fine, g_fine = (p, geom) if fine == 1 else coarse_grain(p, geom, fine)
    vg_fine = vol_geom if fine == 1 else vol_geom.binned(fine)
    emit(stage="reconstruct", what="initial")
    vol_initial = reconstruct(p_fine, vg_fine, g_fine)

    last = None
    status, message = 0, "iteration cap reached"
    for si in range(start_scale_index, len(sched)):
        s = sched[si]
        p_s, g_s = (p, geom) if s == 1 else coarse_grain(p, geom, s)
        vg_s = vol_geom if s == 1 else vol_geom.binned(s)
        w_s = None
        if weights is not None:
            from ..correlation._engine import _coarse_weights

            w_s = np.asarray(weights, np.float32) if s == 1 else _coarse_weights(weights, s, g_s.det_shape)

        def outer_cb(info, s=s):
            info = dict(info)
            if "stage" in info:
                info["phase"] = info.pop("stage")
            info.update(scale=s)
            history_entry = {k: info[k] for k in ("iteration", "chi_before", "chi_after", "snr", "increment_px") if k in info}
            emit(stage="outer", **info)
            return history_entry

        emit(stage="scale", scale=s, det_shape=g_s.det_shape, volume=vg_s.shape)
        done_before = rounds_done if si == start_scale_index else 0
        prior = [dict(h) for h in history]

        def round_checkpoint(rv_k, t_k, hist_k, si=si, s=s, done_before=done_before, prior=prior):
            if checkpoint is not None:
                entries = prior + [dict(h, scale=s) for h in hist_k]
                checkpoint(dict(rotvecs=rv_k, translations=t_k, history=entries, scale_index=si,
                                rounds_done=done_before + len(hist_k), offset_px=offset_px))

        if done_before >= n_outer:
            rounds_left = 0
        else:
            rounds_left = n_outer - done_before
        out = None if rounds_left == 0 else self_calibrate(
            p_s, g_s, vg_s,
            initial_rotvecs=rv, initial_translations=t,
            oversample=oversample, basis=basis, method=method, frame=frame, fixed=tuple(fixed),
            n_outer=rounds_left, tol_px=tol_px / s, weights=w_s, times=times, fix_scale=fix_scale,
            checkpoint=round_checkpoint,
            noise_variance=gamma2 * coarse_noise_factor(s),
            callback=outer_cb, **correlate_options,
        )
        if out is not None:
            rv, t = out.rotvecs, out.translations
            for h in out.history:
                entry = dict(h)
                entry["scale"] = s
                history.append(entry)
            last = out
            status, message = out.status, out.message
        if checkpoint is not None:
            checkpoint(dict(rotvecs=rv, translations=t, history=list(history), scale_index=si + 1, rounds_done=0, offset_px=offset_px))

    # Too large for the linearisation? Two signs, either is enough (no coarse
    # initialisation having placed the axis first): the last outer iteration still
    # moves sample points by more than a pixel, or the data consistency of the
    # reconstruction (chi of a fresh FDK re-projected) stayed far above the noise
    # (> 3) and fell by less than half over the whole run.
    if history and status <= 0 and offset_px is None:
        inc = float(history[-1].get("increment_px", 0.0)) * sched[-1]
        c0, c1 = float(history[0].get("chi_before", np.nan)), float(history[-1].get("chi_before", np.nan))
        stuck = np.isfinite(c0) and np.isfinite(c1) and c1 > 3.0 and c1 > 0.5 * c0
        if inc > max(1.0, 20 * tol_px) or stuck:
            message = (
                f"not converged: the last outer iteration moved sample points by {inc:.2f} px and the "
                f"reconstruction's chi went {c0:.3g} -> {c1:.3g} (1 = noise only); the motion may be too large "
                f"for the linearisation at scale {sched[0]}: start at a coarser scale "
                f"(e.g. scales = [{4 * sched[0]}, {2 * sched[0]}, {sched[-1]}]), use init = 'axis', or raise n_outer"
            )
            status = min(status, 0)
            log.warning(message)
    rv, t = fix_gauge(rv, t, geom, center=c, scale=fix_scale)
    calibrated = geom.apply_poses(rv, t)
    emit(stage="reconstruct", what="calibrated")
    g_fine_cal = calibrated if fine == 1 else calibrated.binned(fine)
    vol = reconstruct(p_fine, vg_fine, g_fine_cal)
    snr_before = per_view_snr(p_fine, vol_initial, vg_fine, g_fine)
    snr_after = per_view_snr(p_fine, vol, vg_fine, g_fine_cal)
    lo, hi = np.percentile(vol, [0.1, 99.9])
    e_before = shannon_entropy(vol_initial, value_range=(float(lo), float(hi)))
    e_after = shannon_entropy(vol, value_range=(float(lo), float(hi)))

    motion = None
    try:
        from ._axis import describe_motion

        motion = describe_motion(geom, rv, t, vol_geom, times=times)
    except Exception as exc:  # the summary is a report, never a reason to lose the calibration
        log.warning("motion summary unavailable: %s", exc)

    result = CalibrationResult(
        geometry=calibrated,
        nominal=geom,
        rotvecs=rv,
        translations=t,
        engine=last.result if last is not None else None,
        history=tuple(history),
        volume=vol,
        volume_initial=vol_initial,
        vol_geom=vg_fine,
        snr_before=snr_before,
        snr_after=snr_after,
        entropy_before=float(e_before),
        entropy_after=float(e_after),
        motion=motion,
        initial_offset_px=offset_px,
        projections_fine=p_fine if fine != 1 else None,
        gauge=GAUGE,
        scales=sched,
        status=int(status),
        message=str(message),
        elapsed_s=time.perf_counter() - t_start,
        options=options,
    )
    log.info(
        "calibration done in %.1f s: SNR %.2f -> %.2f dB, entropy %.3f -> %.3f bits",
        result.elapsed_s, float(np.mean(snr_before)), float(np.mean(snr_after)), e_before, e_after,
    )
    return result

