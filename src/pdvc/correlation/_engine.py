"""P-DVC engine: rigid motion of the sample per view, regularised in time.

Unknowns: ``u(x, θ_k) = Σ_n Σ_j a_nj σ_n(θ_k) ψ_j(x)``, ψ_j the six rigid
modes about a centre c (``POSE_PARAMETERS`` order), σ_n a temporal basis.
Every Gauss–Newton iteration is one fused Jacobian pass over the current
geometry (``reduce_views``), giving per view ``M_k`` (6x6) and ``b_k``; all
solves are then small and dense (``DESIGN.md`` §2):

* full identification: ``H = Σ_k (σ_k σ_kᵀ) ⊗ M_k``, ``h = Σ_k σ_k ⊗ b_k``;
* PGD: greedy space-time modes ``α(θ) Φ(x)`` by an alternating fixed point.

Updates are composed exactly with the current poses (the geometry is
rewritten, the volume never warped).  Unknowns are scaled so that one unit
moves the sample by about one voxel (rotations times a radius), directions
the data cannot see are found from the eigenvalues of the scaled normal
matrix, left out of the update and reported with their standard deviation.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import Callable, Optional

import numpy as np

from ..errors import PdvcError, ShapeError
from ..geometry import Poses, VectorGeometry, VolumeGeometry, sample_points
from ..status import Status
from ..projectors import POSE_PARAMETERS, ViewReduction, forward, reduce_views
from ._background import BACKGROUND_DEGREES, reduce_views_background, view_offset
from ._bases import TemporalBasis, make_basis
from ._frames import lab_to_sample_map, view_angles
from ._noise import estimate_noise_variance
from ._scales import coarse_grain, coarse_noise_factor, coarse_volume, coarse_weights

__all__ = ["correlate", "residual_scale", "CorrelationResult", "Mode", "Observability", "CorrelationError"]

log = logging.getLogger(__name__)


class CorrelationError(PdvcError, ValueError):
    """Bad options for the correlation engine."""


@dataclass(frozen=True)
class Mode:
    """One PGD space-time mode ``α(θ) Φ(x)``.

    Attributes
    ----------
    spatial : (6,) float64
        Φ as rigid-motion parameters in the chosen frame (length units, rad).
    coefficients : (n_funcs,) float64
        Temporal amplitudes a_n on the basis.
    alpha : (n_views,) float64
        α(θ_k) = Σ_n a_n σ_n(θ_k), normalised to max |α| = 1.
    alpha_free : (n_views,) float64
        The same spatial mode with a free (Dirac) history, measured at the end:
        compare with ``alpha`` as in the paper's Figs 11–13.
    chi : float
        χ after this mode was added.
    """

    spatial: np.ndarray
    coefficients: np.ndarray
    alpha: np.ndarray
    alpha_free: np.ndarray
    chi: float


@dataclass(frozen=True)
class Observability:
    """Directions of the unknowns the data cannot determine.

    Attributes
    ----------
    directions : list of (6,) arrays
        Unit directions in parameter space (scaled units: one unit ≈ one
        voxel of motion), with the views they concern.
    std : list of float
        Their standard deviation (scaled units) from γ² H⁻¹; ``inf`` when
        the data carry no information at all.
    views : list
        Index of the view (free temporal basis) or ``None`` (global).
    condition : float
        Condition number of the (scaled) normal matrix on the kept subspace.
    """

    directions: list = field(default_factory=list)
    std: list = field(default_factory=list)
    views: list = field(default_factory=list)
    condition: float = 1.0

    def describe(self) -> list[str]:
        out = []
        for d, s, v in zip(self.directions, self.std, self.views):
            j = int(np.argmax(np.abs(d)))
            where = "all views" if v is None else f"view {v}"
            out.append(f"{POSE_PARAMETERS[j]}-like direction ({where}): std {s:.3g}")
        return out


@dataclass(frozen=True)
class CorrelationResult:
    """Outcome of :func:`correlate` (always the same structure).

    Attributes
    ----------
    geometry : VectorGeometry
        The calibrated geometry, ``geom.apply_poses(rotvecs, translations)``.
    rotvecs, translations : (n_views, 3)
        Poses ``x -> R_k x + t_k`` of the sample relative to the input
        geometry (sample/volume frame), exactly as ``apply_poses`` takes them.
    params : (n_views, 6)
        The same poses as (tx, ty, tz, rx, ry, rz) about ``center``:
        ``x -> R (x - c) + c + τ`` in the sample frame.
    params_lab : (n_views, 6)
        ``params`` expressed in the lab frame of each view.
    std : (n_views, 6)
        Standard deviations of ``params`` (sample frame) from γ² H⁻¹ at the
        end; directions reported unobservable have ``nan``.
    center : (3,)
    frame : str
    basis : TemporalBasis
    method : str
    modes : tuple of Mode
        PGD modes (empty for full identification).
    chi_history : (n_iter + 1,) float
        χ before the first and after every accepted iteration.
    snr_history : (n_iter + 1,) float
        Overall SNR (dB) alongside.
    mode_table : tuple of (n_modes, chi, snr_db)
        χ and SNR after each PGD mode (the paper's Table 1); (0, χ0, SNR0) first.
    snr_before, snr_after : (n_views,) float
        Per-view SNR (dB) before and after.
    noise_variance : float
        γ² used to normalise χ.
    observability : Observability
    n_iter : int
        Jacobian passes (each is one projection-sized pass over the data).
    status : pdvc.Status
        Why it stopped; ``status.success`` (also ``success``) is false for
        ``MAX_ITER`` (still moving at the cap) and ``NO_DESCENT`` (no damped
        step lowered χ: never reported as converged).
    message : str
    scale_history : tuple of (scale, chi_start, chi_end, n_iter)
        One entry per scale of a multi-scale run (``scales=``), coarse to
        fine; the histories and per-view SNR above belong to the last scale.
    background : int or None
        Degree of the background per view that was fitted (None: none).
    offset_sigma : float
        How much the per-view offset of the residual at the poses returned
        varies from view to view (weighted RMS about its mean, in noise
        standard deviations): what the motion did not explain of an air
        level or a flat field that drifts (0 when a background was
        fitted). The calibration's ``background = "auto"`` reads it
        (:func:`pdvc.correlation._background.view_offset`).
    """

    geometry: VectorGeometry
    rotvecs: np.ndarray
    translations: np.ndarray
    params: np.ndarray
    params_lab: np.ndarray
    std: np.ndarray
    center: np.ndarray
    frame: str
    basis: TemporalBasis
    method: str
    modes: tuple
    chi_history: np.ndarray
    snr_history: np.ndarray
    mode_table: tuple
    snr_before: np.ndarray
    snr_after: np.ndarray
    noise_variance: float
    observability: Observability
    n_iter: int
    status: Status
    message: str
    scale_history: tuple = ()
    background: Optional[int] = None
    offset_sigma: float = 0.0

    @property
    def chi(self) -> float:
        return float(self.chi_history[-1])

    @property
    def success(self) -> bool:
        return Status(self.status).success

    @property
    def poses(self) -> Poses:
        """``rotvecs`` and ``translations`` as one :class:`pdvc.geometry.Poses`."""
        return Poses(self.rotvecs, self.translations)


# ----------------------------------------------------------------------------
# poses
# ----------------------------------------------------------------------------
def _compose_increment(rv, t, delta_params, center):
    """Current pose P, increment δ (parameters about ``center``) measured on the geometry posed by P: P ∘ δ."""
    return tuple(Poses(rv, t).compose(Poses.from_params(delta_params, center)))


# ----------------------------------------------------------------------------
# linear algebra helpers
# ----------------------------------------------------------------------------
def _scaling(radius: float) -> np.ndarray:
    """Parameter scale: one scaled unit moves the sample by about one `radius`-unit."""
    return np.array([1.0, 1.0, 1.0, 1.0 / radius, 1.0 / radius, 1.0 / radius])


def _eig_solve(H: np.ndarray, h: np.ndarray, rcond: float, damping: float):
    """Solve on the observable subspace of a symmetric H (batched over a leading axis).

    Returns (x, kept_mask, eigvals, eigvecs).
    """
    w, V = np.linalg.eigh(H)
    wmax = np.max(w, axis=-1, keepdims=True)
    keep = w > rcond * np.maximum(wmax, 1e-300)
    # damping on the kept eigenvalues: Levenberg-Marquardt in the eigenbasis
    wd = np.where(keep, w + damping * np.where(keep, w, 0).mean(axis=-1, keepdims=True), 1.0)
    proj = np.einsum("...ji,...j->...i", V, h)
    x = np.einsum("...ij,...j->...i", V, np.where(keep, proj / wd, 0.0))
    return x, keep, w, V


@dataclass
class _Problem:
    volume: np.ndarray
    vol_geom: VolumeGeometry
    projections: np.ndarray
    geom: VectorGeometry
    weights: Optional[np.ndarray]
    center: np.ndarray
    lab: bool  # the solve's parameters are lab-frame ones (mapped to the sample frame by lab_map)
    free: np.ndarray  # (6,) bool
    scale: np.ndarray  # (6,)
    gamma2: float
    backend: str
    points: np.ndarray
    n_pass: int = 0
    background: Optional[int] = None  # degree of the smooth background per view profiled out (None: none)
    robust: Optional[tuple] = None  # (cut, shift per view) of the Huber weights of every pass, or None
    weight_total: float = 0.0  # Σ w of the pixel weights (robust: χ's normalisation, fixed through the call)

    def reduce(self, rv, t) -> ViewReduction:
        self.n_pass += 1
        g = self.geom.apply_poses(rv, t)
        if self.background is not None:
            return reduce_views_background(self.volume, self.vol_geom, g, self.projections, degree=self.background,
                                           weights=self.weights, center=self.center, backend=self.backend, robust=self.robust)
        return reduce_views(self.volume, self.vol_geom, g, self.projections, weights=self.weights, center=self.center,
                            backend=self.backend, robust=self.robust)

    def chi(self, red: ViewReduction) -> float:
        """χ of a pass: √(rss / (Σ w γ²)); with Huber weights rss is Huber's loss and Σ w the pixel weights' sum."""
        total = self.weight_total if self.robust is not None else red.weight_sum.sum()
        return float(np.sqrt(red.rss.sum() / (max(total, 1e-300) * self.gamma2)))

    def offset_sigma(self, red: ViewReduction) -> float:
        """:func:`view_offset` of the residual at a pass (the Huber weights' shift per view put back)."""
        if self.robust is not None and self.background is None:
            red = replace(red, resid_sum=red.resid_sum + self.robust[1] * red.weight_sum)
        return view_offset(red, self.gamma2)

    def lab_map(self, rv) -> Optional[np.ndarray]:
        """(n, 6, 6) lab -> sample map of an increment composed on poses of rotation vectors ``rv``; None in the sample
        frame.

        The increment acts before the current pose (:func:`_compose_increment`): its lab axes are the posed
        geometry's (``lab_to_sample_map(..., rotvecs=rv)``). With the nominal ones, a tilt of the current poses leaked
        a part of each lab parameter into the others: on a parallel beam the translation along the rays, which no view
        sees, got a small curvature of its own, and the warm-up of a real 360° scan drifted along it by 39 length
        units (``docs/method.md`` §5.36).
        """
        return lab_to_sample_map(self.geom, rotvecs=rv) if self.lab else None

    def framed(self, red: ViewReduction, rv):
        """M, b in the solve's frame and scaled units, restricted to free parameters, linearised at rotations ``rv``."""
        M, b = red.M, red.b
        T = self.lab_map(rv)
        if T is not None:
            M = np.einsum("kji,kjl,klm->kim", T, M, T)
            b = np.einsum("kji,kj->ki", T, b)
        S = self.scale
        M = M * S[None, :, None] * S[None, None, :]
        b = b * S[None, :]
        f = self.free
        return M[:, f][:, :, f], b[:, f]

    def to_sample_params(self, delta_scaled_free: np.ndarray, rv) -> np.ndarray:
        """(n_views, n_free) scaled increments in the solve frame -> (n_views, 6) sample params, at rotations ``rv``."""
        d = np.zeros((delta_scaled_free.shape[0], 6))
        d[:, self.free] = delta_scaled_free
        d = d * self.scale[None, :]
        T = self.lab_map(rv)
        if T is not None:
            d = np.einsum("kij,kj->ki", T, d)
        return d

    def max_displacement_px(self, rv, t, rv2, t2) -> float:
        a = self.geom.apply_poses(rv, t).project_points(self.points)
        b = self.geom.apply_poses(rv2, t2).project_points(self.points)
        return float(np.max(np.linalg.norm(a - b, axis=-1)))


# ----------------------------------------------------------------------------
# full identification
# ----------------------------------------------------------------------------
def _assemble(S: np.ndarray, M: np.ndarray, b: np.ndarray):
    n_f, nfree = S.shape[1], M.shape[1]
    H = np.einsum("kn,km,kij->nimj", S, S, M).reshape(n_f * nfree, n_f * nfree)
    h = np.einsum("kn,ki->ni", S, b).reshape(-1)
    return H, h


def _full_step(prob: _Problem, basis: TemporalBasis, red: ViewReduction, rv, rcond: float, damping: float):
    M, b = prob.framed(red, rv)
    nfree = M.shape[1]
    if basis.kind == "dirac":
        x, keep, w, V = _eig_solve(M, b, rcond, damping)
        delta = x
        obs = Observability()
        for k in range(M.shape[0]):
            for i in np.nonzero(~keep[k])[0]:
                d = np.zeros(6)
                d[prob.free] = V[k][:, i]
                obs.directions.append(d)
                obs.std.append(float(np.sqrt(prob.gamma2 / w[k, i])) if w[k, i] > 0 else float("inf"))
                obs.views.append(k)
        kept = np.where(keep, w, np.nan)
        cond = float(np.nanmax(np.nanmax(kept, axis=1) / np.nanmin(kept, axis=1)))
        cov = np.einsum("kij,kj,klj->kil", V, np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0), V)
        var = np.einsum("kii->ki", cov) * prob.gamma2
        var = np.where(np.abs(np.einsum("kij,kj->ki", V**2, ~keep)) > 1e-3, np.nan, var)
    else:
        Smat = basis.matrix
        H, h = _assemble(Smat, M, b)
        x, keep, w, V = _eig_solve(H, h, rcond, damping)
        delta = (Smat @ x.reshape(basis.n_funcs, nfree))
        obs = Observability()
        for i in np.nonzero(~keep)[0]:
            coeff = V[:, i].reshape(basis.n_funcs, nfree)
            d = np.zeros(6)
            d[prob.free] = coeff[int(np.argmax(np.abs(coeff).sum(1)))]
            obs.directions.append(d / max(np.linalg.norm(d), 1e-300))
            obs.std.append(float(np.sqrt(prob.gamma2 / w[i])) if w[i] > 0 else float("inf"))
            obs.views.append(None)
        kept = w[keep]
        cond = float(kept.max() / kept.min()) if kept.size else float("inf")
        cov = (V * np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0)) @ V.T * prob.gamma2
        cov4 = cov.reshape(basis.n_funcs, nfree, basis.n_funcs, nfree)
        var = np.einsum("kn,nimi,km->ki", Smat, cov4, Smat)
        bad = np.abs(V[:, ~keep]).sum(1).reshape(basis.n_funcs, nfree).sum(0) > 1e-3
        var[:, bad] = np.nan
    obs = Observability(obs.directions, obs.std, obs.views, cond)
    return delta, obs, var


