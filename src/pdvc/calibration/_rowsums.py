"""The axis's tilt in parallel beam from the row sums of the views, without a reconstruction.

In a parallel-beam scan about the nominal axis, every detector row sees one
horizontal slab of the sample, whatever the angle: the sum of a row,
``m_k(v) = Σ_j p_k(v, j)``, is the slab's mass, the same in every view (the
order-0 Helgason–Ludwig condition, row by row). A tilted axis breaks it. At
view ``k`` a small constant lab rotation of the axis moves a sample point at column ``a``
(pixels from the projected axis) and depth ``c`` (pixels along the ray) up by

    δv = π c - ρ a

— ρ (``roll``) leans the axis within the detector plane, π (``pitch``)
along the beam, signed as :class:`pdvc.calibration.MotionSummary`'s
``roll_deg`` and ``pitch_deg`` — and the row sums change, to first order, by

    δm_k(v) = -∂_v Σ δv p = ρ ∂_v U_k(v) - π ∂_v W_k(v),

with ``U_k(v) = Σ_j a_j p_k(v, j)`` the row's first moment and
``W_k(v)`` the slab's first moment along the ray, which the data give too:
the first moment of a row is a sinusoid of the view direction,
``U_k(v) = X(v) · û_k + C(v)`` (``X(v)`` the slab's horizontal moment), and
then ``W_k(v) = X(v) · r̂_k`` (``r̂_k`` the ray). A tilted axis is a constant
lab rotation, so ρ and π are two numbers for the whole scan, fitted by least
squares to all rows of all views together with a mean profile per row (what a
sample-fixed rotation changes, the gauge) and an offset per view (a uniform
change of the air level). A vertical drift of the sample shifts the profiles
by more than a linearisation follows; each view's profile is first registered
vertically to the mean one.

This is what a reconstruction-based loop settles slowly in parallel beam: the
pitch changes the reprojections of a half turn so little that the
reconstruct-and-correlate rounds creep toward it (``docs/method.md`` §5.15);
the row sums measure it at once. It needs the whole sample across the
detector's width (a region-of-interest scan breaks the moments) but not along
its height: each row's rays stay in its slab, so a rod longer than the field
of view is fine.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d as _gaussian
from scipy.ndimage import median_filter as _median
from scipy.ndimage import shift as _shift

from ..correlation import estimate_noise_variance
from ..errors import InputTypeError
from ..geometry import Poses, VectorGeometry
from ..io._preprocess import _robust_std
from ..io._zingers import isolated_outliers
from ._init import InitError, offset_poses

__all__ = ["AxisTiltEstimate", "RowSumConsistency", "VerticalMotion", "estimate_axis_tilt", "tilt_poses"]

log = logging.getLogger(__name__)

_EDGE_ROWS = 4  # rows left out at the top and bottom (the vertical registration's spline edges)
_REGISTRATION_ROUNDS = 6
_SMOOTH_ROWS = 1.0  # Gaussian sigma, rows, of the profiles before their derivatives
_HUBER = 2.0  # robust weights: residuals beyond this many sigmas are down-weighted (zingers, dead pixels)


@dataclass(frozen=True, eq=False)
class AxisTiltEstimate:
    """The axis's constant tilt found from the row sums (:func:`estimate_axis_tilt`).

    Attributes
    ----------
    roll, pitch : float, radians
        The lab rotation that takes the nominal axis to the scan's: ``roll``
        about the beam (the axis leans toward ``+x``, larger columns, going
        up: :attr:`pdvc.calibration.MotionSummary.roll_deg`), ``pitch``
        about the detector's ``u`` (it leans toward ``+y``, away from the
        source: ``MotionSummary.pitch_deg``).
    roll_sd, pitch_sd : float, radians
        Their standard deviations from the least-squares fit, with the
        residual's correlation along views and rows (``sd_inflation``).
    shifts_px : (n_views,) float64
        The vertical registration of each view's row-sum profile, pixels, mean
        zero: how far the sample moved up between views (a vertical drift).
    explained : float
        Fraction of the row sums' inconsistency (after the per-row means, the
        per-view offsets and the registration) that the tilt explains.
    moments_fit : float
        Fraction of the rows' first moments' change over the views that the
        sinusoids ``X(v) · û_k + C(v)`` explain: near 1 when the whole sample
        is in the field across the detector's width and the motion is small.
    n_rows : int
        Detector rows used.
    sd_inflation : float
        How many times ``roll_sd`` or ``pitch_sd`` (the larger ratio) exceeds
        what the residual would give were it white noise: the standard
        deviations are those of a residual correlated along views or rows
        (a sandwich estimate clustered by view and by row), as model error is.
        1 for a white residual; measured 1.1-5 on simulated scans whose tilt
        the row sums hold, 5-8 on rods whose drift with acceleration or
        precession they misread, 9 on a real neutron scan.
    """

    roll: float
    pitch: float
    roll_sd: float
    pitch_sd: float
    shifts_px: np.ndarray
    explained: float
    moments_fit: float
    n_rows: int
    sd_inflation: float = 1.0

    @property
    def significance(self) -> float:
        """The tilt's size in standard deviations, ``hypot(roll/roll_sd, pitch/pitch_sd)``."""
        return float(np.hypot(self.roll / self.roll_sd, self.pitch / self.pitch_sd))

    @property
    def tilt_deg(self) -> float:
        """Angle between the scan's axis and the nominal one, degrees."""
        return float(np.rad2deg(np.hypot(self.roll, self.pitch)))

    def describe(self) -> str:
        """One line: both tilts in degrees with their standard deviations, the significance and the moments' fit."""
        d = np.rad2deg
        return (f"roll {d(self.roll):+.3f}° ± {d(self.roll_sd):.3f}°, pitch {d(self.pitch):+.3f}° ± {d(self.pitch_sd):.3f}° "
                f"({self.significance:.1f} standard deviations, {self.sd_inflation:.1f}x noise's; the rows' first moments "
                f"{100 * self.moments_fit:.0f}% sinusoidal)")


