"""The outer loop of self-calibration: reconstruct, correlate, rewrite the geometry, repeat.

:func:`self_calibrate` alternates a reconstruction with the current per-view
geometry and a P-DVC measurement (:func:`pdvc.correlation.correlate`) of the
sample's poses against that reconstruction, until the poses stop moving.

Why this recipe
---------------
Measured on ``tests/correlation/cases.py`` (48³ cast-iron phantom, analytic
projections with Poisson noise i0 = 2e4, cone beam SOD 8n / ODD 4n, 90
views, detector 57 x 67). Errors: RMS detector distance of 125 sample points
between the recovered and the true geometry, both gauge fixed, pixels.

1. **Oversampled correlation grid** (``oversample=2``). On the detector's own
   grid (one voxel = one pixel at the axis) the interpolating projector is
   biased: even the exact voxelised phantom, started at the truth, drifts to
   0.28 px (a false 0.8° tilt); with voxels of half a pixel it stays at
   0.018 px, and FDK at the true geometry gives 0.030 px. The correlation
   volume is on a grid ``oversample`` times finer than ``vol_geom``; the
   final volume is on ``vol_geom``.

2. **Translations first** (``warmup=1``, progressive enrichment). The first
   reconstruction is blurred by the motion, and rotations measured against
   it are noise: with rotations free from the start, ``precession_drift``
   had 1.6–3.8° RMS rotation errors after the first correlation and the
   loop diverged (tens of degrees after four rounds). The warm-up measures
   translations only, in the lab frame, on :func:`drift_basis`
   {1, t, t², cos θ, sin θ} (offset, drift with acceleration, shifted axis):
   ``precession_drift`` 1.02 -> 0.091 px (0.064 after a second round), a
   pure vertical drift 0.22 -> 0.041 -> 0.012 px, ``jolts`` 1.58 -> 0.25 px
   (the jumps need the free basis of the model). Then the user's model
   (``basis``, ``frame``, ``fixed``, ``method``) takes over. One warm-up
   round is the default: ``tilted_axis`` ends at 0.042 px after one and at
   0.048 px after two (its tilt is a rotation, measured later).

3. **rz fixed** (``fixed=("rz",)``). A per-view rotation about the axis is
   nearly absorbed by FDK (a linear-in-time rz is an angular scale): with rz
   free the angle errors reached 1.7° RMS.

4. **Weak rotation modes** limit the accuracy. The loop is a fixed-point
   iteration ``x <- G(x)``; its gain along a mode δ,
   ``(G(x* + δ) - G(x* - δ)) / 2δ`` at the truth x* (0 is ideal, >= 1 never
   converges), measured with 0.3° / 0.3-voxel perturbations:

   ================================================  ===========  =================
   mode (lab frame)                                   gain         effect
   ================================================  ===========  =================
   translations: offset, drift                        0.04–0.15    2–3 rounds
   roll about the beam, constant (axis tilt seen      0.54–0.91    slow
   in the projections)
   pitch toward the source, constant                  1.09–1.31    near-gauge
   precession (first harmonic, counter-rotating)      1.39–2.08    unstable
   ================================================  ===========  =================

   (oversample 1 gives 1.86 and 2.94 for the last two: the excess over 1 is
   the reconstruction's own bias.) A rotation that is π-periodic in the
   sample frame, ``ω(θ + π) = ω(θ)``, leaves opposite views consistent with
   each other: in parallel beam the data are then exactly those of a
   modified (non-compact) object in the nominal geometry, and only the cone
   angle breaks this. ``precession_poses`` with its default
   ``cycles_per_turn=1`` is such a mode (sample-frame 2θ); a wobble locked to
   the table (``cycles_per_turn=-1``) is a static tilt of the sample, a pure
   gauge. FDK is also less self-consistent on a non-planar source orbit
   (clean data, 1° precession at the true geometry: ``|Π FDK(s) - s|²`` 87
   against 39 without), which pulls the loop away from precessions. A 0.5°
   wobble of another frequency converges (lab ``spline:4`` rotations):
   ``cycles_per_turn=2`` 0.109 -> 0.032 px, ``0.25`` 0.107 -> 0.050 px in
   five rounds. A drift along the axis biases the rotations through the
   reconstruction (one correlation at the true geometry: roll error 0.034°
   with a 0.75-voxel linear vertical drift, 0.003° with a closed sinusoidal
   one; excluding the views at the seam does not help); in the loop the
   roll settles 0.1° off and the pitch walks ~0.02° per round.

5. **Stopping.** A round's increment is the RMS detector displacement of
   sample points between the geometries before and after it. The loop stops
   when it is below ``tol_px`` (status 1), or when it grows
   (``stall_ratio=1``, status 3: the contracting part has converged and what
   still moves is a walk along weak modes), returning the poses before that
   round: ``tilted_axis`` increments 0.055, 0.033, 0.021, 0.014, 0.013,
   0.011, 0.0105, 0.0113 px, errors down to 0.042 px, then growing when the
   increments grow; ``precession_drift`` stops after three rounds at
   0.082 px (0.15 px after eight rounds without the rule). The data
   consistency of a fresh reconstruction, ``chi_before`` (χ of
   ``Π_x FDK_x(s) - s``), guards against divergence: a rise of more than
   ``diverge_tol`` (0.5 %) over its best value in the model stage stops the
   loop with the best poses (status 2).

6. **No acceleration by default.** Anderson (``accelerate=True``, depth 2,
   steps capped at twice the plain increment, history reset when
   ``chi_before`` rises) on ``tilted_axis``: without warm-up 0.109, 0.078,
   0.046, 0.045 px (plain: 0.109, 0.078, 0.062, 0.052, 0.046, 0.043); with
   two warm-up rounds 0.082, 0.052, 0.056, 0.059, 0.061 while ``chi_before``
   kept falling: it converges faster to the reconstruction's biased
   consistency, not to the truth.

7. **Precessing axes: model, reconstruction and entropy guard** (options,
   not defaults). On ``precession_drift`` the default recipe's 0.082 px is
   the model's floor, not the loop's: a once-per-turn precession is a
   first harmonic of the lab rotation, a second one in the sample frame,
   which ``fourier:1`` (sample) lacks, and the recovered poses hold none of
   the 0.3° (the lab-frame decomposition of the error is the precession
   itself: 0.044 px from rx and 0.043 px from ry). With a model that spans it
   (``frame="lab"``, ``basis=drift_basis(angles)``) FDK still walks away
   (0.091 -> 0.076 -> 0.094 px): what FDK lacks on the non-planar orbit is
   consistency. The non-negative least-squares volume
   (``reconstruct="nonneg_ls"``: cubic B-spline coefficients on
   ``vol_geom``, sampled on the 2x grid, non-negative on a support) is the
   consistent one, and reaches 0.028 / 0.026 / 0.025 px (seeds 0, 1, 2)
   after one model round, from a better warm-up (0.067 px; FDK 0.091).
   It does not stay there: the consistency ``chi_before`` keeps falling
   while the precession amplitude and a constant lab tilt grow (seed 0,
   rounds 1–6: 0.029, 0.029, 0.056, 0.079, 0.096, 0.108 px, measured
   before the momentum restart was added): data consistency alone has its
   minimum off the truth along these near-gauge modes (with noise-free
   data too: the bias is the discrete model's). The sharpness of the
   image does see it: the entropy of the FDK volume on ``vol_geom`` rose
   by 0.08–0.15 % over the first model round and by 0.7–0.9 % over the
   second, in the three seeds; ``guard="entropy"`` (``entropy_tol``
   0.3 %) stops there and returns the poses before the rise (status 4).
   Measured on ``tilted_axis``, this recipe ends at 0.086 px where the
   default one reaches 0.042: a constant lab tilt is one of the modes the
   lab model leaves weak, so it is the recipe for precession, not the
   default. Also measured: B-spline least squares without the
   constraints converges (no walk) but to 0.051 px after 12 rounds, and
   unconstrained least squares on the 2x voxels overfits (0.76 px); a
   larger cone angle (SOD 4n, ~8°) does not change the FDK loop's walk.

Also measured, not defaults: the cone-artefact ROI
(``detector_weights(rows=cone_artifact_rows(...))`` passed as ``weights``):
``tilted_axis`` 0.043 -> 0.040 px after six rounds of the plain loop; 150
views instead of 90: faster early (0.068 against 0.078 px at round 2), same
floor (0.042); a rich lab-frame rotation basis ({1, t, t², cos θ, sin θ,
cos 2θ, sin 2θ}) diverges (precession_drift 0.21 px after seven rounds);
rotations at scale 2 diverge.

Gauge: the poses are relative to the geometry given; a global rigid motion
and (cone beam) the magnification are fixed by
:func:`pdvc.geometry.fix_gauge` after every round (``gauge`` says so).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from ..correlation import (
    CorrelationResult,
    correlate,
    custom_basis,
    estimate_noise_variance,
    fourier_basis,
    polynomial_basis,
    shannon_entropy,
)
from ..correlation._engine import _params_to_rt, _rt_to_params
from ..correlation._frames import view_angles
from ..errors import PdvcError, ShapeError
from ..geometry import VectorGeometry, VolumeGeometry, fix_gauge, sample_points
from ..recon import fbp, fdk, nonneg_ls

__all__ = [
    "self_calibrate", "OuterResult", "OuterError", "OUTER_STATUS", "RECONSTRUCTORS", "drift_basis", "refined_grid",
]

log = logging.getLogger(__name__)

#: Termination table of :func:`self_calibrate`.
OUTER_STATUS = {
    0: "maximum number of outer iterations reached before the poses stopped moving",
    1: "converged: an outer iteration moved the sample points by less than tol_px (RMS) on the detector",
    2: "stopped: the data consistency of the reconstruction got worse (diverging); the best poses are returned",
    3: "stopped: the outer iterations no longer contract (what still moves is weakly determined); "
    "the poses before the last iteration are returned",
    4: "stopped: the entropy of the reconstruction rose (the data consistency is walking along weakly "
    "determined modes); the poses before the last iteration are returned",
}

_ROTATIONS = ("rx", "ry", "rz")


class OuterError(PdvcError, ValueError):
    """Bad options for the outer loop."""


@dataclass(frozen=True)
class OuterResult:
    """Outcome of :func:`self_calibrate` (always the same structure).

    Attributes
    ----------
    rotvecs, translations : (n_views, 3) float64
        Poses of the sample relative to the geometry given (``apply_poses``
        convention, radians and length units), gauge fixed as ``gauge`` says.
    gauge : str
        How the unobservable global motion was fixed.
    geometry : VectorGeometry
        ``geom.apply_poses(rotvecs, translations)``.
    result : CorrelationResult
        The last P-DVC measurement (its poses are before gauge fixing).
    history : tuple of dict
        One dict per outer iteration: ``iteration``, ``stage``
        (``"warmup"`` or ``"model"``), ``chi_before`` (χ of the fresh
        reconstruction at the poses the iteration started from),
        ``chi_after``, ``snr_before``, ``snr`` (overall SNR in dB before
        and after the correlation), ``entropy`` (bits, of the analytic
        reconstruction on ``vol_geom`` at the poses the iteration started
        from; NaN unless ``guard="entropy"``), ``increment_px`` and
        ``increment_max_px`` (RMS and largest detector displacement of
        sample points caused by the iteration), ``n_iter`` (Jacobian
        passes), ``accelerated``.
    volume : (nz, ny, nx) float32
        Reconstruction with ``geometry`` on ``vol_geom``.
    vol_geom : VolumeGeometry
        The grid given.
    corr_vol_geom : VolumeGeometry
        The (oversampled) grid the correlation used.
    status : int
        See ``OUTER_STATUS``: 1 converged, 3 stopped contracting, 4 stopped
        by the entropy guard (all ``success``), 0 iteration cap, 2 stopped on
        divergence.
    message : str
    """

    rotvecs: np.ndarray
    translations: np.ndarray
    gauge: str
    geometry: VectorGeometry
    result: CorrelationResult
    history: tuple
    volume: np.ndarray
    vol_geom: VolumeGeometry
    corr_vol_geom: VolumeGeometry
    status: int
    message: str

    @property
    def n_outer(self) -> int:
        return len(self.history)

    @property
    def success(self) -> bool:
        """Converged (1), stopped contracting (3) or by the entropy guard (4)."""
        return self.status in (1, 3, 4)

    @property
    def chi_before(self) -> np.ndarray:
        """``chi_before`` of every outer iteration."""
        return np.array([h["chi_before"] for h in self.history])

    @property
    def increments_px(self) -> np.ndarray:
        """``increment_px`` of every outer iteration."""
        return np.array([h["increment_px"] for h in self.history])


def refined_grid(vol_geom: VolumeGeometry, oversample: int) -> VolumeGeometry:
    """The same region as ``vol_geom`` with ``oversample`` x finer voxels."""
    ov = int(oversample)
    return VolumeGeometry(
        tuple(n * ov for n in vol_geom.shape),
        voxel_size=tuple(s / ov for s in vol_geom.voxel_size),
        offset=vol_geom.offset,
    )


def drift_basis(angles, times=None):
    """Temporal basis of the translation warm-up: {1, t, t², cos θ, sin θ}.

    A constant offset, a drift with constant acceleration in time, and a
    shifted rotation axis (first harmonic of the angle). Falls back to fewer
    functions when the views cannot determine them (very few views).
    """
    th = np.asarray(angles, float)
    n = th.size
    t = np.arange(n, dtype=float) if times is None else np.asarray(times, float)
    for degree, order in ((2, 1), (1, 1), (0, 1), (0, 0)):
        try:
            cols = [polynomial_basis(t, degree).matrix] if degree > 0 else [np.ones((n, 1))]
            if order:
                cols.append(fourier_basis(th, t, order, drift=False).matrix[:, 1:])
            return custom_basis(np.column_stack(cols))
        except PdvcError:
            continue
    raise OuterError(f"no translation basis can be determined from {n} views")  # pragma: no cover


def _default_reconstruct(projections, vol_geom, geom):
    return (fdk if geom.kind == "cone" else fbp)(projections, vol_geom, geom)


#: Names accepted by ``self_calibrate(reconstruct=)``.
RECONSTRUCTORS = ("fdk", "nonneg_ls")


def _reconstructors(reconstruct, oversample):
    """(correlation-volume reconstruction, final-volume reconstruction) for ``reconstruct``."""
    if reconstruct is None or reconstruct == "fdk":
        return _default_reconstruct, _default_reconstruct
    if isinstance(reconstruct, str):
        if reconstruct != "nonneg_ls":
            raise OuterError(f"reconstruct must be a callable or one of {RECONSTRUCTORS}, got {reconstruct!r}")

        def rec(projections, vol_geom, geom):
            return nonneg_ls(projections, vol_geom, geom, coarsen=oversample)

        return rec, _default_reconstruct
    if not callable(reconstruct):
        raise OuterError(f"reconstruct must be a callable or one of {RECONSTRUCTORS}, got {reconstruct!r}")
    return reconstruct, reconstruct


def _gauge_text(kind: str, scale: bool) -> str:
    text = (
        "poses relative to the geometry given; gauge: zero mean rigid pose over the views "
        "(mean rotation = identity, mean position of the volume centre unchanged)"
    )
    if kind == "cone" and scale:
        text += " and zero mean magnification change (the nominal source-object distance is the mean one)"
    return text


def _check(projections, geom, vol_geom, oversample, n_outer, warmup, tol_px, guard, entropy_tol):
    if not isinstance(geom, VectorGeometry):
        raise OuterError(f"geom must be a VectorGeometry, got {type(geom).__name__}")
    if not isinstance(vol_geom, VolumeGeometry):
        raise OuterError(f"vol_geom must be a VolumeGeometry, got {type(vol_geom).__name__}")
    p = np.asarray(projections, dtype=np.float32)
    if p.shape != (geom.n_views,) + tuple(geom.det_shape):
        raise ShapeError(f"projections must have shape {(geom.n_views,) + tuple(geom.det_shape)}, got {p.shape}")
    for name, val, lo in (("oversample", oversample, 1), ("n_outer", n_outer, 1), ("warmup", warmup, 0)):
        if not isinstance(val, (int, np.integer)) or isinstance(val, bool) or val < lo:
            raise OuterError(f"{name} must be an int >= {lo}, got {val!r}")
    if not (tol_px > 0):
        raise OuterError(f"tol_px must be positive (pixels), got {tol_px!r}")
    if guard not in (None, "entropy"):
        raise OuterError(f"guard must be None or 'entropy', got {guard!r}")
    if not (isinstance(entropy_tol, (int, float, np.floating)) and entropy_tol > 0):
        raise OuterError(f"entropy_tol must be a positive relative rise (e.g. 0.003), got {entropy_tol!r}")
    return p


def self_calibrate(
    projections,
    geom: VectorGeometry,
    vol_geom: VolumeGeometry,
    *,
    reconstruct=None,
    oversample: int = 2,
    basis="fourier:1",
    method: str = "full",
    frame: str = "sample",
    fixed=("rz",),
    warmup: int = 1,
    warmup_basis="drift",
    n_outer: int = 10,
    tol_px: float = 0.01,
    weights=None,
    noise_variance: Optional[float] = None,
    scales=(1,),
    accelerate: bool = False,
    diverge_tol: float = 0.005,
    stall_ratio: Optional[float] = 1.0,
    guard: Optional[str] = None,
    entropy_tol: float = 0.003,
    fix_scale: bool = True,
    initial_rotvecs=None,
    initial_translations=None,
    angles=None,
    times=None,
    callback: Optional[Callable[[dict], object]] = None,
    checkpoint: Optional[Callable[[np.ndarray, np.ndarray, list], object]] = None,
    **correlate_options,
) -> OuterResult:
    """Calibrate the per-view geometry by alternating reconstruction and P-DVC.

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) array
        Measured line integrals; not modified.
    geom : VectorGeometry
        The geometry given (nominal); the poses returned are relative to it.
    vol_geom : VolumeGeometry
        Reconstruction grid of the final volume. The correlation uses the
        same region with ``oversample`` x finer voxels.
    reconstruct : "fdk", "nonneg_ls" or callable, optional
        Reconstruction of the correlation volume at every outer iteration.
        ``"fdk"`` (default): FDK (cone beam) or FBP (parallel beam).
        ``"nonneg_ls"``: :func:`pdvc.recon.nonneg_ls` with B-spline
        coefficients on ``vol_geom`` (``coarsen=oversample``), the most
        consistent non-negative volume under the projector for any orbit
        (point 7 of the module docstring); about 40 projector pairs per
        call. With a name the final volume is FDK/FBP. A callable
        ``reconstruct(projections, vol_geom, geom) -> volume`` serves both.
    oversample : int
        Refinement of the correlation grid (module docstring, point 1).
    basis, method, frame, fixed
        The P-DVC model of the model stage (:func:`pdvc.correlation.correlate`).
        ``fixed`` names parameters of ``frame``.
    warmup : int
        Outer iterations at the start measuring translations only, in the lab
        frame, on ``warmup_basis`` (point 2); 0 to start with the model.
        The warm-up ends early when its increment is below ``tol_px``.
    warmup_basis : "drift", str, TemporalBasis or array
        ``"drift"``: {1, t, t², cos θ, sin θ} (:func:`drift_basis`).
    n_outer : int
        Outer iterations at most, warm-up included.
    tol_px : float
        Stop when an iteration of the model stage moves the sample points by
        less than this on the detector (RMS, pixels).
    weights : (n_rows, n_cols) or (n_views, n_rows, n_cols) array, optional
        Detector ROI / weights (e.g. from :func:`pdvc.correlation.detector_weights`).
    noise_variance : float, optional
        γ² of the projections; estimated once from them if not given.
    scales : sequence of int
        Coarse-to-fine schedule of every correlation (``correlate(scales=)``).
    accelerate : bool
        Anderson acceleration (depth 2, safeguarded) of the model stage.
    diverge_tol : float
        Relative rise of ``chi_before`` over its best value in the model stage
        that stops the loop (status 2, best poses returned).
    stall_ratio : float or None
        Stop the model stage (status 3) when an increment is at least this
        times the previous one, returning the poses before that round;
        ``None`` to run to ``tol_px`` or ``n_outer``.
    guard : None or "entropy"
        ``"entropy"``: before every iteration of the model stage, the
        Shannon entropy of the analytic reconstruction on ``vol_geom``
        (value range fixed by the first one) is compared with the lowest
        seen in the model stage; a rise of more than ``entropy_tol``
        (relative) stops the loop (status 4) with the poses before the
        last iteration (point 7).
    entropy_tol : float
        Relative entropy rise that the guard tolerates.
    fix_scale : bool
        Cone beam: also fix the magnification gauge (:func:`pdvc.geometry.fix_gauge`).
    initial_rotvecs, initial_translations : (n_views, 3), optional
        Poses to start from (relative to ``geom``).
    angles, times : (n_views,) arrays, optional
        Passed to the engine's temporal bases (default: angles from the
        geometry, times = view order).
    callback : callable, optional
        Called with the history dict after every outer iteration.
    checkpoint : callable, optional
        ``checkpoint(rotvecs, translations, history)`` after every outer
        iteration, with the poses the next one starts from (to save them:
        an interrupted run resumes from there).
    **correlate_options
        Passed to :func:`pdvc.correlation.correlate` (``max_iter`` defaults
        to 30 here, ``max_modes``, ``rcond``, ...).

    Returns
    -------
    OuterResult

    Examples
    --------
    >>> out = self_calibrate(projections, geom, pdvc.VolumeGeometry((64, 64, 64)))  # doctest: +SKIP
    >>> out.geometry, out.message  # doctest: +SKIP
    """
    p = _check(projections, geom, vol_geom, oversample, n_outer, warmup, tol_px, guard, entropy_tol)
    rec, rec_final = _reconstructors(reconstruct, oversample)
    vg_c = refined_grid(vol_geom, oversample)
    c = np.asarray(vol_geom.offset, float)
    n = geom.n_views
    radius = 0.5 * float(np.min(vol_geom.extent_xyz))
    gamma2 = float(noise_variance) if noise_variance is not None else estimate_noise_variance(p)
    if angles is None:
        angles = view_angles(geom)
    wb = drift_basis(angles, times) if isinstance(warmup_basis, str) and warmup_basis == "drift" else warmup_basis
    opts = dict(max_iter=30)
    opts.update(correlate_options)
    points = sample_points(vol_geom, 3, fraction=0.8)

    rv = np.zeros((n, 3)) if initial_rotvecs is None else np.array(initial_rotvecs, float).reshape(n, 3)
    t = np.zeros((n, 3)) if initial_translations is None else np.array(initial_translations, float).reshape(n, 3)
    if initial_rotvecs is not None or initial_translations is not None:
        rv, t = fix_gauge(rv, t, geom, center=c, scale=fix_scale)

    def to_x(rv_, t_):
        q = _rt_to_params(rv_, t_, c)
        q[:, 3:] *= radius
        return q.ravel()

    def from_x(x):
        q = x.reshape(n, 6).copy()
        q[:, 3:] /= radius
        return _params_to_rt(q, c)

    def increment(rv1, t1, rv2, t2):
        a = geom.apply_poses(rv1, t1).project_points(points)
        b = geom.apply_poses(rv2, t2).project_points(points)
        d = np.linalg.norm(a - b, axis=-1)
        return float(np.sqrt(np.mean(d**2))), float(d.max())

    history: list = []
    res = None
    status = 0
    # The warm-up guards free rotations against the first, motion-blurred
    # reconstructions; a model without free rotations needs none. In the lab
    # frame it also holds the translations the user fixed.
    free_rot = not set(_ROTATIONS) <= set(fixed)
    warm_fixed = _ROTATIONS + (tuple(x for x in fixed if x not in _ROTATIONS) if frame == "lab" else ())
    stage = "warmup" if warmup > 0 and free_rot else "model"
    n_warm = 0
    best = None  # (chi_before, rv, t) in the model stage
    ent_best = None  # lowest entropy in the model stage
    ent_range = None
    refs: list = []  # the guard's last two volumes on vol_geom: the final volume may be one of them
    rv_prev, t_prev = rv, t
    X: list = []
    Fh: list = []
    for it in range(n_outer):
        entropy = float("nan")
        if guard == "entropy" and stage == "model":
            ref = rec_final(p, vol_geom, geom.apply_poses(rv, t))
            refs = (refs + [(rv, t, ref)])[-2:]
            if ent_range is None:
                ent_range = tuple(float(q) for q in np.percentile(ref, [0.1, 99.9]))
            entropy = shannon_entropy(ref, value_range=ent_range)
            if ent_best is not None and entropy > ent_best * (1 + entropy_tol):
                log.info("outer %d: entropy %.5g rose above the lowest %.5g; stopping", it, entropy, ent_best)
                status = 4
                rv, t = rv_prev, t_prev
                break
            ent_best = entropy if ent_best is None else min(ent_best, entropy)
        vol = rec(p, vg_c, geom.apply_poses(rv, t))
        if stage == "warmup":
            kw = dict(basis=wb, frame="lab", fixed=warm_fixed, method="full")
        else:
            kw = dict(basis=basis, frame=frame, fixed=tuple(fixed), method=method)
        res = correlate(
            vol, vg_c, p, geom, weights=weights, noise_variance=gamma2, scales=scales, angles=angles, times=times,
            initial_rotvecs=rv, initial_translations=t, **kw, **opts,
        )
        chi_before = float(res.chi_history[0])
        if stage == "model":
            if best is None or chi_before < best[0]:
                best = (chi_before, rv.copy(), t.copy())
            elif chi_before > best[0] * (1 + diverge_tol):
                log.info(
                    "outer %d: chi_before %.5g rose above the best %.5g; returning the best poses", it, chi_before, best[0]
                )
                status = 2
                rv, t = best[1], best[2]
                break
        rv2, t2 = fix_gauge(res.rotvecs, res.translations, geom, center=c, scale=fix_scale)
        accelerated = False
        if stage == "model" and accelerate:
            x, gx = to_x(rv, t), to_x(rv2, t2)
            if len(history) and history[-1]["stage"] == "model" and chi_before > history[-1]["chi_before"] * (1 + 1e-4):
                X.clear()
                Fh.clear()
            X.append(x)
            Fh.append(gx - x)
            if len(X) > 1:
                m = min(2, len(X) - 1)
                dF = np.array([Fh[-i] - Fh[-i - 1] for i in range(1, m + 1)]).T
                dG = np.array([(X[-i] + Fh[-i]) - (X[-i - 1] + Fh[-i - 1]) for i in range(1, m + 1)]).T
                gam = np.linalg.lstsq(dF, Fh[-1], rcond=1e-6)[0]
                xa = gx - dG @ gam
                cap = 2.0 * np.linalg.norm(Fh[-1])
                step = xa - gx
                if np.linalg.norm(step) > cap > 0:
                    xa = gx + step * (cap / np.linalg.norm(step))
                rv2, t2 = fix_gauge(*from_x(xa), geom, center=c, scale=fix_scale)
                accelerated = True
        inc, inc_max = increment(rv, t, rv2, t2)
        rv_prev, t_prev = rv, t
        rv, t = rv2, t2
        entry = dict(
            iteration=it,
            stage=stage,
            chi_before=chi_before,
            chi_after=float(res.chi),
            snr_before=float(res.snr_history[0]),
            snr=float(res.snr_history[-1]),
            entropy=entropy,
            increment_px=inc,
            increment_max_px=inc_max,
            n_iter=int(res.n_iter),
            accelerated=accelerated,
        )
        history.append(entry)
        log.info(
            "outer %d (%s): chi %.5g -> %.5g, increment %.3g px%s",
            it, stage, chi_before, entry["chi_after"], inc, " (accelerated)" if accelerated else "",
        )
        if checkpoint is not None:  # saved before anything is reported: a Ctrl-C in a callback loses no round
            checkpoint(rv.copy(), t.copy(), [dict(h) for h in history])
        if callback is not None:
            callback(dict(entry))
        if stage == "warmup":
            n_warm += 1
            if n_warm >= warmup or inc < tol_px:
                stage = "model"
        elif inc < tol_px:
            status = 1
            break
        elif (
            stall_ratio is not None
            and len(history) >= 2
            and history[-2]["stage"] == "model"
            and inc >= stall_ratio * history[-2]["increment_px"]
        ):
            log.info(
                "outer %d: increment %.3g px did not contract (previous %.3g px); stopping",
                it, inc, history[-2]["increment_px"],
            )
            status = 3
            rv, t = rv_prev, t_prev
            break

    geometry = geom.apply_poses(rv, t)
    volume = next((v for r, tt, v in refs if r is rv and tt is t), None)
    if volume is None:
        volume = rec_final(p, vol_geom, geometry)
    return OuterResult(
        rotvecs=rv,
        translations=t,
        gauge=_gauge_text(geom.kind, fix_scale),
        geometry=geometry,
        result=res,
        history=tuple(history),
        volume=np.asarray(volume, np.float32),
        vol_geom=vol_geom,
        corr_vol_geom=vg_c,
        status=status,
        message=OUTER_STATUS[status],
    )