# ----------------------------------------------------------------------------
# public entry point
# ----------------------------------------------------------------------------
def correlate(
    volume,
    vol_geom: VolumeGeometry,
    projections,
    geom: VectorGeometry,
    *,
    basis="dirac",
    method: str = "full",
    frame: str = "sample",
    center=None,
    fixed=(),
    weights=None,
    noise_variance: Optional[float] = None,
    angles=None,
    times=None,
    initial_rotvecs=None,
    initial_translations=None,
    max_iter: int = 20,
    tol_px: float = 1e-3,
    rcond: float = 1e-6,
    max_modes: int = 5,
    pgd_passes: int = 5,
    mode_iter: int = 4,
    min_gain: float = 0.01,
    noise_floor: float = 1.05,
    accelerate: bool = True,
    scales=(1,),
    backend: str = "auto",
    callback: Optional[Callable[[dict], None]] = None,
    max_start_chi: Optional[float] = None,
    background: Optional[int] = None,
    robust: Optional[float] = None,
) -> CorrelationResult:
    """Find the rigid pose of the sample at every view from its projections.

    Parameters
    ----------
    volume : (nz, ny, nx) array
        Reconstruction of the sample (with ``geom``).
    vol_geom : VolumeGeometry
    projections : (n_views, n_rows, n_cols) array
        Measured line integrals ``s``.
    geom : VectorGeometry
        Current geometry of the scan; the poses found are relative to it.
    basis : str, TemporalBasis or (n_views, n_funcs) array
        Temporal basis: ``"dirac"`` (free, one pose per view), ``"constant"``,
        ``"poly:D"``, ``"fourier:M"`` (order M + constant + linear drift; the
        paper's 4-function basis is ``"fourier:1"``), ``"spline:N"``.
    method : {"full", "pgd"}
        Full identification of all amplitudes, or PGD modes one at a time.
    frame : {"sample", "lab"}
        Frame of the rigid modes: in the lab frame a fixed lab translation
        or tilt is one constant mode.
    center : (x, y, z), optional
        Centre of the rotation modes (default the volume centre).
    fixed : iterable of str
        Parameters held at zero, among ``POSE_PARAMETERS`` (in ``frame``).
    weights : (n_rows, n_cols) or (n_views, n_rows, n_cols), optional
        Pixel weights / ROI mask.
    noise_variance : float, optional
        γ² of the projections; estimated from them if absent.
    angles, times : (n_views,) arrays, optional
        Rotation angles (rad) and acquisition times for the temporal basis;
        by default the angles are read from the geometry and the time is
        the view index.
    initial_rotvecs, initial_translations : (n_views, 3), optional
        Starting poses (``apply_poses`` convention).
    max_iter : int
        Jacobian passes at most (full identification; per mode for PGD:
        ``mode_iter``).
    tol_px : float
        Stop when the pose increment moves no sample point by more than this
        many pixels on the detector: after a step that small, or where the
        next undamped Gauss-Newton step would be that small (it is then not
        taken, and no pass is spent on it; the first step only where it is
        below 1e-3 px as well, so that a loose tolerance never ends a
        correlation before any step).
    rcond : float
        Eigenvalues below ``rcond`` x the largest (scaled normal matrix) are
        unobservable directions: left out and reported.
    max_modes, pgd_passes, mode_iter, min_gain, noise_floor
        PGD: at most ``max_modes`` modes; ``pgd_passes`` alternating passes
        per fixed point; ``mode_iter`` re-projections per mode; stop when χ
        falls below ``noise_floor`` or a mode lowers χ by less than the
        fraction ``min_gain``.
    accelerate : bool
        Anderson-accelerate the Gauss–Newton steps of the full
        identification once they lower χ by less than 5 % per pass
        (``docs/method.md`` §5.6); an accelerated step that raises χ is
        replaced by the plain one.
    scales : sequence of int
        Multi-scale schedule, coarse to fine, e.g. ``(4, 2, 1)``: at scale
        ``s`` the projections are Gaussian coarse-grained (σ = s/2 px, then
        s x s block means, geometry scaled; :func:`coarse_grain`), the volume
        is block-averaged (:func:`coarse_volume`) and γ² is carried over
        (:func:`coarse_noise_factor`); the poses found start the next scale.
        Large motions, which are small in coarse pixels, converge this way.
        The returned geometry is always the full-resolution ``geom`` posed.
    callback : callable, optional
        Called with a dict (iteration, chi, snr, step_px, mu) after each
        iteration.
    max_start_chi : float, optional
        Return after the first pass, poses unchanged and status
        ``CONSISTENCY_GUARD``, when χ at the starting poses is above it
        (the calibration driver's consistency guard: a round whose fresh
        reconstruction already fits worse than the best is not measured).
        Single scale only.
    background : {None, 0, 1, 2}
        Also fit a smooth background per view, a polynomial of this degree
        in the detector coordinates (0: an offset per view, e.g. an air level
        that drifts; 2: up to quadratic, e.g. the attenuation of material
        outside the volume), profiled out of the normal equations
        (``pdvc.correlation._background``). χ and the SNR are then those of
        the residual after it. Degree 0 costs nothing extra; 1 and 2 compute
        the sensitivity images (threaded, by chunks of views).
    robust : float, optional
        Huber's M-estimator instead of least squares (iteratively
        reweighted: every pass weighs each pixel by ``min(1, c / |e|)`` of
        its own residual ``e``, :func:`pdvc.projectors.reduce_views`), so
        that outliers (zingers, hot pixels, a detector defect) do not steer
        the poses. The cut ``c`` is ``robust`` times the robust std of the
        residual at the starting poses, and ``e`` the residual less its
        median per view there (:func:`residual_scale`; one forward
        projection more), both fixed through the call. χ is then
        √(Huber's loss / (Σ w γ²)), the same as least squares' where no
        pixel is beyond the cut.

    Returns
    -------
    CorrelationResult
    """
    sched = _check_scales(scales)
    if max_start_chi is not None and sched != (1,):
        raise CorrelationError("max_start_chi needs a single scale (scales=(1,))")
    if sched != (1,):
        return _correlate_multiscale(
            sched,
            volume,
            vol_geom,
            projections,
            geom,
            dict(
                basis=basis, method=method, frame=frame, center=center, fixed=fixed, angles=angles, times=times,
                max_iter=max_iter, tol_px=tol_px, rcond=rcond, max_modes=max_modes, pgd_passes=pgd_passes,
                mode_iter=mode_iter, min_gain=min_gain, noise_floor=noise_floor, accelerate=accelerate, backend=backend,
                callback=callback, background=background, robust=robust,
            ),
            weights,
            noise_variance,
            initial_rotvecs,
            initial_translations,
        )
    for name, val in (("max_iter", max_iter), ("max_modes", max_modes), ("pgd_passes", pgd_passes), ("mode_iter", mode_iter)):
        if not isinstance(val, (int, np.integer)) or val < 1:
            raise CorrelationError(f"{name} must be a positive int, got {val!r}")
    if not (tol_px > 0):
        raise CorrelationError(f"tol_px must be positive, got {tol_px!r}")
    if method not in ("full", "pgd"):
        raise CorrelationError(f"method must be 'full' or 'pgd', got {method!r}")
    prob, basis_obj = _problem(volume, vol_geom, projections, geom, basis, frame, center, fixed, weights, noise_variance, angles, times, backend,
                               background)
    n, c, gamma2 = geom.n_views, prob.center, prob.gamma2
    rv = np.zeros((n, 3)) if initial_rotvecs is None else np.array(initial_rotvecs, float).reshape(n, 3)
    t = np.zeros((n, 3)) if initial_translations is None else np.array(initial_translations, float).reshape(n, 3)
    if robust is not None:
        if isinstance(robust, bool) or not isinstance(robust, (int, float, np.integer, np.floating)) or not robust > 0 \
                or not np.isfinite(robust):
            raise CorrelationError(f"robust must be None or a positive Huber threshold (in residual std), got {robust!r}")
        sigma, shift = residual_scale(prob.volume, prob.vol_geom, prob.projections, geom.apply_poses(rv, t),
                                      weights=prob.weights, noise_variance=gamma2, backend=backend)
        prob.robust = (float(robust) * sigma, shift)
        w = prob.weights
        prob.weight_total = float(np.prod(prob.projections.shape)) if w is None else \
            float(np.broadcast_to(np.asarray(w, np.float64), prob.projections.shape).sum())
        log.info("correlate: Huber weights beyond %.3g (%.3g x the residual's robust std %.3g)", prob.robust[0], robust, sigma)

    red = prob.reduce(rv, t)
    snr_before = red.snr_db()
    chi_hist = [prob.chi(red)]
    snr_hist = [_overall_snr(red)]
    log.info("correlate: start chi = %.4g, SNR = %.2f dB, noise variance %.3g", chi_hist[0], snr_hist[0], gamma2)

    if max_start_chi is not None and chi_hist[0] > max_start_chi:
        log.info("correlate: start chi %.5g above max_start_chi %.5g; not measured", chi_hist[0], max_start_chi)
        status, var, obs = Status.CONSISTENCY_GUARD, np.full((n, int(prob.free.sum())), np.nan), Observability()
        modes, mode_table = (), ()
    elif method == "full":
        rv, t, red, status, var, obs, it = _run_full(
            prob, basis_obj, rv, t, red, chi_hist, snr_hist, max_iter, tol_px, rcond, callback, accelerate=bool(accelerate)
        )
        modes: tuple = ()
        mode_table = ()
    else:
        rv, t, red, status, var, obs, modes, mode_table = _run_pgd(
            prob, basis_obj, rv, t, red, chi_hist, snr_hist, max_modes, pgd_passes, mode_iter, tol_px, rcond, min_gain, noise_floor, callback
        )
    poses = Poses(rv, t)
    params = poses.to_params(c)
    params_lab = poses.lab_params(geom, c)
    std = _std_sample(prob, var, rv)
    return CorrelationResult(
        geometry=geom.apply_poses(rv, t),
        rotvecs=rv,
        translations=t,
        params=params,
        params_lab=params_lab,
        std=std,
        center=c,
        frame=frame,
        basis=basis_obj,
        method=method,
        modes=tuple(modes),
        chi_history=np.array(chi_hist),
        snr_history=np.array(snr_hist),
        mode_table=tuple(mode_table),
        snr_before=snr_before,
        snr_after=red.snr_db(),
        noise_variance=gamma2,
        observability=obs,
        n_iter=prob.n_pass,
        status=status,
        message=status.message,
        scale_history=((1, chi_hist[0], chi_hist[-1], prob.n_pass),),
        background=prob.background,
        offset_sigma=prob.offset_sigma(red),
    )


