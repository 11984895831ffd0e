"""Stages as data, and the named recipes that are lists of them.

A :class:`Stage` says everything one part of a calibration does: the motion
model it measures (temporal basis, frame, fixed parameters, full
identification or PGD), the reconstruction of the correlation volume, the
scale of the data and the refinement of the correlation grid, the stopping
rule and its guards, and the number of rounds. :func:`pdvc.calibration.run_stages`
runs a list of them; a *recipe* is a named list (:func:`recipe_stages`). The
reasons behind every default are in ``docs/method.md``.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from ..correlation import BASIS_NAMES, TemporalBasis, is_basis_name
from ..errors import PdvcError
from ..projectors import POSE_PARAMETERS
from ._select import MODELS

log = logging.getLogger("pdvc.calibration")

__all__ = [
    "Stage",
    "StageError",
    "RECIPES",
    "RECONSTRUCTIONS",
    "OVERSAMPLE_BY",
    "GUARDS",
    "recipe_stages",
    "jolt_stage",
    "refine_stage",
    "JOLT_BASIS",
    "auto_scales",
    "capped_oversample",
    "stages_to_dicts",
    "stages_from_dicts",
]

#: Reconstructions of the correlation volume a stage can name.
RECONSTRUCTIONS = ("fdk", "nonneg_ls", "cgls")
#: Guards a stage can run before or after each round.
OVERSAMPLE_BY = ("spline", "reconstruction", "auto")
GUARDS = ("consistency", "entropy")
#: The basis of a jolt stage: a step at each view whose fit stays poor after the previous stages.
JOLT_BASIS = "jolt_steps"
#: The named recipes (:func:`recipe_stages`).
RECIPES = ("default", "precession", "jolts", "axis")

_ROTATIONS = ("rx", "ry", "rz")


class StageError(PdvcError, ValueError):
    """A stage or recipe that cannot run: a bad field, an unknown recipe."""


@dataclass(frozen=True)
class Stage:
    """One stage of a calibration: a motion model measured over rounds of reconstruct + correlate.

    Attributes
    ----------
    name : str
        A label for logs, history and report (e.g. ``"warmup"``, ``"model"``).
    basis : str or TemporalBasis or array
        Temporal basis (:func:`pdvc.correlation.make_basis` names, ``"drift"``
        = {1, t, t², cos θ, sin θ}). Only names can be written to a config.
        ``"jolt_steps"``: the ``drift`` basis plus a step starting at each
        view whose fit stays poor after the previous stages (a local dip of
        its SNR, or the kink of a broad V where the smooth model took a jolt
        up: :func:`pdvc.calibration.jolt_views`), or at which the views'
        positions, each measured on its own against the previous stage's
        last volume, step (:func:`pdvc.calibration.jolt_steps`), and at its
        two neighbours; the stage is skipped when no view stands out. Only
        those views are freed.
    frame : {"sample", "lab"}
    fixed : tuple of str
        Parameters of ``frame`` held at zero, among ``tx ty tz rx ry rz``.
    method : {"full", "pgd"}
    reconstruct : {"fdk", "nonneg_ls", "cgls"} or callable
        The correlation volume: FDK (FBP in parallel beam); non-negative
        least squares on cubic B-splines (:func:`pdvc.recon.nonneg_ls`,
        consistent on non-planar orbits); CGLS. A callable
        ``f(projections, vol_geom, geom) -> volume`` also makes the final
        volume of the stage. :func:`pdvc.calibrate` sets ``nonneg_ls`` on
        short scans (parallel over half a turn, cone beam over 180° plus
        the fan angle) when the user did not choose
        (:func:`pdvc.calibration.short_scan_reconstruction`).
    scale : int
        The data are coarse-grained ``scale`` x ``scale`` for this stage.
    oversample : int
        Correlation voxels are ``oversample`` x finer than the stage's grid.
    oversample_by : {"spline", "reconstruction", "auto"}
        How the FDK/FBP or ``nonneg_ls`` correlation volume reaches the
        finer grid: ``"spline"`` reconstructs on the stage's grid and
        interpolates by cubic B-splines (:func:`pdvc.recon.spline_upsample`;
        ``oversample³`` x cheaper); ``"reconstruction"`` reconstructs on the
        fine grid (``nonneg_ls``: B-spline unknowns on the stage's grid, the
        projector on the fine one). ``cgls`` always solves on the fine grid.
        ``"auto"``: ``"spline"`` in parallel beam, ``"reconstruction"`` in
        cone beam and on a region-of-interest scan (:func:`pdvc.calibrate`
        decides; what :func:`resolve_stages` gives a parallel scan's FDK
        stages, ``docs/method.md`` §5.50).
    rounds : int
        Rounds (reconstruct, correlate, fix the gauge) at most.
    tol_px : float
        A round that moves the sample points by less than this (RMS,
        full-resolution detector pixels) ends the stage.
    until : {"converged", "rounds"}
        ``"converged"``: the stage must converge; running out of rounds is
        not a success, and a round whose increment does not contract
        (``stall_ratio``) ends it with the poses before that round.
        ``"rounds"``: the stage runs its rounds (a warm-up), ending early on
        ``tol_px``.
    stall_ratio : float or None
        Stop when an increment is at least this times the previous one,
        keeping the poses before that round (either ``until``). None: no
        such rule.
    guards : tuple of str
        ``"consistency"``: stop when the data consistency of a fresh
        reconstruction rises by more than ``diverge_tol`` over the best of the
        stage (0: at all; a round whose fresh reconstruction fits worse is
        then not measured), keeping the best poses (``CONSISTENCY_GUARD``, a success; or
        ``DIVERGED`` when no round beat the stage's starting poses). ``"entropy"``: before each
        round, stop when the entropy of the stage's final-grid volume rises by
        more than ``entropy_tol`` over the lowest, keeping the poses before
        the last round.
    background : "auto" or int
        -1 (none) or the degree (0, 1, 2) of a smooth background per view
        fitted with the motion (:func:`pdvc.correlate`'s ``background``): an
        air level that drifts, a gain ramp, material outside the volume.
        ``"auto"`` (default): decided once per run, at the first round, from
        the per-view offset of the residual (a plane per view when it is
        well above the noise, none otherwise; ``docs/method.md`` §5.10); the
        later stages keep that choice.
    extrapolate : bool
        ``until="converged"``, no entropy guard: when two rounds in a row
        move the sample points the same way by increments that shrink
        slowly (ratio in ``EXTRAPOLATE_RATIO``, cosine at least
        ``EXTRAPOLATE_COS``), start the next round from the limit of that
        geometric series (Aitken's extrapolation, at most
        ``EXTRAPOLATE_MAX`` steps on; constants of
        ``pdvc.calibration._driver``). A jump whose fresh reconstruction
        fits the data worse than the stage's best round is undone, and no
        other is tried in the stage; so is one whose round does not contract
        on the round before the jump (the stall rule), and the stage goes on
        by plain rounds from where the jump started. Off by default: it
        reaches the loop's own fixed point sooner, which is not always
        nearer the truth (``docs/method.md`` §5.6, §5.15).
    candidates : tuple of str
        Named motion models (:data:`pdvc.calibration.MODELS`:
        ``"fixed_axis"``, ``"axis"``, ``"precession"``) compared with the
        stage's own before its first round, from the poses it starts from,
        on views they were not fitted to (:func:`compare_models`). From the
        simplest up, a richer model is kept only when it predicts them
        better than the simpler one by more than ``MIN_MODEL_GAIN`` (the
        stage's own model: ``OWN_MODEL_GAIN``; on a short scan simpler
        candidates are not compared), and a model simpler than the stage's
        own only where no richer one predicts better than it by more than
        ``OWN_MODEL_GAIN`` (:func:`pick_model`); the winner replaces the stage's model,
        and every later stage that lists candidates takes it. Once per run,
        at the first such stage. Empty (default for a stage): no choice.
    subsets : "auto" or int
        Ordered subsets of a ``nonneg_ls`` volume (:func:`pdvc.recon.nonneg_ls`'s
        ``subsets``): ``"auto"``, at most ``NONNEG_MAX_SUBSETS`` (3)
        interleaved subsets of at least ``NONNEG_SUBSET_VIEWS`` (30) views
        each; an int m, at most m subsets of at least
        ``NONNEG_MIN_SUBSET_VIEWS`` (15) views each (constants of
        ``pdvc.calibration._driver``). More subsets are cheaper and lean
        more toward their last views: over a stage's rounds that moved rods
        by 0.01 px (``docs/method.md`` §5.24), in the default recipe's one
        refining round at the finest scale of a short scan (6,
        ``NONNEG_REFINE_SUBSETS``) it did not (§5.52). Other volumes
        ignore it.
    robust : float or None
        Huber's cut on the residual, in its robust standard deviation
        (:func:`pdvc.correlate`'s ``robust``): every Jacobian pass weighs
        each pixel by Huber's weight of its own residual (iteratively
        reweighted least squares), the cut measured again at every round
        against its fresh reconstruction, so that outliers the
        preprocessing left (zingers, hot pixels, a defect of the detector)
        do not steer the poses; 5 was measured. ``None`` or 0 (default):
        least squares. Not the default: on clean scans it moves the loop's
        fixed point (``docs/method.md`` §5.19).
    max_iter, accelerate, max_modes, pgd_passes, min_gain, noise_floor, rcond
        The engine's options (:func:`pdvc.correlate`).
    """

    name: str = "model"
    basis: Any = "fourier:1"
    frame: str = "sample"
    fixed: tuple = ("rz",)
    method: str = "full"
    reconstruct: Any = "fdk"
    scale: int = 1
    oversample: int = 2
    oversample_by: str = "reconstruction"
    rounds: int = 9
    tol_px: float = 0.01
    until: str = "converged"
    stall_ratio: Optional[float] = 1.0
    guards: tuple = ("consistency",)
    diverge_tol: float = 0.005
    entropy_tol: float = 0.003
    max_iter: int = 10
    accelerate: bool = True
    max_modes: int = 5
    pgd_passes: int = 5
    min_gain: float = 0.01
    noise_floor: float = 1.05
    rcond: float = 1e-6
    background: Any = "auto"
    candidates: tuple = ()
    extrapolate: bool = False
    robust: Optional[float] = None
    subsets: Any = "auto"

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731
        if not isinstance(self.name, str) or not self.name:
            raise StageError(f"stage name must be a non-empty string, got {self.name!r}")
        w = f"stage {self.name!r}: "
        if isinstance(self.basis, str):
            if self.basis.strip().lower() != JOLT_BASIS and not is_basis_name(self.basis):
                raise StageError(f"{w}basis must be one of {BASIS_NAMES}, a TemporalBasis or an array, got {self.basis!r}")
            set_("basis", self.basis.strip().lower())
        elif not isinstance(self.basis, (TemporalBasis, np.ndarray)):
            raise StageError(f"{w}basis must be one of {BASIS_NAMES}, a TemporalBasis or an array, got {self.basis!r}")
        for key, allowed in (("frame", ("sample", "lab")), ("method", ("full", "pgd")), ("until", ("converged", "rounds")),
                             ("oversample_by", OVERSAMPLE_BY)):
            if getattr(self, key) not in allowed:
                raise StageError(f"{w}{key} must be one of {allowed}, got {getattr(self, key)!r}")
        fixed = (self.fixed,) if isinstance(self.fixed, str) else tuple(self.fixed)
        bad = [f for f in fixed if f not in POSE_PARAMETERS]
        if bad or len(set(fixed)) != len(fixed) or len(fixed) == 6:
            raise StageError(f"{w}fixed must name distinct parameters among {POSE_PARAMETERS}, leaving one free, got {list(fixed)}")
        set_("fixed", fixed)
        if not (callable(self.reconstruct) or self.reconstruct in RECONSTRUCTIONS):
            raise StageError(f"{w}reconstruct must be one of {RECONSTRUCTIONS} or a callable, got {self.reconstruct!r}")
        guards = (self.guards,) if isinstance(self.guards, str) else tuple(self.guards)
        if any(g not in GUARDS for g in guards) or len(set(guards)) != len(guards):
            raise StageError(f"{w}guards must be distinct names among {GUARDS}, got {list(guards)}")
        set_("guards", guards)
        for key, lo in (("scale", 1), ("oversample", 1), ("rounds", 1), ("max_iter", 1), ("max_modes", 1), ("pgd_passes", 1)):
            val = getattr(self, key)
            if not isinstance(val, (int, np.integer)) or isinstance(val, bool) or val < lo:
                raise StageError(f"{w}{key} must be an int >= {lo}, got {val!r}")
            set_(key, int(val))
        for key in ("tol_px", "entropy_tol", "rcond"):
            val = getattr(self, key)
            if not isinstance(val, (int, float, np.floating)) or isinstance(val, bool) or not (val > 0):
                raise StageError(f"{w}{key} must be a positive number, got {val!r}")
            set_(key, float(val))
        for key in ("diverge_tol", "min_gain", "noise_floor"):
            val = getattr(self, key)
            if not isinstance(val, (int, float, np.floating)) or isinstance(val, bool) or not (val >= 0):
                raise StageError(f"{w}{key} must be a non-negative number, got {val!r}")
            set_(key, float(val))
        if self.background != "auto":
            if isinstance(self.background, bool) or self.background not in (-1, 0, 1, 2):
                raise StageError(f"{w}background must be 'auto', -1 (none), 0, 1 or 2 (a polynomial degree), got {self.background!r}")
            set_("background", int(self.background))
        cands = (self.candidates,) if isinstance(self.candidates, str) else tuple(self.candidates)
        if any(c not in MODELS for c in cands) or len(set(cands)) != len(cands):
            raise StageError(f"{w}candidates must be distinct names among {tuple(MODELS)}, got {list(cands)}")
        set_("candidates", cands)
        if not isinstance(self.accelerate, (bool, np.bool_)):
            raise StageError(f"{w}accelerate must be true or false, got {self.accelerate!r}")
        set_("accelerate", bool(self.accelerate))
        if not isinstance(self.extrapolate, (bool, np.bool_)):
            raise StageError(f"{w}extrapolate must be true or false, got {self.extrapolate!r}")
        set_("extrapolate", bool(self.extrapolate))
        if self.robust is not None:
            val = self.robust
            if not isinstance(val, (int, float, np.integer, np.floating)) or isinstance(val, bool) or not (np.isfinite(val) and val >= 0):
                raise StageError(f"{w}robust must be a positive Huber threshold (residual std), or 0 or None (plain least squares), "
                                 f"got {val!r}")
            set_("robust", float(val) if val > 0 else None)
        if self.subsets != "auto":
            val = self.subsets
            if not isinstance(val, (int, np.integer)) or isinstance(val, bool) or val < 1:
                raise StageError(f"{w}subsets must be 'auto' or an int >= 1 (nonneg_ls ordered subsets), got {val!r}")
            set_("subsets", int(val))
        if self.stall_ratio is not None and not (isinstance(self.stall_ratio, (int, float)) and self.stall_ratio > 0):
            raise StageError(f"{w}stall_ratio must be a positive number or None, got {self.stall_ratio!r}")

    @property
    def frees_rotation(self) -> bool:
        return not set(_ROTATIONS) <= set(self.fixed)

    def replace(self, **changes) -> "Stage":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """The stage as a ``[[calibration.stage]]`` table (TOML types; ``stall_ratio = 0`` means none)."""
        if not isinstance(self.basis, str) or callable(self.reconstruct):
            raise StageError(f"stage {self.name!r} holds a custom basis or reconstruction: it cannot be written to a config")
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d["fixed"] = list(self.fixed)
        d["guards"] = list(self.guards)
        d["candidates"] = list(self.candidates)
        d["stall_ratio"] = 0.0 if self.stall_ratio is None else float(self.stall_ratio)
        d["robust"] = 0.0 if self.robust is None else float(self.robust)
        return d

    @classmethod
    def from_dict(cls, table: dict, where: str = "stage") -> "Stage":
        """A stage from a ``[[calibration.stage]]`` table; unknown keys are an error."""
        if not isinstance(table, dict):
            raise StageError(f"{where} must be a table, got {type(table).__name__}")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(table) - names)
        if unknown:
            raise StageError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(names)}")
        d = dict(table)
        if "reconstruct" in d and not isinstance(d["reconstruct"], str):
            raise StageError(f"{where}.reconstruct must be one of {RECONSTRUCTIONS}, got {d['reconstruct']!r}")
        if "basis" in d and not isinstance(d["basis"], str):
            raise StageError(f"{where}.basis must be one of {BASIS_NAMES}, got {d['basis']!r}")
        if d.get("stall_ratio") == 0:
            d["stall_ratio"] = None
        try:
            return cls(**d)
        except StageError as exc:
            raise StageError(f"{where}: {exc}") from None
        except TypeError as exc:  # pragma: no cover - all fields have defaults
            raise StageError(f"{where}: {exc}") from None


def stages_to_dicts(stages) -> list:
    return [s.to_dict() for s in stages]


def stages_from_dicts(tables, where: str = "calibration.stage") -> tuple:
    if not isinstance(tables, (list, tuple)) or not tables:
        raise StageError(f"{where} must be a non-empty list of tables")
    return tuple(Stage.from_dict(t, f"{where}[{i}]") for i, t in enumerate(tables))


# the largest correlation grid of the automatic schedule's finest scale, in voxels (256^3: 64 MiB of float32)
MAX_CORRELATION_VOXELS = 256**3


def auto_scales(det_shape, vol_shape=None, oversample: int = 2) -> tuple:
    """Default coarse-to-fine scales of the data: coarse enough for ~64+ px, down to 1.

    Large detectors (512 columns or more) run 4 -> 2 (the paper's schedule:
    at scale 2 a 2k detector still has ~1000 columns), small ones (under
    512) 2 -> 1, tiny ones (under 128) 1 only. With ``vol_shape`` (the
    user's grid) and the model's ``oversample``, the schedule moves an
    octave coarser while the finest scale's correlation grid (the grid
    binned by the scale, refined ``oversample`` times per axis) would exceed
    ``MAX_CORRELATION_VOXELS`` (256³) and the coarsest scale keeps 64+ px:
    the standard problem (256³, 256×384 detector) runs 4 -> 2, whose
    correlation grid is 256³ instead of 512³ (``docs/method.md`` §2).
    Whatever the scales, the final volume is reconstructed at full
    resolution on the user's grid.
    """
    n = min(det_shape[1], max(det_shape[0], 1) * 4)  # thin detectors (a few rows) count by columns
    sched = (4, 2) if n >= 512 else (2, 1) if n >= 128 else (1,)
    if vol_shape is not None:
        voxels = float(np.prod(vol_shape))
        while voxels * (oversample / sched[-1]) ** 3 > MAX_CORRELATION_VOXELS and n / (2 * sched[0]) >= 64:
            sched = tuple(2 * s for s in sched)
    return sched


def capped_oversample(vol_shape, scale: int, oversample: int) -> int:
    """The oversampling at ``scale``, at most ``oversample``, whose correlation grid stays within ``MAX_CORRELATION_VOXELS``.

    :func:`auto_scales` keeps the cap by moving the schedule an octave
    coarser, but not below 64 px at its first scale: a detector of 128-255
    columns under a volume above 128³ voxels (a 134 x 160 detector and a
    134 x 160 x 160 volume, as a config without ``[volume]`` makes) keeps
    scales 2 -> 1, whose finest grid at 2x would be 268 x 320 x 320. There
    the finest scale correlates on a less refined grid instead (at 1x, the
    voxels of the coarser scale's 2x grid; ``docs/method.md`` §5.29). Never
    below 1.
    """
    voxels = float(np.prod(vol_shape))
    k = int(oversample)
    while k > 1 and voxels * (k / scale) ** 3 > MAX_CORRELATION_VOXELS:
        k -= 1
    return k


# diverge_tol of the model stage at the scales after the first (the finest scales refine)
FINER_SCALE_DIVERGE_TOL = 0.0

# the models the default recipe compares with its own (docs/method.md §5.12): the fixed axis of beamline tools (since
# session 50: a scan whose axis is only offset and tilted no longer gets the small wobble and drift the axis model
# invents, §5.48) and the precession model
DEFAULT_CANDIDATES = ("fixed_axis", "precession")

# the model stage of each recipe, before the user's overrides
_RECIPE_MODEL = {
    "default": dict(basis="fourier:1", frame="sample", fixed=("rz",)),
    "precession": dict(basis="drift", frame="lab", fixed=("rz",), reconstruct="nonneg_ls", guards=("consistency", "entropy")),
    "jolts": dict(basis="dirac", frame="lab", fixed=("rx", "ry", "rz", "ty")),
    "axis": dict(basis="constant", frame="lab", fixed=("rz", "ty")),
}
_RECIPE_ROUNDS = {"default": 10, "precession": 8, "jolts": 8, "axis": 10}

# the default recipe on non-negative least-squares volumes over several scales (short scans): the
# coarser scales get NONNEG_COARSE_ROUNDS times the recipe's rounds and the finest scale only
# NONNEG_FINE_ROUNDS refining rounds (a fine round costs ~8 coarse ones; docs/method.md §5.15)
NONNEG_COARSE_ROUNDS = 2
NONNEG_FINE_ROUNDS = 1
# ... whose volume is fitted by 6 ordered subsets instead of the rounds' 3: one round cannot accumulate the lean of
# each subset toward its own views that several rounds did (the 180-degree stand-in's refining nonneg_ls 20.4 -> 10.4 s,
# the tuning and fresh two-scale half turns and cone-beam short scans within 0.0008 px per case; docs/method.md §5.52)
NONNEG_REFINE_SUBSETS = 6
# the default recipe on a full turn over several scales (FDK volumes): the finest scale refines by this many rounds (a
# round on its grid costs ~10 coarse ones; the precession recipe's second run follows there, and the rounds after the
# first crept by a few hundredths of a pixel until the finer scale's guard discarded one; docs/method.md §5.53)
FULL_TURN_FINE_ROUNDS = 1

# the default recipe's refinement (docs/method.md §5.22): rounds of the precession model on non-negative
# least-squares volumes at the coarsest scale, from the poses the model stages kept
REFINE_ROUNDS = 4


def recipe_stages(
    recipe: str = "default", det_shape=None, *, vol_shape=None, scales="auto", max_outer: Optional[int] = None, warmup: int = 1,
    warmup_basis: str = "drift", jolts: bool = True, refine: bool = False, strict_first_scale: bool = False,
    fine_rounds: Optional[int] = None, **model,
) -> tuple:
    """The stage list of a named recipe.

    Parameters
    ----------
    recipe : {"default", "precession", "jolts", "axis"}
        ``default``: a tilted, offset axis and smooth drift (sample-frame
        ``fourier:1``, FDK). ``precession``: a precessing axis (lab-frame
        ``drift`` basis, non-negative least-squares volume, entropy guard).
        Both end with the jolt stage unless ``jolts=False``.
        ``jolts``: sudden jumps (free per-view lab translations).
        ``axis``: only a fixed (offset, tilted) axis (constant lab model).
    det_shape : (rows, cols)
        Needed for ``scales="auto"`` (:func:`auto_scales`).
    vol_shape : (nz, ny, nx), optional
        The user's grid: ``scales="auto"`` then caps the finest scale's
        correlation grid (:func:`auto_scales`; where a coarser schedule
        cannot, by that scale's oversampling, :func:`capped_oversample`,
        unless ``oversample`` is given).
    scales : "auto" or sequence of int
        A model stage per scale, coarse to fine (the first scale also a warm-up).
    max_outer : int, optional
        Rounds per scale, warm-up included (recipe default: 10, 8 for
        ``precession`` and ``jolts``). Unset, the ``default`` recipe on
        ``reconstruct="nonneg_ls"`` over several scales (short scans) gives
        the coarser scales twice its rounds and the finest one refining
        round (``docs/method.md`` §5.15).
    warmup : int
        Translation-only rounds before the model at the first scale, when the
        model frees a rotation (0: none).
    warmup_basis : {"drift", "model"}
        The warm-up's translation model: ``"drift"``, the lab-frame
        {1, t, t², cos θ, sin θ}; ``"model"``, the model stage's own basis
        and frame (so that the model can take back anything the warm-up
        measured).
    jolts : bool
        ``default`` and ``precession`` recipes: end with :func:`jolt_stage`
        (skipped unless some views' fit stays poor after the smooth model).
    refine : bool
        ``default`` recipe with its model chosen from the data (no
        ``basis``, ``frame`` or ``fixed`` given) and its own volume (no
        ``reconstruct`` given; a short scan's ``nonneg_ls`` counts as
        given): end the smooth model with :func:`refine_stage` at the
        coarsest scale, before the jolts (``docs/method.md`` §5.22). Off by
        default: better on the benchmark's scans, worse on a plain tilted
        axis.
    strict_first_scale : bool
        The model stage at the first scale stops, as those of the finer
        scales do, at the first fresh reconstruction that fits worse than the
        stage's best (``diverge_tol`` = ``FINER_SCALE_DIVERGE_TOL``) instead of
        0.5 % worse, unless ``diverge_tol`` is given. :func:`pdvc.calibrate`
        sets it for the default recipe on full turns, where the precession
        recipe's second run follows: the rounds past the best one crept there
        without changing what is returned (``docs/method.md`` §5.50).
    fine_rounds : int, optional
        Over several scales (and unless ``max_outer`` is given): the rounds of
        the finest scale's model stage, a refinement of what the coarser
        scales measured (``until = "rounds"``), where fewer than the recipe's.
        None: the recipe's. :func:`pdvc.calibrate` sets
        ``FULL_TURN_FINE_ROUNDS`` with ``strict_first_scale``
        (``docs/method.md`` §5.53).
    **model
        Overrides of the model stage's fields (``basis``, ``frame``,
        ``fixed``, ``method``, ``reconstruct``, ``oversample``, ``tol_px``,
        ``guards``, ``max_iter``, ...).
    """
    if recipe not in RECIPES:
        raise StageError(f"recipe must be one of {RECIPES}, got {recipe!r}")
    if scales == "auto":
        if det_shape is None:
            raise StageError("scales='auto' needs the detector shape")
        sched = None  # once the model stage (its oversampling) is known
    else:
        try:
            sched = tuple(int(s) for s in scales)
        except (TypeError, ValueError):
            raise StageError(f"scales must be 'auto' or positive ints, coarse to fine, got {scales!r}") from None
        if not sched or any(s < 1 for s in sched) or any(b >= a for a, b in zip(sched, sched[1:])):
            raise StageError(f"scales must be 'auto' or positive ints, strictly decreasing (coarse to fine), got {scales!r}")
    n_outer = _RECIPE_ROUNDS[recipe] if max_outer is None else max_outer
    if not isinstance(n_outer, (int, np.integer)) or isinstance(n_outer, bool) or n_outer < 1:
        raise StageError(f"max_outer must be a positive int, got {max_outer!r}")
    if fine_rounds is not None and (not isinstance(fine_rounds, (int, np.integer)) or isinstance(fine_rounds, bool)
                                    or fine_rounds < 1):
        raise StageError(f"fine_rounds must be a positive int or None, got {fine_rounds!r}")
    if not isinstance(warmup, (int, np.integer)) or isinstance(warmup, bool) or warmup < 0:
        raise StageError(f"warmup must be an int >= 0, got {warmup!r}")
    if warmup_basis not in ("drift", "model"):
        raise StageError(f"warmup_basis must be 'drift' or 'model', got {warmup_basis!r}")
    fields = {f.name for f in dataclasses.fields(Stage)} - {"name", "scale", "rounds"}
    unknown = sorted(set(model) - fields)
    if unknown:
        raise StageError(f"unknown model option(s) {unknown}; a stage takes {sorted(fields)}")
    spec = dict(_RECIPE_MODEL[recipe])
    if recipe == "default" and not any(model.get(k) is not None for k in ("basis", "frame", "fixed")):
        spec["candidates"] = DEFAULT_CANDIDATES  # the model is chosen from the data unless the user chose it
    spec.update({k: v for k, v in model.items() if v is not None})
    base = Stage(name="model", rounds=1, **spec)
    over = {}  # scale -> oversampling, where the automatic schedule's cap takes less than the model's
    if sched is None:
        sched, plain = auto_scales(det_shape, vol_shape, base.oversample), auto_scales(det_shape)
        if sched != plain:
            edge = round((float(np.prod(vol_shape)) * (base.oversample / plain[-1]) ** 3) ** (1 / 3))
            log.info("scales %s: the finest scale's correlation grid is capped at %d^3 voxels (scales %s would correlate "
                     "on %d^3); set scales to choose", sched, round(MAX_CORRELATION_VOXELS ** (1 / 3)), plain, edge)
        if vol_shape is not None and model.get("oversample") is None:  # resolve_stages puts it in the notes
            over = {s: k for s in sched if (k := capped_oversample(vol_shape, s, base.oversample)) != base.oversample}
    # a finer scale refines what the coarser one measured: it stops at the first fresh reconstruction
    # that fits worse than the best of the stage (docs/method.md, "Stopping"), unless the user set diverge_tol
    finer = {} if model.get("diverge_tol") is not None else dict(diverge_tol=FINER_SCALE_DIVERGE_TOL)
    # the rounds of each scale: a non-negative least-squares loop creeps along its near-gauge modes by
    # increments that shrink 10-40 % a round, cheaply at a coarse scale; the finest scale refines
    rounds = [n_outer] * len(sched)
    nonneg = isinstance(base.reconstruct, str) and base.reconstruct == "nonneg_ls"
    if recipe == "default" and nonneg and len(sched) > 1 and max_outer is None:
        rounds = [NONNEG_COARSE_ROUNDS * n_outer] * (len(sched) - 1) + [NONNEG_FINE_ROUNDS]
    elif fine_rounds is not None and len(sched) > 1 and max_outer is None:
        rounds[-1] = min(rounds[-1], int(fine_rounds))

    def at(s: int) -> Stage:  # the model stage at scale s, its oversampling capped there
        return base.replace(oversample=over[s]) if s in over else base

    stages = []
    for j, s in enumerate(sched):
        # translations first at the first scale only: a finer scale starts from poses the coarser one measured
        n_warm = min(warmup, rounds[j] - 1) if base.frees_rotation and j == 0 else 0
        if n_warm:
            stages.append(warmup_stage(at(s), scale=s, rounds=n_warm, basis=warmup_basis))
        # a refinement: its rounds, not a convergence; its one volume by more ordered subsets, unless the user chose them
        fine = dict(until="rounds", subsets=NONNEG_REFINE_SUBSETS if base.subsets == "auto" else base.subsets) \
            if rounds[j] < n_outer else {}
        stages.append(at(s).replace(scale=s, rounds=rounds[j] - n_warm, **(finer if j > 0 or strict_first_scale else {}), **fine))
    last = stages[-1]  # the jolts are looked for at the finest scale, on the smooth model's own volumes
    if recipe == "default" and refine and spec.get("candidates") and model.get("reconstruct") is None:
        stages.append(refine_stage(at(sched[0]), scale=sched[0]))
    if recipe in ("default", "precession") and jolts:
        stages.append(jolt_stage(last))
    return tuple(stages)


def refine_stage(model: Stage, *, scale: int, rounds: int = REFINE_ROUNDS) -> Stage:
    """After the default's smooth model: the precession model on non-negative least-squares volumes.

    A precession once per turn is taken up by the FDK volume the default's
    model is fitted to, and the model choice does not see it; the
    consistent volume gives it back. On a plain tilted axis its rounds can
    walk along the weak modes, which is why it is an option
    (``docs/method.md`` §5.22). Lab-frame ``drift``
    basis on the translations and the tilts, ``nonneg_ls`` volume, the
    consistency and entropy guards; it runs at most ``rounds`` rounds at
    ``scale`` and stops when a round does not contract (the poses before
    it kept). A refinement: its status does not replace the model's.
    """
    return model.replace(
        name="refine", **_RECIPE_MODEL["precession"], scale=scale, rounds=rounds, until="rounds", stall_ratio=1.0,
        candidates=(),
    )


def jolt_stage(model: Stage, rounds: int = 5) -> Stage:
    """After a smooth model: a step in the lab translations at each view whose fit stays poor, or where the views'
    positions measured one by one step (a jolt).

    Skipped when no view stands out. Rotations and the translation along
    the beam (a magnification change) stay fixed; it runs its rounds (a
    refinement: its status does not replace the model's).
    """
    return model.replace(
        name="jolts", basis=JOLT_BASIS, frame="lab", fixed=("rx", "ry", "rz", "ty"), method="full", rounds=rounds,
        until="rounds", stall_ratio=None, guards=("consistency",), candidates=(),
    )


def warmup_stage(model: Stage, *, scale: int, rounds: int = 1, basis: str = "drift") -> Stage:
    """Translations first: the lab-frame ``drift`` model that precedes a model with free rotations.

    The first reconstructions are blurred by the motion; rotations measured
    against them are noise (``docs/method.md``). In the lab frame it also
    holds the translations the model fixes.
    """
    if basis == "model":
        fixed = _ROTATIONS + tuple(x for x in model.fixed if x not in _ROTATIONS)
        return model.replace(
            name="warmup", fixed=fixed, method="full", scale=scale, rounds=rounds, until="rounds", guards=(), stall_ratio=None,
            candidates=(),
        )
    fixed = _ROTATIONS + (tuple(x for x in model.fixed if x not in _ROTATIONS) if model.frame == "lab" else ())
    return model.replace(
        name="warmup", basis="drift", frame="lab", fixed=fixed, method="full", scale=scale, rounds=rounds,
        until="rounds", guards=(), stall_ratio=None, candidates=(),
    )
