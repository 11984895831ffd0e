"""The calibration a user runs: coarse initialisation, the stages, the final volume, the checks, the metrics.

This is the only module that knows the order::

    projections + nominal geometry
      -> coarse initialisation (axis offset from opposite views, when the scan has them)
      -> the stage list (a recipe, or stages given) run by :func:`run_stages`
      -> final reconstruction on the user's grid, at full resolution
      -> never worse than nominal: the calibrated geometry must fit the data better, and move the sample points by
         more than the stages' tolerance from the nominal one (else the nominal geometry holds)
      -> metrics (per-view SNR, entropy), what moved (``describe_motion``) and the
         assessment of the poses kept (uncertainty, observability, motion modes)

Writing files is not done here (the calibration layer imports no io or
report code): ``checkpoint`` is called after every round with the state that
``resume`` takes back; :func:`pdvc.calibrate` wires both to an output folder.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Optional

import numpy as np

from ..compute import current_session, scheduler_keyword
from ..correlation import Assessment, assess, coarse_volume, estimate_noise_variance, shannon_entropy, snr_db
from ..errors import PdvcError, ShapeError
from ..geometry import Poses, VectorGeometry, VolumeGeometry
from ..projectors import forward
from ..status import Status
from ._diagnose import diagnose_residual
from ._init import MIRROR_MIN_T, SHORT_SCAN_OPPOSITE_FRACTION, InitError, distinct_directions, opposite_fraction
from ._driver import (PosesResult, correlation_volume, data_at_scale, hold_vertical, increment_points, nonneg_subsets,
                      point_moves, reconstruct, refined_grid, run_stages, stage_background)
from ._outer import gauge_text
from ._select import with_model
from ._stages import (_RECIPE_ROUNDS, FULL_TURN_FINE_ROUNDS, MAX_CORRELATION_VOXELS, NONNEG_COARSE_ROUNDS,
                      NONNEG_REFINE_SUBSETS, Stage, StageError, recipe_stages)

log = logging.getLogger("pdvc.calibration")

__all__ = ["calibrate", "CalibrationResult", "CalibrationError", "reconstruct", "per_view_snr", "resolve_stages"]


class CalibrationError(PdvcError, ValueError):
    """The calibration cannot run with the inputs or options given."""


@dataclass(frozen=True)
class CalibrationResult(PosesResult):
    """Outcome of :func:`calibrate`.

    Attributes
    ----------
    geometry : VectorGeometry
        The geometry returned, at full detector resolution: the calibrated
        one, or the nominal one when the calibration fitted the data worse
        (``status`` ``WORSE_THAN_NOMINAL``) or moved the sample points by
        less than the stages' ``tol_px`` from it, or by less than
        ``NEAR_NOMINAL_PX`` without predicting the views left out of a
        reconstruction better (``NOMINAL_HOLDS``).
    nominal : VectorGeometry
    poses : Poses
        ``geometry`` as poses relative to ``nominal``, gauge fixed (``gauge``).
    assessment : Assessment or None
        The measurement at the poses returned: uncertainties, unobservable
        directions, motion modes (free and constrained histories).
    history : tuple of dict
        One entry per round of every stage (:class:`DriverResult`).
    stages : tuple of Stage
        The stage list that ran.
    stage_outcomes : tuple of StageOutcome
    volume, volume_initial : (nz, ny, nx) float32
        Reconstructions with ``geometry`` and with ``nominal`` on ``vol_geom``,
        the grid the user asked for.
    vol_geom : VolumeGeometry
    snr_before, snr_after : (n_views,) float
        Per-view SNR (dB) of the projections against the re-projection of
        the nominal and of the returned geometry's reconstruction, at the
        last stage's scale (coarse-grained data, its grid) and on its
        correlation grid (``oversample`` x finer): the fit as the calibration
        measures it, and the one the check against nominal compares.
    entropy_before, entropy_after : float
        Shannon entropy (bits) of the two volumes on a common gray range.
    motion : MotionSummary or None
    initial_offset_px : float or None
        The coarse axis-offset estimate used to start, in detector pixels.
    status : Status
        ``success`` is false when a stage diverged or did not converge, or
        when the result fitted the data worse than the nominal geometry.
    message : str
    timings : dict
        Seconds per step (``init``, ``stages``, each stage, ``final``).
    rejected_geometry : VectorGeometry or None
        The calibrated geometry that the final check rejected (the nominal
        geometry returned, or with ``Status.AXIS_OFFSET`` the axis that
        the opposite views confirm); with ``Status.NOMINAL_HOLDS`` the
        stages' geometry, near the nominal one.
    truncation : Truncation or None
        Whether the sample reaches past the volume box (read off the
        nominal reconstruction); when it crosses the top or bottom face the
        rays leaving there were left out, and SNR is on the rays kept.
    residual : (ResidualDiagnosis, ResidualDiagnosis)
        What the residual is made of, with the nominal and the returned
        geometry (:func:`diagnose_residual`); the calibrated one is logged as
        a warning when its χ is above 2 (at the nominal geometry the motion
        itself dominates the residual).
    residual_note : str
        With the calibrated geometry returned and a last stage that
        correlated against another volume than FDK/FBP (``nonneg_ls``):
        that the returned diagnosis is against FDK/FBP and what the stages'
        volume fitted (the report's residual row); else ``""``.
    """

    geometry: VectorGeometry
    nominal: VectorGeometry
    poses: Poses
    assessment: Optional[Assessment]
    history: tuple
    stages: tuple
    stage_outcomes: tuple
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
    status: Status
    message: str
    elapsed_s: float
    options: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    rejected_geometry: Optional[VectorGeometry] = None
    truncation: object = None
    residual: tuple = ()
    residual_note: str = ""


def per_view_snr(projections, volume, vol_geom, geom, *, weights=None) -> np.ndarray:
    """SNR (dB) of each view: ``20 log10(std(s_k) / std(s_k - Π_k f))``."""
    p = np.asarray(projections, np.float32)
    if current_session() is not None:  # on a Dask cluster: one number per view comes back
        return current_session().per_view(_snr_chunk, volume, vol_geom, geom, p, weights)
    return _snr_of(p, p - forward(volume, vol_geom, geom), weights)


def _snr_chunk(volume, vol_geom, geom, p, weights) -> np.ndarray:
    """:func:`per_view_snr` of one chunk of views (run by a Dask worker)."""
    return _snr_of(p, p - forward(volume, vol_geom, geom), weights)


def _snr_of(p, res, weights) -> np.ndarray:
    if weights is not None:
        w = np.broadcast_to(np.asarray(weights, np.float32), p.shape) > 0
        return np.array([snr_db(p[k][w[k]], res[k][w[k]]) for k in range(p.shape[0])], float)
    return np.asarray(snr_db(p, res, axis=(1, 2)), float)


def resolve_stages(det_shape, *, vol_shape=None, recipe="default", stages=None, scales="auto", max_outer=None, warmup=1,
                   geom: Optional[VectorGeometry] = None, notes: Optional[list] = None, region_of_interest: bool = False,
                   **model) -> tuple:
    """The stage list a calibration runs: ``stages`` as given, or the recipe's with the model overrides.

    With ``geom`` and automatic ``scales``, a parallel-beam scan leaves out the finest scales its views' distinct
    directions undersample (:func:`_direction_limited_scales`); why goes to ``notes`` (a list), or to the log. With
    ``geom``, the default recipe on a full turn stops its first scale at the first worse reconstruction
    (``strict_first_scale``) and refines at its finest scale by ``FULL_TURN_FINE_ROUNDS`` rounds (§5.53), and a
    parallel-beam scan's FDK/FBP stages get ``oversample_by = "auto"`` unless it is given
    (:func:`_spline_oversampled`); neither with ``region_of_interest`` (a scan that ``calibrate`` found
    truncated laterally: no second run follows, and material lies outside the volume; ``docs/method.md`` §5.50).
    """
    try:
        if stages is not None:
            if model or scales != "auto" or max_outer is not None:
                given = sorted(k for k in model) + [k for k, v in (("scales", scales != "auto"), ("max_outer", max_outer is not None)) if v]
                raise CalibrationError(f"stages= is given: set {given} in the stages instead")
            out = tuple(stages)
            if not out or not all(isinstance(s, Stage) for s in out):
                raise CalibrationError("stages must be a non-empty sequence of pdvc.calibration.Stage")
            return out
        # on a full turn the default's first scale stops at its first worse reconstruction, as the finer ones do: the
        # precession recipe's second run follows there, and the rounds past the best one only crept (§5.50)
        strict = (recipe == "default" and geom is not None and not region_of_interest
                  and opposite_fraction(geom) >= SHORT_SCAN_OPPOSITE_FRACTION)
        # ... and its finest scale refines by FULL_TURN_FINE_ROUNDS rounds (§5.53)
        fine = FULL_TURN_FINE_ROUNDS if strict else None
        out = recipe_stages(recipe, det_shape, vol_shape=vol_shape, scales=scales, max_outer=max_outer, warmup=warmup,
                            strict_first_scale=strict, fine_rounds=fine, **model)
        if geom is not None and isinstance(scales, str) and scales == "auto":
            kept, why = _direction_limited_scales(geom, out)
            if why:
                notes.append(why) if notes is not None else log.info(why)
                out = recipe_stages(recipe, det_shape, vol_shape=vol_shape, scales=kept, max_outer=max_outer,
                                    warmup=warmup, strict_first_scale=strict, fine_rounds=fine, **model)
        if geom is not None and geom.kind == "parallel" and model.get("oversample_by") is None and not region_of_interest:
            out = tuple(_spline_oversampled(st) for st in out)
        if isinstance(scales, str) and scales == "auto" and vol_shape is not None and model.get("oversample") is None:
            top = Stage.oversample  # the model's, which recipe_stages lowered where its grid is above the cap
            for s in sorted({st.scale for st in out if st.oversample < top}, reverse=True):
                k = min(st.oversample for st in out if st.scale == s)
                why = (f"scales: scale {s} correlates at {k}x instead of {top}x: at {top}x its grid would hold "
                       f"{float(np.prod(vol_shape)) * (top / s) ** 3 / 1e6:.1f}M voxels, above the "
                       f"{round(MAX_CORRELATION_VOXELS ** (1 / 3))}^3 cap that a coarser schedule cannot keep (the "
                       f"detector would fall below 64 px; docs/method.md §5.29); set oversample to choose")
                notes.append(why) if notes is not None else log.info(why)
        return out
    except StageError as exc:
        raise CalibrationError(str(exc)) from None


def _region_of_interest_stages(stage_list, geom, vol_geom, recipe, scales, max_outer, warmup, model) -> tuple:
    """The stages a region-of-interest scan runs: where ``stage_list`` is what the recipe gives the scan (from
    :func:`calibrate`'s keywords or a config's recipe), the recipe's for a region of interest (``resolve_stages(...,
    region_of_interest=True)``); otherwise ``stage_list`` with ``oversample_by = "auto"`` made ``"reconstruction"``.

    Neither the strict first scale nor the spline-filled grid was measured to help there: no second run follows, and
    rods wider than the field fitted worse on the spline volume (``docs/method.md`` §5.50)."""
    kw = dict(vol_shape=vol_geom.shape, recipe=recipe, scales=scales, max_outer=max_outer, warmup=warmup, geom=geom,
              notes=[], **model)
    try:
        same = tuple(stage_list) == resolve_stages(geom.det_shape, **kw)
    except (CalibrationError, ValueError, TypeError):  # a stage of the user's own (an array basis) is not the recipe's
        same = False
    if same:
        return resolve_stages(geom.det_shape, region_of_interest=True, **kw)
    return tuple(st.replace(oversample_by="reconstruction") if st.oversample_by == "auto" else st for st in stage_list)


def _spline_oversampled(stage: Stage) -> Stage:
    """A parallel-beam FDK/FBP stage with ``oversample_by = "auto"``: its fine grid filled by cubic B-splines from
    its own grid (``calibrate`` makes it ``"reconstruction"`` on a region-of-interest scan).

    Back-projected on the 2x grid, every other slice of a parallel-beam scan lies on a detector row when the axis's
    pitch toward the beam is 0, and the reprojection of that FBP fits the data worse there than at a pitch of
    ±0.3-0.9° (noise-free rods longer than the field, truncation weights; on the 1x and 3x grids and with the spline
    the minimum is at 0): the FBP rounds walked the pitch to -0.6 to -0.9° (0.096-0.130 px, the opposite-view
    baseline 0.007-0.020 px; ``docs/method.md`` §5.50). On region-of-interest scans of rods the spline volume fitted
    worse (``bench_accuracy.py --quick --roi 1.0 --parallel --split tuning``: three rods 0.054-0.26 -> 0.10-0.49 px).
    """
    if stage.oversample > 1 and isinstance(stage.reconstruct, str) and stage.reconstruct == "fdk":
        return stage.replace(oversample_by="auto")
    return stage


def short_scan_reconstruction(geom: VectorGeometry, stages=None, **model) -> tuple[dict, Optional[str]]:
    """The model overrides with ``reconstruct = "nonneg_ls"`` for a short scan, and why (None: unchanged).

    A parallel scan over 180° (fewer than half of its views with a view
    opposite) determines the axis offset only weakly: a constant shift of
    every projection is, over half a turn, mostly a translation of the
    sample (the gauge), so the FBP's model error biases the offset. The
    consistent reconstruction removes that bias (``docs/method.md`` §6).
    A cone-beam short scan (180° plus the fan angle) is in the same case,
    and its FDK's Parker weights add their own model error. Only when
    neither ``stages`` nor ``reconstruct`` is given. On a parallel half
    turn whose model frees the tilts (``fixed`` without both ``rx`` and
    ``ry``) the note also says that the axis's tilt along the beam is
    weakly determined: the loop creeps along it (``docs/method.md`` §5.15).
    """
    if stages is not None or model.get("reconstruct") is not None:
        return model, None
    frac = opposite_fraction(geom)
    if frac >= SHORT_SCAN_OPPOSITE_FRACTION:
        return model, None
    analytic = "FBP" if geom.kind == "parallel" else "FDK"
    note = (f"a short {geom.kind}-beam scan ({100 * frac:.0f} % of the views have an opposite view): the axis offset "
            f"is weakly determined and the {analytic}'s model error would bias it; the calibration reconstructs by "
            f"non-negative least squares (slower; reconstruct = \"fdk\" for the {analytic})")
    fixed = model.get("fixed")
    tilts = fixed is None or not {"rx", "ry"} <= set([fixed] if isinstance(fixed, str) else fixed)
    if geom.kind == "parallel" and tilts:  # method.md §5.15: the rounds creep along it, stop where its bias leaves them
        note += ("; the axis's tilt along the beam is weakly determined too: where the model frees it, the rounds "
                 "walk along it (docs/method.md §5.15); they start from the tilt that the views' row sums measure without a "
                 "reconstruction where it stands out of its uncertainty (§5.30, §5.32; not with init = \"none\"), and a stage "
                 "stops where its rounds walk the tilt away from what the row sums say, if they hold it well (§5.31)")
    return dict(model, reconstruct="nonneg_ls"), note


def _validate(projections, geom, vol_geom, weights):
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
    p = np.asarray(p, np.float32)
    bad = ~np.isfinite(p)
    if bad.any():
        views = np.nonzero(bad.any(axis=(1, 2)))[0]
        raise CalibrationError(
            f"projections contain {int(bad.sum())} NaN/Inf values (first in view {int(views[0])}); "
            "expected finite line integrals: check the flat/dark normalisation"
        )
    if weights is not None:
        w = np.asarray(weights, np.float32)
        if w.shape[-2:] != tuple(geom.det_shape):
            raise ShapeError(f"weights must have the detector shape {tuple(geom.det_shape)}, got {w.shape}")
        if not (w > 0).any():
            raise CalibrationError("weights (detector ROI) select no pixel; expected a non-empty region")
    return p


@scheduler_keyword  # scheduler=None | "threads" | "local:N" | "tcp://host:port": the whole run on it
def calibrate(
    projections,
    geom: VectorGeometry,
    vol_geom: VolumeGeometry,
    *,
    recipe: str = "default",
    stages=None,
    scales="auto",
    max_outer: Optional[int] = None,
    warmup: int = 1,
    init: str = "auto",
    fix_scale: bool = True,
    weights=None,
    truncation: str = "auto",
    zingers: str = "auto",
    rings: str = "auto",
    roi: str = "auto",
    air: str = "auto",
    second_run: str = "auto",
    noise_variance: Optional[float] = None,
    times=None,
    center=None,
    backend: str = "auto",
    initial_poses: Optional[Poses] = None,
    checkpoint: Optional[Callable[[dict], None]] = None,
    resume: Optional[dict] = None,
    progress: Optional[Callable[[dict], None]] = None,
    **model,
) -> CalibrationResult:
    """Calibrate a scan from its own projections.

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) array
        Line integrals (flat/dark normalised, −log); not modified.
    geom : VectorGeometry
        Nominal per-view geometry.
    vol_geom : VolumeGeometry
        Reconstruction grid at full resolution; the final volume is on it.
    recipe : {"default", "precession", "jolts", "axis"}
        The named stage list (:func:`pdvc.calibration.recipe_stages`).
    stages : sequence of Stage, optional
        A stage list to run instead of a recipe.
    scales, max_outer, warmup, **model
        Recipe parameters: coarse-to-fine scales (``"auto"``: from the
        detector and the volume, :func:`pdvc.calibration.auto_scales`;
        in parallel beam without the finest ones that the views' distinct
        directions undersample by more than ``MAX_SCALE_UNDERSAMPLING``, a
        full turn of few views: ``docs/method.md`` §5.27), rounds per
        scale, warm-up rounds, and fields of the model stage (``basis``,
        ``frame``, ``fixed``, ``method``, ``reconstruct``, ``oversample``,
        ``tol_px``, ``max_iter``, ...; :class:`Stage`). A
        short scan (parallel over half a turn, cone beam over 180° plus
        the fan angle) without ``reconstruct`` (nor ``stages``)
        reconstructs by ``nonneg_ls`` (:func:`short_scan_reconstruction`).
        The recipe's switches go there too: ``jolts=False`` leaves out the
        jolt stage, ``refine=True`` adds the default recipe's refinement
        (:func:`pdvc.calibration.refine_stage`, ``docs/method.md`` §5.22).
    init : {"auto", "axis", "none"}
        Coarse initialisation: the axis offset from opposite views by
        cross-correlation (needs views ~180° apart). "auto" uses it when
        such pairs exist; an estimate refused as unreliable (pairs that
        correlate weakly or disagree) is still used when its FDK/FBP from
        half the views predicts the other half better than the nominal
        axis's. "axis" raises when the estimate is refused.
    fix_scale : bool
        Cone beam: also fix the magnification gauge (mean source-object
        distance = nominal); see :func:`pdvc.geometry.fix_gauge`.
    weights : (n_rows, n_cols) or (n_views, n_rows, n_cols) array, optional
        Detector ROI / weights at full resolution.
    truncation : {"auto", "on", "off"}
        Samples longer than the volume: drop the rays that leave the volume
        through its top or bottom face (:func:`truncation_weights`), which
        no reconstruction on ``vol_geom`` can explain. ``"auto"`` does so
        when the nominal reconstruction shows material in the end slices
        (:func:`detect_truncation`).
    zingers : {"auto", "off"}
        ``"auto"``: find zingers, hot and dead pixels (isolated pixels, or
        bright spots of 2-9 pixels, far from the reprojection of the nominal
        reconstruction, :func:`pdvc.io.remove_zingers`) and replace them by the median of
        their neighbours before calibrating; the volume is then
        reconstructed again without them. The projections given are not
        modified; the calibration and its final volume use the copy.
    rings : {"auto", "on", "off"}
        A fixed pattern of the detector (the same offset at a pixel in
        every view, from a flat field wrong at some pixels: stripes in the
        sinograms, rings in the volume) pulls the poses back toward the
        nominal geometry. ``"on"``: subtract it from every view before
        calibrating (:func:`pdvc.io.remove_rings`); ``"auto"``: when it
        holds ``RING_SHARE`` of the residual at the calibrated geometry
        or more in the columns away from the sample's outline (where a
        sharp edge leaves the reconstruction's own model error), and more
        than the sample's structure does (:class:`ResidualDiagnosis`: a
        pattern of the columns), subtract it and calibrate again
        (``docs/method.md`` §5.13, §5.40). The
        projections given are not modified; the calibration and its final
        volume use the copy.
    roi : {"auto", "on", "off"}
        A sample wider than the detector's field of view (a region-of-
        interest scan) adds the material outside the volume to every ray.
        ``"on"``: subtract from every view what the material outside the
        volume's inscribed cylinder adds on average over the views
        (:func:`outside_pattern`; the reconstructions carry the rows' edge
        values outward for the ramp filter) and calibrate on that copy;
        the final volumes are reconstructed from the data given, with the
        same padding; a scan whose nominal fit is then already at the noise
        (chi <= ``ROI_NOMINAL_CHI``) returns the nominal geometry with
        ``Status.UNDETERMINED``, and one whose calibrated geometry predicts
        views it was not reconstructed from worse than the nominal one
        (:func:`roi_cross_validated_rss`) with ``WORSE_THAN_NOMINAL``.
        On any scan whose rows' ends hold material (the sample reaches the
        volume's sides), the coarse axis offset is measured again with the
        opposite views compared over the columns both hold
        (:func:`estimate_axis_offset` with ``overlap=True``), and in
        parallel beam with opposite views each view is compared with its
        opposite reflected about the axis, upright or leaning in the
        detector plane where the views ask for the lean
        (:func:`estimate_axis_roll`): the stages start from that axis;
        where their geometry is then rejected and the opposite views match
        their mirror images better about that axis than about the nominal
        one (:func:`compare_offsets`), it is returned with
        ``Status.AXIS_OFFSET`` instead of the nominal geometry
        (``docs/method.md`` §5.42, §5.43).
        ``"auto"``: when the nominal reconstruction shows material at the
        volume's sides (:func:`detect_truncation`)
        and the volume is about as wide as the field of view (its inscribed
        radius at least ``ROI_FIELD_COVER`` of the field's): a narrower
        volume leaves out material that every view sees (``docs/method.md``
        §5.17).
    air : {"auto", "off"}
        What the rays that miss the sample read: 0 when the flat field
        matches. A flat field that does not leaves an air level, an offset
        per view and a profile across the columns
        (:func:`pdvc.io.estimate_air`), on every ray: the reconstructions
        take it for material (FBP turns it into a bright rim at the edge of
        the field) and the calibration for motion. ``"auto"``: when it is
        measurably off 0 and is air (:func:`air_to_subtract`: at most 90 %
        of the pixels, flat up to the noise, seen on both sides of the detector),
        subtract the part the views share (``AirEstimate.fitted``: the
        level and the column profile) and calibrate and reconstruct on that
        copy; what varies from view to view is left to the background
        fitted with the motion (``Stage.background``). A sample that covers
        the detector has no air to measure and is left as it is. ``"off"``:
        take the data as they are. The projections given are not modified
        (``docs/method.md`` §5.18).
    second_run : {"auto", "off"}
        A precession once per turn is taken up by the default recipe's
        volume, and its model choice cannot see it. ``"auto"``: when the
        default recipe kept a model without the precession on a full turn,
        the ``precession`` recipe runs as well, at the default's scales
        whose correlation grid holds at most ``SECOND_RUN_MAX_VOXELS`` (on
        a large scan the coarser ones only, with
        ``SECOND_RUN_COARSE_ROUNDS`` rounds, compared with the default's
        geometry before its finer scales, which run only if that is kept:
        §5.27, §5.55; where none holds that,
        at a coarser scale than the default's, §5.28), and the geometry whose
        reconstruction predicts the views it was not made from better by
        more than ``SECOND_RUN_GAIN`` (:func:`cross_validated_misfit`) is
        returned; the motion model's note says which and by how much
        (``docs/method.md`` §5.25). When
        the precession recipe's geometry predicts them worse than the
        default's by more than ``SECOND_RUN_TWICE_LOSS``, it runs once more
        with a precession at one and two cycles per turn (``basis =
        "drift:2"``), and that geometry is compared instead (§5.26).
    initial_poses : Poses, optional
        Where to start instead of the coarse initialisation.
    checkpoint, resume
        ``checkpoint(state)`` after every round; ``resume=state`` continues
        an interrupted run from such a state.
    progress : callable, optional
        Called with a dict ``{"event": ...}`` at every step.
    scheduler : {None, "threads", "local:N", "tcp://host:port"} or distributed.Client
        Where the projection passes and reconstructions run
        (:func:`pdvc.compute.use_scheduler`); None keeps the current one
        (threads unless inside ``use_scheduler``). Same results.

    Returns
    -------
    CalibrationResult
        ``status.success`` is false when the run diverged, did not
        converge, or fitted the data worse than the nominal geometry (then
        the nominal geometry is returned).
    """
    t_start = time.perf_counter()
    given = dict(recipe=recipe, stages=stages, scales=scales, max_outer=max_outer, warmup=warmup, init=init,
                 fix_scale=fix_scale, weights=weights, truncation=truncation, zingers=zingers, roi=roi, air=air,
                 second_run=second_run, noise_variance=noise_variance,
                 times=times, center=center, backend=backend, initial_poses=initial_poses, checkpoint=checkpoint,
                 progress=progress, **model)
    p = _validate(projections, geom, vol_geom, weights)
    if init not in ("auto", "axis", "none"):
        raise CalibrationError(f"init must be 'auto', 'axis' or 'none', got {init!r}")
    if truncation not in ("auto", "on", "off"):
        raise CalibrationError(f"truncation must be 'auto', 'on' or 'off', got {truncation!r}")
    if zingers not in ("auto", "off"):
        raise CalibrationError(f"zingers must be 'auto' or 'off', got {zingers!r}")
    if rings not in ("auto", "on", "off"):
        raise CalibrationError(f"rings must be 'auto', 'on' or 'off', got {rings!r}")
    if roi not in ("auto", "on", "off"):
        raise CalibrationError(f"roi must be 'auto', 'on' or 'off', got {roi!r}")
    if air not in ("auto", "off"):
        raise CalibrationError(f"air must be 'auto' or 'off', got {air!r}")
    if second_run not in ("auto", "off"):
        raise CalibrationError(f"second_run must be 'auto' or 'off', got {second_run!r}")
    if resume and resume.get("rings") == "on":  # the run being resumed had decided to remove them
        rings = "on"
    model, short_scan = short_scan_reconstruction(geom, stages, **model)
    if short_scan:
        log.info(short_scan)
    scale_notes: list = []
    stage_list = resolve_stages(geom.det_shape, vol_shape=vol_geom.shape, recipe=recipe, stages=stages, scales=scales,
                                max_outer=max_outer, warmup=warmup, geom=geom, notes=scale_notes, **model)
    for note in scale_notes:
        log.info(note)
    auto = stages is None and isinstance(scales, str) and scales == "auto"
    scales_text = "; ".join(scale_notes) or ("automatic (auto_scales)" if auto else "as given")
    if short_scan is None and stages is not None and any(s.reconstruct == "nonneg_ls" for s in stage_list):
        short_scan = short_scan_reconstruction(geom)[1]  # stages resolved from a config by the same rule: say why
    emit = progress if progress is not None else (lambda info: None)
    timings: dict = {}
    p, air_text = _air(air, p, timings)  # before the coarse initialisation: a column profile biases opposite views
    poses, history, start, offset_px = _start(p, geom, vol_geom, init, initial_poses, resume, fix_scale, emit, timings,
                                              stage_list[0].scale)
    # the row sums of a parallel scan whose axis offset is known: the stages start from their tilt where the coarse
    # initialisation started the run (not a resumed one), and they guard the rounds of a half turn (a resumed run too)
    tilt, tilt_text, row_sums = _tilt_init(p, geom, offset_px, timings) if offset_px is not None else (None, "", None)
    # where they give no tilt, a short parallel scan's stages may start from the lean its views near opposite measure
    lean, lean_text = (_lean_init(p, geom, timings) if tilt is None and offset_px is not None and not resume
                       else (None, ""))
    if resume:
        tilt, tilt_text = None, ""  # the poses are the checkpoint's
    p, found_rings = _rings(p, noise_variance, timings) if rings == "on" else (p, None)
    emit(dict(event="reconstruct", what="nominal"))
    vol_initial = reconstruct(p, vol_geom, geom)
    p, vol_initial, found_zingers = _zingers(zingers, p, vol_geom, geom, vol_initial, timings, poses)
    gamma2 = float(noise_variance) if noise_variance is not None else estimate_noise_variance(p)
    weights, trunc = _truncation(truncation, weights, None if air == "auto" else p, geom, vol_geom, vol_initial)
    p_out = None  # the data the output volumes are made from, when the stages calibrate on a corrected copy
    lateral = roi == "on" or (trunc is not None and trunc.lateral)
    pattern_text, pattern = "", None
    if lateral and air == "auto":  # before anything compares opposite views or fits the motion
        p, vol_initial, pattern_text, pattern = _roi_pattern(p, geom, vol_geom, vol_initial, timings)
    # a region-of-interest scan's axis offset that its opposite views confirm (the fallback), or why none can be
    mirror_start = _undecided(pattern, geom, offset_px) if lateral else None
    if lateral and offset_px is not None and not resume and mirror_start is None:
        poses, offset_px, mirror_start = _roi_start(p, geom, poses, offset_px, timings)
    fixed_pattern = mirror_start if isinstance(mirror_start, str) else ""  # the views less their mean vetoed the offset
    mirror_start = None if fixed_pattern else mirror_start
    if tilt is not None:
        poses, tilt_text = _with_tilt(poses, tilt, tilt_text, geom, offset_px, lateral)
    # the vertical motion the row sums measured: a resumed run holds what its first run held
    vertical_text, held = "", tuple(resume.get("held", ())) if resume else ()
    vm = row_sums.vertical_motion() if held and row_sums is not None else None
    known_jolts = vm.steps if vm is not None else ()
    if row_sums is not None and not resume:
        poses, held, known_jolts, vertical_text = _with_vertical(poses, row_sums, geom, vol_geom, lateral)
        vm = row_sums.vertical_motion() if held else None
    if lean is not None:
        poses, lean_text = _with_lean(poses, lean, lean_text, geom, lateral, held)
    row_sums, guard_text = _row_sums_guard(row_sums, geom, lateral)
    if roi == "on" or (roi == "auto" and trunc is not None and trunc.lateral and _covers_field(geom, vol_geom)):
        p_out, p, vol_initial = p, *_roi(p, geom, vol_geom, poses, timings)
    if lateral:
        stage_list = _region_of_interest_stages(stage_list, geom, vol_geom, recipe, scales, max_outer, warmup, model)

    def state_checkpoint(state):
        if checkpoint is not None:
            checkpoint(dict(state, offset_px=offset_px, rings=rings, held=list(held)))

    # the precession recipe's second run at the coarse scales only (the finer ones' grids above the cap): compared
    # before the default's finer scales, which run only if the default's geometry is kept (docs/method.md §5.55)
    deferred: dict = {}
    kept_scales, dropped_scales = _second_run_scales(stage_list, vol_geom, geom.det_shape, geom.n_views)

    def compare_first(i, partial):
        """run_stages' ``before_stage``: at the default's first stage of a scale the second run leaves out, the
        precession recipe runs and is compared with the default's geometry so far; true: its geometry is returned."""
        if deferred or stage_list[i].scale not in dropped_scales or not any(st.scale in kept_scales for st in stage_list[:i]):
            return False
        deferred["t_first"] = time.perf_counter() - t_start
        if not _second_run_reason(recipe, partial, geom, given, stage_list, vol_geom, p_out is not None)[0]:
            deferred["verdict"] = None  # no second run: the end of the run says why
            return False
        later = ", ".join(str(sc) for sc in sorted({st.scale for st in stage_list[i:]}, reverse=True))
        alt, take, verdict, t_alt = _precession_opinion(geom.apply(partial.poses), projections, geom, vol_geom, p, weights,
                                                        stage_list, partial, rings, given, emit, before=later)
        deferred.update(verdict=verdict, timings=t_alt, alt=alt if take else None)
        return take

    defer = (second_run == "auto" and recipe == "default" and not resume and DEFER_SECOND_RUN and bool(kept_scales)
             and bool(dropped_scales))

    t0 = time.perf_counter()
    drv = run_stages(
        p, geom, vol_geom, stage_list, poses=poses, noise_variance=gamma2, weights=weights, fix_scale=fix_scale,
        times=times, center=center, backend=backend, start=start, history=history, checkpoint=state_checkpoint,
        progress=emit, row_sums=row_sums, held=held, known_jolts=known_jolts,
        vertical=vm.translation if vm is not None and "tz" in held else None,
        before_stage=compare_first if defer else None,
    )
    timings["stages"] = time.perf_counter() - t0
    if deferred.get("alt") is not None:
        alt, verdict = deferred["alt"], deferred["verdict"]
        res = _replace(alt, options=dict(alt.options, model=f"{drv.model_choice.text()}; {verdict}", second_run=verdict),
                       timings=dict(alt.timings, **deferred["timings"], **{"first run (default recipe)": deferred["t_first"]}),
                       elapsed_s=time.perf_counter() - t_start)
        _log_done(res)
        return res
    for i, o in enumerate(drv.stages):
        timings[f"stage {i + start[0]} ({o.name}, scale {o.scale})"] = o.elapsed_s
    status, message = _too_large(drv, offset_px, stage_list)
    options = dict(
        recipe=recipe, stages=[_stage_text(s) for s in stage_list], init=init, fix_scale=bool(fix_scale),
        truncation=truncation, truncation_found=trunc.describe() if trunc is not None else "not checked",
        roi=_roi_text(roi, p_out is not None, trunc), air=air_text,
        background=_background_text(drv), zingers=found_zingers.describe() if found_zingers is not None else "not checked",
        rings=found_rings.describe() if found_rings is not None else (
            "not removed (rings = 'off')" if rings == "off" else "not removed: no fixed pattern of the detector stood out "
            "in the residual at the calibrated geometry"),
        model=drv.model_choice.text() if drv.model_choice is not None else "as given (no candidates compared)",
        reconstruction=short_scan or "as the stages set it", scales=scales_text,
    )
    if pattern_text:
        options["detector_pattern"] = pattern_text
    if tilt_text:
        options["axis_tilt"] = tilt_text
    if lean_text:
        options["axis_lean"] = lean_text
    if guard_text:
        options["row_sums_guard"] = guard_text
    if vertical_text:
        options["vertical_motion"] = vertical_text
    if isinstance(drv.background, int):
        log.info("background: %s", options["background"])
    res = _finish(
        p, geom, vol_geom, vol_initial, drv, stage_list, status, message, gamma2, weights, times, center, backend,
        fix_scale, emit, timings, dict(initial_offset_px=offset_px, options=options, truncation=trunc), p_out=p_out,
        mirror_start=mirror_start, fixed_pattern=fixed_pattern,
    )
    res = _replace(res, elapsed_s=time.perf_counter() - t_start)
    share = _fixed_pattern_share(res)
    if rings == "auto" and share >= RING_SHARE:
        log.warning("rings: a fixed pattern of the detector holds %.0f%% of the residual at the calibrated geometry, "
                    "away from the sample's outline (%.0f%% or more: it pulls the poses toward the nominal geometry); "
                    "it is subtracted from every view and the scan calibrated again (rings = 'auto')",
                    100 * share, 100 * RING_SHARE)
        emit(dict(event="rings", share=share))
        # from where the first pass started: its poses are pulled toward nominal, and a run started there stops short
        again = calibrate(projections, geom, vol_geom, rings="on", **given)
        rings_text = (f"{again.options['rings']}, then calibrated again: a pattern of the columns held {100 * share:.0f}% "
                      f"of the residual away from the sample's outline at the geometry of a first pass "
                      f"({res.elapsed_s:.1f} s)")
        return _replace(again, elapsed_s=time.perf_counter() - t_start, options=dict(again.options, rings=rings_text),
                        timings=dict(again.timings, first_pass=res.elapsed_s))
    if rings == "off" and share >= RING_SHARE:
        log.warning("a pattern of the detector columns holds %.0f%% of the residual at the calibrated geometry, away "
                    "from the sample's outline (rings "
                    "that pull the poses toward the nominal geometry): rings = 'auto' or 'on' subtracts the detector's "
                    "fixed pattern (docs/method.md)", 100 * share)
    if second_run == "auto":
        res = _second_run(res, projections, geom, vol_geom, p, weights, stage_list, drv, recipe, rings, given, emit, t_start,
                          roi_scan=p_out is not None,
                          decided=(deferred["verdict"], deferred["timings"]) if deferred.get("verdict") else None)
    _log_done(res)
    return res


def _log_done(res) -> None:
    log.info(
        "calibration done in %.1f s (%s): SNR %.2f -> %.2f dB, entropy %.3f -> %.3f bits",
        res.elapsed_s, res.status.name.lower(), float(np.mean(res.snr_before)), float(np.mean(res.snr_after)),
        res.entropy_before, res.entropy_after,
    )


#: ``second_run = "auto"``: the precession recipe's geometry is returned when its reconstruction predicts the views
#: it was not made from better than the default's by more than this fraction of the misfit (docs/method.md §5.25)
SECOND_RUN_GAIN = 2e-4
#: ... and when the precession recipe's geometry predicts them worse than the default's by more than this fraction, the
#: precession recipe runs once more with a precession at one and two cycles per turn (lab-frame drift:2;
#: docs/method.md §5.26)
SECOND_RUN_TWICE_LOSS = 5e-4
#: ... that run's rounds per scale (the recipe's 8 and 4 more: its model has 7 functions per free parameter, not 5; a
#: tuning scan's run reached 8 rounds still moving and stopped at 9 with 12)
SECOND_RUN_TWICE_ROUNDS = 12
#: ... and it runs at the default's scales whose correlation grid holds at most this many voxels, at a coarser scale
#: when none does (the precession recipe's rounds are non-negative least-squares fits on it: 5-10x an FDK round)
SECOND_RUN_MAX_VOXELS = 200**3
#: ... and whose views' rays at that scale times the grid's longest edge (the voxels one projection of its
#: non-negative least-squares iterations walks) are at most this many: the cost grows with the views and the detector
#: as well as the grid. A 2k scan of 1440 views binned by 4 (bench_large.py: 128^3 at scale 2, 1440 views of 256^2)
#: walks 1.2e10, its precession recipe's rounds 5 minutes each there; the benchmark suites' scans 3e7-6e8. Where the
#: default's coarsest scale is above it, the second run is not made (docs/method.md §5.57)
SECOND_RUN_MAX_RAY_STEPS = 1e9
#: ... where none of the default's scales is below that cap, at a coarser scale than the default's, if the detector has
#: at least this many columns there (the automatic schedule's coarsest scale keeps 64 or more; docs/method.md §5.28)
SECOND_RUN_MIN_COLUMNS = 48
#: ... where the finer scales are above it, the precession recipe runs at the coarser ones only, with this many rounds
#: (twice the recipe's, as the short scans' coarse scales: its loop creeps along the near-gauge modes, cheaply at a
#: coarse scale, and no finer scale refines what it leaves; docs/method.md §5.15, §5.27)
SECOND_RUN_COARSE_ROUNDS = NONNEG_COARSE_ROUNDS * _RECIPE_ROUNDS["precession"]
#: ... and these guards: the consistency guard alone. The recipe's entropy guard judges the FDK volume, which does not
#: hold a non-planar orbit; on the 128^3 benchmark scan with a 0.5 deg precession it stopped the coarse run after two
#: rounds at 0.213 px, where the run goes on to 0.019 px (docs/method.md §5.27). At the finest scale it stays: on the
#: 48^3 precession_drift case it stops a walk that the cross-validation would have taken (§5.12)
SECOND_RUN_COARSE_GUARDS = ("consistency",)
#: the comparison's volumes (one nonneg_ls fit per set of views and geometry, no rounds): at most this many ordered
#: subsets of at least NONNEG_MIN_SUBSET_VIEWS views each, as the short scans' refining round (docs/method.md §5.52)
SECOND_RUN_SUBSETS = NONNEG_REFINE_SUBSETS


#: ... and where it runs at the coarser scales only, it runs (and is compared) before the default's finer scales, which
#: run only where the default's geometry is kept: the precession recipe's geometry returned otherwise saves them
#: (docs/method.md §5.55)
DEFER_SECOND_RUN = True


#: model fields that make the user's model and volume: given, the default's run is the user's and runs alone
SECOND_RUN_USER_FIELDS = ("basis", "frame", "fixed", "reconstruct", "oversample", "oversample_by", "candidates")


def _second_run_reason(recipe, drv, geom, model, stage_list, vol_geom, roi_scan: bool = False) -> tuple:
    """(run it, why not): whether ``second_run = "auto"`` runs the precession recipe after the default's stages.

    ``model``: the options the user gave (a model or volume of their own: no second run). ``roi_scan``: the stages
    calibrated a region-of-interest scan (the outside's average subtracted)."""
    choice = drv.model_choice
    if recipe != "default" or choice is None or "precession" not in choice.scores or choice.winner == "precession":
        return False, ""
    if any(model.get(k) is not None for k in SECOND_RUN_USER_FIELDS):
        return False, ""
    if opposite_fraction(geom) < SHORT_SCAN_OPPOSITE_FRACTION:
        return False, ""  # half a turn: the views left out cannot tell the models apart (docs/method.md §5.12)
    if roi_scan:
        # every ray also crosses material outside the volume, which no reconstruction holds: a 32^3 foam wider than the
        # field had its 0.042 px geometry replaced by a 0.147 px one that predicted 0.12 % better (docs/method.md §5.26)
        return False, ("the precession recipe was not run as well: on a region-of-interest scan the views left out "
                       "cannot rank two geometries (second_run; docs/method.md §5.26)")
    if not _second_run_scales(stage_list, vol_geom, geom.det_shape, geom.n_views)[0]:
        top = max(st.scale for st in stage_list)
        above = _second_run_fits(stage_list, vol_geom, geom.det_shape, geom.n_views, top, top)
        return False, (f"the precession recipe was not run as well: {above} (second_run); "
                       f"for a stage that wobbles, run recipe = \"precession\"")
    return True, ""


#: The finest scales of an automatic schedule are left out while the views' distinct directions undersample that
#: scale's detector columns by more than this (π/2 columns per direction is the sampling FBP needs): on the 128³
#: tuning split a parallel full turn of 90 views (45 directions, 6.25×) walked at scale 1 from 0.013 to 0.078 px,
#: one of 60 directions (4.69×) did not move (docs/method.md §5.27)
MAX_SCALE_UNDERSAMPLING = 5.5


def _direction_limited_scales(geom, stage_list) -> tuple:
    """(scales, why): the stages' scales without the finest ones whose detector the views' distinct directions
    undersample by more than ``MAX_SCALE_UNDERSAMPLING``, the coarsest always kept; why: '' when none is left out.

    Parallel beam only: the scans seen to walk were parallel full turns, whose mirrored views halve the directions;
    cone-beam scans of 90 views (3.1x) refined well at the finest scale, and fewer were not measured."""
    scales = sorted({st.scale for st in stage_list}, reverse=True)
    if geom.kind != "parallel":
        return tuple(scales), ""
    n_dir = distinct_directions(geom)
    ratio = {s: np.pi / 2 * (geom.det_shape[1] / s) / max(n_dir, 1) for s in scales}
    kept = list(scales)
    while len(kept) > 1 and ratio[kept[-1]] > MAX_SCALE_UNDERSAMPLING:
        kept.pop()
    if len(kept) == len(scales):
        return tuple(scales), ""
    left = scales[len(kept):]
    return tuple(kept), (
        f"scales: {', '.join(map(str, left))} left out, the calibration ends at scale {kept[-1]}: the {geom.n_views} "
        f"views hold {n_dir} distinct directions (parallel beam: a view and the one half a turn later see the same "
        f"rays); FBP at scale {left[0]} ({geom.det_shape[1] // left[0]} detector columns) needs about "
        f"{np.pi / 2 * geom.det_shape[1] / left[0]:.0f} directions, {ratio[left[0]]:.2f}x as many (above "
        f"{MAX_SCALE_UNDERSAMPLING}, where a finer scale was seen to walk away from the coarser one's result; "
        f"docs/method.md §5.27). The final volume is still reconstructed at full resolution")


def _voxels(n: int) -> str:
    """``n`` voxels as ``edge^3`` when it is a cube."""
    e = round(n ** (1 / 3))
    return f"{e}^3" if e**3 == n else f"{n:.3g}"


def _correlation_grid(stage_list, vol_geom, scale, like=None):
    """The grid the stages of ``scale`` correlate on (their oversampling of the binned volume); a scale none of them
    runs at: with the oversampling of the stages of scale ``like``."""
    k = max(st.oversample for st in stage_list if st.scale == (scale if like is None else like))
    return refined_grid(vol_geom.binned(scale) if scale > 1 else vol_geom, k)


def _second_run_fits(stage_list, vol_geom, det_shape, n_views, scale, like) -> str:
    """'' where the precession recipe's rounds at ``scale`` fit the second run's caps, else which cap they are above:
    the correlation grid's voxels (``SECOND_RUN_MAX_VOXELS``) or, with ``n_views`` given, the views' rays at that
    scale times the grid's longest edge (``SECOND_RUN_MAX_RAY_STEPS``)."""
    grid = _correlation_grid(stage_list, vol_geom, scale, like=like).shape
    if int(np.prod(grid)) > SECOND_RUN_MAX_VOXELS:
        return f"the correlation grid of scale {scale}, {'x'.join(map(str, grid))}, is above " \
               f"{_voxels(SECOND_RUN_MAX_VOXELS)} voxels"
    steps = _ray_steps(det_shape, n_views, scale, grid)
    if steps > SECOND_RUN_MAX_RAY_STEPS:
        return (f"at scale {scale} the {n_views} views' rays cross the {'x'.join(map(str, grid))} grid in {steps:.2g} "
                f"voxel steps, above {SECOND_RUN_MAX_RAY_STEPS:.2g}")
    return ""


def _ray_steps(det_shape, n_views, scale, grid_shape) -> float:
    """The voxel steps of one projection of ``n_views`` views at ``scale`` through a grid of ``grid_shape`` (its rays
    times the grid's longest edge); 0 where ``n_views`` is None (not counted)."""
    if n_views is None:
        return 0.0
    return float(n_views) * (int(det_shape[0]) // scale) * (int(det_shape[1]) // scale) * max(grid_shape)


def _second_run_scales(stage_list, vol_geom, det_shape, n_views=None) -> tuple:
    """(scales, dropped): the default's scales, coarse to fine, whose correlation grid holds at most
    ``SECOND_RUN_MAX_VOXELS`` and whose ``n_views`` views' rays (when given) cross it in at most
    ``SECOND_RUN_MAX_RAY_STEPS`` voxel steps, and the finer ones left out (the precession recipe's rounds are
    non-negative least-squares fits: on a 256^3 grid a round takes a minute on 2 cores; docs/method.md §5.27, §5.57);
    none where the default's coarsest scale is above the voxel-step cap. Every grid is
    oversampled as the default's coarsest stages, as the precession recipe's stages at the scales it is given are
    (not as a finest scale whose oversampling the 256^3 cap lowered: ``capped_oversample``, §5.29).

    Where none does (a single scale on a detector below 128 columns with a volume above 100^3), the first scale
    coarser than the default's, by octaves, whose grid (oversampled as the default's coarsest stages) holds at most
    that while the detector keeps ``SECOND_RUN_MIN_COLUMNS`` columns at it (docs/method.md §5.28); none if no such
    scale."""
    scales = sorted({st.scale for st in stage_list}, reverse=True)
    fits = [not _second_run_fits(stage_list, vol_geom, det_shape, n_views, s, scales[0]) for s in scales]
    kept, dropped = tuple(s for s, ok in zip(scales, fits) if ok), tuple(s for s, ok in zip(scales, fits) if not ok)
    top = _correlation_grid(stage_list, vol_geom, scales[0], like=scales[0]).shape
    if kept or _ray_steps(det_shape, n_views, scales[0], top) > SECOND_RUN_MAX_RAY_STEPS:
        # the coarser scale is for grids above the voxel cap (§5.28); where the views' work at the default's coarsest
        # scale is above its cap, none: on the 2k scan of 1440 views the precession recipe at scale 8 (a 32^3 grid)
        # came back 67 px (full resolution) from the truth and its comparison there kept it (§5.57)
        return kept, dropped
    s = 2 * scales[0]
    while int(det_shape[1]) // s >= SECOND_RUN_MIN_COLUMNS:
        if not _second_run_fits(stage_list, vol_geom, det_shape, n_views, s, scales[0]):
            return (s,), dropped
        s *= 2
    return (), dropped


def _second_run(res, projections, geom, vol_geom, p, weights, stage_list, drv, recipe, rings, given, emit, t_start,
                roi_scan=False, decided=None):
    """The precession recipe run as well, and the geometry that predicts the views left out better returned.

    The default recipe's model choice scores the models on one volume, which
    has taken up a precession once per turn; two finished calibrations are
    compared on reconstructions that never saw the views they predict
    (:func:`cross_validated_misfit`, at the default's coarsest scale, with
    its detector weights). A precession recipe that predicts worse than the
    default by more than ``SECOND_RUN_TWICE_LOSS`` runs again with the
    lab-frame ``drift:2`` basis (a precession twice a turn, which neither
    model holds), and that run is compared instead.

    ``decided``: (verdict, timings) of the comparison made before the default's finer scales, which kept the default
    (``compare_first`` in :func:`calibrate`): only reported.
    """
    if decided is not None:
        verdict, timings_alt = decided
        return _replace(res, options=dict(res.options, model=f"{res.options.get('model', '')}; {verdict}", second_run=verdict),
                        timings=dict(res.timings, **timings_alt), elapsed_s=time.perf_counter() - t_start)
    run, why_not = _second_run_reason(recipe, drv, geom, given, stage_list, vol_geom, roi_scan)
    if not run:
        if why_not:
            log.info(why_not)
            res = _replace(res, options=dict(res.options, model=f"{res.options.get('model', '')}; {why_not}"))
        return res
    alt, take, verdict, timings_alt = _precession_opinion(res.geometry, projections, geom, vol_geom, p, weights,
                                                          stage_list, drv, rings, given, emit)
    if alt is None:
        return _replace(res, options=dict(res.options, model=f"{res.options.get('model', '')}; {verdict}",
                                          second_run=verdict), elapsed_s=time.perf_counter() - t_start)
    chosen = alt if take else res
    timings = dict(chosen.timings, **timings_alt)
    if take:
        timings["first run (default recipe)"] = res.elapsed_s
    model_text = f"{res.options.get('model', '')}; {verdict}"
    return _replace(chosen, options=dict(chosen.options, model=model_text, second_run=verdict), timings=timings,
                    elapsed_s=time.perf_counter() - t_start)


def _precession_opinion(default_geometry, projections, geom, vol_geom, p, weights, stage_list, drv, rings, given, emit,
                        before=""):
    """(result, take it, verdict, timings): the precession recipe's calibration and whether its geometry predicts the
    views left out better than ``default_geometry`` (:func:`_second_run`); result None when its run failed.

    ``before``: the default's finer scales not yet run, when the comparison comes before them (§5.55)."""
    from ._select import cross_validated_misfit

    scales, dropped = _second_run_scales(stage_list, vol_geom, geom.det_shape, geom.n_views)
    coarse = ""
    if dropped:
        above = _second_run_fits(stage_list, vol_geom, geom.det_shape, geom.n_views, max(dropped),
                                 max(st.scale for st in stage_list))
        coarser = ", coarser than the default's" if scales[0] > max(st.scale for st in stage_list) else ""
        coarse = f" at scale{'s' if len(scales) > 1 else ''} {', '.join(map(str, scales))} only{coarser} ({above})"
    if before:
        coarse += f", before the default's scale{'s' if ',' in before else ''} {before}"
    log.info("second run: the default kept the %s model; the precession recipe runs as well%s, and the geometry whose "
             "reconstruction predicts the views left out better is kept", drv.model_choice.winner,
             coarse or f" (scales {scales})")

    def precession_run(basis):
        """(result or None, seconds, why it failed): the precession recipe on the data as this run treated them."""
        emit(dict(event="second_run", recipe="precession", basis=basis or "recipe's"))
        t0 = time.perf_counter()
        kw = dict(given, recipe="precession", stages=None, scales=scales, rings=rings, checkpoint=None, resume=None,
                  second_run="off")  # rings: "on" when this is the run again without them
        if basis is not None:
            kw["basis"] = basis
        if dropped and given.get("guards") is None:
            kw["guards"] = SECOND_RUN_COARSE_GUARDS
        if given.get("max_outer") is None and (basis is not None or dropped):
            kw["max_outer"] = max(SECOND_RUN_TWICE_ROUNDS if basis is not None else 0,
                                  SECOND_RUN_COARSE_ROUNDS if dropped else 0)
        try:
            return calibrate(projections, geom, vol_geom, **kw), time.perf_counter() - t0, ""
        except (PdvcError, ValueError, ArithmeticError, MemoryError, np.linalg.LinAlgError) as exc:
            # a second opinion that fails loses nothing the first run found
            return None, time.perf_counter() - t0, f"{type(exc).__name__}: {exc}"

    # the background per view the default run fitted with the motion (an air level that drifts) is taken out of the
    # predicted views as well: it is the data's, not either geometry's (docs/method.md §5.25)
    background = drv.background if isinstance(drv.background, int) else None

    def misfit(geometries):
        # each volume by ordered subsets (the verdicts of the plain iteration within 0.01 %; more subsets than the
        # rounds' own, a single fit cannot accumulate their lean: docs/method.md §5.52)
        return cross_validated_misfit(p, vol_geom, geometries, scale=max(scales), weights=weights, background=background,
                                      subsets=nonneg_subsets(geom.n_views // 2, SECOND_RUN_SUBSETS),
                                      backend=given.get("backend", "auto"))

    alt, t_alt, why = precession_run(None)
    if alt is None:
        verdict = (f"then the precession recipe was run as well and failed after {t_alt:.1f} s ({why}): the default's "
                   f"geometry is kept")
        log.warning("second run: %s", verdict)
        return None, False, verdict, {"second run (precession recipe)": t_alt}
    t0 = time.perf_counter()
    m = misfit([default_geometry, alt.geometry])
    t_cv = time.perf_counter() - t0

    def better(m1):  # the fraction by which a misfit is below the default's
        return 1.0 - m1 / m[0] if m[0] > 0 else 0.0

    gain = better(m[1])

    def compared(name, t_run, g, m1):
        return (f"{name} ({t_run:.1f} s): its geometry predicts the views left out of its reconstruction "
                f"{100 * abs(g):.3g} % {'better' if g >= 0 else 'worse'} than the default's (cross-validated misfit "
                f"{m[0]:.6g} against {m1:.6g}, scale {max(scales)})")

    verdict = f"then {compared('the precession recipe ran as well' + coarse, t_alt, gain, m[1])}"
    timings_alt, basis = {"second run (precession recipe)": t_alt}, ""
    if gain < -SECOND_RUN_TWICE_LOSS:
        # a motion the default's model holds better than a precession once per turn: a precession twice a turn is
        # one (the lab-frame drift:2 basis; docs/method.md §5.26)
        log.info("second run: %s; the precession recipe runs once more with a precession at one and two cycles per "
                 "turn (basis drift:2)", verdict)
        alt2, t_alt2, why = precession_run("drift:2")
        timings_alt["second run (precession twice a turn)"] = t_alt2
        if alt2 is None:
            verdict += f"; the precession recipe with a precession twice a turn failed after {t_alt2:.1f} s ({why})"
        else:
            t0 = time.perf_counter()
            m2 = float(misfit([alt2.geometry])[0])
            t_cv += time.perf_counter() - t0
            alt, gain, basis = alt2, better(m2), " (basis drift:2)"
            verdict += "; then " + compared("with a precession at one and two cycles per turn (basis drift:2)",
                                            t_alt2, gain, m2)
    take = bool(alt.status.success and gain > SECOND_RUN_GAIN)
    verdict += (f"; comparisons {t_cv:.1f} s; more than {100 * SECOND_RUN_GAIN:.2g} % better needed"
                f"{'' if alt.status.success else ', and it did not succeed: ' + alt.message}: ")
    verdict += f"the precession recipe's geometry is returned{basis}" if take else "the default's geometry is kept"
    log.info("second run: %s", verdict)
    emit(dict(event="model", text=verdict, elapsed_s=sum(timings_alt.values()) + t_cv))
    timings_alt["second run (comparison)"] = t_cv
    return alt, take, verdict, timings_alt


def _replace(res, **kw):
    import dataclasses

    return dataclasses.replace(res, **kw)


def _stage_text(s: Stage) -> str:
    try:
        d = s.to_dict()
    except StageError:
        return f"{s.name} (custom)"
    return ", ".join(f"{k}={v}" for k, v in d.items())


def _start(p, geom, vol_geom, init, initial_poses, resume, fix_scale, emit, timings, scale: int = 1):
    """(poses, history, (stage index, rounds done), coarse offset) to start from; ``scale``: the first stage's."""
    if resume:
        log.info("resuming from checkpoint: stage %d, %d rounds done", resume["stage_index"], len(resume["history"]))
        emit(dict(event="resume", stage_index=int(resume["stage_index"]), rounds=len(resume["history"])))
        return (resume["poses"], list(resume["history"]), (int(resume["stage_index"]), int(resume.get("rounds_done", 0))),
                resume.get("offset_px"))
    if initial_poses is not None:
        if not isinstance(initial_poses, Poses) or initial_poses.n_views != geom.n_views:
            raise CalibrationError(f"initial_poses must be a pdvc.geometry.Poses of {geom.n_views} views")
        return initial_poses.gauge_fixed(geom, center=vol_geom.offset, scale=fix_scale), [], (0, 0), None
    if init == "none":
        return None, [], (0, 0), None
    from ._init import estimate_axis_offset, offset_poses, pairs_phrase

    emit(dict(event="init"))
    t0 = time.perf_counter()
    try:
        est = estimate_axis_offset(p, geom)
    except InitError as exc:
        if init == "axis":
            raise
        est = _checked_init(p, geom, vol_geom, scale, exc)
        if est is None:
            return None, [], (0, 0), None
    finally:
        timings["init"] = time.perf_counter() - t0
    log.info("coarse initialisation: axis offset %.2f px from %s", est.offset_px, pairs_phrase(geom, est.n_pairs))
    return offset_poses(geom, float(est.offset_px)), [], (0, 0), float(est.offset_px)


# the row sums' tilt is used to start from when it stands this many standard deviations above 0 (the standard
# deviations of a residual correlated along views and rows, AxisTiltEstimate.sd_inflation: docs/method.md §5.32), is
# at most this large (the linearisation), and the rows' first moments are the sinusoids the method assumes (the whole
# sample across the detector's width)
TILT_INIT_MIN_SIGNIFICANCE = 5.0
TILT_INIT_MAX_DEG = 3.0
TILT_INIT_MIN_MOMENTS_FIT = 0.7
# the row sums' guard is on, and their tilt a start, only where they hold the tilt to this many pixels at the
# detector's top and bottom rows (the larger standard deviation of roll and pitch times half the detector's height):
# a rod's row sums, with little off the axis to tilt, hold it to 0.12-0.31 px at 40 rows and read a drift with
# acceleration as a tilt (§5.32), at 5.4-5.8 standard deviations on two held-out rods (§5.39)
ROW_SUMS_MAX_SD_PX = 0.1


def _tilt_init(p, geom, offset_px: float, timings: Optional[dict] = None):
    """(The axis's tilt from the row sums when it is usable, else None; what they said, "" in cone beam; the row sums'
    :class:`RowSumConsistency` where they were measured, else None).

    :func:`pdvc.calibration.estimate_axis_tilt`, its time added to ``timings["init"]``; whether the stages start
    from it is :func:`_with_tilt`'s decision, once the nominal reconstruction has shown the sample.

    Parallel beam only. In a parallel half turn the reconstruct-and-correlate rounds creep toward the axis's tilt
    along the beam (``docs/method.md`` §5.15); the row sums measure it without a reconstruction.
    """
    if geom.kind != "parallel":
        return None, "", None
    from ._rowsums import RowSumConsistency

    t0 = time.perf_counter()
    try:
        rs = RowSumConsistency(p, geom, offset_px=offset_px)
    except InitError as exc:
        log.info("axis tilt from the row sums skipped: %s", exc)
        return None, f"not measured: {exc}", None
    finally:
        if timings is not None:
            timings["init"] = timings.get("init", 0.0) + time.perf_counter() - t0
    est = rs.estimate
    what = est.describe()
    sd_px = _row_sums_sd_px(est, geom)
    if (est.significance < TILT_INIT_MIN_SIGNIFICANCE or est.tilt_deg > TILT_INIT_MAX_DEG
            or est.moments_fit < TILT_INIT_MIN_MOMENTS_FIT or sd_px > ROW_SUMS_MAX_SD_PX):
        text = (f"{what}: not used (needs at least {TILT_INIT_MIN_SIGNIFICANCE:g} standard deviations, at most "
                f"{TILT_INIT_MAX_DEG:g}°, {100 * TILT_INIT_MIN_MOMENTS_FIT:.0f}% sinusoidal moments and the tilt held to "
                f"{ROW_SUMS_MAX_SD_PX:g} px at the detector's top and bottom rows, here {sd_px:.2f} px); the stages started "
                "from the untilted axis")
        log.info("axis tilt from the row sums %s", text)
        return None, text, rs
    log.info("coarse initialisation: axis tilt from the row sums: %s", what)
    return est, what, rs


def _with_tilt(poses, tilt, what: str, geom, offset_px: float, lateral: bool):
    """(The poses to start from, what the report says): the row sums' tilted axis, unless the sample reaches the sides.

    A sample wider than the volume (a region-of-interest scan, as the nominal reconstruction shows it, or
    ``roi = "on"``) leaves the rows' moments short of what lies outside the field: there the tilt measured is not
    used (on the tuning half turns of ``bench_accuracy.py --quick --half-turn --roi 0.9`` it made a foam and a
    granular scan 0.005 and 0.007 px worse).
    """
    if lateral:
        text = (f"{what}: not used, the sample reaches the sides of the volume (a region-of-interest scan: the rows' "
                "moments miss what lies outside the field); the stages started from the untilted axis")
        log.info("axis tilt from the row sums %s", text)
        return poses, text
    from ._rowsums import tilt_poses

    log.info("coarse initialisation: the stages start from the row sums' tilted axis")
    return (tilt_poses(geom, roll=tilt.roll, pitch=tilt.pitch, offset_px=offset_px),
            f"{what}: the stages started from this tilted axis")


#: a parallel scan without a full turn (fewer than SHORT_SCAN_OPPOSITE_FRACTION of its views with an opposite view)
#: whose row sums give no tilt and measure no vertical motion: its stages start from the axis's lean in the detector
#: plane that its views near opposite measure (estimate_axis_lean), where it is at least LEAN_INIT_MIN_DEG and at most
#: LEAN_INIT_MAX_DEG. Over half a turn the lean is weakly determined for the rounds, which start from the upright axis
#: and creep part of the way (a low-dose rod leaning 0.95 deg: 0.45 deg after five rounds, 0.094 px). Below 0.2 deg
#: the upright start is as good: on the tuning scans that do not lean, the views near opposite read 0.07-0.16 deg of
#: lean from a precession, a drift or jolts between the scan's first and last views (docs/method.md §5.59)
LEAN_INIT = True
LEAN_INIT_MIN_DEG = 0.2
LEAN_INIT_MAX_DEG = 3.0


def _lean_init(p, geom, timings: Optional[dict] = None):
    """(The axis's lean that a short parallel scan's views near opposite measure, or None where it is not measured or
    beyond ``LEAN_INIT_MAX_DEG``; what the report says, "" where it was not measured): the stages' start when the row
    sums give none (:data:`LEAN_INIT`; :func:`_with_lean` decides)."""
    from ._init import estimate_axis_lean

    if not LEAN_INIT or geom.kind != "parallel" or opposite_fraction(geom) >= SHORT_SCAN_OPPOSITE_FRACTION:
        # a full turn settles the lean in its rounds; in cone beam a view's opposite is its mirror image near the
        # mid-plane only, and the halves' lean started fresh cone-beam short scans worse (docs/method.md §5.59)
        return None, ""
    t0 = time.perf_counter()
    try:
        est = estimate_axis_lean(p, geom)
    except InitError as exc:
        log.info("axis lean from the views near opposite skipped: %s", exc)
        return None, f"not measured: {exc}"
    finally:
        if timings is not None:
            timings["init"] = timings.get("init", 0.0) + time.perf_counter() - t0
    what = (f"{est.roll_deg:+.3f} ± {np.degrees(est.roll_sd):.3f}° at {est.offset_px:+.3f} px (the offsets of the "
            f"detector's top and bottom halves of rows, {est.top.n_pairs} pairs of views near opposite)")
    if abs(est.roll_deg) > LEAN_INIT_MAX_DEG:
        text = f"{what}: not used (at most {LEAN_INIT_MAX_DEG:g}°); the stages started from the upright axis"
        log.info("axis lean %s", text)
        return None, text
    return est, what


def _with_lean(poses, lean, what: str, geom, lateral: bool, held: tuple = ()):
    """(The poses to start from, what the report says): the axis leaning as the views near opposite say, unless the
    sample reaches the sides (a region-of-interest scan starts from its own comparison of opposite views) or the row
    sums measured a vertical motion (``held``: the scan's first and last views, which the lean compares, lie at
    different heights, and the halves' offsets mix that with the lean: 2.0° read on a granular scan that drifted by
    2 px up and leaned none, docs/method.md §5.59)."""
    if lateral:
        why = "the sample reaches the sides of the volume (a region-of-interest scan)"
    elif "tz" in held:
        why = "the row sums measured a vertical motion, which the halves of the views near opposite read as a lean"
    elif abs(lean.roll_deg) < LEAN_INIT_MIN_DEG:
        why = f"below {LEAN_INIT_MIN_DEG:g}° (the upright axis is as good a start)"
    else:
        why = ""
    if why:
        text = f"{what}: not used, {why}; the stages started from the upright axis"
        log.info("axis lean %s", text)
        return poses, text
    log.info("coarse initialisation: the stages start from the axis's lean, %s", what)
    return _axis_poses(geom, lean.offset_px, lean.roll), f"{what}: the stages started from this leaning axis"


# the vertical motion that the row sums' registration measured (RowSumConsistency.vertical_motion) is where the stages
# start and is held there by every stage of a smooth model (docs/method.md §5.35) when: its fit stands this far above
# the noise of the views' shifts (energy over noise's, an F ratio), its residual is at most this many times that noise
# (the fit holds the motion; a tilted or precessing axis left a foam's registration 1.7-2x its noise), and it moves the
# sample by at least this RMS, pixels (a tilted axis reads as 0.001-0.011 px of it on the tuning half turns, drifts as
# 0.05-0.37 px)
VERTICAL_MIN_F = 25.0
VERTICAL_MAX_MISFIT = 1.5
VERTICAL_MIN_RMS_PX = 0.03


def _with_vertical(poses, row_sums, geom, vol_geom, lateral: bool):
    """(The poses to start from, the parameters the stages hold, the views at which it steps, what the report says):
    the vertical motion that the row sums' registration measured, where it stands out of their noise and holds their
    shifts. Half and full turns alike (the rounds walked a rod's vertical position away from the truth on both;
    ``docs/method.md`` §5.35, §5.36), not on a region-of-interest scan (``lateral``: the rows' sums miss what lies
    outside the field)."""
    if lateral or poses is None:
        return poses, (), (), ""
    vm = row_sums.vertical_motion()
    rms_px = float(np.sqrt(np.mean(vm.translation**2))) / float(np.linalg.norm(geom.v[0]))
    steps = f", steps at views {', '.join(map(str, vm.steps.tolist()))}" if vm.steps.size else ""
    what = (f"vertical motion from the row sums' registration: {rms_px:.3f} px RMS (a drift with acceleration{steps}), "
            f"{vm.f_stat:.0f}x the energy of the views' noise ({vm.noise_px:.3f} px), residual {vm.misfit:.2f}x that noise")
    if vm.f_stat < VERTICAL_MIN_F or vm.misfit > VERTICAL_MAX_MISFIT or rms_px < VERTICAL_MIN_RMS_PX:
        text = (f"{what}: not used (needs at least {VERTICAL_MIN_F:g}x, at most {VERTICAL_MAX_MISFIT:g}x and "
                f"{VERTICAL_MIN_RMS_PX:g} px)")
        log.info("%s", text)
        return poses, (), (), text
    text = (f"{what}: the stages start there and hold it (the jolt stage frees it again, with a step at the views it "
            f"finds{' and at those steps' if vm.steps.size else ''})")
    log.info("coarse initialisation: %s", text)
    return hold_vertical(poses, vm.translation, geom, vol_geom.offset), ("tz",), vm.steps, text


def _row_sums_sd_px(est, geom) -> float:
    """How well the row sums hold the axis's tilt, pixels: the larger of its standard deviations times half the detector's height."""
    return float(max(est.roll_sd, est.pitch_sd) * (geom.det_shape[0] - 1) / 2)


def _row_sums_guard(row_sums, geom, lateral: bool):
    """(The row sums the stages' guard reads, or None; what the report says of it, "" where none were measured).

    The guard (``run_stages(row_sums=...)``, ``docs/method.md`` §5.31) stops the walk along the pitch of a scan
    without opposite views; a full turn settles the tilt itself, a sample wider than the volume leaves the rows'
    moments short of what lies outside the field, and row sums that hold the tilt to more than
    ``ROW_SUMS_MAX_SD_PX`` (a rod's, with little off the axis; a drift they read as a tilt) would stop the rounds on
    their own error (§5.32).
    """
    if row_sums is None:
        return None, ""
    est = row_sums.estimate
    sd_px = _row_sums_sd_px(est, geom)
    why = ("the rows' first moments are not sinusoidal enough"
           if est.moments_fit < TILT_INIT_MIN_MOMENTS_FIT
           else f"the row sums hold the tilt to ±{sd_px:.2f} px only, over {ROW_SUMS_MAX_SD_PX:g} px "
                "(too little structure off the axis, or model error: docs/method.md §5.32)"
           if sd_px > ROW_SUMS_MAX_SD_PX
           else "the sample reaches the sides of the volume (a region-of-interest scan)" if lateral
           else "the scan has opposite views, whose rounds settle the tilt"
           if opposite_fraction(geom) >= SHORT_SCAN_OPPOSITE_FRACTION else "")
    if why:
        return None, f"off: {why}"
    return row_sums, ("on: once the rounds creep, a stage stops where its poses leave the tilt the row sums agree with "
                      "(docs/method.md §5.31)")


def _checked_init(p, geom, vol_geom, scale: int, exc: Exception):
    """The opposite views' offset that ``estimate_axis_offset`` refused as unreliable, if it predicts the views better.

    A region-of-interest scan or a noisy one correlates its opposite views weakly (the material outside the volume,
    the cone, the noise), yet their offset can be right where the stages, started at the nominal axis, creep toward
    it by a tenth of a pixel a round and stop short (a held-out granular scan: 2.31 px nominal, 2.71 px calibrated
    from nominal, 0.27 px from the refused offset of +2.13 px). The refused offset is kept when its FDK/FBP from half
    the views predicts the other half better than the nominal geometry's (:func:`cross_validated_rss`, at the first
    stage's scale), so that an offset that is wrong for a reason of its own (a bright detector column steering the
    pairs, ``tests/calibration/test_init.py``) is still refused. The estimate is made again without its two gates
    (refusal path only: a few FFT correlations).
    """
    from ._init import InitError, estimate_axis_offset, offset_poses

    try:
        est = estimate_axis_offset(p, geom, min_correlation=-np.inf, max_spread=np.inf)
    except InitError:
        est = None
    if est is None or not np.isfinite(est.offset_px) or geom.n_views < 4:
        log.info("coarse initialisation skipped: %s", exc)
        return None
    s = int(scale)
    p_s, g_s, vg_s = data_at_scale(p, geom, vol_geom, None, 1.0, s)[:3]
    moved = geom.apply(offset_poses(geom, float(est.offset_px)))
    cv_nominal = cross_validated_rss(p_s, vg_s, g_s)
    cv_offset = cross_validated_rss(p_s, vg_s, moved.binned(s) if s > 1 else moved)
    if not cv_offset < cv_nominal:
        log.info("coarse initialisation skipped: %s; its offset %+.2f px predicts the views left out no better than the "
                 "nominal axis (cross-validated residual %.6g against %.6g)", exc, est.offset_px, cv_offset, cv_nominal)
        return None
    log.info("coarse initialisation: the opposite views' estimate was refused (%s), but its offset %+.2f px predicts "
             "the views left out better than the nominal axis (FDK/FBP from half the views: cross-validated residual "
             "%.6g against %.6g): kept", exc, est.offset_px, cv_offset, cv_nominal)
    return est


def _too_large(drv, offset_px, stages):
    """The driver's status, or MOTION_TOO_LARGE when the signs say the linearisation could not follow.

    Either sign is enough when no coarse initialisation placed the axis: the
    last round still moves sample points by more than a pixel, or the data
    consistency of the reconstruction stayed far above the noise (χ > 3) and
    fell by less than half over the run.
    """
    status, message = drv.status, drv.message
    hist = drv.history
    if not hist or status.success or offset_px is not None:
        return status, message
    inc = float(hist[-1]["increment_px"])
    c0, c1 = float(hist[0]["chi_before"]), float(hist[-1]["chi_before"])
    stuck = np.isfinite(c0) and np.isfinite(c1) and c1 > 3.0 and c1 > 0.5 * c0
    if inc > max(1.0, 20 * stages[-1].tol_px) or stuck:
        s0 = stages[0].scale
        message = (
            f"{Status.MOTION_TOO_LARGE.message}: the last round moved sample points by {inc:.2f} px and the "
            f"reconstruction's chi went {c0:.3g} -> {c1:.3g} (1 = noise only); start at a coarser scale "
            f"(e.g. scales = [{4 * s0}, {2 * s0}, 1]), use init = 'axis', or raise max_outer"
        )
        log.warning(message)
        return Status.MOTION_TOO_LARGE, message
    return status, message


#: rings = "auto": the share of the residual at the calibrated geometry that a pattern of the detector columns must hold,
#: away from the sample's outline, for the detector's fixed pattern to be removed and the scan calibrated again
#: (docs/method.md §5.13, §5.40: tuning scans without rings at most 0.043, with rings of 0.02 RMS 0.08-0.37; 0.06
#: fired on more of these and made the tuning half turns worse)
RING_SHARE = 0.10


def _fixed_pattern_share(res) -> float:
    """The share of the residual at ``res``'s geometry that is a pattern of the detector columns, the same in every view,
    in the columns away from the sample's outline where the data tell them (:class:`ResidualDiagnosis`; at most 4.3 %
    on the tuning scans without rings, 8-37 % with rings of 0.02 RMS; docs/method.md §5.40): a rod centred on the axis
    keeps its edge at the same columns in every view, and what the reconstruction does not reproduce of it there
    (up to 64 % of the residual of a clean rod) is no fixed pattern of the detector. 0 when the sample's structure
    holds more than the column pattern (motion the model did not hold, e.g. an axis offset, also leaves a pattern of
    the columns)."""
    d = res.residual[1] if getattr(res, "residual", None) else None
    if d is None or d.column_pattern <= d.structure:
        return 0.0
    return float(d.column_pattern if d.column_pattern_off_outline is None else d.column_pattern_off_outline)


def _rings(p, noise_variance, timings):
    """(projections, RingReport): the detector's fixed pattern subtracted from every view."""
    from ..io import remove_rings

    t0 = time.perf_counter()
    gamma2 = float(noise_variance) if noise_variance is not None else estimate_noise_variance(p)
    p, found = remove_rings(p, noise_variance=gamma2)
    log.info("rings: %s", found.describe())
    timings["rings"] = time.perf_counter() - t0
    return p, found


_ZINGER_PROBE_STEP = 8


def zinger_probe(p, volume, vol_geom, geom):
    """:func:`pdvc.io.remove_zingers`'s report on every ``_ZINGER_PROBE_STEP``-th view against the reprojection
    of ``volume`` (zingers are spread over the views, a hot pixel is in all of them), or None for a scan too
    short to be probed (fewer than 8 such views)."""
    from ..io import remove_zingers

    if geom.n_views < 8 * _ZINGER_PROBE_STEP:
        return None
    sub = slice(None, None, _ZINGER_PROBE_STEP)
    _, probe = remove_zingers(p[sub], forward(volume, vol_geom, geom[sub]))
    return replace(probe, every=_ZINGER_PROBE_STEP)


def _zingers(mode, p, vol_geom, geom, vol_initial, timings, poses=None):
    """(projections, nominal volume, ZingerReport or None): zingers replaced when ``mode`` is "auto".

    Found on the residual against the nominal reconstruction (no extra reconstruction), on every
    ``_ZINGER_PROBE_STEP``-th view first (a scan without zingers costs that forward projection; zingers
    are spread over the views, a hot pixel is in all of them), then on all views. When some were, once
    more against a reconstruction without them at the coarse initialisation's poses (the ramp filter
    spreads a zinger over the reconstruction, which hides weaker ones nearby, and a misplaced edge
    hides those on it); the nominal volume is then made again without them.
    """
    if mode == "off":
        return p, vol_initial, None
    from ..io import ZingerReport, remove_zingers

    t0 = time.perf_counter()
    probe = zinger_probe(p, vol_initial, vol_geom, geom)  # on a scan without zingers that is all it costs
    if probe is not None and not probe.count:
        log.info("zingers: %s", probe.describe())
        timings["zingers"] = time.perf_counter() - t0
        return p, vol_initial, probe
    p, total = remove_zingers(p, forward(vol_initial, vol_geom, geom))
    if total.count:
        g = geom if poses is None else geom.apply(poses)
        p, again = remove_zingers(p, forward(reconstruct(p, vol_geom, g), vol_geom, g))
        total = ZingerReport(total.count + again.count, total.fraction + again.fraction,
                             max(total.views, again.views), total.sigma, total.threshold,
                             blobs=total.blobs + again.blobs)
        vol_initial = reconstruct(p, vol_geom, geom)
    (log.warning if total.fraction > 1e-3 else log.info)("zingers: %s", total.describe())
    timings["zingers"] = time.perf_counter() - t0
    return p, vol_initial, total


#: a calibrated geometry that moves the sample points by less than this from the nominal one (RMS, full-resolution
#: pixels, gauge taken out) is a measurement only where its reconstruction predicts the views it was not made from
#: better than the nominal one's by more than NEAR_NOMINAL_GAIN; otherwise the nominal geometry holds. The stages'
#: loop walks 0.005-0.06 px on scans that did not move (still full turns, half turns, short scans of the tuning
#: splits), each walk fitting the data a hair better by its own FDK/FBP; a real motion of that size moves the
#: prediction of views left out by percents (docs/method.md §5.56). Above this move the check is not made (its cost:
#: two non-negative least-squares volumes per geometry)
NEAR_NOMINAL_PX = 0.25
#: ... the fraction of the cross-validated misfit by which the calibrated geometry must predict better. Tuning (the
#: still quick splits: full and half turns, the synchrotron list with its flat field, short scans; 48 scans): walks
#: of 0.005-0.06 px predict between 0.18 % better and 0.11 % worse; the moving tuning scans, 3.5-95 % better
NEAR_NOMINAL_GAIN = 5e-3


#: roi: a region-of-interest scan whose fit at the nominal geometry has chi at most this (the outside's average
#: subtracted) returns the nominal geometry with Status.UNDETERMINED. Tuning (bench_accuracy.py --quick --roi 1.0
#: --split tuning): three rods at i0 = 2e3, chi 0.90-0.94 at nominal, calibrated 0.05-0.19 px farther from the truth;
#: foam and granular 1.75-3.27
ROI_NOMINAL_CHI = 1.1


#: roi = "auto" compensates a region-of-interest scan only when the volume's inscribed radius is at least this
#: fraction of the field of view's radius: material seen in every view but cut off by the window (a volume narrower
#: than the field) is structure the model cannot explain (bench_accuracy.py --quick --roi 1.0, held out: with the
#: volume as wide as the field, median 0.65 -> 0.48 px and foams 0.12-0.42 -> 0.023-0.089 px; with a volume of
#: 0.71 of the field, a granular scan 0.15 -> 1.26 px; docs/method.md §5.17)
ROI_FIELD_COVER = 0.9


def cross_validated_rss(p, vol_geom: VolumeGeometry, geom: VectorGeometry, weights=None) -> float:
    """How well a geometry predicts views it was not reconstructed from: FDK/FBP from the even views, the odd views
    predicted (and the other way round), each prediction scaled by least squares; the weighted residual sum of squares.

    A geometry that fits the data better only because the reconstruction adapts to it (a model that leaves
    structure out) predicts the views it has not seen no better.
    """
    w = np.broadcast_to(np.float32(1.0) if weights is None else np.asarray(weights, np.float32), p.shape)
    total = 0.0
    for a, b in ((0, 1), (1, 0)):
        q = forward(reconstruct(p[a::2], vol_geom, geom[a::2]), vol_geom, geom[b::2])
        s = np.asarray(p[b::2], np.float32)
        wb = w[b::2]
        k = float(np.sum(wb * q * s, dtype=np.float64) / max(float(np.sum(wb * q * q, dtype=np.float64)), 1e-300))
        total += float(np.sum(wb * (s - k * q) ** 2, dtype=np.float64))
    return total


def roi_cross_validated_rss(p, vol_geom: VolumeGeometry, geom: VectorGeometry, weights=None) -> float:
    """:func:`cross_validated_rss` of a region-of-interest scan ``p`` with the outside's average estimated at ``geom``
    itself (:func:`outside_pattern`): an average taken at one geometry favours that geometry."""
    from ._truncation import outside_pattern

    return cross_validated_rss(p - outside_pattern(p, vol_geom, geom)[None], vol_geom, geom, weights)


def _covers_field(geom, vol_geom) -> bool:
    """Whether the volume's inscribed cylinder reaches ``ROI_FIELD_COVER`` of the field of view (and says so if not)."""
    from ._truncation import field_cover

    cover = field_cover(geom, vol_geom)
    if cover >= ROI_FIELD_COVER:
        return True
    log.warning("roi: a region-of-interest scan, not compensated: the volume's inscribed radius is %.0f%% of the field "
                "of view's; reconstruct the whole field (a volume as wide as the detector sees, the default of a config "
                "without [volume]) for roi = 'auto' to compensate it, or set roi = 'on'", 100 * cover)
    return False


#: a region-of-interest half turn without opposite views: its opposite views' offset is a fallback only when at least
#: this many times the change of the pairs' line over the step it is extrapolated (a held-out foam, 0.068 px nominal:
#: offset 0.38 px, 1.3 times the 0.29 px change, returned at 0.139 px; the tuning half turns 3.6 times or more;
#: docs/method.md §5.42)
MIRROR_MIN_EXTRAPOLATIONS = 2.0


def _undecided(est, geom, offset_px) -> str | None:
    """Why the axis of a region-of-interest scan without a full turn cannot be confirmed, where a pattern fixed on the
    detector and the axis cannot be told apart (:attr:`~pdvc.calibration.DetectorPatternEstimate.undecided`; ``est``
    from :func:`_roi_pattern`, None where it made none); else None. Nothing measures such a pattern there (no air, no
    full turn's mean as :func:`_fixed_pattern_check` has), and the opposite views' offset is where it, if there is one,
    looks symmetric: the stages start where they would have without the scan being a region of interest and the final
    check is to reject their geometry, as for the veto of :func:`_fixed_pattern_check` (docs/method.md §5.46)."""
    if est is None or not est.undecided or _full_turn(geom):
        return None
    log.warning("roi: the opposite views' axis offset (%+.2f px) is not used: with a line common to every pair (a "
                "pattern fixed on the detector) the axis goes to %+.2f px, not held within a pixel (%.1f standard "
                "errors), and with no air in the field and no full turn nothing else measures such a pattern; the "
                "stages start from %s", est.plain_offset_px, est.offset_px, est.offset_t,
                "the nominal axis" if offset_px is None else f"the coarse initialisation's {offset_px:+.2f} px")
    return (f"the opposite views put the axis at {est.plain_offset_px:+.2f} px, but with a line common to every pair "
            f"(a pattern fixed on the detector, a flat field that varies across the columns?) at {est.offset_px:+.2f} "
            f"px, not held within a pixel ({est.offset_t:.1f} standard errors): the axis cannot be told from such a "
            f"pattern, and with no air in the field and no full turn nothing measures it")


def _roi_start(p, geom, poses, offset_px: float, timings):
    """A region-of-interest scan (material at the rows' ends): the coarse axis offset measured again with the opposite
    views compared over the columns both hold (:func:`estimate_axis_offset` with ``overlap=True``); in parallel beam
    with opposite views, each view against its opposite reflected about the axis, upright or leaning in the detector
    plane where the views ask for the lean (:func:`estimate_axis_roll`); and whether their mirror images confirm that
    axis against the nominal one (:func:`compare_offsets`).

    Returns ``(poses, offset_px, mirror_start)``, the poses the stages start from; ``mirror_start`` is ``(offset_px,
    roll, comparison, line)`` where the opposite views match better about that axis than about the nominal one, else
    None (``roll`` 0 and ``line`` None where no lean was kept), or a sentence where the views less their mean veto
    the offset (:func:`_fixed_pattern_check`: the stages start from ``poses`` and the final check is to reject
    their geometry). The correlation of whole rows takes out a straight
    line through each row's ends, which on such a scan pulls the offset toward the detector's centre (rods of
    ``bench_accuracy.py --quick --roi 1.0``: -0.20 px found for +1.28 px).
    """
    from ._init import _pairs, _scan_angles, compare_offsets

    t0 = time.perf_counter()
    start_poses = poses
    try:
        est = _overlap_offset(p, geom)
        line = _roi_line(p, geom, est)
    except InitError as exc:
        log.info("roi: the opposite views compared over the columns both hold give no axis offset (%s); the coarse "
                 "initialisation's %+.2f px kept", exc, offset_px)
        return poses, offset_px, None
    finally:
        timings["init"] = timings.get("init", 0.0) + time.perf_counter() - t0
    t0 = time.perf_counter()
    offset, roll = float(est.offset_px), 0.0
    if line is not None:
        kept = line.comparison.second_better
        offset, roll = (line.offset_px, line.roll) if kept else (line.upright_offset_px, 0.0)
        line = line if kept else None
    log.info("roi: the rows' ends hold material: axis offset %+.2f px%s from the opposite views compared over the columns "
             "both hold (the correlation of whole rows said %+.2f px); the stages start there", offset,
             f", leaning {np.degrees(roll):+.3f} deg" if roll else "", offset_px)
    poses = _axis_poses(geom, offset, roll)
    try:
        mirror = compare_offsets(p, geom, 0.0, offset, mismatch_slope=est.mismatch_slope)
    except InitError as exc:
        log.info("roi: the offset not compared with the nominal axis: %s", exc)
        return poses, offset, None
    finally:
        timings["init"] = timings.get("init", 0.0) + time.perf_counter() - t0
    log.info("roi: each view against its mirrored opposite, mean squared difference %.4g with the nominal axis, %.4g "
             "with the axis at %+.2f px (%.1f standard errors over %d pairs)", mirror.msd[0], mirror.msd[1],
             offset, mirror.t, mirror.n_pairs)
    fixed = _fixed_pattern_check(p, geom, offset)
    if fixed is not None and fixed.t < -MIRROR_MIN_T:
        log.warning("roi: the axis offset %+.2f px from the opposite views is not used: with the mean of the views taken "
                    "out (what the detector adds to every view alike, a flat field that varies across the columns), the "
                    "views match their opposites better about the nominal axis by %.1f standard errors (mean squared "
                    "difference %.4g against %.4g); the stages start from the coarse initialisation's %+.2f px",
                    offset, -fixed.t, fixed.msd[0], fixed.msd[1], offset_px)
        return start_poses, offset_px, (
            f"a pattern fixed on the detector (a flat field that varies across the columns?) pulled the comparison of "
            f"opposite views to {offset:+.2f} px; with the mean of the views taken out they match better about the "
            f"nominal axis by {-fixed.t:.1f} standard errors, and with no air in the field nothing measures the "
            f"pattern")
    if est.mismatch_slope:
        # a 180-degree scan: the offset is the line through pairs 0-2 steps from opposite, extrapolated by up to a
        # step; one within MIRROR_MIN_EXTRAPOLATIONS of that step's change is not told from it
        step = _pairs(_scan_angles(geom))[2]
        change = abs(est.mismatch_slope) * step
        if abs(offset) < MIRROR_MIN_EXTRAPOLATIONS * change:
            log.info("roi: the offset is not kept as a fallback: %.2f px is less than %g times the %.2f px by which the "
                     "pairs' line changes over the step it is extrapolated (fewer than two pairs of views opposite "
                     "within half a step)", abs(offset), MIRROR_MIN_EXTRAPOLATIONS, change)
            return poses, offset, None
    return poses, offset, ((offset, roll, mirror, line) if mirror.second_better else None)


def _roi_pattern(p, geom, vol_geom, vol_initial, timings):
    """A region-of-interest scan: a pattern fixed on the detector that its opposite views (or, on a 180-degree scan, its
    views near opposite) see mirrored (a flat field tilted across the columns, which such a scan has no air to
    measure), fitted with the axis offset (:func:`estimate_detector_pattern`) and, where found, its part antisymmetric
    about the axis subtracted from every view (a copy) and the nominal volume reconstructed again. Returns ``(p,
    vol_initial, text, est)``; ``text`` is empty and ``est`` (the :class:`~pdvc.calibration.DetectorPatternEstimate`)
    None where the scan has no such views to compare. A pattern confounded with the axis
    (:attr:`~pdvc.calibration.DetectorPatternEstimate.confounded`) is not found, nor subtracted."""
    from ._init import estimate_detector_pattern

    t0 = time.perf_counter()
    try:
        est = estimate_detector_pattern(p, geom)
    except InitError as exc:
        log.info("roi: no pattern fixed on the detector looked for: %s", exc)
        return p, vol_initial, "", None
    finally:
        timings["init"] = timings.get("init", 0.0) + time.perf_counter() - t0
    figures = est.describe()
    if est.confounded:
        log.warning("roi: a pattern fixed on the detector cannot be told from the axis offset: %s", figures)
        return p, vol_initial, f"not told from the axis (each view against its mirrored opposite: {figures})", est
    if not est.found:
        return p, vol_initial, f"none found (each view against its mirrored opposite: {figures})", est
    log.warning("roi: a pattern fixed on the detector (a flat field that varies across the columns?), which the opposite "
                "views see mirrored: %s; its part antisymmetric about the axis is subtracted from every view", figures)
    p = p - est.pattern(geom.det_shape)[None]
    return p, reconstruct(p, vol_geom, geom), f"subtracted: {figures}", est


#: roi: the offset from opposite views smoothed along the columns is used where it is within this many pixels of the
#: unsmoothed one (the smoothing takes out the noise's pull toward fractional shifts, 0.21-0.23 px on a cylinder at
#: i0 = 2e3; it also weakens a fine structure against a pattern fixed on the detector: a granular scan under issue #10's
#: flat field at -6.7 px smoothed, +1.39 px unsmoothed, +1.4 px true; docs/method.md §5.43)
OVERLAP_SMOOTH_AGREE_PX = 0.5


def _overlap_offset(p, geom):
    """:func:`estimate_axis_offset` over the overlap, smoothed where it agrees with the unsmoothed estimate within
    ``OVERLAP_SMOOTH_AGREE_PX``, else unsmoothed."""
    from ._init import estimate_axis_offset

    try:
        smooth = estimate_axis_offset(p, geom, overlap=True)
    except InitError as exc:
        log.info("roi: the opposite views smoothed give no axis offset (%s); unsmoothed", exc)
        return estimate_axis_offset(p, geom, overlap=True, smooth=False)
    try:
        raw = estimate_axis_offset(p, geom, overlap=True, smooth=False)
    except InitError:
        return smooth
    if abs(smooth.offset_px - raw.offset_px) <= OVERLAP_SMOOTH_AGREE_PX:
        return smooth
    log.warning("roi: the opposite views smoothed along the columns put the axis at %+.2f px, unsmoothed at %+.2f px: "
                "the smoothing weakened the sample's fine structure against something else (a pattern fixed on the "
                "detector?); the unsmoothed offset is used", smooth.offset_px, raw.offset_px)
    return raw


def _fixed_pattern_check(p, geom, offset: float):
    """A full turn's views less their mean, each against its mirrored opposite with the nominal axis and at ``offset``
    (:func:`compare_offsets`); None on other scans or where they cannot be compared.

    What the detector adds to every view alike (a flat field that varies across the columns, which a region-of-interest
    scan has no air to measure) pulls the comparison of raw views toward where it looks symmetric; the mean of a full
    turn's views holds it, and is itself symmetric about the true axis, so that the views less their mean are still
    each other's mirror images about it, without the pattern. They hold less of a rod's information (its symmetric
    profile is in the mean), so they are a veto only: an offset they reject by ``MIRROR_MIN_T`` standard errors is
    not used (rods of ``bench_accuracy.py --quick --roi 1.0 --parallel --flat 0.69``: started and returned 2.0-2.2 px
    from the truth, farther than nominal, docs/method.md §5.43)."""
    from ._init import compare_offsets

    if not _full_turn(geom):
        return None
    try:
        fixed = compare_offsets(_LessMean(p), geom, 0.0, offset)
    except InitError:
        return None
    log.info("roi: the views less their mean, each against its mirrored opposite: mean squared difference %.4g with the "
             "nominal axis, %.4g at %+.2f px (%.1f standard errors)", fixed.msd[0], fixed.msd[1], offset, fixed.t)
    return fixed


def _full_turn(geom) -> bool:
    """Whether every view (but one) has an opposite: a full turn, whose views' mean is symmetric about the axis."""
    from ._init import _pairs, _scan_angles

    pairs, delta, _ = _pairs(_scan_angles(geom))
    return delta is None and pairs.shape[0] >= geom.n_views // 2 - 1


class _LessMean:
    """The views less their mean, view by view as they are read (no copy of the scan)."""

    def __init__(self, p):
        self.p = p
        self.mean = np.mean(p, axis=0, dtype=np.float64)

    def __getitem__(self, k):
        return np.asarray(self.p[k], np.float64) - self.mean


def _axis_poses(geom, offset_px: float, roll: float):
    """The poses of an axis offset by ``offset_px`` and leaning by ``roll`` (radians) in the detector plane."""
    from ._init import offset_poses
    from ._rowsums import tilt_poses

    return tilt_poses(geom, roll=roll, pitch=0.0, offset_px=offset_px) if roll else offset_poses(geom, offset_px)


def _roi_line(p, geom, est):
    """Each view of a parallel full turn against its opposite reflected about the axis, upright or leaning
    (:func:`estimate_axis_roll`, started from ``est``); None in cone beam or without opposite views."""
    from ._init import _pairs, _scan_angles, estimate_axis_roll

    if geom.kind != "parallel" or _pairs(_scan_angles(geom))[1] is not None:
        return None  # cone beam, or a half turn: fewer than two views are another's reflection
    try:
        line = estimate_axis_roll(p, geom, est)
    except InitError as exc:
        log.info("roi: the axis not fitted by reflecting the opposite views: %s", exc)
        return None
    cmp = line.comparison
    log.info("roi: each view against its opposite reflected about the axis: upright at %+.3f px (the overlap's estimate "
             "%+.3f px); leaning %+.3f deg at %+.3f px, mean squared difference %.4g upright, %.4g leaning (%.1f "
             "standard errors over %d pairs): %s", line.upright_offset_px, est.offset_px, line.roll_deg,
             line.offset_px, cmp.msd[0], cmp.msd[1], cmp.t, cmp.n_pairs,
             "the lean kept" if cmp.second_better else f"upright (the lean needs {MIRROR_MIN_T:g} standard errors)")
    return line


def _roi(p, geom, vol_geom, poses, timings):
    """A region-of-interest scan: the data with the outside's average subtracted, and its nominal reconstruction."""
    from ._truncation import outside_pattern

    t0 = time.perf_counter()
    g = geom if poses is None else geom.apply(poses)
    pattern = outside_pattern(p, vol_geom, g)
    log.info("roi: the material outside the volume's inscribed cylinder adds %.3g on average to a ray (RMS over the "
             "detector, line integrals); subtracted from every view", float(np.sqrt(np.mean(pattern.astype(np.float64) ** 2))))
    q = p - pattern[None]
    timings["roi"] = time.perf_counter() - t0
    return q, reconstruct(q, vol_geom, geom)


def _roi_text(mode: str, done: bool, trunc) -> str:
    if done:
        return ("the average over the views of what the material outside the volume's inscribed cylinder adds to a "
                "ray was subtracted (a region-of-interest scan); the output volumes are reconstructed from the data "
                "given, the rows' edge values carried outward for the ramp filter")
    if mode == "off":
        return "not compensated (roi = 'off')"
    if trunc is not None and trunc.lateral:
        return ("not compensated: a region-of-interest scan, but the volume is narrower than the field of view "
                "(roi = 'on' forces it)")
    return "not compensated: the sample lies within the volume's sides"


def _air(mode, p, timings):
    """The data with a measured air level subtracted when ``mode`` says so, and what was done, in words."""
    if mode == "off":
        return p, "not checked (air = 'off')"
    from ..io import estimate_air
    from ._truncation import air_to_subtract

    t0 = time.perf_counter()
    est = estimate_air(p)
    if air_to_subtract(est, p):
        # the part the views share: what a reconstruction takes for material. What varies from view to view (a
        # drift) is left to the background fitted with the motion (Stage.background), which also takes a plane
        p = p - est.fitted.astype(np.float32)[None, None, :]
        if est.row_profile is not None:  # a flat that does not match along the rows either: shared by the views too
            p = p - est.row_profile.astype(np.float32)[None, :, None]
        text = (f"subtracted (the level and the degree-{est.degree} column profile the views share"
                f"{', and the profile along the rows' if est.row_profile is not None else ''}; what varies from "
                f"view to view is left to the background per view): {est.summary()}")
        log.warning("air: the rays that miss the sample do not read 0 (a flat field that does not match): %s", text)
    elif est.found and est.significant:
        text = f"left as it is (what looks like air is not flat or covers the detector: a sample wider than the field?): {est.summary()}"
        log.info("air: %s", text)
    elif est.found:
        text = f"left as it is (within the noise of 0): {est.summary()}"
        log.info("air: %s", text)
    else:
        text = est.summary()
    timings["air"] = time.perf_counter() - t0
    return p, text


def _truncation(mode, weights, p, geom, vol_geom, vol_initial):
    """The detector weights with the truncated rays dropped when ``mode`` says so (and what was found).

    ``p``: the data, when an air level may still be in them (``air = "off"``): the test then reads the nominal
    reconstruction with it removed (:func:`detect_scan_truncation`); None: ``_air`` already took it out.
    """
    from ._truncation import detect_scan_truncation, detect_truncation, truncation_weights

    found = detect_truncation(vol_initial, vol_geom) if p is None else detect_scan_truncation(p, vol_geom, geom, vol_initial)[0]
    (log.warning if found.lateral else log.info)("truncation: %s", found.describe())
    if mode == "off" or (mode == "auto" and not found.vertical):
        return weights, found
    w = truncation_weights(geom, vol_geom)
    if weights is not None:
        w = w * np.asarray(weights, np.float32)
    if not (w > 0).any():
        raise CalibrationError("truncation: no ray stays inside the volume; enlarge the volume or set truncation = 'off'")
    log.info("truncation: %.1f%% of the rays leave the volume through its top or bottom face and are dropped", 100 * (1 - w.mean()))
    return w, found


def _fit(scaled, poses, stage: Stage, volume=None, made=None, own=False):
    """Per-view SNR and residual diagnosis of the data against FDK/FBP with the geometry posed by ``poses``.

    Measured as ``stage`` correlates: on ``scaled``, its scale's
    :func:`data_at_scale`, and its correlation grid; ``volume`` (on the
    user's grid) is reused when that is the same grid, and ``made`` (a
    driver's ``fit_volume``) when a round already reconstructed that volume.
    ``own``: against the stage's own reconstruction (e.g. ``nonneg_ls``,
    with the stage's detector weights) instead of FDK/FBP.
    """
    p, geom, vol_geom, weights, gamma2 = scaled
    g = geom.apply(poses)
    if own:
        volume = correlation_volume(p, vol_geom, g, stage, weights=weights)
    elif made is not None and made[0] is poses and _same_volume(made[1], stage):
        volume = made[2]
    elif volume is None or stage.scale != 1 or stage.oversample != 1:
        volume = correlation_volume(p, vol_geom, g, stage.replace(reconstruct="fdk"))
    res = p - forward(volume, refined_grid(vol_geom, stage.oversample), g)
    return _snr_of(p, res, weights), diagnose_residual(res, gamma2, weights, data=p)


_BACKGROUND_NAMES = {0: "an offset", 1: "a plane", 2: "a quadratic"}


def _background_text(drv) -> str:
    """What the stages with ``background = "auto"`` decided, and on what."""
    b, off = drv.background, drv.offset_sigma
    if b == "auto":
        return "as each stage says (no stage decided 'auto')"
    if b is None:
        return f"none: the first round's poses left a per-view offset of {off:.2g} noise std (background = 'auto')"
    return (f"{_BACKGROUND_NAMES[b]} per view fitted with the motion: the first round's poses left a per-view offset of "
            f"{off:.2g} noise std (background = 'auto'; an air level or flat field that drifts)")


def _recheck(scaled, poses, stage: Stage, snr_before, snr_after):
    """The per-view SNR of the nominal and the calibrated geometry against ``stage``'s own volume.

    Called when the FDK/FBP fits rank the nominal geometry first while the
    stages correlated against another volume (``nonneg_ls`` on a short
    scan). Both geometries are measured the same way, on the same data.
    """
    nominal = Poses.identity(scaled[1].n_views)
    fits = [_fit(scaled, q, stage, own=True)[0] for q in (nominal, poses)]
    name = stage.reconstruct if isinstance(stage.reconstruct, str) else "own"
    log.warning("against FDK/FBP the nominal geometry fits better (mean SNR %.2f dB, calibrated %.2f dB); against the "
                "stages' %s volume %.2f dB nominal, %.2f dB calibrated: that comparison decides (on a short scan FDK/FBP "
                "leaves an error of its own)", np.mean(snr_before), np.mean(snr_after), name, np.mean(fits[0]),
                np.mean(fits[1]))
    return fits[0], fits[1]


def _stage_fit_text(stage: Stage, history) -> str:
    """'' when ``stage`` correlated against FDK/FBP (the volume the final fits use), else what it fitted."""
    if isinstance(stage.reconstruct, str) and stage.reconstruct == "fdk":
        return ""
    chi = [h["chi_after"] for h in history if "chi_after" in h and h.get("scale") == stage.scale]
    name = stage.reconstruct if isinstance(stage.reconstruct, str) else "its own"
    fit = f"; the stages' {name} volume fitted the same data to chi {chi[-1]:.3g}" if chi else ""
    return (f" (against FDK/FBP, as for the nominal geometry{fit}; on a short scan or a non-planar orbit FDK/FBP leaves an error "
            f"of its own, which this diagnosis counts)")


def _same_volume(made_by: Stage, stage: Stage) -> bool:
    """Whether ``made_by``'s correlation volume is the one :func:`_fit` makes for ``stage`` (FDK/FBP, same grid)."""
    return (isinstance(made_by.reconstruct, str) and made_by.reconstruct == "fdk"
            and (made_by.scale, made_by.oversample, made_by.oversample_by) == (stage.scale, stage.oversample, stage.oversample_by))


def _nominal_predicts_as_well(p, geom, vol_geom, calibrated, stages, weights, background, backend, moved,
                              timings) -> str:
    """Why the nominal geometry holds against ``calibrated``, a geometry ``moved`` px from it: its reconstruction
    predicts the views it was not made from no better than the nominal one's by more than ``NEAR_NOMINAL_GAIN``
    (:func:`pdvc.calibration.cross_validated_misfit`, as the second run compares two recipes' geometries: two
    interleaved sets of views, non-negative least squares by ordered subsets, the background per view the run fitted
    taken out), at the finest of the scales the second run would take (:func:`_second_run_scales`: the grid and the
    views' voxel steps within its caps); '' where the calibrated geometry predicts better, or where no scale is within
    them (the check is then not made)."""
    from ._select import cross_validated_misfit

    kept, _ = _second_run_scales(stages, vol_geom, geom.det_shape, geom.n_views)
    if not kept:
        return ""
    t0 = time.perf_counter()
    scale = min(kept)
    m = cross_validated_misfit(p, vol_geom, [geom, calibrated], scale=scale, weights=weights,
                               background=background if isinstance(background, int) else None,
                               subsets=nonneg_subsets(geom.n_views // 2, SECOND_RUN_SUBSETS), backend=backend)
    timings["near-nominal check"] = time.perf_counter() - t0
    gain = 1.0 - m[1] / m[0] if m[0] > 0 else 0.0
    text = (f"the calibrated geometry moves the sample points by {moved:.4f} px RMS from the nominal one, and its "
            f"reconstruction predicts the views it was not made from {100 * abs(gain):.3g} % "
            f"{'better' if gain >= 0 else 'worse'} than the nominal one's (cross-validated misfit {m[0]:.6g} nominal, "
            f"{m[1]:.6g} calibrated, scale {scale}; more than {100 * NEAR_NOMINAL_GAIN:.2g} % better needed below "
            f"{NEAR_NOMINAL_PX:g} px)")
    log.info("near-nominal check: %s", text)
    return text if gain <= NEAR_NOMINAL_GAIN else ""


def _moved_from_nominal(geom: VectorGeometry, vol_geom: VolumeGeometry, poses: Poses, fix_scale) -> float:
    """How far ``poses`` move the sample points from the nominal geometry: RMS over the views and the points of
    their displacement on the detector (full-resolution pixels), the gauge taken out, as the stages measure a round's
    increment (``tol_px``)."""
    q = poses.gauge_fixed(geom, center=vol_geom.offset, scale=fix_scale)
    d = np.linalg.norm(point_moves(geom, increment_points(vol_geom), Poses.identity(geom.n_views), q), axis=-1)
    return float(np.sqrt(np.mean(d**2)))


def _finish(p, geom, vol_geom, vol_initial, drv, stages, status, message, gamma2, weights, times, center, backend, fix_scale, emit, timings, extra,
            p_out=None, mirror_start=None, fixed_pattern=""):
    """Final volume on the user's grid, the check against nominal, metrics, motion summary and assessment.

    ``p_out``: the data the output volumes are reconstructed from (with the rows' edges carried outward) when the
    stages calibrated on a copy with the outside of a region-of-interest scan subtracted (``p``); the fits and the
    assessment use ``p``.
    """
    t0 = time.perf_counter()
    poses = drv.poses
    calibrated = geom.apply(poses)
    emit(dict(event="reconstruct", what="calibrated"))
    vol = reconstruct(p, vol_geom, calibrated)
    # the fit is measured as the correlation measured it: at the last stage's scale, on its grid
    # (the interpolating projector on the user's grid is biased enough to rank a 0.02 px geometry
    # below a 0.16 px one: docs/method.md)
    scaled = data_at_scale(p, geom, vol_geom, weights, gamma2, stages[-1].scale)  # once for both fits and the assessment
    (snr_before, d0), (snr_after, d1) = (
        _fit(scaled, q, stages[-1], v, m) for q, v, m in ((Poses.identity(geom.n_views), vol_initial, None), (poses, vol, drv.fit_volume))
    )
    diagnoses = (d0, d1)
    log.info("nominal geometry: %s", d0.describe())  # motion dominates here: informative only
    # both fits are against FDK/FBP; a stage that correlated against another volume (the non-negative
    # least squares of a short scan) fitted better, and the FDK/FBP's own error over a short arc (a
    # per-view offset, structure) is not a defect of the data
    last = with_model(stages[-1], drv.model_choice)  # the model the last stage ran
    other = _stage_fit_text(last, drv.history)
    fitted = any(h.get("background", -1) >= 0 for h in drv.history)
    # the diagnosis is of the data against the volume: a background the correlation fitted with the motion is still in
    # it (as the report says)
    before = " (before the background per view fitted with the motion)" if fitted else ""
    (log.warning if d1.chi > 2.0 and not other else log.info)("calibrated geometry: %s%s%s", d1.describe(), before, other)
    if d1.chi > 1.5 and d1.view_offset >= 0.3 and not other and not fitted:
        log.warning("a constant per view holds %.0f%% of the residual: [calibration] background = 0 (1: with a ramp "
                    "across the detector) fits a smooth background per view with the motion (docs/method.md)",
                    100 * d1.view_offset)
    if np.mean(snr_after) < np.mean(snr_before) and other:
        # FDK/FBP ranks the nominal geometry first; its own error over a short arc can rank wrongly (a
        # held-out 180-degree scan: a 0.034 px geometry rejected for its 0.272 px nominal). Judge both
        # again against the volume the stages correlated with, on the same data, and keep that verdict
        snr_before, snr_after = _recheck(scaled, poses, last, snr_before, snr_after)
    rejected, why = None, ""
    if fixed_pattern:
        # a region-of-interest scan whose views hold a pattern fixed on the detector that pulled the comparison of its
        # opposite views (_fixed_pattern_check): the stages fitted it too, and nothing measures it without air
        rejected, status = calibrated, Status.UNDETERMINED
        why = f"region-of-interest scan: {fixed_pattern}"
    elif p_out is not None and d0.chi <= ROI_NOMINAL_CHI:
        # a region-of-interest scan whose nominal fit is already at the noise once the outside's average is
        # subtracted: what the calibration moves is not seen above the noise (docs/method.md §5.17)
        rejected, status = calibrated, Status.UNDETERMINED
        why = f"region-of-interest scan: chi {d0.chi:.3f} at the nominal geometry, {d1.chi:.3f} calibrated"
    elif (moved := _moved_from_nominal(geom, vol_geom, poses, fix_scale)) < (tol := min(st.tol_px for st in stages)):
        # the loop treats a round that moves the sample points by less than tol_px as no move: a geometry that close
        # to the nominal one is no measurement of motion, and it fits as well by chance as worse (docs/method.md §5.51)
        rejected, status = calibrated, Status.NOMINAL_HOLDS
        why = (f"the calibrated geometry moves the sample points by {moved:.4f} px RMS from the nominal one, less than "
               f"{tol:g} px; mean SNR {np.mean(snr_before):.3f} dB nominal, {np.mean(snr_after):.3f} dB calibrated")
    elif moved < NEAR_NOMINAL_PX and p_out is None and (
            held := _nominal_predicts_as_well(p, geom, vol_geom, calibrated, stages, weights, drv.background, backend,
                                              moved, timings)):
        # stages that walked a little from the nominal geometry along what the data hardly measure: their geometry
        # predicts the views left out of a reconstruction no better than the nominal one (docs/method.md §5.56)
        rejected, status, why = calibrated, Status.NOMINAL_HOLDS, held
    elif np.mean(snr_after) < np.mean(snr_before):
        rejected, status = calibrated, Status.WORSE_THAN_NOMINAL
        why = f"mean SNR {np.mean(snr_before):.2f} dB nominal, {np.mean(snr_after):.2f} dB calibrated"
    elif p_out is not None:
        # a region-of-interest scan: what the model leaves out can make a wrong geometry fit better (rods
        # wider than the field: SNR up, the truth farther); judge both by how well the views they were not
        # reconstructed from are predicted (docs/method.md §5.17)
        cv_nominal, cv_calibrated = (roi_cross_validated_rss(p_out, vol_geom, g, weights) for g in (geom, calibrated))
        log.info("roi: cross-validated residual (half the views reconstructed, the other half predicted): nominal "
                 "%.6g, calibrated %.6g", cv_nominal, cv_calibrated)
        if cv_calibrated > cv_nominal:
            rejected, status = calibrated, Status.WORSE_THAN_NOMINAL
            why = (f"region-of-interest scan: reconstructed from half the views, the calibrated geometry predicts the "
                   f"other half worse than the nominal one, residual x{cv_calibrated / cv_nominal:.4f}")
    fallback = None
    if rejected is not None and mirror_start is not None and status != Status.NOMINAL_HOLDS:
        # a region-of-interest scan whose stages' geometry its reconstructions cannot confirm: the axis offset that
        # its opposite views confirm against the nominal axis, without a reconstruction, where its mean SNR is not
        # below the nominal one's either (docs/method.md §5.42)
        offset, roll, mirror, line = mirror_start
        off_poses = _axis_poses(geom, offset, roll)
        off_vol = reconstruct(p, vol_geom, geom.apply(off_poses))
        off_snr, off_d = _fit(scaled, off_poses, stages[-1], off_vol)
        lean = ("" if line is None else
                f", leaning {np.degrees(roll):+.3f}° in the detector plane (each view against its opposite reflected "
                f"about the line: mean squared difference {line.comparison.msd[0]:.4g} upright, "
                f"{line.comparison.msd[1]:.4g} leaning, {line.comparison.t:.1f} standard errors)")
        mirror_text = (f"axis offset {offset:+.2f} px{lean}: each view against its mirrored opposite, mean squared "
                       f"difference {mirror.msd[0]:.4g} with the nominal axis, {mirror.msd[1]:.4g} with the offset, "
                       f"{mirror.t:.1f} standard errors over {mirror.n_pairs} pairs; mean SNR {np.mean(snr_before):.2f} "
                       f"dB nominal, {np.mean(off_snr):.2f} dB with this axis")
        if np.mean(off_snr) >= np.mean(snr_before):
            fallback = (off_poses, off_vol, off_snr, off_d)
        else:
            why = f"{why}; the opposite views' {mirror_text}: not kept either"
    nominal_returned = rejected is not None and fallback is None
    if nominal_returned:
        message = f"{status.message} ({why}; the run itself ended with: {message})"
        (log.info if status.success else log.warning)(message)
        poses, calibrated, vol, snr_after = Poses.identity(geom.n_views), geom, vol_initial, snr_before
        diagnoses = (diagnoses[0], diagnoses[0])
        other = ""  # the nominal geometry returned: its diagnosis is the nominal one
    elif rejected is not None:
        message = (f"{Status.AXIS_OFFSET.message} ({mirror_text}; the stages' geometry not kept, "
                   f"{status.name.lower()}: {why}; the run itself ended with: {message})")
        log.warning(message)
        status = Status.AXIS_OFFSET
        poses, vol, snr_after, d1 = fallback
        calibrated = geom.apply(poses)
        diagnoses, other = (diagnoses[0], d1), ""
    vol_fit = vol
    if p_out is not None:  # the user's volumes hold the whole field of view, the outside's average included
        emit(dict(event="reconstruct", what="output volumes"))
        vol_initial = reconstruct(p_out, vol_geom, geom, padding="edge")
        vol = vol_initial if nominal_returned else reconstruct(p_out, vol_geom, calibrated, padding="edge")
    lo, hi = np.percentile(vol, [0.1, 99.9])
    e_before = shannon_entropy(vol_initial, value_range=(float(lo), float(hi)))
    e_after = shannon_entropy(vol, value_range=(float(lo), float(hi)))
    timings["final"] = time.perf_counter() - t0
    motion = None
    try:
        from ._axis import describe_motion

        motion = describe_motion(geom, poses.rotvecs, poses.translations, vol_geom, times=times)
    except Exception as exc:  # the summary is a report, never a reason to lose the calibration
        log.warning("motion summary unavailable: %s", exc)
    emit(dict(event="assess"))
    t0 = time.perf_counter()
    ran = [with_model(s, drv.model_choice) for s in stages]  # the model a stage with candidates ran
    assessment = _assess(p, geom, vol_geom, vol_fit, poses, ran, gamma2, weights, times, center, backend, scaled, drv.background)
    timings["assess"] = time.perf_counter() - t0
    return CalibrationResult(
        geometry=calibrated, nominal=geom, poses=poses, assessment=assessment, history=drv.history, stages=tuple(stages),
        stage_outcomes=drv.stages, volume=np.asarray(vol, np.float32), volume_initial=np.asarray(vol_initial, np.float32),
        vol_geom=vol_geom, snr_before=snr_before, snr_after=snr_after, entropy_before=float(e_before),
        entropy_after=float(e_after), motion=motion, gauge=gauge_text(geom.kind, fix_scale), status=status,
        message=str(message), elapsed_s=0.0, timings=timings, rejected_geometry=rejected, residual=diagnoses,
        residual_note=other, **extra,
    )


def _assess(p, geom, vol_geom, vol, poses, stages, gamma2, weights, times, center, backend, scaled, auto_background=None):
    """The model of the last stage that had to converge, measured at the poses kept, at that stage's scale.

    ``scaled`` is the data at the last stage's scale (reused when the model's scale is the same);
    ``auto_background`` what the run fitted for ``background = "auto"``.
    """
    model = next((s for s in reversed(stages) if s.until == "converged"), stages[-1])
    s = model.scale
    try:
        data, g, _, w, g2 = scaled if s == stages[-1].scale else data_at_scale(p, geom, vol_geom, weights, gamma2, s)
        v, vg = (vol, vol_geom) if s == 1 else coarse_volume(vol, vol_geom, s)
        return assess(
            v, vg, data, g, poses, basis=model.basis, frame=model.frame, fixed=model.fixed, center=center, weights=w,
            noise_variance=g2, times=times, rcond=model.rcond, backend=backend,
            background=stage_background(model, auto_background),
        )
    except PdvcError as exc:  # a report, never a reason to lose the calibration
        log.warning("assessment of the poses unavailable: %s", exc)
        return None