def _problem(volume, vol_geom, projections, geom, basis, frame, center, fixed, weights, noise_variance, angles, times, backend,
             background=None):
    """The checked problem of one measurement (shared by :func:`correlate` and :func:`assess`)."""
    vol = np.asarray(volume, dtype=np.float32)
    s = np.asarray(projections, dtype=np.float32)
    if not isinstance(geom, VectorGeometry) or not isinstance(vol_geom, VolumeGeometry):
        raise CorrelationError("geom must be a VectorGeometry and vol_geom a VolumeGeometry")
    n = geom.n_views
    if s.shape != (n,) + geom.det_shape:
        raise ShapeError(f"projections must have shape {(n,) + geom.det_shape}, got {s.shape}")
    if frame not in ("sample", "lab"):
        raise CorrelationError(f"frame must be 'sample' or 'lab', got {frame!r}")
    if background is not None and (isinstance(background, bool) or background not in BACKGROUND_DEGREES):
        raise CorrelationError(f"background must be None or a polynomial degree in {BACKGROUND_DEGREES}, got {background!r}")
    free = np.ones(6, bool)
    for name in fixed:
        if name not in POSE_PARAMETERS:
            raise CorrelationError(f"fixed must name parameters among {POSE_PARAMETERS}, got {name!r}")
        free[POSE_PARAMETERS.index(name)] = False
    if not free.any():
        raise CorrelationError("fixed leaves no parameter to measure")
    if angles is None:
        angles = view_angles(geom)
    basis_obj = make_basis(basis, angles=np.asarray(angles, float), times=times) if not isinstance(basis, TemporalBasis) else basis
    if basis_obj.n_views != n:
        raise CorrelationError(f"basis must have {n} rows (views), got {basis_obj.n_views}")
    c = np.asarray(vol_geom.offset, float) if center is None else np.asarray(center, float).reshape(3)
    radius = 0.5 * float(np.min(vol_geom.extent_xyz))
    gamma2 = float(noise_variance) if noise_variance is not None else estimate_noise_variance(s)
    if not (gamma2 > 0):
        raise CorrelationError(f"noise_variance must be positive, got {gamma2!r}")
    prob = _Problem(
        volume=vol, vol_geom=vol_geom, projections=s, geom=geom, weights=weights, center=c,
        lab=frame == "lab", free=free, scale=_scaling(radius), gamma2=gamma2,
        backend=backend, points=sample_points(vol_geom, 3, fraction=0.8),
        background=None if background is None else int(background),
    )
    return prob, basis_obj