def _unit(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a, axis=1)[:, None]


def _check_geometry(geom: VectorGeometry) -> None:
    """Raise InitError unless every view is parallel beam with a common vertical ``v`` square to ``u`` and the ray."""
    if not isinstance(geom, VectorGeometry):
        raise InputTypeError(f"geom must be a pdvc.VectorGeometry, got {type(geom).__name__}")
    if geom.kind != "parallel":
        raise InitError("the row sums measure the axis's tilt in parallel beam only (cone-beam rows mix slabs)")
    v = geom.v
    vu, pitch = _unit(v), np.linalg.norm(v, axis=1)
    common = np.abs(vu - vu[0]).max() <= 1e-6 and np.abs(pitch - pitch[0]).max() <= 1e-9 * pitch[0]
    square = max(np.abs(np.sum(vu * _unit(geom.u), axis=1)).max(), np.abs(np.sum(vu * _unit(geom.ray), axis=1)).max()) <= 1e-6
    if not (common and square):
        raise InitError("the row sums need every view's detector rows along one common direction, square to the "
                        "columns and the ray (a nominal parallel scan about one axis)")
    if geom.n_views < 8:
        raise InitError(f"the row sums need at least 8 views, got {geom.n_views}")


def _robust_weights(r: np.ndarray) -> np.ndarray:
    s = _robust_std(r)
    if not s > 0:
        return np.ones_like(r)
    a = np.abs(r) / (_HUBER * s)
    return np.where(a > 1, 1.0 / np.maximum(a, 1e-12), 1.0)


def _register(m: np.ndarray, keep: slice, offsets: bool = False) -> np.ndarray:
    """Vertical shift of each view's profile onto the mean one (Gauss–Newton on a cubic spline), mean zero.

    ``offsets``: each view's profile may also differ from the mean one by a constant, fitted with the shift (an air
    level that changes from view to view adds one; where the profile's ends differ, a rod's cut by the field, the
    shift alone would take part of it up)."""
    dz = np.zeros(m.shape[0])
    for _ in range(_REGISTRATION_ROUNDS):
        ms = np.stack([_shift(m[k], -dz[k], order=3, mode="nearest") for k in range(m.shape[0])])
        ref = ms.mean(0)
        g = np.gradient(ref)[keep]
        if offsets:
            g = g - g.mean()  # the shift's regressor less what a constant takes up
        gg = float(g @ g)
        if not gg > 0:
            break
        step = -((ms[:, keep] - ref[keep]) @ g) / gg
        dz += np.clip(step, -2.0, 2.0)
        dz -= dz.mean()
        if np.abs(step).max() < 1e-3:
            break
    return dz


