"""Automatic choice of the motion model: candidates scored on views they were not fitted to.

Before the first round of the first stage that names candidates
(``Stage.candidates``), from the poses it starts from (the warm-up's), the
stage's own model and every candidate measure an increment on one half of
the views and predict the other half; the data consistency of those
predictions (χ² of the views left out, against the correlation volume the
stage's first round makes anyway) scores each model. Both halves take each
role (two-fold cross-validation by interleaved blocks of views). The models
are taken from the simplest (fewest free functions) up, and a richer one is
kept only when it lowers the score of the simpler one chosen so far by more
than its threshold (``MIN_MODEL_GAIN`` for a candidate, ``OWN_MODEL_GAIN``
for the stage's own model against a simpler candidate): a richer model has
to predict views it never saw better, not merely fit more
(``docs/method.md`` §5.12).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..correlation import coarse_grain, coarse_weights, correlate, make_basis
from ..correlation._background import BACKGROUND_DEGREES, without_background
from ..correlation._engine import _problem
from ..correlation._frames import lab_to_sample_map, params_to_lab, params_to_sample
from ..errors import InputTypeError, ShapeError
from ..geometry import Poses, VectorGeometry, VolumeGeometry, sample_points
from ..projectors import forward
from ..recon import nonneg_ls, nonneg_ls_lipschitz, refined_grid

log = logging.getLogger("pdvc.calibration")

__all__ = ["MODELS", "MIN_MODEL_GAIN", "OWN_MODEL_GAIN", "ModelChoice", "compare_models", "cross_validated_misfit",
           "pick_model", "richer_than_simpler", "model_fields", "model_name", "with_model"]

#: Named motion models a stage can list as candidates: (basis, frame, fixed).
MODELS = {
    # an offset axis, tilted in the lab and fixed over the scan: nothing else moves (what beamline tools fit)
    "fixed_axis": dict(basis="constant", frame="lab", fixed=("rz",)),
    # a tilted, offset axis and a slow drift (the default recipe's model)
    "axis": dict(basis="fourier:1", frame="sample", fixed=("rz",)),
    # a precessing axis (one and two cycles per turn in the lab) and a drift with acceleration; the precession
    # recipe's volume (consistent on non-planar orbits) and entropy guard (the near-gauge rotation modes)
    "precession": dict(basis="drift:2", frame="lab", fixed=("rz",), reconstruct="nonneg_ls", guards=("consistency", "entropy")),
}
#: A candidate must lower the cross-validated χ² of the simpler model chosen so far by more than this fraction.
MIN_MODEL_GAIN = 0.007
#: The stage's own model must lower a simpler candidate's cross-validated χ² by more than this fraction to be kept.
OWN_MODEL_GAIN = 0.004
# interleaved blocks of views: each half holds every other block
_BLOCKS = 16
# the fewest views a half may hold for a comparison
_MIN_HALF = 8
#: Each half's fit stops at a Gauss-Newton step below this (px on the detector): the scores compare predictions of the
#: other half, which the last thousandths of a pixel do not change (the calibration's rounds iterate to 0.001 px; the
#: choice's four fits spent 2-3 of their 6-8 passes below 0.01 px on the demo's scan; docs/method.md §5.47)
MODEL_FIT_TOL_PX = 0.01


def model_fields(name: str) -> dict:
    """The stage fields of a named model (basis, frame, fixed; its reconstruction and guards)."""
    return dict(MODELS[name])


def with_model(stage, choice: Optional["ModelChoice"]):
    """The stage with the motion model ``choice`` made, if it lists candidates and a candidate won; else itself."""
    if not stage.candidates or choice is None or not choice.changed:
        return stage
    return stage.replace(name=f"{stage.name}:{choice.winner}", **model_fields(choice.winner))


def model_name(stage) -> str:
    """The name of the stage's model among :data:`MODELS`, or ``"basis (frame)"``."""
    for name, f in MODELS.items():
        if isinstance(stage.basis, str) and all(getattr(stage, k) == v for k, v in f.items()):
            return name
    b = stage.basis if isinstance(stage.basis, str) else "custom"
    return f"{b} ({stage.frame} frame)"