def residual_scale(volume, vol_geom, projections, geom, *, weights=None, noise_variance: float, backend: str = "auto"):
    """The robust scale of the residual ``ρ = s - Π f`` at ``geom``, and its offset per view.

    ``shift[k]`` is the median of view k's residual over its pixels of
    non-zero weight (an offset per view, e.g. an air level that drifts, is
    no outlier); ``σ = max(1.4826 MAD, √noise_variance)`` of ``ρ - shift``
    over those pixels, all views together. One forward projection.

    Returns
    -------
    sigma : float
    shift : (n_views,) float64
    """
    s = np.asarray(projections, dtype=np.float32)
    rho = s - forward(volume, vol_geom, geom, backend=backend)
    floor = float(np.sqrt(noise_variance))
    sel = np.ones(s.shape, bool) if weights is None else np.broadcast_to(np.asarray(weights) > 0, s.shape)
    shift = np.array([np.median(rho[k][sel[k]]) if sel[k].any() else 0.0 for k in range(s.shape[0])], np.float64)
    if not sel.any():
        return floor, shift
    rho -= shift[:, None, None].astype(np.float32)
    mad = float(np.median(np.abs(rho[sel])))
    return max(1.4826 * mad, floor), shift


def _check_scales(scales) -> tuple:
    try:
        sched = tuple(scales)
    except TypeError:
        sched = (scales,)
    if not sched or any(not isinstance(x, (int, np.integer)) or isinstance(x, bool) or x < 1 for x in sched):
        raise CorrelationError(f"scales must be a non-empty sequence of positive ints (coarse to fine), got {scales!r}")
    return tuple(int(x) for x in sched)


