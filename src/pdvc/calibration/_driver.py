"""The calibration driver: run a list of stages, each a series of reconstruct -> correlate -> gauge rounds.

:func:`run_stages` is the one loop of pdvc's self-calibration. A round
reconstructs the correlation volume with the current poses, measures the
poses against it with P-DVC (:func:`pdvc.correlate`), fixes the gauge
(:meth:`pdvc.geometry.Poses.gauge_fixed`) and measures the increment: the
RMS detector displacement of sample points between the geometries before
and after, in full-resolution pixels. Each stage ends with a
:class:`pdvc.Status` of its own (``docs/method.md`` explains the rules);
the driver's status is the last stage's.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Callable, Optional

import numpy as np
from scipy.ndimage import median_filter

from ..correlation import (
    CorrelationResult,
    coarse_grain,
    coarse_noise_factor,
    coarse_weights,
    correlate,
    custom_basis,
    drift_basis,
    shannon_entropy,
    view_angles,
)
from ..correlation._background import auto_background
from ..geometry import Poses, VectorGeometry, VolumeGeometry, sample_points
from ..projectors import forward
from ..recon import analytic, cgls, nonneg_ls, nonneg_ls_lipschitz, refined_grid, spline_upsample
from ..status import Status
from ._init import SHORT_SCAN_OPPOSITE_FRACTION, _mismatch, _opposite_pairs, opposite_fraction
from ._select import ModelChoice, compare_models, model_fields, model_name, with_model
from ._stages import JOLT_BASIS, Stage, StageError

# Aitken's extrapolation of creeping rounds (Stage.extrapolate; docs/method.md, "Stopping"): two rounds in a row whose
# increments shrink by a ratio in EXTRAPOLATE_RATIO, moving the sample points in directions whose cosine is at least
# EXTRAPOLATE_COS, are a slowly contracting fixed-point iteration along one mode; the next round starts from the limit
# of the geometric series, at most EXTRAPOLATE_MAX steps beyond the last round's poses
EXTRAPOLATE_RATIO = (0.5, 0.95)
EXTRAPOLATE_COS = 0.9
EXTRAPOLATE_MAX = 4.0
# the calibration's nonneg_ls volumes: FISTA iterations, and the ramp preconditioner (measured faster and less accurate
# on the tuning splits, so off: docs/method.md §5.20)
NONNEG_ITER = 30
NONNEG_PRECONDITION = False
# ... by ordered subsets: interleaved subsets of at least NONNEG_SUBSET_VIEWS views each, at most NONNEG_MAX_SUBSETS of
# them (3 subsets of the 180-degree stand-in's 91 views: the plain iteration's volume within 0.11 %, in 42 % of the
# time; subsets of 15 views, or more than 3 subsets, moved rods of the half-turn splits by 0.01 px; docs/method.md §5.24)
NONNEG_SUBSET_VIEWS = 30
NONNEG_MAX_SUBSETS = 3
# a stage that sets its subsets (Stage.subsets = m: the default's refining round at the finest scale of a short scan):
# at most m subsets of at least NONNEG_MIN_SUBSET_VIEWS views each (docs/method.md §5.52)
NONNEG_MIN_SUBSET_VIEWS = 15
# inexact rounds on full turns: a round's Gauss-Newton passes stop at a step that moves the sample points by less than
# INNER_FORCING times the last round's increment (a forcing term, as in inexact Newton methods), never below the
# engine's own INNER_TOL_PX: the next reconstruction moves the target by about that increment anyway. Not on short
# scans, whose rounds creep (increments 10-20 % shorter a round, which the stall rule reads): there every round's
# passes run to INNER_TOL_PX (docs/method.md §5.58)
INNER_FORCING = 0.1
INNER_TOL_PX = 1e-3

__all__ = ["run_stages", "DriverResult", "StageOutcome", "refined_grid", "reconstruct", "correlation_volume", "data_at_scale",
           "jolt_views", "jolt_steps"]

log = logging.getLogger("pdvc.calibration")


@dataclass(frozen=True)
class StageOutcome:
    """How one stage ended: its name, scale, status, message and number of rounds."""

    name: str
    scale: int
    status: Status
    message: str
    rounds: int
    elapsed_s: float


class PosesResult:
    """What every calibration result shares: the poses kept and a status (``poses``, ``status`` fields)."""

    @property
    def rotvecs(self) -> np.ndarray:
        return self.poses.rotvecs

    @property
    def translations(self) -> np.ndarray:
        return self.poses.translations

    @property
    def success(self) -> bool:
        return Status(self.status).success


@dataclass(frozen=True)
class DriverResult(PosesResult):
    """Outcome of :func:`run_stages`.

    Attributes
    ----------
    poses : Poses
        The poses kept (relative to the geometry given, gauge fixed).
    status : Status
        The last stage's status; ``message`` says why.
    history : tuple of dict
        One dict per round: ``iteration`` (over the whole run), ``stage`` (name), ``stage_index``, ``scale``,
        ``round`` (in the stage), ``chi_before`` (χ of the fresh
        reconstruction at the round's starting poses), ``chi_after``,
        ``snr_before``, ``snr`` (dB), ``entropy`` (NaN unless the entropy
        guard runs), ``increment_px``, ``increment_max_px`` (full-resolution
        pixels), ``n_iter`` (Jacobian passes), ``engine_status``,
        ``elapsed_s``, ``background`` (the degree of the background per view
        fitted, -1: none), ``offset_sigma`` (how much the per-view offset of
        the residual varies from view to view, RMS in noise std of the
        full-resolution projections, at the poses measured without a
        background; 0 when the round fitted one from the start), ``model``
        (the motion model's name, :func:`pdvc.calibration._select.model_name`);
        the first round of the stage that chose the model also holds
        ``model_choice`` (:meth:`ModelChoice.to_dict`).
    stages : tuple of StageOutcome
    correlation : CorrelationResult or None
        The measurement whose poses were kept (None if no round was kept).
    guard_volume : tuple (Poses, scale, volume) or None
        The last analytic volume the entropy guard made, for reuse.
    fit_volume : tuple (Poses, Stage, volume) or None
        The correlation volume a round reconstructed at the poses returned
        (``poses`` itself), with the stage that made it, for reuse; None
        when the poses returned were never reconstructed (a last round that
        converged).
    background : int, None or "auto"
        What the stages with ``background = "auto"`` fitted (from their first
        round, measured again once decided): a degree, None (none), or
        ``"auto"`` when no round decided.
    offset_sigma : float
        The per-view offset (in noise standard deviations) the first round's
        poses left, on which that was decided (nan if none).
    model_choice : ModelChoice or None
        The motion model the first stage with ``candidates`` chose and the
        cross-validated scores it chose on (None: no stage compared models).
    """

    poses: Poses
    status: Status
    message: str
    history: tuple
    stages: tuple
    correlation: Optional[CorrelationResult]
    guard_volume: Optional[tuple] = None
    fit_volume: Optional[tuple] = None
    background: Any = "auto"
    offset_sigma: float = float("nan")
    model_choice: Optional[ModelChoice] = None


def stage_background(stage: Stage, decided):
    """The background degree a stage fits (None: none): its own, or for ``"auto"`` what the run ``decided`` (a degree,
    None, or ``"auto"`` while undecided: none)."""
    if stage.background == "auto":
        return decided if isinstance(decided, int) else None
    return None if stage.background < 0 else int(stage.background)


def jolt_views(snr_per_view, *, window: int = 7, z: float = 5.0, min_drop_db: float = 1.0, kink_window: int = 5,
               min_kink_db: float = 0.2) -> np.ndarray:
    """Views whose SNR dips below their neighbours': where a smooth model missed a jolt.

    The dip of view k is the median SNR of the ``window`` views around it
    (acquisition order) minus its own; a view stands out when its dip is
    above ``z`` times the view-to-view scatter of the SNR (1.4826 MAD of the
    differences between neighbours, over √2) and above ``min_drop_db``. A smooth dependence of the SNR on the angle (an
    elongated sample) is no dip.

    A jolt that the smooth model took up as a drift leaves no such dip but a
    broad V: the model passes through the middle of the step, so the views
    fit worse and worse toward the jolt and better after it, over tens of
    views (a rod's 1.4 px jolt at view 29 of 120: 32 dB far from it, 22 dB
    at view 28). Its minimum is a kink: the SNR's slope over the
    ``kink_window`` views after a view minus that over the views before is
    above ``z`` times its noise (from the same scatter) and ``min_kink_db``
    per view, the view is the lowest of the ``2 kink_window + 1`` around it,
    lies ``min_drop_db`` below the mean of the two ends, and below the
    scan's median SNR by a third of the deepest such V at least. A smooth
    dependence on the angle turns gently; the troughs of a full turn's SNR
    with the angle do not, and the stages use this rule on scans without
    opposite views only (``kink_window=0`` leaves it out; ``docs/method.md``
    §5.33).
    """
    s = np.asarray(snr_per_view, float)
    n = s.size
    if n < window + 2:
        return np.array([], int)
    dip = median_filter(s, size=window, mode="nearest") - s
    # the view-to-view scatter of the SNR (robust: 1.4826 MAD of the differences between neighbours)
    diff = np.diff(s)
    sigma = 1.4826 * float(np.median(np.abs(diff - np.median(diff)))) / np.sqrt(2.0)
    if not sigma > 0:
        return np.array([], int)
    found = (dip > z * sigma) & (dip > min_drop_db)
    w = int(kink_window)
    if w >= 2 and n >= 2 * w + 1:
        x = np.arange(w + 1) - w / 2
        slope = np.lib.stride_tricks.sliding_window_view(s, w + 1) @ (x / (x @ x))  # slope[j]: of s[j : j + w + 1]
        k = np.arange(w, n - w)
        kink = slope[k] - slope[k - w]  # after view k minus before it (both windows hold k)
        lowest = s[k] <= np.lib.stride_tricks.sliding_window_view(s, 2 * w + 1).min(axis=1)
        depth = 0.5 * (s[k - w] + s[k + w]) - s[k]
        hit = lowest & (kink > z * sigma * np.sqrt(2.0 / (x @ x))) & (kink > min_kink_db) & (depth > min_drop_db)
        # below the scan's median SNR by a third of the deepest such V at least: the smooth model's overshoot beside a
        # jolt it took up makes shallower Vs of its own (1.0-1.6 dB beside the 10 dB one above)
        below = float(np.median(s)) - s[k]
        if hit.any():
            found[k[hit & (below >= max(min_drop_db, below[hit].max() / 3))]] = True
    return np.nonzero(found)[0]


#: jolts are also found as steps in each view's position measured on its own (free lab translations across the beam
#: and up) against the smooth model's last volume: a step of JOLT_STEP_MIN voxels at least that stands JOLT_STEP_Z times above
#: its noise, a line and a step fitted over JOLT_STEP_WINDOW views each side (docs/method.md §5.34)
JOLT_STEP_WINDOW = 6
JOLT_STEP_Z = 8.0
JOLT_STEP_MIN = 0.15
JOLT_STEP_MAX = 16
#: a step within this many angular steps of 180° from a larger one is its ghost (``jolt_steps(angles=)``, §5.37)
JOLT_GHOST_REACH = 2


def _is_jolt_stage(stage: Stage) -> bool:
    """Whether ``stage`` is the jolt stage (:func:`pdvc.calibration.jolt_stage`: its basis is ``JOLT_BASIS``)."""
    return isinstance(stage.basis, str) and stage.basis == JOLT_BASIS


def series_noise(x: np.ndarray) -> np.ndarray:
    """The noise of each column of a per-view series, robust to its smooth trend and to steps: 1.4826 MAD of its second
    differences, over √6 (what :func:`jolt_steps` and the row sums' vertical motion measure a series against)."""
    d2 = np.diff(np.asarray(x, dtype=float), 2, axis=0)
    return 1.4826 * np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0) / np.sqrt(6.0)


def _step_at(x: np.ndarray, sigma: np.ndarray, k: int, window: int, skip: tuple = (), known=()) -> tuple[float, np.ndarray]:
    """(z, size) of a step at view k (views >= k moved): a line and a step fitted by least squares to the ``window``
    views on each side, leaving out the views at offsets ``skip`` from k, with the steps at the ``known`` views fitted
    as well; z = √Σ (step / its std)² over the components, each of noise ``sigma``. (0, 0) where it cannot be fitted."""
    n = x.shape[0]
    idx = np.array([i for i in range(max(0, k - window), min(n, k + window)) if i - k not in skip])
    after = idx >= k
    if k in known or after.sum() < 2 or (~after).sum() < 2:
        return 0.0, np.zeros(x.shape[1])
    cols = [np.ones(idx.size), idx - k + 0.5, after.astype(float)]
    for j in known:  # a known step in the window: fitted with this one, not taken for a part of it
        c = (idx >= j).astype(float)
        if 0 < c.sum() < idx.size and not any(np.array_equal(c, q) for q in cols[2:]):
            cols.append(c)
    row = np.linalg.pinv(np.column_stack(cols))[2]  # the step's row of the least-squares solution
    size = row @ x[idx]
    return float(np.sqrt(np.sum((size / (sigma * np.sqrt(row @ row))) ** 2))), size


def jolt_steps(displacements, *, window: int = JOLT_STEP_WINDOW, z: float = JOLT_STEP_Z, min_step: float = JOLT_STEP_MIN,
               max_steps: int = JOLT_STEP_MAX, angles=None) -> np.ndarray:
    """Views at which a series of per-view displacements steps: where a jolt moved the sample.

    ``displacements`` (n_views, m), in acquisition order: each view's
    position measured on its own (free per view) against the volume of a
    smooth model, minus the model's. A jolt that the model took up as a
    drift leaves a sawtooth there, a ramp toward the jump and a step at it
    (a granular scan's 1.1 px jolt at view 129 of 180: +0.55 px before it,
    −0.58 px after); a smooth model error leaves no step. At each view k a
    line and a step (views k on moved) are fitted by least squares to the
    ``window`` views on each side; the step stands out when its size over
    its standard deviation, combined over the components (√Σ z²), is at
    least ``z`` and its size at least ``min_step``. Each component's noise
    is the series' own (1.4826 MAD of its second differences, over √6). The
    largest such step is taken and the search repeats with the steps found
    fitted beside each new one, up to ``max_steps`` steps; a step must also stand
    without the two views beside it (k − 1, k), so that a single view that
    fits poorly (a zinger left over) is not taken for one
    (``docs/method.md`` §5.34).

    ``angles`` (n_views,), radians, optional: the views' scan angles. The
    steps are then taken largest first, and none at a view within
    ``JOLT_GHOST_REACH`` angular steps of 180° from one already taken that
    has an opposite view (within half a step): on a full turn a jolt that
    the smooth model took up leaves a smaller step at its opposite view
    (whose rays the volume averaged with it), and a step freed there only
    moves the jolt's across-beam part between the two views: the pairs of
    opposite views fix the sum of the two steps, and 81 % of the half-turn
    square wave that tells them apart is a rigid translation
    (``docs/method.md`` §5.37).
    """
    x = np.array(displacements, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    n = x.shape[0]
    if n < 2 * window + 2 or not np.all(np.isfinite(x)):
        return np.array([], int)
    sigma = np.maximum(series_noise(x), 1e-3 * max(float(min_step), 1e-12))  # a noise-free series: the size decides
    theta = None if angles is None else np.asarray(angles, dtype=np.float64)
    if theta is not None and theta.shape != (n,):
        raise ValueError(f"angles must hold one scan angle per view, shape ({n},), got {theta.shape}")
    step = _opposite_pairs(np.mod(theta, 2 * np.pi), None)[1] if theta is not None else 0.0
    found: list = []
    ghost = np.zeros(n, bool)  # the views near the opposite of a step taken
    while len(found) < int(max_steps):
        scores = [(0.0, 0.0) if ghost[k] else _step_at(x, sigma, k, window, known=found) for k in range(n)]
        k = int(np.argmax([zk for zk, _ in scores]))
        if scores[k][0] < z or np.linalg.norm(scores[k][1]) < min_step:
            break
        zr, sr = _step_at(x, sigma, k, window, skip=(-1, 0), known=found)
        if zr < z or np.linalg.norm(sr) < min_step:
            break  # the largest step left is one view's misfit
        found.append(k)
        if theta is not None:
            ghost |= _opposite_of(theta, k, JOLT_GHOST_REACH, step)
    return np.array(sorted(found), int)


def _opposite_of(theta: np.ndarray, k: int, reach: float, step: float) -> np.ndarray:
    """The views within ``reach`` angular steps ``step`` of view ``k``'s opposite direction, ``θ_k + 180°`` (every
    turn), where view ``k`` has an opposite view within half a step; none elsewhere (a half turn's views)."""
    d = np.abs(_mismatch(theta, k))
    d[k] = np.inf
    if not step > 0 or d.min() > 0.5 * step * (1 + 1e-9):
        return np.zeros(theta.size, bool)
    return d <= (reach + 0.5) * step


#: the row sums' guard (``run_stages(row_sums=...)``): once a stage's rounds creep (a round moved the sample points by
#: less than ROW_SUMS_CREEP x its tol_px), it stops when their misfit rises ROW_SUMS_TOL above the lowest since
#: (docs/method.md §5.31)
ROW_SUMS_TOL = 0.01
ROW_SUMS_CREEP = 10.0
#: jolt views are confirmed on the residual without each view's largest pixels, this fraction of them (and at least
#: JOLT_TRIM_MIN): a zinger or spot the filter left makes its view's SNR dip as a jolt does, but a jolt misplaces
#: every edge of its views
JOLT_TRIM = 0.005
JOLT_TRIM_MIN = 9


def trimmed_snr(projections, residual, weights=None, trim: float = JOLT_TRIM, min_trim: int = JOLT_TRIM_MIN) -> np.ndarray:
    """Per-view SNR (dB) with each view's ``max(min_trim, trim × its pixels)`` largest residuals (in absolute value,
    about the view's median) left out: a few wild pixels cannot make a view's fit look poor."""
    s, r = np.asarray(projections), np.asarray(residual)
    w = np.ones(s.shape, bool) if weights is None else np.broadcast_to(np.asarray(weights) > 0, s.shape)
    out = np.full(s.shape[0], np.nan)
    for k in range(s.shape[0]):  # a view at a time, in float64
        sk, rk = s[k][w[k]].astype(np.float64), r[k][w[k]].astype(np.float64)
        m = rk.size - max(int(min_trim), int(trim * rk.size))
        if m < 2:
            continue
        rk = rk - np.median(rk)
        rk = rk[np.argpartition(np.abs(rk), m - 1)[:m]]
        with np.errstate(divide="ignore", invalid="ignore"):
            out[k] = 10.0 * np.log10(np.var(sk) / np.var(rk))
    return out


def reconstruct(projections, vol_geom: VolumeGeometry, geom: VectorGeometry, **kw) -> np.ndarray:
    """FDK (cone beam) or FBP (parallel beam): the analytic reconstruction of the calibration (:func:`pdvc.recon.analytic`:
    a cone-beam short scan whose arc the poses shorten below 180° + the fan angle loses its Parker weights, not the run)."""
    return analytic(projections, vol_geom, geom, **kw)


def correlation_volume(projections, vol_geom: VolumeGeometry, geom: VectorGeometry, stage: Stage, weights=None,
                       lipschitz: Optional[dict] = None):
    """The volume a stage correlates against, on ``refined_grid(vol_geom, stage.oversample)``.

    ``vol_geom`` is the stage's grid. FDK/FBP and ``nonneg_ls`` with
    ``oversample_by="spline"`` (``"auto"`` in parallel beam) reconstruct on it and interpolate by cubic
    B-splines; otherwise the stage's reconstruction runs on the fine grid. ``weights`` (the
    stage's detector weights) weigh the rays of the ``nonneg_ls`` fit (a ray
    that leaves the volume through a face the sample crosses does not pull
    it); FDK, FBP and CGLS take every ray. ``lipschitz``: a dict the caller
    keeps between reconstructions of one scan; ``nonneg_ls`` takes its step
    bound from it (per grid and coarsening) instead of estimating it again
    (:func:`pdvc.recon.nonneg_ls_lipschitz`).
    """
    k = stage.oversample
    r = stage.reconstruct
    fine = refined_grid(vol_geom, k)
    spline = stage.oversample_by == "spline" or (stage.oversample_by == "auto" and geom.kind == "parallel")
    if callable(r):
        return r(projections, fine, geom)
    if r == "fdk":
        if k > 1 and spline:
            return spline_upsample(reconstruct(projections, vol_geom, geom), k)
        return reconstruct(projections, fine, geom)
    if r == "nonneg_ls":
        grid, coarsen = (vol_geom, 1) if k > 1 and spline else (fine, k)
        lip = None
        if lipschitz is not None:
            key = (tuple(grid.shape), tuple(grid.voxel_size), coarsen, geom.kind, geom.n_views, tuple(geom.det_shape),
                   NONNEG_PRECONDITION)
            if key not in lipschitz:
                lipschitz[key] = nonneg_ls_lipschitz(grid, geom, coarsen=coarsen, precondition=NONNEG_PRECONDITION)
            lip = lipschitz[key]
        vol = nonneg_ls(projections, grid, geom, coarsen=coarsen, weights=weights, lipschitz=lip, n_iter=NONNEG_ITER,
                        precondition=NONNEG_PRECONDITION, subsets=nonneg_subsets(geom.n_views, stage.subsets))
        return spline_upsample(vol, k) if grid is vol_geom and k > 1 else vol
    return cgls(projections, fine, geom)


def nonneg_subsets(n_views: int, subsets="auto") -> int:
    """The ordered subsets of a calibration's ``nonneg_ls`` volume for a scan of ``n_views`` views.

    ``subsets`` is the stage's (:class:`Stage`): ``"auto"``, at most
    ``NONNEG_MAX_SUBSETS`` of at least ``NONNEG_SUBSET_VIEWS`` views each;
    an int m, at most m of at least ``NONNEG_MIN_SUBSET_VIEWS`` views each.
    """
    if subsets == "auto":
        return max(1, min(NONNEG_MAX_SUBSETS, int(n_views) // NONNEG_SUBSET_VIEWS))
    return max(1, min(int(subsets), int(n_views) // NONNEG_MIN_SUBSET_VIEWS))


def data_at_scale(projections, geom: VectorGeometry, vol_geom: VolumeGeometry, weights, gamma2: float, s: int):
    """(projections, geometry, grid, weights, γ²) of a run at scale ``s``: coarse-grained (``s`` = 1: as given)."""
    if s == 1:
        p, g, vg = projections, geom, vol_geom
    else:
        p, g = coarse_grain(projections, geom, s)
        vg = vol_geom.binned(s)
    return p, g, vg, coarse_weights(weights, s, g.det_shape), gamma2 * coarse_noise_factor(s)


def _final_reconstruction(stage: Stage):
    """The stage's reconstruction on a grid given (the entropy guard's volume)."""
    return stage.reconstruct if callable(stage.reconstruct) else reconstruct


class _Context:
    """What every round needs: the data at each scale, the noise, the points, the callbacks."""

    def __init__(self, projections, geom, vol_geom, *, weights, gamma2, fix_scale, angles, times, backend, center):
        self.p = projections
        self.geom = geom
        self.vol_geom = vol_geom
        self.weights = weights
        self.gamma2 = gamma2
        self.fix_scale = fix_scale
        self.angles = view_angles(geom) if angles is None else np.asarray(angles, float)
        self.times = times
        self.backend = backend
        self.center = np.asarray(vol_geom.offset, float) if center is None else np.asarray(center, float)
        self.points = increment_points(vol_geom)
        self.opposite = opposite_fraction(geom)  # the views with an opposite view: a full turn's 1, a short scan's ~0
        self._scaled: dict = {}
        self.lipschitz: dict = {}  # nonneg_ls step bounds, per grid: estimated once per scan
        self.auto_background: Any = "auto"  # stages with background = "auto": decided at the first round, then kept
        self.offset_sigma = float("nan")
        self.model_choice: Optional[ModelChoice] = None  # stages with candidates: decided at the first one, then kept
        self.held: tuple = ()  # parameters no smooth model moves (run_stages' held)
        self.known_jolts = np.array([], int)  # views the jolt stage frees whatever it finds (run_stages' known_jolts)
        self.vertical: Optional[np.ndarray] = None  # the vertical motion "tz" is held at (run_stages' vertical)

    @property
    def full_turn(self) -> bool:
        """At least ``SHORT_SCAN_OPPOSITE_FRACTION`` of the views have an opposite view."""
        return self.opposite >= SHORT_SCAN_OPPOSITE_FRACTION

    def fixed(self, stage: Stage) -> tuple:
        """The parameters ``stage`` keeps fixed: its own, and the run's ``held`` unless it is the jolt stage."""
        if not self.held or _is_jolt_stage(stage):
            return tuple(stage.fixed)
        return tuple(dict.fromkeys(tuple(stage.fixed) + self.held))

    def with_model(self, stage: Stage) -> Stage:
        """The stage with the motion model chosen (stages with ``candidates``, once a choice was made)."""
        return with_model(stage, self.model_choice)

    def stage_volume(self, stage: Stage, poses: Poses):
        """The stage's correlation volume at ``poses`` (what its first round makes)."""
        p, g, vg, w, _ = self.at_scale(stage.scale)
        return correlation_volume(p, vg, g.apply(poses), stage, weights=w, lipschitz=self.lipschitz)

    def choose_model(self, stage: Stage, poses: Poses, volume) -> ModelChoice:
        """Compare the stage's model with its candidates on views they were not fitted to (``docs/method.md`` §5.12)."""
        p, g, vg, w, gamma2 = self.at_scale(stage.scale)
        own = model_name(stage)
        # over half a turn the reconstruction takes up smooth motions and the views left out no longer tell a simpler
        # model from the stage's own (docs/method.md §5.12): simpler candidates are compared on full scans only
        short = "" if self.full_turn else \
            f"a short scan ({100 * self.opposite:.0f} % of the views have an opposite view) cannot tell them apart"
        # plain least squares (no robust weights): what a model predicts better is in the large residuals at the
        # sample's edges, which Huber weights would lower (a foam's combined motion 0.009 -> 0.043 px, tuning split)
        self.model_choice = compare_models(
            volume, refined_grid(vg, stage.oversample), p, g, poses,
            dict(basis=stage.basis, frame=stage.frame, fixed=self.fixed(stage)),
            {c: dict(model_fields(c), fixed=self.fixed(stage.replace(**model_fields(c)))) for c in stage.candidates},
            noise_variance=gamma2, weights=w, angles=self.angles, times=self.times, center=self.center,
            background=stage_background(stage, self.auto_background), backend=self.backend, max_iter=stage.max_iter,
            own_name=own, skip_simpler=short,
        )
        return self.model_choice

    @staticmethod
    def full_resolution_sigma(offset_sigma: float, scale: int) -> float:
        """An offset in noise std at ``scale`` in noise std of the full-resolution projections (coarse-graining
        lowers the noise, not the offset)."""
        return float(offset_sigma) * float(np.sqrt(coarse_noise_factor(scale)))

    def decided(self, stage: Stage, offset_sigma: float) -> bool:
        """``"auto"``, the first round: whether it decided to fit a background, because the per-view offset its poses
        left (``offset_sigma``, full-resolution noise std) is above ``AUTO_OFFSET_SIGMA`` (``docs/method.md`` §5.10);
        the decision holds for the rest of the run."""
        if stage.background != "auto" or self.auto_background != "auto":
            return False
        self.offset_sigma = offset_sigma
        self.auto_background = auto_background(self.offset_sigma)
        if self.auto_background is None:
            return False
        log.info("background per view of degree %d fitted (background = 'auto'): the first round's poses left a per-view "
                 "offset of %.2f noise std; the round is measured again with it", self.auto_background, self.offset_sigma)
        return True

    def at_scale(self, s: int):
        """(projections, geometry, grid, weights, γ²) at scale ``s``, made once."""
        if s not in self._scaled:
            self._scaled = {k: v for k, v in self._scaled.items() if k < s}  # finer scales never go back up
            self._scaled[s] = data_at_scale(self.p, self.geom, self.vol_geom, self.weights, self.gamma2, s)
        return self._scaled[s]

    def gauge(self, poses: Poses) -> Poses:
        return poses.gauge_fixed(self.geom, center=self.vol_geom.offset, scale=self.fix_scale)

    def hold(self, poses: Poses, stage: Stage) -> Poses:
        """``poses`` with the held vertical motion set again (:func:`hold_vertical`), after a round of a held stage."""
        if self.vertical is None or "tz" not in self.fixed(stage):
            return poses
        return hold_vertical(poses, self.vertical, self.geom, self.vol_geom.offset)

    def moves(self, a: Poses, b: Poses) -> np.ndarray:
        """Detector displacement of the sample points from poses ``a`` to ``b`` (full-resolution pixels)."""
        return point_moves(self.geom, self.points, a, b)


def increment_points(vol_geom: VolumeGeometry) -> np.ndarray:
    """The sample points whose detector displacement measures a round's increment (``Stage.tol_px``): 3 x 3 x 3 over
    80 % of the volume."""
    return sample_points(vol_geom, 3, fraction=0.8)


def point_moves(geom: VectorGeometry, points, a: Poses, b: Poses) -> np.ndarray:
    """Detector displacement of ``points`` from poses ``a`` to ``b`` on ``geom`` (its pixels)."""
    return geom.apply(b).project_points(points) - geom.apply(a).project_points(points)


def hold_vertical(poses: Poses, vertical, geom, center) -> Poses:
    """``poses`` whose lab vertical translation at ``center`` moves, view by view, as ``vertical`` does.

    ``vertical`` (n_views,) is a vertical motion of the sample itself, as the
    row sums' registration measures it (``RowSumConsistency.vertical_motion``;
    relative: only its change from the first view is used). It is written
    in the frame where the first view's pose is the identity, the sample as
    it stood at that view, and the poses are then put back in theirs: in any
    other frame the vertical translation at the centre is the sample's own
    motion plus what the frame's rotation adds view by view (a lever arm).
    Everything but that translation is kept.
    """
    n = poses.n_views
    first = Poses(np.repeat(poses.rotvecs[:1], n, axis=0), np.repeat(poses.translations[:1], n, axis=0))
    q = poses.compose(first.inverse()).lab_params(geom, center)
    v = np.asarray(vertical, dtype=np.float64)
    q[:, 2] = v - v[0]
    return Poses.from_lab_params(q, geom, center).compose(first)


def run_stages(
    projections,
    geom: VectorGeometry,
    vol_geom: VolumeGeometry,
    stages,
    *,
    poses: Optional[Poses] = None,
    noise_variance: float,
    weights=None,
    fix_scale: bool = True,
    angles=None,
    times=None,
    center=None,
    backend: str = "auto",
    start: tuple = (0, 0),
    history=(),
    checkpoint: Optional[Callable[[dict], object]] = None,
    progress: Optional[Callable[[dict], object]] = None,
    row_sums=None,
    held: tuple = (),
    known_jolts=(),
    vertical=None,
    before_stage: Optional[Callable[[int, "DriverResult"], bool]] = None,
) -> DriverResult:
    """Run ``stages`` in order from ``poses``; return the poses kept and why it stopped.

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) float32
        Line integrals at full resolution (not modified).
    geom, vol_geom
        The geometry given and the user's grid (full resolution).
    stages : sequence of Stage
    poses : Poses, optional
        Where to start (relative to ``geom``); default no motion.
    noise_variance : float
        γ² of the full-resolution projections (carried to each scale).
    weights : detector weights at full resolution, optional
    start : (stage index, rounds done in it)
        Resume an interrupted run there (``history`` holds its rounds).
    checkpoint : callable, optional
        Called after every round with ``dict(poses, history, stage_index,
        rounds_done)``, before anything is reported.
    progress : callable, optional
        Called with a dict at the start of every stage (``event="stage"``)
        and after every round (``event="round"``).
    row_sums : RowSumConsistency, optional
        The row sums of a parallel scan (:class:`pdvc.calibration.RowSumConsistency`):
        once a stage's rounds creep (a round moved the sample points by less
        than ``ROW_SUMS_CREEP × tol_px``), a round that raises their misfit
        by more than ``ROW_SUMS_TOL`` above the lowest since stops the stage,
        which keeps the poses of that lowest (``ROW_SUMS_GUARD``;
        ``docs/method.md`` §5.31).
    held : tuple of str
        Pose parameters (of :data:`POSE_PARAMETERS`) that no stage of a smooth
        model moves from ``poses`` (the jolt stage is not held), e.g.
        ``("tz",)`` where the row sums measured the vertical motion
        (``docs/method.md`` §5.35).
    known_jolts : sequence of int
        Views at which the sample is known to have jumped (the steps of the
        vertical motion the row sums measured): the jolt stage frees a step
        there too, besides the views it finds.
    vertical : (n_views,) array, optional
        With ``"tz"`` held: the vertical motion it is held at (length units,
        :func:`hold_vertical`), set again after every round of a held stage.
        The vertical translation at the centre that a motion measured on the
        sample itself gives depends on the poses' rotations and on their gauge
        (``docs/method.md`` §5.36); held as a number, it drifted from the
        truth as the rounds moved the rest.
    before_stage : callable, optional
        ``before_stage(i, result)`` before every stage ``i`` after the first this call runs, with the result the run
        would return if it ended there; when it returns true the run ends there and returns that result (the
        precession recipe's comparison before the default's finer scales: ``docs/method.md`` §5.55).
    """
    stages = tuple(stages)
    if not stages or not all(isinstance(s, Stage) for s in stages):
        raise StageError("stages must be a non-empty sequence of pdvc.calibration.Stage")
    ctx = _Context(
        projections, geom, vol_geom, weights=weights, gamma2=float(noise_variance), fix_scale=fix_scale,
        angles=angles, times=times, backend=backend, center=center,
    )
    ctx.row_sums = row_sums
    ctx.held = tuple(held)
    ctx.known_jolts = np.unique(np.asarray(known_jolts, dtype=int))
    if vertical is not None:
        vertical = np.asarray(vertical, dtype=np.float64)
        if vertical.shape != (geom.n_views,) or not np.all(np.isfinite(vertical)):
            raise StageError(f"vertical must be {geom.n_views} finite values, one per view, got shape {vertical.shape}")
        if "tz" not in ctx.held:
            raise StageError("vertical needs held to name 'tz'")
    ctx.vertical = vertical
    poses = Poses.identity(geom.n_views) if poses is None else poses
    history = list(history)
    for h in history:  # a resumed run keeps the decision its first round made
        if "offset_sigma" in h and 0 <= int(h.get("stage_index", -1)) < len(stages) and stages[int(h["stage_index"])].background == "auto":
            b = int(h.get("background", -1))
            ctx.offset_sigma = float(h["offset_sigma"])
            ctx.auto_background = b if b >= 0 else auto_background(ctx.offset_sigma)
            break
    for h in history:  # ... and the model its first stage with candidates chose
        if isinstance(h.get("model_choice"), dict):
            ctx.model_choice = ModelChoice(**h["model_choice"])
    outcomes: list = []
    kept = None
    guard_volume = fit_volume = None
    last = None  # (stage, (poses, volume)) of the stage before, where the next is a jolt stage (it measures views on it)
    i0, r0 = int(start[0]), int(start[1])

    def result(i_end):
        """What the run returns when it ends before stage ``i_end``."""
        # the run's status is that of the last stage that had to converge (warm-ups and refinements run their rounds)
        musts = [o for o, s in zip(outcomes, stages[i0:i_end]) if s.until == "converged"]
        last = musts[-1] if musts else outcomes[-1] if outcomes else StageOutcome(
            stages[i_end - 1].name, stages[i_end - 1].scale, Status.ROUNDS_DONE, Status.ROUNDS_DONE.message, 0, 0.0
        )
        return DriverResult(
            poses=poses, status=last.status, message=last.message, history=tuple(history), stages=tuple(outcomes),
            correlation=kept, guard_volume=guard_volume,
            fit_volume=fit_volume if fit_volume is not None and fit_volume[0] is poses else None,
            background=ctx.auto_background, offset_sigma=ctx.offset_sigma, model_choice=ctx.model_choice,
        )

    for i in range(i0, len(stages)):
        if before_stage is not None and i > i0:
            partial = result(i)
            if before_stage(i, partial):
                log.info("the run ends before stage %d (%s, scale %d)", i, stages[i].name, stages[i].scale)
                return partial
        stage, first, primed = stages[i], (r0 if i == i0 else 0), None
        t0 = time.perf_counter()  # the stage's time holds its model choice
        if stage.candidates and ctx.model_choice is None:
            # the first stage with candidates chooses its model, from the poses it starts from: does a candidate predict
            # views it was not fitted to better than the stage's own model?
            tc = time.perf_counter()
            if progress is not None:
                progress(dict(event="choosing", index=i, n_stages=len(stages), name=stage.name, scale=stage.scale,
                              models=[model_name(stage)] + list(stage.candidates)))
            primed = (poses, ctx.stage_volume(stage, poses))
            choice = ctx.choose_model(stage, poses, primed[1])
            if progress is not None:
                progress(dict(event="model", text=choice.text(), elapsed_s=time.perf_counter() - tc, **choice.to_dict()))
        chosen = ctx.with_model(stage)
        if primed is not None and any(getattr(chosen, k) != getattr(stage, k) for k in ("reconstruct", "oversample", "oversample_by")):
            primed = None  # the chosen model reconstructs its own way
        stage = chosen
        _, g_s, vg_s, _, _ = ctx.at_scale(stage.scale)
        if progress is not None:
            progress(dict(event="stage", index=i, n_stages=len(stages), name=stage.name, scale=stage.scale,
                          det_shape=g_s.det_shape, volume=vg_s.shape, rounds=stage.rounds))
        # does it start from poses an earlier stage measured and kept (a warm-up's, a coarser scale's)?
        refines = any(o.status.success and o.rounds > 0 for o in outcomes)
        run = _StageRun(ctx, stage, i, poses, history, checkpoint, progress, previous=kept, refines=refines, volume=primed,
                        last_volume=last)
        poses, status, res, gv = run.run(first)
        jolts_next = i + 1 < len(stages) and _is_jolt_stage(stages[i + 1])
        last = (stage, run.last_volume) if jolts_next and run.last_volume is not None else None
        kept = res if res is not None else kept
        guard_volume = gv if gv is not None else guard_volume
        fit_volume = (poses, stage, run.volume_at_poses) if run.volume_at_poses is not None else fit_volume
        outcomes.append(StageOutcome(stage.name, stage.scale, status, status.message, run.n_rounds, time.perf_counter() - t0))
        if checkpoint is not None:
            checkpoint(dict(poses=poses, history=[dict(h) for h in history], stage_index=i + 1, rounds_done=0))
        log.info("stage %d (%s, scale %d): %s after %d round(s)", i, stage.name, stage.scale, status.message, run.n_rounds)
    return result(len(stages))


class _StageRun:
    """The rounds of one stage and its stopping rules (``docs/method.md``, "Stopping")."""

    def __init__(self, ctx: _Context, stage: Stage, index: int, poses: Poses, history: list, checkpoint, progress, previous=None,
                 refines=False, volume=None, last_volume=None):
        self.ctx, self.stage, self.index = ctx, stage, index
        self.refines = refines  # the poses it starts from were measured and kept by an earlier stage
        self.previous = previous  # the correlation kept by the stages before (a jolt stage reads its per-view fit)
        self.basis = stage.basis
        self.poses = poses
        self.history = history
        self.checkpoint, self.progress = checkpoint, progress
        self.rec_final = _final_reconstruction(stage)
        self.n_rounds = 0
        self.best = None  # (chi_before, poses, result) for the consistency guard
        self.ent_best = None
        self.ent_range = None
        self.guard_volumes: list = []  # the entropy guard's last two volumes: a rollback keeps the one before
        self.kept = None  # the correlation whose poses are self.poses
        self.volume = volume  # (poses, correlation volume) of the current round (given: already made at ``poses``)
        self.given_last = last_volume  # (stage, (poses, volume)): the last volume of the stage before (a jolt stage's)
        self.last_volume = None  # (poses, volume) of this stage's last round
        self.volume_at_poses = None  # the correlation volume made at the poses the stage returns, if one was
        # the row sums' guard: (misfit, poses, correlation, round) of the round's poses they agree with best, from the
        # first round that moved the points by less than ROW_SUMS_CREEP x tol_px on (the rounds before approach the
        # data; the walk is what comes after)
        self.rs_best = None

    def run(self, first_round: int):
        st = self.stage
        status = Status.ROUNDS_DONE if st.until == "rounds" else Status.MAX_ITER
        if _is_jolt_stage(st):
            views = self._jolt_views(self.previous.snr_after) if self.previous is not None else np.array([], int)
            if views.size:
                views = self._jolts_confirmed(views)
            steps = self._jolt_steps()
            if steps.size:
                log.info("stage %s: the views' positions measured one by one step at views %s%s", st.name, steps.tolist(),
                         "" if np.isin(steps, views).all() else f" (the SNR found {views.tolist()})")
                views = np.union1d(views, steps).astype(int)
            known = self.ctx.known_jolts
            if known.size and not np.isin(known, views).all():
                log.info("stage %s: the row sums' vertical motion steps at views %s", st.name, known.tolist())
                views = np.union1d(views, known).astype(int)
            if views.size == 0:
                log.info("stage %s: no view's fit stands out: no jolt, skipped", st.name)
                if self.progress is not None:
                    self.progress(dict(event="skip", name=st.name, why="no view's fit stands out (no jolt)"))
                return self.poses, status, None, None
            n = self.ctx.geom.n_views
            at = np.unique(np.clip(np.concatenate([views - 1, views, views + 1]), 1, n - 1))  # the jump is near the dip
            log.info("stage %s: views %s stand out: the drift basis and a step at views %s", st.name, views.tolist(), at.tolist())
            smooth = drift_basis(self.ctx.angles, self.ctx.times)
            steps = (np.arange(n)[:, None] >= at[None, :]).astype(float)
            self.basis = custom_basis(
                np.column_stack([smooth.matrix, steps]), names=list(smooth.names) + [f"step{v}" for v in at]
            )
        prev_poses, prev_inc, prev_kept = self.poses, None, None
        prev_step = None  # the last round's move of the sample points (for the extrapolation)
        jump = None  # (poses, correlation) of the round a jump started from, while the jump's round runs
        may_jump = st.extrapolate and st.until == "converged" and "entropy" not in st.guards
        for r in range(first_round, st.rounds):
            self.t_round = time.perf_counter()
            jumped, jump = jump, None
            best_before = self.best
            entropy = float("nan")
            if "entropy" in st.guards:
                entropy, rose = self._entropy_check()
                if rose:
                    status = Status.ENTROPY_GUARD
                    self.poses, self.kept = prev_poses, prev_kept
                    break
            res = self._correlate()
            # the history holds the first measurement's offset, in full-resolution noise std
            self.offset_sigma, self.extra_passes = self.ctx.full_resolution_sigma(res.offset_sigma, st.scale), 0
            if self.ctx.decided(st, self.offset_sigma):  # a background from now on: this round is measured again with it
                self.extra_passes = int(res.n_iter)
                res = self._correlate(again=True)
            chi_before = float(res.chi_history[0])
            if jumped is not None and self.best is not None and chi_before > self.best[0]:
                # the extrapolated poses fit the data worse than the best round: back to where the jump started
                log.info("round %d: the extrapolated poses fit worse (chi_before %.5g > %.5g); undone, no more jumps in "
                         "this stage", r, chi_before, self.best[0])
                self.poses, self.kept = jumped
                may_jump, prev_step, prev_inc = False, None, None
                continue
            if "consistency" in st.guards:
                if self.best is None or chi_before < self.best[0]:
                    # a jump's poses have no correlation of their own: a rollback to them goes to where it started
                    self.best = ((chi_before, self.poses, self.kept, r, self.volume[1]) if jumped is None
                                 else (chi_before, jumped[0], jumped[1], r, None))
                elif chi_before > self.best[0] * (1 + st.diverge_tol):
                    log.info("round %d: chi_before %.5g rose above the best %.5g; keeping the best poses", r, chi_before, self.best[0])
                    # past its best point (a success) or never better than where it started: diverged, unless it
                    # started from poses an earlier stage measured, which it then keeps (it found nothing better)
                    status = Status.CONSISTENCY_GUARD if self.best[3] > first_round or self.refines else Status.DIVERGED
                    if self.best[3] == first_round and self.refines:
                        log.info("stage %s: no round fitted better than the poses it started from; they are kept", st.name)
                    self.poses, self.kept = self.best[1], self.best[2]
                    break
            if res.status == Status.NO_DESCENT and len(res.chi_history) == 1:
                status = Status.FIXED_POINT  # nothing lowered chi: the poses stay as they are
                if jumped is not None:
                    self.kept = res  # measured at the jump's poses
                break
            new = self.ctx.gauge(self.ctx.hold(res.poses, st))
            step = self.ctx.moves(self.poses, new)
            d = np.linalg.norm(step, axis=-1)
            inc, inc_max = float(np.sqrt(np.mean(d**2))), float(d.max())
            prev_poses, prev_kept = self.poses, self.kept
            self.poses, self.kept = new, res
            guarded = self.ctx.row_sums is not None and (self.rs_best is not None or inc < ROW_SUMS_CREEP * st.tol_px)
            rs = self.ctx.row_sums.misfit(new.rotvecs) if guarded else None
            self._record(r, res, chi_before, entropy, inc, inc_max, extrapolated=jumped is not None, row_sums=rs)
            if guarded:
                if self.rs_best is None or rs < self.rs_best[0]:
                    self.rs_best = (rs, new, res, r)
                elif rs > self.rs_best[0] * (1 + ROW_SUMS_TOL):
                    log.info("round %d: the row sums' misfit %.5g rose above the lowest %.5g (round %d); keeping its poses",
                             r, rs, self.rs_best[0], self.rs_best[3])
                    status = Status.ROW_SUMS_GUARD
                    self.poses, self.kept = self.rs_best[1], self.rs_best[2]
                    break
            if inc < st.tol_px:
                status = Status.CONVERGED if st.until == "converged" else Status.ROUNDS_DONE
                break
            if st.stall_ratio is not None and prev_inc is not None and inc >= st.stall_ratio * prev_inc:
                if jumped is not None:
                    # the jump overshot or left the series: back to where it started (and to the best round before
                    # it), and on by plain rounds, which stop where they would have without it (one round spent)
                    log.info("round %d: the round from the extrapolated poses moved %.3g px, not less than the %.3g px "
                             "before the jump; undone, no more jumps in this stage", r, inc, prev_inc)
                    self.poses, self.kept, self.best = jumped[0], jumped[1], best_before
                    may_jump, prev_step = False, None
                    continue
                log.info("round %d: increment %.3g px did not contract (previous %.3g px); stopping", r, inc, prev_inc)
                status = Status.STOPPED_CONTRACTING
                self.poses, self.kept = prev_poses, prev_kept  # the poses before this round
                break
            if may_jump and prev_step is not None and r < st.rounds - 1:
                target, cos = self._extrapolated(prev_poses, new, inc / prev_inc, step, prev_step)
                log.debug("round %d: increments %.3g -> %.3g px, cosine %.3f between the steps", r, prev_inc, inc, cos)
                if target is not None:
                    log.info("round %d: increments %.3g -> %.3g px along one direction (cosine %.3f); the next round starts "
                             "from their extrapolated limit", r, prev_inc, inc, cos)
                    jump, self.poses = (self.poses, self.kept), target
                    # the jump's round must contract on this round's increment (the stall rule), and starts a new series
                    prev_step, prev_inc = None, inc
                    continue
            prev_step, prev_inc = step, inc
        gv = next((v for v in self.guard_volumes if v[0] is self.poses), None)
        made = [self.volume] + ([(self.best[1], self.best[4])] if self.best is not None else [])
        self.volume_at_poses = next((v for q, v in made if q is self.poses), None) if self.volume is not None else None
        self.last_volume, self.volume = self.volume, None
        return self.poses, status, self.kept, gv

    def _extrapolated(self, before: Poses, after: Poses, ratio: float, step, prev_step) -> tuple[Optional[Poses], float]:
        """Aitken's limit of rounds that creep (``EXTRAPOLATE_RATIO``, ``EXTRAPOLATE_COS``) or None; the steps' cosine."""
        a, b = step.ravel(), prev_step.ravel()
        cos = float(a @ b) / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-300)
        if not (EXTRAPOLATE_RATIO[0] <= ratio <= EXTRAPOLATE_RATIO[1] and cos >= EXTRAPOLATE_COS):
            return None, cos
        lam = min(ratio / (1.0 - ratio), EXTRAPOLATE_MAX)
        rv = after.rotvecs + lam * (after.rotvecs - before.rotvecs)
        t = after.translations + lam * (after.translations - before.translations)
        return self.ctx.gauge(Poses(rv, t)), cos

    def _entropy_check(self) -> tuple[float, bool]:
        """Entropy of the stage's analytic volume at the current poses; True if it rose past the tolerance."""
        p, g, vg, _, _ = self.ctx.at_scale(self.stage.scale)
        ref = self.rec_final(p, vg, g.apply(self.poses))
        self.guard_volumes = (self.guard_volumes + [(self.poses, self.stage.scale, ref)])[-2:]
        if self.ent_range is None:
            self.ent_range = tuple(float(q) for q in np.percentile(ref, [0.1, 99.9]))
        entropy = float(shannon_entropy(ref, value_range=self.ent_range))
        if self.ent_best is not None and entropy > self.ent_best * (1 + self.stage.entropy_tol):
            log.info("entropy %.5g rose above the lowest %.5g; stopping", entropy, self.ent_best)
            return entropy, True
        self.ent_best = entropy if self.ent_best is None else min(self.ent_best, entropy)
        return entropy, False

    def _jolt_views(self, snr: np.ndarray) -> np.ndarray:
        """:func:`jolt_views`, the kink of a broad V on scans without opposite views only: there a smooth model takes a
        jolt up as a drift; a full turn's opposite views hold the jump, and its SNR's troughs with the angle (a
        sample's faces, a precession twice a turn) made kinks of their own (``docs/method.md`` §5.33)."""
        short = not self.ctx.full_turn
        return jolt_views(snr) if short else jolt_views(snr, kink_window=0)

    def _jolt_steps(self) -> np.ndarray:
        """:func:`jolt_steps` of the views' positions measured one by one (free lab translations across the beam and up,
        one Gauss-Newton step) against the last volume of the stage before, or the stage's own at its poses."""
        st, ctx = self.stage, self.ctx
        p, g, vg, w, gamma2 = ctx.at_scale(st.scale)
        if self.volume is not None and self.volume[0] is self.poses:  # made at the poses (the SNR's dips confirmed)
            made_by, vol = st, self.volume[1]
        elif self.given_last is not None and self.given_last[0].scale == st.scale:
            made_by, vol = self.given_last[0], self.given_last[1][1]
        else:
            self.volume = (self.poses, ctx.stage_volume(st, self.poses))
            made_by, vol = st, self.volume[1]
        self.given_last = None
        res = correlate(
            vol, refined_grid(vg, made_by.oversample), p, g, basis="dirac", frame="lab", fixed=("rx", "ry", "rz", "ty"),
            method="full", center=ctx.center, weights=w, noise_variance=gamma2, angles=ctx.angles, times=ctx.times,
            initial_rotvecs=self.poses.rotvecs, initial_translations=self.poses.translations, max_iter=1, accelerate=False,
            backend=ctx.backend, background=stage_background(st, ctx.auto_background),
        )
        # across the beam and up, in each view's lab axes (along the beam is fixed), in voxels of the user's grid
        d = (res.params_lab - self.poses.lab_params(g, ctx.center))[:, [0, 2]] / float(np.mean(ctx.vol_geom.voxel_size))
        return jolt_steps(d, angles=ctx.angles)

    def _jolts_confirmed(self, views: np.ndarray) -> np.ndarray:
        """The views whose SNR still dips without their largest residuals (:func:`trimmed_snr`), against the volume the
        stage's first round then reuses."""
        st, ctx = self.stage, self.ctx
        p, g, vg, w, _ = ctx.at_scale(st.scale)
        self.volume = (self.poses, ctx.stage_volume(st, self.poses))
        res = p - forward(self.volume[1], refined_grid(vg, st.oversample), g.apply(self.poses), backend=ctx.backend)
        kept = self._jolt_views(trimmed_snr(p, res, w))
        if kept.size < views.size:
            log.info("stage %s: views %s dip in SNR; without each view's %.2g %% largest residuals %s", st.name,
                     views.tolist(), 100 * JOLT_TRIM, f"only {kept.tolist()} do" if kept.size else "none does (outlier pixels)")
        return kept

    def _correlate(self, again: bool = False) -> CorrelationResult:
        """The round's measurement against a fresh reconstruction at its poses (``again``: the same one)."""
        st, ctx = self.stage, self.ctx
        p, g, vg, w, gamma2 = ctx.at_scale(st.scale)
        vg_c = refined_grid(vg, st.oversample)
        if not again and not (self.volume is not None and self.volume[0] is self.poses):
            self.volume = None  # at most two volumes alive: the best round's and this one
            self.volume = (self.poses, correlation_volume(p, vg, g.apply(self.poses), st, weights=w, lipschitz=ctx.lipschitz))
        vol = self.volume[1]
        # a fresh reconstruction that already fits worse than the best ends the stage: measure nothing more
        limit = self.best[0] * (1 + st.diverge_tol) if "consistency" in st.guards and self.best is not None else None
        return correlate(
            vol, vg_c, p, g, basis=self.basis, frame=st.frame, fixed=ctx.fixed(st), method=st.method, center=ctx.center,
            weights=w, noise_variance=gamma2, angles=ctx.angles, times=ctx.times,
            initial_rotvecs=self.poses.rotvecs, initial_translations=self.poses.translations,
            max_iter=st.max_iter, tol_px=self._inner_tol_px(), accelerate=st.accelerate, max_modes=st.max_modes,
            pgd_passes=st.pgd_passes, min_gain=st.min_gain, noise_floor=st.noise_floor, rcond=st.rcond, backend=ctx.backend,
            max_start_chi=limit,
            background=stage_background(st, ctx.auto_background), robust=st.robust,
        )

    def _inner_tol_px(self) -> float:
        """The round's Gauss-Newton tolerance (pixels of its scale): ``INNER_FORCING`` x the last round's increment on a
        full turn, ``INNER_TOL_PX`` on a short scan and in the first round."""
        if not self.history or not self.ctx.full_turn:
            return INNER_TOL_PX
        return max(INNER_TOL_PX, INNER_FORCING * float(self.history[-1]["increment_px"]) / self.stage.scale)

    def _record(self, r, res, chi_before, entropy, inc, inc_max, extrapolated=False, row_sums=None):
        st = self.stage
        entry = dict(
            iteration=len(self.history), stage=st.name, stage_index=self.index, scale=st.scale, round=r, chi_before=chi_before,
            chi_after=float(res.chi), snr_before=float(res.snr_history[0]), snr=float(res.snr_history[-1]),
            entropy=entropy, increment_px=inc, increment_max_px=inc_max, n_iter=int(res.n_iter) + self.extra_passes,
            engine_status=Status(res.status).name.lower(), elapsed_s=time.perf_counter() - self.t_round,
            background=-1 if res.background is None else int(res.background), offset_sigma=self.offset_sigma,
            model=model_name(st), extrapolated=bool(extrapolated),
        )
        if row_sums is not None:  # the row sums' misfit of the round's poses, where the guard read it
            entry["row_sums_misfit"] = float(row_sums)
        choice = self.ctx.model_choice
        if st.candidates and choice is not None and not any("model_choice" in h for h in self.history):
            entry["model_choice"] = choice.to_dict()  # saved with the stage's first round: a resumed run keeps the choice
        self.history.append(entry)
        self.n_rounds += 1
        log.info("stage %s round %d: chi %.5g -> %.5g, increment %.3g px%s", st.name, r, chi_before, entry["chi_after"], inc,
                 f", the row sums' misfit {row_sums:.5g}" if row_sums is not None else "")
        if self.checkpoint is not None:  # saved before anything is reported: a Ctrl-C in a callback loses no round
            self.checkpoint(dict(poses=self.poses, history=[dict(h) for h in self.history], stage_index=self.index, rounds_done=r + 1))
        if self.progress is not None:
            self.progress(dict(entry, event="round"))