@dataclass(frozen=True)
class ModelChoice:
    """What :func:`compare_models` measured.

    Attributes
    ----------
    winner : str
        The model kept (the stage's own unless a candidate won).
    own : str
        The stage's own model.
    scores : dict
        Cross-validated χ² of each model (mean of the views left out, noise
        variance 1), in the order compared.
    gain : float
        Relative decrease of the winner's score against the own model's (0 if
        it kept its own; negative or small when a simpler model won).
    n_views : int
    n_passes : int
        Jacobian passes spent (fits and scores).
    shifts_px : dict
        RMS detector displacement (pixels of the data compared) of the
        sample points between each model's predictions and the stage's
        poses, over the views left out (gauge-free).
    min_gain : float
        The gain a candidate had to exceed over a simpler model.
    note : str
        Why a model was not compared ("" when all were).
    simpler : bool
        The winner is simpler than the own model (fewer free functions): the
        own model did not predict better than it by more than ``own_gain``.
    own_gain : float
        The gain the own model had to exceed over a simpler candidate.
    sizes : dict
        Free functions of each model compared (basis functions times free
        parameters): what "simpler" means.
    """

    winner: str
    own: str
    scores: dict = field(default_factory=dict)
    gain: float = 0.0
    n_views: int = 0
    n_passes: int = 0
    shifts_px: dict = field(default_factory=dict)
    min_gain: float = MIN_MODEL_GAIN
    note: str = ""
    simpler: bool = False
    own_gain: float = OWN_MODEL_GAIN
    sizes: dict = field(default_factory=dict)

    @property
    def changed(self) -> bool:
        return self.winner != self.own

    def text(self) -> str:
        if not self.scores:
            return f"{self.winner} (not compared{': ' + self.note if self.note else ''})"
        return self._verdict() + (f"; {self.note}" if self.note else "")

    def _blind_spot(self) -> str:
        """What the comparison cannot see, when it kept the axis model over the precession model."""
        if self.changed or self.own != "axis" or "precession" not in self.scores:
            return ""
        # measured on 92^3 tuning scans: gains of 0.0-2 % where the precession model lowers the error 5-20x
        return ("; a precession once per turn hardly changes this comparison (the reconstruction takes it up): "
                "second_run = \"auto\" compares finished calibrations of both recipes (docs/method.md §5.25)")

    def _verdict(self) -> str:
        parts = ", ".join(f"{k} {v:.4g}" for k, v in self.scores.items())
        if self.changed and self.simpler:
            lead = 1.0 - self.scores[self.own] / self.scores[self.winner] if self.scores.get(self.winner) else 0.0
            how = f"{100 * lead:.2g} % better, not more than {100 * self.own_gain:.2g} %" if lead > 0 else \
                f"{100 * -lead:.2g} % worse"
            return f"{self.winner}: predicts the views it was not fitted to as well as {self.own}, with fewer parameters " \
                   f"({self.own}: {how}; cross-validated chi^2: {parts})"
        if self.changed:
            return f"{self.winner}: predicts the views it was not fitted to {100 * self.gain:.2g} % better than {self.own} " \
                   f"(cross-validated chi^2: {parts})"
        simpler = [k for k in self.scores if k in self.sizes and self.sizes[k] < self.sizes.get(self.own, 0) and self.scores[k] > 0]
        if not simpler:
            return f"{self.own} kept: no candidate predicts the views it was not fitted to more than {100 * self.min_gain:.2g} % " \
                   f"better (cross-validated chi^2: {parts}){self._blind_spot()}"
        own_beats = [k for k in simpler if self.scores[self.own] < self.scores[k] * (1.0 - self.own_gain)]
        if not own_beats:
            # the own model alone did not beat the simpler ones by own_gain: a richer candidate did (pick_model)
            seen = []
            for k in simpler:
                for r in richer_than_simpler(self.scores, self.sizes, k, self.own_gain):
                    seen.append(f"{r} {100 * (1.0 - self.scores[r] / self.scores[k]):.2g} % better than {k}")
            seen = "; ".join(seen)
            return f"{self.own} kept: a richer model predicts the views it was not fitted to better than the simpler " \
                   f"one by more than {100 * self.own_gain:.2g} % ({seen}: a motion beyond it), and no richer candidate " \
                   f"more than {100 * self.min_gain:.2g} % better than {self.own} (cross-validated chi^2: {parts})" \
                   f"{self._blind_spot()}"
        beats = " and ".join(f"{100 * (1.0 - self.scores[self.own] / self.scores[k]):.2g} % better than {k}" for k in simpler)
        return f"{self.own} kept: it predicts the views it was not fitted to {beats} (more than {100 * self.own_gain:.2g} %), " \
               f"and no richer candidate more than {100 * self.min_gain:.2g} % better than it (cross-validated chi^2: {parts})" \
               f"{self._blind_spot()}"

    def to_dict(self) -> dict:
        return dict(winner=self.winner, own=self.own, scores=dict(self.scores), gain=self.gain, n_views=self.n_views,
                    n_passes=self.n_passes, shifts_px=dict(self.shifts_px), min_gain=self.min_gain, note=self.note,
                    simpler=self.simpler, own_gain=self.own_gain, sizes=dict(self.sizes))