def _correlate_multiscale(sched, volume, vol_geom, projections, geom, options, weights, noise_variance, rv, t):
    s_full = np.asarray(projections, dtype=np.float32)
    if s_full.shape != (geom.n_views,) + geom.det_shape:
        raise ShapeError(f"projections must have shape {(geom.n_views,) + geom.det_shape}, got {s_full.shape}")
    gamma2 = float(noise_variance) if noise_variance is not None else estimate_noise_variance(s_full)
    history = []
    res = None
    for sc in sched:
        if sc == 1:
            data, g, vol, vg, w, gam = s_full, geom, volume, vol_geom, weights, gamma2
        else:
            data, g = coarse_grain(s_full, geom, sc)
            vol, vg = coarse_volume(volume, vol_geom, sc)
            w = coarse_weights(weights, sc, g.det_shape)
            gam = gamma2 * coarse_noise_factor(sc)
        log.info("correlate: scale %d, detector %s, volume %s", sc, g.det_shape, vg.shape)
        res = correlate(vol, vg, data, g, weights=w, noise_variance=gam, initial_rotvecs=rv, initial_translations=t, scales=(1,), **options)
        history.append((sc, float(res.chi_history[0]), float(res.chi_history[-1]), int(res.n_iter)))
        rv, t = res.rotvecs, res.translations
    return replace(res, geometry=geom.apply_poses(rv, t), scale_history=tuple(history))