def _row_moments(U: np.ndarray, uu: np.ndarray) -> np.ndarray:
    """``(X_x, X_y, C)`` per row: the robust fit ``U_k(v) = X(v) · û_k + C(v)`` over the views; (3, n_rows)."""
    A = np.column_stack([uu[:, 0], uu[:, 1], np.ones(uu.shape[0])])
    coef = np.linalg.lstsq(A, U, rcond=None)[0]
    for _ in range(2):
        w = _robust_weights((U - A @ coef).ravel()).reshape(U.shape)
        # one small weighted normal system per row
        N = np.einsum("ki,kj,kr->rij", A, A, w)
        b = np.einsum("ki,kr->ri", A, w * U)
        coef = np.linalg.solve(N + 1e-12 * np.eye(3), b[..., None])[..., 0].T
    return coef


def _without_zingers(view: np.ndarray, sigma: float) -> np.ndarray:
    """One view with its isolated outliers (zingers, hot or dead pixels) replaced by the median of their 3x3 block.

    A row sum adds every pixel of the row: one zinger (a line integral 0.5 to 3 too low) outweighs the row's noise
    many times over, and 1 % of them turned a 0.42° roll into -0.13°. Only pixels beyond ``ZINGER_SIGMA`` noise
    standard deviations from the median whose four neighbours are not (:func:`pdvc.io.isolated_outliers`'s rule)
    are replaced: a foam's thin walls are lines, not isolated pixels.
    """
    if not sigma > 0:
        return view
    med = _median(view, size=3, mode="nearest")
    hit = isolated_outliers((view - med)[None], sigma)[0]
    return np.where(hit, med, view) if hit.any() else view


def _clustered_sd(Ni: np.ndarray, scores: np.ndarray, shape: tuple) -> np.ndarray:
    """Standard deviations of a weighted least-squares fit whose residual may be correlated along views or rows.

    The sandwich ``N⁻¹ (Σ_g s_g s_gᵀ) N⁻¹`` with the scores ``s_g`` (regressor × weight × residual) summed within each
    view, then within each detector row, each with the small-sample factor ``G / (G - 1)``; the larger of the two per
    parameter. With white residuals both are the usual ``σ² N⁻¹``; where the residual is model error (a drift the
    model does not hold, a slab's profile that the registration cannot follow) it lies along rows or views, and the
    white-noise standard deviation was 2-9× too small on the scans measured (``docs/method.md`` §5.32).
    """
    S = scores.reshape(*shape, scores.shape[1])
    out = np.zeros(scores.shape[1])
    for g in (S.sum(1), S.sum(0)):  # per view, per row
        n = g.shape[0]
        cov = Ni @ (g.T @ g) @ Ni * (n / max(n - 1, 1))
        out = np.maximum(out, np.sqrt(np.clip(np.diag(cov), 0.0, None)))
    return out


def _double_centre(z: np.ndarray) -> np.ndarray:
    return z - z.mean(0) - z.mean(1)[:, None] + z.mean()


# vertical_motion(): a step of the views' shifts counts at this many standard deviations over a line fitted to this
# many views on each side (jolt_steps' z and window; its 8 and 6 for the poses measured one by one missed every 0.8 px
# jolt of a cast-iron rod at i0 2e3, 3.7-4.5 standard deviations with 6 views, 5.6-6.7 with 12; found on three noise
# draws of it, no step found on eight of the rod drifting without a jolt)
VERTICAL_STEP_Z = 4.0
VERTICAL_STEP_WINDOW = 12


@dataclass(frozen=True, eq=False)
class VerticalMotion:
    """The sample's vertical lab translation per view, read from the row sums' registration (parallel beam).

    Attributes
    ----------
    translation : (n_views,) float64
        Vertical lab translation, length units, mean zero (a constant is the gauge).
    steps : (n_steps,) int
        Views at which the fit has a step (a jolt).
    f_stat : float
        The fit's energy over what the noise of one view's shift would give it.
    misfit : float
        The fit's residual over that noise (about 1 where the fit holds the motion).
    noise_px : float
        The noise of one view's shift, pixels.
    """

    translation: np.ndarray
    steps: np.ndarray
    f_stat: float
    misfit: float
    noise_px: float