def halves(n_views: int, blocks: int = _BLOCKS) -> tuple:
    """Two complementary index arrays: interleaved blocks of consecutive views."""
    k = np.arange(n_views)
    a = ((k * blocks) // n_views) % 2 == 0
    return np.nonzero(a)[0], np.nonzero(~a)[0]


def _subset(x, idx):
    return x[idx] if x is not None and np.ndim(x) == 3 else x


def pick_model(scores: dict, sizes: dict, own: str, *, min_gain: float = MIN_MODEL_GAIN, own_gain: float = OWN_MODEL_GAIN) -> str:
    """The model kept from cross-validated ``scores``: from the simplest (smallest ``sizes``, the ``own`` model first
    among equals) up, a richer model replaces the one chosen so far when it scores lower by more than ``min_gain``
    (``own_gain`` for the own model) of that one's score.

    A model simpler than the own one is kept only where no richer model scores lower than it by more than
    ``own_gain``: where one does (a precession that neither the own model nor the precession model holds clearly
    enough to be chosen, but that both see), the simpler models are left out and the choice is made from the own
    model up (:func:`richer_than_simpler`; ``docs/method.md`` §5.48)."""
    order = sorted(scores, key=lambda k: (sizes[k], k != own))

    def climb(models):
        winner = models[0]
        for k in models[1:]:
            if scores[k] < scores[winner] * (1.0 - (own_gain if k == own else min_gain)):
                winner = k
        return winner

    winner = climb(order)
    if own in sizes and sizes[winner] < sizes[own] and richer_than_simpler(scores, sizes, winner, own_gain):
        winner = climb([k for k in order if sizes[k] >= sizes[own]])
    return winner


def richer_than_simpler(scores: dict, sizes: dict, simple: str, own_gain: float = OWN_MODEL_GAIN) -> list:
    """The models richer than ``simple`` whose cross-validated score is lower than its by more than ``own_gain``."""
    return [k for k in scores if sizes[k] > sizes[simple] and scores[k] < scores[simple] * (1.0 - own_gain)]


def compare_models(
    volume, vol_geom, projections, geom, poses: Poses, own: dict, candidates: dict, *, noise_variance: float,
    weights=None, angles, times=None, center, background: Optional[int] = None, backend: str = "auto",
    max_iter: int = 6, min_gain: float = MIN_MODEL_GAIN, own_gain: float = OWN_MODEL_GAIN, own_name: str = "own",
    skip_simpler: str = "", tol_px: float = MODEL_FIT_TOL_PX,
) -> ModelChoice:
    """Score the models on views they were not fitted to; return the winner.

    From the simplest model (fewest free functions: basis functions times
    free parameters) up, a richer model replaces the one chosen so far when
    its score is lower by more than ``min_gain`` (``own_gain`` for the own
    model) of that one's.

    Parameters
    ----------
    volume, vol_geom
        The correlation volume made at ``poses`` and its grid.
    projections, geom
        Data and geometry of the stage's scale; ``poses`` is relative to ``geom``.
    own, candidates
        ``dict(basis=, frame=, fixed=)`` of the stage's model, and named candidates.
    skip_simpler : str
        Non-empty: the reason why candidates simpler than the own model are
        not compared (the choice's ``note`` says it).
    tol_px : float
        Each fit's Gauss-Newton iterations stop at a step below this
        (detector pixels; ``MODEL_FIT_TOL_PX``).
    """
    n = geom.n_views
    angles = np.asarray(angles, float)
    t_all = None if times is None else np.asarray(times, float)
    models = {own_name: own}
    models.update({k: v for k, v in candidates.items() if k != own_name})
    if n < 2 * _MIN_HALF:
        return ModelChoice(winner=own_name, own=own_name, n_views=n, min_gain=float(min_gain), note=f"{n} views")
    folds = halves(n)
    bases = {k: make_basis(m["basis"], angles=angles, times=t_all).matrix for k, m in models.items()}
    size = {k: bases[k].shape[1] * (6 - len(set(models[k]["fixed"]))) for k in models}
    skipped = ""
    if skip_simpler:
        drop = [k for k in models if size[k] < size[own_name]]
        if drop:
            skipped = f"{', '.join(drop)} left out: {skip_simpler}"
            log.info("motion model: %s", skipped)
            models = {k: m for k, m in models.items() if k not in drop}
            if len(models) == 1:
                return ModelChoice(winner=own_name, own=own_name, n_views=n, min_gain=float(min_gain), note=skipped)
    # each half must determine a model's increment (two views per function at least), or the model is not compared
    few = min(f.size for f in folds)
    short = [k for k in models if few < max(2 * bases[k].shape[1], _MIN_HALF)]
    if short:
        note = f"half of the {n} views ({few}) cannot determine {', '.join(short)}"
        log.info("motion model: %s not compared: %s", ", ".join(short), note)
        note = "; ".join(x for x in (skipped, note) if x)
        if own_name in short or len(short) == len(models) - 1:
            return ModelChoice(winner=own_name, own=own_name, n_views=n, min_gain=float(min_gain), note=note)
        models = {k: m for k, m in models.items() if k not in short}
        skipped = note
    start = poses.gauge_fixed(geom, center=np.asarray(center, float))
    rss = {k: 0.0 for k in models}
    wsum = {k: 0.0 for k in models}
    moved = {k: 0.0 for k in models}  # sum of squared detector displacements of the predictions from the stage's poses
    pts = sample_points(vol_geom, 3, fraction=0.8)
    passes = 0
    c = np.asarray(center, float)
    for fit, test in (folds, folds[::-1]):
        g_fit, g_test = geom[fit], geom[test]
        p0_fit, p0_test = poses[fit], poses[test]
        for name, m in models.items():
            S = bases[name]
            res = correlate(
                volume, vol_geom, projections[fit], g_fit, basis=S[fit], frame=m["frame"], fixed=m["fixed"], center=c,
                weights=_subset(weights, fit), noise_variance=noise_variance, angles=angles[fit],
                times=None if t_all is None else t_all[fit], initial_rotvecs=p0_fit.rotvecs,
                initial_translations=p0_fit.translations, max_iter=max_iter, tol_px=tol_px, backend=backend,
                background=background,
            )
            passes += int(res.n_iter)
            # the increment the fit added to the stage's poses, on the basis; then evaluated at the views left out
            d = (p0_fit.inverse() @ res.poses).to_params(c)
            if m["frame"] == "lab":
                d = params_to_lab(d, lab_to_sample_map(g_fit, rotvecs=p0_fit.rotvecs))
            coef = np.linalg.lstsq(S[fit], d, rcond=None)[0]
            d_test = S[test] @ coef
            if m["frame"] == "lab":
                d_test = params_to_sample(d_test, lab_to_sample_map(g_test, rotvecs=p0_test.rotvecs))
            pred = p0_test @ Poses.from_params(d_test, c)
            # how far the model moves the sample from the stage's poses, gauge-free (a motion of the whole scan is not one)
            rv_m, t_m = np.empty((n, 3)), np.empty((n, 3))
            rv_m[fit], t_m[fit] = res.poses.rotvecs, res.poses.translations
            rv_m[test], t_m[test] = pred.rotvecs, pred.translations
            moved_to = Poses(rv_m, t_m).gauge_fixed(geom, center=c)
            shift = geom[test].apply(moved_to[test]).project_points(pts) - geom[test].apply(start[test]).project_points(pts)
            moved[name] += float(np.sum(shift**2)) / pts.shape[0]
            prob, _ = _problem(volume, vol_geom, projections[test], g_test, "constant", "sample", c, (), _subset(weights, test),
                               noise_variance, angles[test], None, backend, background)
            red = prob.reduce(pred.rotvecs, pred.translations)
            passes += 1
            rss[name] += float(red.rss.sum())
            wsum[name] += float(red.weight_sum.sum())
    scores = {k: rss[k] / (max(wsum[k], 1e-300) * noise_variance) for k in models}
    shifts = {k: float(np.sqrt(moved[k] / n)) for k in models}
    winner = pick_model(scores, size, own_name, min_gain=min_gain, own_gain=own_gain)
    gain = 1.0 - scores[winner] / scores[own_name] if winner != own_name and scores[own_name] > 0 else 0.0
    choice = ModelChoice(winner=winner, own=own_name, scores=scores, gain=gain, n_views=n, n_passes=passes, shifts_px=shifts,
                         min_gain=float(min_gain), simpler=bool(size[winner] < size[own_name]), own_gain=float(own_gain),
                         sizes={k: int(size[k]) for k in models}, note=skipped)
    log.info("motion model: %s", choice.text())
    log.debug("motion model: each model's predictions moved the sample by %s px (gauge-free RMS, the views left out)",
              {k: round(v, 4) for k, v in shifts.items()})
    return choice


def _positive_int(x, name: str, least: int = 1) -> int:
    if not isinstance(x, (int, np.integer)) or isinstance(x, bool) or x < least:
        raise InputTypeError(f"{name} must be an int >= {least}, got {x!r}")
    return int(x)


def cross_validated_misfit(projections, vol_geom: VolumeGeometry, geometries, *, scale: int = 1, oversample: int = 2,
                           folds: int = 2, n_iter: int = 30, weights=None, subsets: int = 1,
                           background: Optional[int] = None, backend: str = "auto") -> np.ndarray:
    """How well each geometry's reconstruction predicts the views it was not made from (lower is better).

    A comparison of finished calibrations (the geometries two recipes
    returned, say), not of motion models on one volume as
    :func:`compare_models` makes: for each geometry, the views are split
    into ``folds`` interleaved sets (view ``k`` in set ``k % folds``); a
    non-negative least-squares volume (:func:`pdvc.recon.nonneg_ls`, cubic
    B-splines on ``vol_geom`` at ``scale``, sampled ``oversample`` times
    finer) is made from the other sets at that geometry and re-projected
    onto each set. A motion the reconstruction takes up (a precession once
    per turn against a volume made without it) then counts too. Measured
    in ``docs/method.md`` §5.12; :func:`pdvc.calibrate`'s ``second_run``
    compares its two recipes' geometries with it (§5.25).

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) array
        Line integrals; not modified.
    vol_geom : VolumeGeometry
        The reconstruction grid at full resolution.
    geometries : sequence of VectorGeometry
        The geometries compared, each of the projections' shape.
    scale : int
        Compare at this scale (:func:`pdvc.correlation.coarse_grain`).
    oversample, n_iter
        Of the volumes (as a calibration stage's).
    folds : int, >= 2
        Sets of views.
    weights : array, optional
        Detector weights at full resolution (e.g. rays that leave the volume
        at 0), broadcastable to the projections.
    subsets : int
        Ordered subsets of each volume's views (:func:`pdvc.recon.nonneg_ls`;
        1: the plain iteration). :func:`pdvc.calibrate`'s ``second_run``
        takes the calibration's rule (``docs/method.md`` §5.25).
    background : {None, 0, 1, 2}
        Also take out of each predicted view's residual the polynomial of
        this degree in the detector coordinates that fits it best (weighted
        least squares), as the calibration fits a smooth background per view
        with the motion (:mod:`pdvc.correlation._background`): an air level
        that drifts from view to view is then not counted against either
        geometry. None: the residual as it is.

    Returns
    -------
    (len(geometries),) float64 array
        Weighted residual of the predicted views over the weighted energy
        of the data, summed over the sets.
    """
    geoms = list(geometries) if not isinstance(geometries, VectorGeometry) else [geometries]
    if not geoms or not all(isinstance(g, VectorGeometry) for g in geoms):
        raise InputTypeError("geometries must be a non-empty sequence of pdvc.VectorGeometry")
    if not isinstance(vol_geom, VolumeGeometry):
        raise InputTypeError(f"vol_geom must be a pdvc.VolumeGeometry, got {type(vol_geom).__name__}")
    s = _positive_int(scale, "scale")
    k = _positive_int(oversample, "oversample")
    n_sets = _positive_int(folds, "folds", 2)
    n_sub = _positive_int(subsets, "subsets")
    shape = np.shape(projections)
    for i, g in enumerate(geoms):
        if shape != (g.n_views,) + tuple(g.det_shape):
            raise ShapeError(f"geometries[{i}] is for projections of shape {(g.n_views,) + tuple(g.det_shape)}, got {shape}")
    if shape[0] < 2 * n_sets:
        raise ShapeError(f"folds={n_sets} needs at least {2 * n_sets} views, got {shape[0]}")
    if background is not None and (isinstance(background, bool) or background not in BACKGROUND_DEGREES):
        raise InputTypeError(f"background must be None or a polynomial degree in {BACKGROUND_DEGREES}, got {background!r}")
    p_s = coarse_grain(projections, geoms[0], s)[0]  # the data's coarse-graining does not depend on the geometry
    w = None if weights is None else coarse_weights(np.broadcast_to(np.asarray(weights, np.float32), shape), s, p_s.shape[1:])
    vg = vol_geom.binned(s) if s > 1 else vol_geom
    fine = refined_grid(vg, k)
    idx = np.arange(shape[0])
    out = np.empty(len(geoms))
    # the step bound of each set's volumes depends on the grid and the views' geometry only: measured once per set (3
    # power iterations, a projection and a back-projection each), at the first geometry, for all of them; the geometries
    # compared differ by fractions of a pixel, and their volumes then take the same steps (docs/method.md §5.47)
    lips = {}
    for i, g in enumerate(geoms):
        g_s = g.binned(s) if s > 1 else g
        rss = energy = 0.0
        for r in range(n_sets):
            fit, test = idx[idx % n_sets != r], idx[idx % n_sets == r]
            if r not in lips:
                lips[r] = nonneg_ls_lipschitz(fine, g_s[fit], coarsen=k, backend=backend)
            vol = nonneg_ls(p_s[fit], fine, g_s[fit], coarsen=k, n_iter=n_iter, weights=None if w is None else w[fit],
                            subsets=n_sub, lipschitz=lips[r], backend=backend)
            d = (forward(vol, fine, g_s[test], backend=backend) - p_s[test]).astype(np.float64)
            wt = 1.0 if w is None else w[test]
            if background is not None:
                d = without_background(d, int(background), wt)
            rss += float(np.sum(wt * d * d))
            energy += float(np.sum(wt * p_s[test].astype(np.float64) ** 2))
        out[i] = rss / max(energy, 1e-300)
        log.info("cross-validated misfit of geometry %d: %.6g (%d sets of views, scale %d)", i, out[i], n_sets, s)
    return out