def _overall_snr(red: ViewReduction) -> float:
    w = max(red.weight_sum.sum(), 1e-300)
    var_s = red.meas_sq_sum.sum() / w - (red.meas_sum.sum() / w) ** 2
    var_r = red.rss.sum() / w - (red.resid_sum.sum() / w) ** 2
    return float(10 * np.log10(var_s / var_r))


def _std_sample(prob: _Problem, var_scaled_free: np.ndarray, rv) -> np.ndarray:
    """Per-view std of the sample-frame parameters from scaled, framed variances (diagonal only), at rotations ``rv``."""
    n = var_scaled_free.shape[0]
    var = np.full((n, 6), 0.0)
    var[:, prob.free] = var_scaled_free
    var[:, ~prob.free] = 0.0
    var = var * prob.scale[None, :] ** 2
    T = prob.lab_map(rv)
    if T is not None:
        T2 = T**2
        var = np.einsum("kij,kj->ki", T2, np.nan_to_num(var, nan=np.inf))
        var[~np.isfinite(var)] = np.nan
    return np.sqrt(var)


_FIRST_STEP_TOL_PX = 1e-3  # a first Gauss-Newton step this small is not taken, whatever the caller's tol_px
_AA_REGIME = 0.05  # accelerate once a Gauss-Newton step lowers chi by less than 5 %