class RowSumConsistency:
    """The row sums of a parallel scan, fitted once: the axis's tilt and how consistent any poses are with them.

    ``RowSumConsistency(projections, geom, offset_px=...)`` makes the fit of
    :func:`estimate_axis_tilt` (its result is :attr:`estimate`) and keeps
    what :meth:`misfit` needs to score per-view poses by the same first-order
    model, view by view: the row sums predicted for the tilts that the poses
    give each view, against those measured. No reconstruction; a
    reconstruct-and-correlate loop that walks along the pitch of a parallel
    half turn (``docs/method.md`` §5.31) raises it.

    Parameters are those of :func:`estimate_axis_tilt`, which raises the same errors.
    """

    def __init__(self, projections, geom: VectorGeometry, *, offset_px: float = 0.0):
        _check_geometry(geom)
        p = np.asarray(projections)
        nv, nr, nc = geom.n_views, *geom.det_shape
        if p.shape != (nv, nr, nc):
            raise InitError(f"projections must have shape {(nv, nr, nc)}, got {p.shape}")
        if nr < 3 * _EDGE_ROWS:
            raise InitError(f"the row sums need at least {3 * _EDGE_ROWS} detector rows, got {nr}")
        a = np.arange(nc, dtype=np.float64) - (nc - 1) / 2 - float(offset_px)
        m = np.empty((nv, nr))
        U = np.empty((nv, nr))
        bad = [k for k in range(nv) if not np.all(np.isfinite(p[k]))]
        if bad:
            raise InitError(f"the projections hold NaN or Inf values (views {bad[:5]}{' ...' if len(bad) > 5 else ''})")
        sigma = float(np.sqrt(estimate_noise_variance(p)))
        for k in range(nv):  # one view at a time: no float64 copy of the whole stack
            pk = _without_zingers(np.asarray(p[k], dtype=np.float64), sigma)
            m[k] = pk.sum(1)
            U[k] = pk @ a
        keep = slice(_EDGE_ROWS, nr - _EDGE_ROWS)
        self._m_raw = m.copy()  # vertical_motion() registers them again, with an offset per view
        dz = _register(m, keep)
        m = np.stack([_shift(m[k], -dz[k], order=3, mode="nearest") for k in range(nv)])
        U = np.stack([_shift(U[k], -dz[k], order=3, mode="nearest") for k in range(nv)])
        uu, rr = _unit(geom.u), _unit(geom.ray)
        coef = _row_moments(U, uu)
        U_fit = np.column_stack([uu[:, 0], uu[:, 1], np.ones(nv)]) @ coef
        spread = float(np.sum((U - U.mean(0))[:, keep] ** 2))
        moments_fit = 1.0 - float(np.sum((U - U_fit)[:, keep] ** 2)) / spread if spread > 0 else 0.0
        # derivatives along the rows of the profiles smoothed by a Gaussian, and the profiles smoothed the same way: the
        # first-order relation holds for the smoothed profiles exactly, and the Gaussian's derivative is exact where a
        # finite difference of sharp profiles is not (central differences of a foam's 2-4 px cells overestimated the
        # tilt by 25 %)
        dU = _gaussian(U_fit, _SMOOTH_ROWS, axis=1, order=1)
        dW = _gaussian(rr[:, :2] @ coef[:2], _SMOOTH_ROWS, axis=1, order=1)
        dM = _gaussian(m.mean(0), _SMOOTH_ROWS, order=1)
        m = _gaussian(m, _SMOOTH_ROWS, axis=1)
        t = np.linspace(-1.0, 1.0, nv)[:, None]
        # roll, pitch, and what the registration left of a vertical drift (a quadratic in time)
        # (a drift constant in time is a per-row mean, which the double centring removes)
        cols = [dU, -dW, -t * dM[None, :], -(t * t) * dM[None, :]]
        X = np.column_stack([_double_centre(c)[:, keep].ravel() for c in cols])
        y = _double_centre(m)[:, keep].ravel()
        if not np.any(X[:, :2]):
            raise InitError("the row sums hold no signal for the tilt (an empty or featureless scan)")
        w = np.ones_like(y)
        for _ in range(4):
            sw = np.sqrt(w)
            beta, *_ = np.linalg.lstsq(X * sw[:, None], y * sw, rcond=None)
            res = y - X @ beta
            w = _robust_weights(res)
        dof = max(int(np.sum(w > 0)) - X.shape[1], 1)
        s2 = float(np.sum(w * res * res)) / dof
        N = (X * w[:, None]).T @ X
        try:
            Ni = np.linalg.inv(N)
        except np.linalg.LinAlgError as exc:
            raise InitError("the row sums cannot tell the tilt from a vertical drift (singular fit)") from exc
        sd_noise = np.sqrt(np.clip(s2 * np.diag(Ni)[:2], 0.0, None))
        sd = np.maximum(sd_noise, _clustered_sd(Ni, X * (w * res)[:, None], (nv, nr - 2 * _EDGE_ROWS))[:2])
        res0 = y - X[:, 2:] @ np.linalg.lstsq(X[:, 2:] * np.sqrt(w)[:, None], y * np.sqrt(w), rcond=None)[0]
        ss0, ss1 = float(np.sum(w * res0 * res0)), float(np.sum(w * res * res))
        explained = 1.0 - ss1 / ss0 if ss0 > 0 else 0.0
        self.estimate = AxisTiltEstimate(
            roll=float(beta[0]), pitch=float(beta[1]), roll_sd=float(sd[0]), pitch_sd=float(sd[1]), shifts_px=dz,
            explained=float(explained), moments_fit=float(moments_fit), n_rows=nr - 2 * _EDGE_ROWS,
            sd_inflation=float(np.max(sd / np.maximum(sd_noise, 1e-300))))
        # what misfit() needs: the smoothed profiles, the regressors per view, the weights of the fit, its residual
        self._m, self._dW, self._keep = m, dW, keep
        self._dU = _gaussian(uu[:, :2] @ coef[:2], _SMOOTH_ROWS, axis=1, order=1)
        self._ray, self._u = rr, uu
        self._w, self._drift = w, X[:, 2:]
        self._ss = ss1
        self._n_views = nv
        self._row_pitch = float(np.linalg.norm(geom.v[0]))  # vertical_motion(): pixels to length
        self._vertical = None  # vertical_motion(), measured once

    def vertical_motion(self) -> "VerticalMotion":
        """The sample's vertical lab translation per view from the registration of the row sums (:class:`VerticalMotion`).

        The shifts that bring each view's row-sum profile onto the mean one
        (as :attr:`AxisTiltEstimate.shifts_px`, here with a constant per view
        fitted beside each: an air level that drifts) are the slabs' vertical
        motion, measured without a reconstruction. They are fitted by a drift with
        acceleration, ``{1, t, t²}``, and a step at each view where :func:`pdvc.calibration.jolt_steps`
        finds one (``VERTICAL_STEP_Z`` standard deviations, ``VERTICAL_STEP_WINDOW``
        views each side); the fit averages the noise of the views' shifts (a rod's
        few features: 0.05-0.15 px per view at 40 rows). Measured once; every call returns that (read-only) result.
        """
        if self._vertical is not None:
            return self._vertical
        from ._driver import jolt_steps, series_noise

        dz = _register(self._m_raw, self._keep, offsets=True)
        nv = dz.size
        t = np.linspace(-1.0, 1.0, nv)
        steps = jolt_steps(dz, z=VERTICAL_STEP_Z, window=VERTICAL_STEP_WINDOW)
        cols = [np.ones(nv), t, t * t]
        cols += [(np.arange(nv) >= k).astype(float) for k in steps]
        H = np.column_stack(cols)
        c = np.linalg.lstsq(H, dz, rcond=None)[0]
        fit = H @ c
        fit = fit - fit.mean()
        res = dz - H @ c
        # the noise of one view's shift, as jolt_steps measures it, and how far the residual of the fit is above it
        # (model error: a motion the fit does not hold)
        noise = max(float(series_noise(dz)), 1e-12)
        dof = max(nv - H.shape[1], 1)
        misfit = float(_robust_std(res)) * np.sqrt(nv / dof) / noise
        f_stat = float(fit @ fit) / ((H.shape[1] - 1) * noise**2)
        translation = fit * self._row_pitch
        translation.flags.writeable = False
        steps.flags.writeable = False
        self._vertical = VerticalMotion(translation=translation, steps=steps, f_stat=f_stat, misfit=misfit, noise_px=noise)
        return self._vertical

    def misfit(self, rotvecs) -> float:
        """How far per-view poses' rotations are from the row sums: the weighted residual over the best constant tilt's.

        ``rotvecs`` (n_views, 3), the poses' rotation vectors (relative to the
        nominal geometry, as :class:`pdvc.Poses` holds them). Each view's
        tilt is read from its rotation, ``roll_k = -ω_k · r̂_k``, ``pitch_k =
        -ω_k · û_k`` (:func:`tilt_poses` inverted, view by view), the row
        sums are corrected by what those tilts change to first order, and the
        residual after the per-row means, the per-view offsets and the drift
        terms is weighted as in the fit. 1 for the constant tilt of
        :attr:`estimate`, more for poses the row sums agree with less. A
        rotation of the sample itself (the gauge) does not change it: the
        per-row means take it up, as the roll's regressor is the sinusoidal
        part of the rows' first moments only (a rotation about the axis the
        moments locate).
        """
        rv = np.asarray(rotvecs, dtype=np.float64)
        if rv.shape != (self._n_views, 3):
            raise InitError(f"rotvecs must have shape {(self._n_views, 3)}, got {rv.shape}")
        roll = -np.sum(rv * self._ray, axis=1)
        pitch = -np.sum(rv * self._u, axis=1)
        z = _double_centre(self._m - roll[:, None] * self._dU + pitch[:, None] * self._dW)[:, self._keep].ravel()
        sw = np.sqrt(self._w)
        D = self._drift
        r = z - D @ np.linalg.lstsq(D * sw[:, None], z * sw, rcond=None)[0]
        return float(np.sum(self._w * r * r)) / self._ss if self._ss > 0 else float("inf")