class _Anderson:
    """Anderson acceleration of the Gauss–Newton iteration ``x <- x + f(x)`` (type II, depth ``m``).

    The Jacobian of the interpolating projector carries the roughness of
    the interpolant's derivative, so ``JᵀJ`` overstates the curvature of χ²
    along weakly determined directions and plain Gauss–Newton steps there
    shrink geometrically (measured: by ~0.9 per pass on a fourier:1 model,
    ``docs/method.md``). The GN steps ``f_k`` and the iterates ``x_k``
    (accumulated increments, in the solve's scaled units per view) of the
    last passes give the secant model that removes this: the step is
    ``f_k - (ΔX + ΔF) γ`` with ``γ = argmin |f_k - ΔF γ|``. The caller keeps
    the step only if χ does not rise, and restarts (``reset``) otherwise. It
    accelerates only once the plain steps lower χ by less than 5 % (the slow
    regime): far from the solution the secant model is poor and a rejected
    step costs a pass.
    """

    def __init__(self, depth: int = 3):
        self.depth = depth
        self.x: list = []
        self.f: list = []

    def reset(self) -> None:
        self.x, self.f = [], []

    def step(self, x: np.ndarray, f: np.ndarray) -> np.ndarray:
        self.x = (self.x + [x.ravel().copy()])[-(self.depth + 1):]
        self.f = (self.f + [f.ravel().copy()])[-(self.depth + 1):]
        if len(self.f) < 2:
            return f
        dX = np.diff(np.array(self.x), axis=0).T
        dF = np.diff(np.array(self.f), axis=0).T
        gamma = np.linalg.lstsq(dF, f.ravel(), rcond=1e-8)[0]
        s = f.ravel() - (dX + dF) @ gamma
        if not np.all(np.isfinite(s)):
            self.reset()
            return f
        return s.reshape(f.shape)


def _trial_step(prob, rv, t, delta_f):
    """(rotvecs, translations, px): the poses after the scaled increment ``delta_f`` and how far it moves the sample
    points on the detector."""
    rv2, t2 = _compose_increment(rv, t, prob.to_sample_params(delta_f, rv), prob.center)
    return rv2, t2, prob.max_displacement_px(rv, t, rv2, t2)


def _run_full(prob, basis, rv, t, red, chi_hist, snr_hist, max_iter, tol_px, rcond, callback, accelerate=True):
    """Levenberg–Marquardt on the full identification, Anderson-accelerated; a step is kept only if χ does not rise."""
    mu = 0.0
    status = Status.MAX_ITER
    var = np.full((prob.geom.n_views, int(prob.free.sum())), np.nan)
    obs = Observability()
    it = 0
    aa = _Anderson() if accelerate else None
    x = None  # accumulated increments (scaled, solve frame), for the acceleration
    while prob.n_pass < max_iter + 1:
        it += 1
        delta_f, obs, var = _full_step(prob, basis, red, rv, rcond, mu)
        if x is None:
            x = np.zeros_like(delta_f)
        trial = None  # (poses, move in px) of the undamped step, reused where the acceleration leaves it as it is
        if mu == 0.0:
            trial = _trial_step(prob, rv, t, delta_f)
            plain_px = trial[2]
            # the first step is taken unless it is below _FIRST_STEP_TOL_PX too: a caller's looser tolerance (the
            # rounds' forcing term) ends the iteration, it does not make a round report no motion at all
            stop_px = tol_px if len(chi_hist) > 1 else min(tol_px, _FIRST_STEP_TOL_PX)
            if plain_px < stop_px:
                # the Gauss-Newton step this pass predicts moves the sample points by less than the tolerance:
                # converged where it stands, without a pass to evaluate so small a step
                log.info("iteration %d: the next step would move %.3g px (below %.3g): converged", it, plain_px, stop_px)
                status = Status.CONVERGED
                break
        accelerated = aa is not None and mu == 0.0
        if accelerated:
            # only in the slow, nearly linear regime: far from the solution the secant model is poor
            if len(chi_hist) < 2 or chi_hist[-1] < (1.0 - _AA_REGIME) * chi_hist[-2]:
                aa.reset()
            stepped = aa.step(x, delta_f)
            if stepped is not delta_f:
                delta_f, trial = stepped, None
        rv2, t2, step_px = trial if trial is not None else _trial_step(prob, rv, t, delta_f)
        red2 = prob.reduce(rv2, t2)
        chi2 = prob.chi(red2)
        if chi2 <= chi_hist[-1] * (1 + 1e-9):
            rv, t, red = rv2, t2, red2
            x = x + delta_f
            chi_hist.append(chi2)
            snr_hist.append(_overall_snr(red))
            mu = mu / 10 if mu > 1e-6 else 0.0
            log.info("iteration %d: chi %.5g, SNR %.2f dB, step %.3g px", it, chi2, snr_hist[-1], step_px)
            if callback is not None:
                callback(dict(iteration=it, chi=chi2, snr=snr_hist[-1], step_px=step_px, mu=mu))
            if step_px < tol_px:
                status = Status.CONVERGED
                break
        elif accelerated and len(aa.f) > 1:
            # the secant step overshot: forget the history and take the plain Gauss-Newton step next
            aa.reset()
            log.info("iteration %d: chi rose to %.5g (accelerated step %.3g px); plain step next", it, chi2, step_px)
        else:
            # a rejected step is never kept, however small: damp, and give up when damping
            # has shrunk it below the tolerance (or the damping is absurd) without lowering χ
            mu = max(1e-3, 10 * mu)
            if aa is not None:
                aa.reset()
            log.info("iteration %d: chi rose to %.5g (step %.3g px); damping mu = %.3g", it, chi2, step_px, mu)
            if step_px < tol_px or mu > 1e6:
                status = Status.NO_DESCENT
                break
    return rv, t, red, status, var, obs, it


def _pgd_fixed_point(M, b, S, passes, p0, a0):
    """Alternate p ← (Σ α² M)⁻¹ Σ α b and a ← (Σ σσᵀ pᵀMp)⁻¹ Σ σ pᵀb; max|α| = 1."""
    p, a = p0.copy(), a0.copy()
    for _ in range(passes):
        alpha = S @ a
        A = np.einsum("k,kij->ij", alpha**2, M)
        rhs = np.einsum("k,ki->i", alpha, b)
        p_new = np.linalg.lstsq(A, rhs, rcond=1e-10)[0]
        q = np.einsum("i,kij,j->k", p_new, M, p_new)
        B = np.einsum("kn,k,km->nm", S, q, S)
        r = np.einsum("kn,ki,i->n", S, b, p_new)
        a_new = np.linalg.lstsq(B, r, rcond=1e-10)[0]
        alpha = S @ a_new
        m = np.max(np.abs(alpha))
        if m == 0 or not np.isfinite(m):
            break
        i = int(np.argmax(np.abs(alpha)))
        sgn = np.sign(alpha[i])
        a_new, p_new = a_new / (m * sgn), p_new * (m * sgn)
        change = max(np.linalg.norm(p_new - p) / max(np.linalg.norm(p_new), 1e-300), np.linalg.norm(a_new - a) / max(np.linalg.norm(a_new), 1e-300))
        p, a = p_new, a_new
        if change < 1e-3:
            break
    return p, a


def _run_pgd(prob, basis, rv, t, red, chi_hist, snr_hist, max_modes, passes, mode_iter, tol_px, rcond, min_gain, noise_floor, callback):
    S = basis.matrix
    modes = []
    table = [(0, chi_hist[-1], snr_hist[-1])]
    status = Status.MAX_MODES
    obs = Observability()
    var = np.full((prob.geom.n_views, int(prob.free.sum())), np.nan)
    it = 0
    for m in range(max_modes):
        chi_start = chi_hist[-1]
        if chi_start <= noise_floor:
            status = Status.NOISE_FLOOR
            break
        # initial guess: dominant direction of the free per-view solutions
        M, b = prob.framed(red, rv)
        x, keep, _, _ = _eig_solve(M, b, rcond, 0.0)
        _, _, Vt = np.linalg.svd(x, full_matrices=False)
        p = Vt[0]
        alpha0 = x @ p
        a = np.linalg.lstsq(S, alpha0, rcond=None)[0]
        total_alpha = np.zeros(S.shape[0])
        p_mode = None
        for _ in range(mode_iter):
            it += 1
            M, b = prob.framed(red, rv)
            p, a = _pgd_fixed_point(M, b, S, passes, p if p_mode is None else p_mode, a)
            if p_mode is None:
                p_mode = p.copy()
            # the increment is α_k p; keep the mode's spatial direction for the history
            delta = prob.to_sample_params(np.outer(S @ a, p), rv)
            rv2, t2 = _compose_increment(rv, t, delta, prob.center)
            step_px = prob.max_displacement_px(rv, t, rv2, t2)
            red2 = prob.reduce(rv2, t2)
            chi2 = prob.chi(red2)
            if chi2 > chi_hist[-1] * (1 + 1e-9):
                log.info("mode %d: chi rose to %.5g, update rejected", m + 1, chi2)
                break
            rv, t, red = rv2, t2, red2
            # express the accumulated amplitude along the first direction of this mode
            total_alpha += (S @ a) * float(p @ p_mode) / max(float(p_mode @ p_mode), 1e-300)
            chi_hist.append(chi2)
            snr_hist.append(_overall_snr(red))
            if callback is not None:
                callback(dict(iteration=it, mode=m + 1, chi=chi2, snr=snr_hist[-1], step_px=step_px, mu=0.0))
            if step_px < tol_px:
                break
        # free (Dirac) history of the same spatial mode, at the end of the mode
        M, b = prob.framed(red, rv)
        q = np.einsum("i,kij,j->k", p_mode, M, p_mode)
        r = np.einsum("ki,i->k", b, p_mode)
        free_alpha = total_alpha + np.where(q > 0, r / np.where(q > 0, q, 1.0), np.nan)
        scale = np.max(np.abs(total_alpha)) or 1.0
        spatial = np.zeros(6)
        spatial[prob.free] = p_mode * scale
        spatial = spatial * prob.scale
        coeffs = np.linalg.lstsq(S, total_alpha / scale, rcond=None)[0]
        modes.append(Mode(spatial=spatial, coefficients=coeffs, alpha=total_alpha / scale, alpha_free=free_alpha / scale, chi=chi_hist[-1]))
        table.append((m + 1, chi_hist[-1], snr_hist[-1]))
        log.info("mode %d: chi %.5g -> %.5g", m + 1, chi_start, chi_hist[-1])
        if chi_start - chi_hist[-1] < min_gain * chi_start:
            status = Status.MODES_STAGNATED
            break
    else:
        status = Status.MAX_MODES
    if chi_hist[-1] <= noise_floor:
        status = Status.NOISE_FLOOR
    _, obs, var = _full_step(prob, basis, red, rv, rcond, 0.0)
    return rv, t, red, status, var, obs, modes, table