def estimate_axis_tilt(projections, geom: VectorGeometry, *, offset_px: float = 0.0) -> AxisTiltEstimate:
    """The rotation axis's constant tilt from the row sums of a parallel-beam scan (module docstring).

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) array
        Line integrals (any air level that is constant along a row, or uniform
        over a view, cancels). Not modified.
    geom : VectorGeometry
        Nominal parallel-beam geometry: a common vertical detector ``v``
        square to every view's ``u`` and ray.
    offset_px : float
        Column of the projected axis minus ``(n_cols - 1)/2``, e.g. from
        :func:`pdvc.calibration.estimate_axis_offset` (a wrong offset only
        adds a term that the per-row means and the registration absorb).

    Returns
    -------
    AxisTiltEstimate

    Raises
    ------
    InitError
        Not a parallel scan about one axis, too few views or rows, or no
        signal (a featureless or empty scan).
    """
    est = RowSumConsistency(projections, geom, offset_px=offset_px).estimate
    log.debug("row sums: roll %.4f° ± %.4f°, pitch %.4f° ± %.4f°, %.0f%% of the inconsistency explained",
              np.rad2deg(est.roll), np.rad2deg(est.roll_sd), np.rad2deg(est.pitch), np.rad2deg(est.pitch_sd),
              100 * est.explained)
    return est


def tilt_poses(geom: VectorGeometry, *, roll: float, pitch: float, offset_px: float = 0.0) -> Poses:
    """Per-view poses of a sample turning about the axis tilted by ``roll`` and ``pitch`` and offset by ``offset_px``.

    The constant lab rotation of :class:`AxisTiltEstimate` written in each
    view's sample frame, ``-(roll · r̂_k + pitch · û_k)``, first order in the
    tilt (:func:`pdvc.simulate.tilted_axis_poses` is exact), with the
    translations of :func:`pdvc.calibration.offset_poses`.
    """
    base = offset_poses(geom, offset_px)
    rot = -(float(roll) * _unit(geom.ray if geom.kind == "parallel" else geom.det_center - geom.src)
            + float(pitch) * _unit(geom.u))
    return Poses(rot, base.translations)
