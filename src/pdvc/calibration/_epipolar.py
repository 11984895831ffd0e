"""Epipolar consistency of cone-beam views: a criterion on the geometry that does not go through a reconstruction.

Two cone-beam views ``i``, ``j`` see every plane that holds both of their
sources. By Grangeat's formula each view gives, from its own projection
alone, the derivative of the 3D Radon transform of the sample across such a
plane; the two values must agree (Aichert et al. 2015, "Epipolar
consistency in transmission imaging", IEEE TMI 34(11)). In the
coordinates of a view's flat detector (origin at the foot ``P0`` of the
perpendicular from the source, at distance ``D``), a plane of unit normal
``n`` meets the detector in the line ``x m_x + y m_y = t``; with ``G̃ = G D
/ sqrt(D² + x² + y²)`` the cosine-weighted projection,

    ∂ρ R₃f(n, ρ)  =  (1 + t² / D²) · ∂t R₂G̃(m, t),

``∂t R₂G̃`` being the integral along the line of the derivative of ``G̃``
across it (derived in ``docs/method.md`` §5.21). The sign and scale are
the same in both views, since both see the same plane.

What the criterion needs of the data: line integrals; a sample inside the
field of view across the detector's width (a lateral truncation cuts the
lines); the planes used are those whose line crosses the detector from its
left to its right edge in both views, so that a rod longer than the field
of view (cut at the top and bottom) does not break it.

A rigid pose of the sample moves the source and the detector together, so
``D``, ``P0`` on the detector and the weighted images stay what they were:
they are computed once, and each geometry tried costs only the sampling of
its lines.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from ..errors import GeometryError, ShapeError
from ..geometry import Poses, VectorGeometry

__all__ = ["EpipolarViews", "epipolar_views", "epipolar_residuals", "epipolar_refine", "EpipolarFit", "view_pairs"]

# view pairs: each view with the views DEFAULT_SEPARATIONS (degrees) further on (pairs of nearby views see
# nearly the same planes, and their difference is mostly noise)
DEFAULT_SEPARATIONS = (45.0, 90.0, 135.0)
# planes per pair, spread over the rows the detector's height allows
DEFAULT_PLANES = 32
# the lines must stay this many pixels inside the top and bottom rows (the smoothing's and the derivative's reach)
_MARGIN = 3.0
# folds of the view pairs for the amplitudes' standard deviation (_fold_std)
_FOLDS = 8
# a line steeper than this (|m_y| below, i.e. more than 60 degrees from the rows) is not used
_MIN_MY = 0.5


def _frames(geom: VectorGeometry):
    """Per view: source C, unit u, unit v, unit normal a (away from the source), D, P0's pixel coordinates, pixel sizes."""
    C, d, u, v = geom.src, geom.det_center, geom.u, geom.v
    du, dv = np.linalg.norm(u, axis=1), np.linalg.norm(v, axis=1)
    eu, ev = u / du[:, None], v / dv[:, None]
    a = np.cross(eu, ev)
    a /= np.linalg.norm(a, axis=1)[:, None]
    sign = np.sign(np.einsum("ki,ki->k", d - C, a))
    a *= np.where(sign == 0, 1.0, sign)[:, None]
    D = np.einsum("ki,ki->k", d - C, a)
    p0 = C + D[:, None] * a
    nr, nc = geom.det_shape
    # pixel coordinates (row, col) of P0: pixel (i, j) is at d + (j - (nc-1)/2) u + (i - (nr-1)/2) v
    j0 = np.einsum("ki,ki->k", p0 - d, eu) / du + (nc - 1) / 2
    i0 = np.einsum("ki,ki->k", p0 - d, ev) / dv + (nr - 1) / 2
    return C, eu, ev, a, D, i0, j0, du, dv


@dataclass(frozen=True)
class EpipolarViews:
    """The cosine-weighted, smoothed gradients of each view, which rigid poses do not change.

    Attributes
    ----------
    gradients : (n_views, 2, n_rows, n_cols) float64
        Cubic B-spline coefficients (``scipy.ndimage.spline_filter``) of
        ``∂G̃/∂x`` and ``∂G̃/∂y`` (along ``u`` and ``v``) per unit length on
        the detector: the lines are sampled by cubic interpolation, so that
        the residuals are smooth in the geometry (linear interpolation has
        kinks that a Gauss–Newton step of a hundredth of a pixel sees).
    sigma : float
        Gaussian smoothing (pixels) applied before the derivative.
    i0, j0, D : (n_views,)
        Pixel coordinates of the foot of the perpendicular from the source, and the source-detector distance.
    """

    gradients: np.ndarray
    sigma: float
    i0: np.ndarray
    j0: np.ndarray
    D: np.ndarray
    det_shape: tuple


def epipolar_views(projections, geom: VectorGeometry, *, sigma: float = 1.0) -> EpipolarViews:
    """Weigh, smooth and differentiate each projection once (:class:`EpipolarViews`).

    ``projections`` are line integrals, ``(n_views, n_rows, n_cols)``; not modified.
    """
    from scipy import ndimage

    if geom.kind != "cone":
        raise GeometryError("epipolar consistency needs cone-beam views (kind 'cone'); parallel views share no source")
    p = np.asarray(projections, np.float32)
    if p.shape != (geom.n_views,) + tuple(geom.det_shape):
        raise ShapeError(f"projections must have shape {(geom.n_views,) + tuple(geom.det_shape)}, got {p.shape}")
    if not (np.isfinite(sigma) and sigma >= 0):
        raise ShapeError(f"sigma must be a finite number >= 0 (pixels), got {sigma!r}")
    _, _, _, _, D, i0, j0, du, dv = _frames(geom)
    nr, nc = geom.det_shape
    grads = np.empty((geom.n_views, 2, nr, nc), np.float64)
    jj, ii = np.meshgrid(np.arange(nc), np.arange(nr))
    for k in range(geom.n_views):
        x = (jj - j0[k]) * du[k]
        y = (ii - i0[k]) * dv[k]
        w = p[k] * (D[k] / np.sqrt(D[k] ** 2 + x**2 + y**2))
        if sigma > 0:
            w = ndimage.gaussian_filter(w, sigma, mode="nearest")
        gy, gx = np.gradient(w.astype(np.float64), dv[k], du[k])
        grads[k, 0] = ndimage.spline_filter(gx, order=3, mode="constant")
        grads[k, 1] = ndimage.spline_filter(gy, order=3, mode="constant")
    return EpipolarViews(grads, float(sigma), i0, j0, D, tuple(geom.det_shape))


def view_pairs(angles, separations: Sequence[float] = DEFAULT_SEPARATIONS) -> np.ndarray:
    """(n_pairs, 2) view indices: each view with the view nearest to each separation (degrees) further on."""
    ang = np.asarray(angles, float)
    pairs = set()
    for sep in separations:
        target = ang + np.deg2rad(sep)
        diff = np.angle(np.exp(1j * (target[:, None] - ang[None, :])))
        partner = np.argmin(np.abs(diff), axis=1)
        for k, j in enumerate(partner):
            if j != k and abs(diff[k, j]) < np.deg2rad(min(10.0, sep / 4)):
                pairs.add((min(k, j), max(k, j)))
    return np.array(sorted(pairs), int).reshape(-1, 2)


def _line_values(views: EpipolarViews, k: int, frame, normals: np.ndarray):
    """Grangeat's value of view ``k`` for each plane normal (n_planes, 3), and whether its line is usable."""
    from scipy import ndimage

    C, eu, ev, a, D, i0, j0, du, dv = frame
    nr, nc = views.det_shape
    nu, nv, na = normals @ eu[k], normals @ ev[k], normals @ a[k]
    s = np.sqrt(nu**2 + nv**2)
    ok = s > 1e-9
    s = np.where(ok, s, 1.0)
    mx, my = nu / s, nv / s
    t = -D[k] * na / s
    ok &= np.abs(my) >= _MIN_MY
    # the line's rows at the left and right edges (pixel units): y = (t - x m_x) / m_y
    x_edges = (np.array([-0.5, nc - 0.5]) - j0[k]) * du[k]
    with np.errstate(divide="ignore", invalid="ignore"):
        y_edges = (t[:, None] - x_edges[None, :] * mx[:, None]) / my[:, None]
    rows = y_edges / dv[k] + i0[k]
    ok &= np.all((rows >= _MARGIN) & (rows <= nr - 1 - _MARGIN), axis=1)
    # sample along the line across the detector's width, one sample per pixel of the smaller size
    step = float(min(du[k], dv[k]))
    half = 0.5 * nc * du[k] / np.maximum(np.abs(my), _MIN_MY) + 2 * step
    n_s = int(np.ceil(2 * half.max() / step)) + 1
    ls = (np.arange(n_s) - (n_s - 1) / 2) * step
    # the line's point nearest P0 is t m; along it, m_perp = (-m_y, m_x)
    x = t[:, None] * mx[:, None] - ls[None, :] * my[:, None]
    y = t[:, None] * my[:, None] + ls[None, :] * mx[:, None]
    cols = x / du[k] + j0[k]
    rws = y / dv[k] + i0[k]
    coords = np.stack([rws.ravel(), cols.ravel()])
    gx = ndimage.map_coordinates(views.gradients[k, 0], coords, order=3, mode="constant", cval=0.0, prefilter=False)
    gy = ndimage.map_coordinates(views.gradients[k, 1], coords, order=3, mode="constant", cval=0.0, prefilter=False)
    deriv = (gx.reshape(x.shape) * mx[:, None] + gy.reshape(x.shape) * my[:, None]).sum(axis=1) * step
    return (1.0 + t**2 / D[k] ** 2) * deriv, ok


def _plane_normals(Ci, Cj, axis, n_planes: int, kappa_max: float) -> np.ndarray:
    """Unit normals of ``n_planes`` planes through both sources, at angles in [-kappa_max, kappa_max] about their baseline."""
    b = Cj - Ci
    b /= np.linalg.norm(b)
    e1 = axis - (axis @ b) * b
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(b, e1)
    kap = np.linspace(-kappa_max, kappa_max, n_planes)
    return np.cos(kap)[:, None] * e1[None, :] + np.sin(kap)[:, None] * e2[None, :]


def epipolar_residuals(views: EpipolarViews, geom: VectorGeometry, pairs: np.ndarray, *, n_planes: int = DEFAULT_PLANES,
                       axis=(0.0, 0.0, 1.0), mask: Optional[np.ndarray] = None):
    """Differences of Grangeat's values of each pair of views on the planes through both sources.

    Returns ``(residuals, usable)``, both ``(n_pairs, n_planes)``: the
    difference (view ``i`` minus view ``j``) and whether both lines cross
    the detector (``mask``, when given, fixes which planes count, so that
    geometries compared use the same planes).
    """
    frame = _frames(geom)
    C, D = frame[0], frame[4]
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    nr = geom.det_shape[0]
    dv = frame[8]
    # planes up to the detector's half-height seen from the source
    kappa_max = float(np.arctan(0.5 * (nr - 2 * _MARGIN) * np.min(dv) / np.max(D)))
    res = np.zeros((len(pairs), n_planes))
    use = np.zeros((len(pairs), n_planes), bool)
    for q, (i, j) in enumerate(pairs):
        if np.linalg.norm(C[j] - C[i]) < 1e-9:
            continue
        normals = _plane_normals(C[i], C[j], axis, n_planes, kappa_max)
        vi, oki = _line_values(views, i, frame, normals)
        vj, okj = _line_values(views, j, frame, normals)
        res[q] = vi - vj
        use[q] = oki & okj
    if mask is not None:
        use = np.asarray(mask, bool)
    return np.where(use, res, 0.0), use


@dataclass(frozen=True)
class EpipolarFit:
    """Outcome of :func:`epipolar_refine`.

    Attributes
    ----------
    poses : Poses
        The poses given, moved by the amplitudes found along each field.
    amplitudes : (n_fields,)
    std : (n_fields,)
        Their standard deviation, from the spread of the amplitudes that
        folds of the view pairs would give on their own (``_fold_std``).
    rms_before, rms_after : float
        RMS of the consistency residuals (the same planes), at the poses given and at those returned.
    n_pairs, n_planes : int
        View pairs and planes used in all.
    """

    poses: Poses
    amplitudes: np.ndarray
    std: np.ndarray
    rms_before: float
    rms_after: float
    n_pairs: int
    n_planes: int


def epipolar_refine(projections, geom: VectorGeometry, poses: Poses, fields, *, center, angles, views: Optional[EpipolarViews] = None,
                    pairs: Optional[np.ndarray] = None, n_planes: int = DEFAULT_PLANES, sigma: float = 1.0, steps=None,
                    max_iter: int = 6) -> EpipolarFit:
    """Amplitudes along a few pose fields that make the views most consistent (Gauss–Newton, finite differences).

    Parameters
    ----------
    projections, geom
        Cone-beam line integrals and the geometry ``poses`` are relative to.
    poses : Poses
        Where to start (e.g. the calibration's).
    fields : sequence of (n_views, 6) arrays
        Per unit amplitude, sample pose parameters ``(tx, ty, tz, rx, ry, rz)`` about ``center``
        (:meth:`pdvc.geometry.Poses.to_params`); the poses tried are ``poses @ Poses.from_params(Σ a_k field_k)``.
    angles : (n_views,)
        Rotation angles (the pairs are chosen on them).
    steps : sequence of float, optional
        Finite-difference step per field. Default: a step that moves no
        pose parameter by more than 0.01 (length units or radians).
    max_iter : int
        Levenberg–Marquardt iterations (0: only the precision at ``poses``).
    """
    fields = [np.asarray(f, float) for f in fields]
    n = geom.n_views
    if not fields or any(f.shape != (n, 6) for f in fields):
        raise ShapeError(f"fields must be a non-empty sequence of ({n}, 6) arrays")
    c = np.asarray(center, float)
    if views is None:
        views = epipolar_views(projections, geom, sigma=sigma)
    if pairs is None:
        pairs = view_pairs(angles)
    if len(pairs) == 0:
        raise GeometryError("no pair of views at the separations needed for epipolar consistency")
    k = len(fields)
    h = np.array(steps, float) if steps is not None else np.array([0.01 / max(np.abs(f).max(), 1e-300) for f in fields])
    if h.shape != (len(fields),) or not np.all(np.isfinite(h) & (h > 0)):
        raise ShapeError(f"steps must be {len(fields)} finite numbers > 0, got {steps!r}")

    def posed(amp):
        d = sum(a * f for a, f in zip(amp, fields))
        return poses @ Poses.from_params(d, c)

    _, use = epipolar_residuals(views, geom.apply(poses), pairs, n_planes=n_planes)

    def resid(amp):
        r, _ = epipolar_residuals(views, geom.apply(posed(amp)), pairs, n_planes=n_planes, mask=use)
        return r[use]

    amp = np.zeros(k)
    r0 = resid(amp)
    r = r0
    lam = 1e-3
    for _ in range(max_iter):
        J = np.column_stack([(resid(amp + h[q] * np.eye(k)[q]) - r) / h[q] for q in range(k)])
        H = J.T @ J
        g = J.T @ r
        while True:
            step = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-300), g)
            r_new = resid(amp + step)
            if r_new @ r_new < r @ r:
                amp, r, lam = amp + step, r_new, lam / 3
                break
            lam *= 10
            if lam > 1e6:
                break
        if lam > 1e6 or np.all(np.abs(step) < 1e-3 * h):
            break
    J = np.column_stack([(resid(amp + h[q] * np.eye(k)[q]) - r) / h[q] for q in range(k)])
    std = _fold_std(J, r, pairs[np.nonzero(use)[0], 0], n)
    return EpipolarFit(posed(amp), amp, std, float(np.sqrt(np.mean(r0**2))), float(np.sqrt(np.mean(r**2))), len(pairs),
                       int(use.sum()))


def _fold_std(J, r, first_view, n_views: int, folds: int = _FOLDS) -> np.ndarray:
    """The amplitudes' standard deviation from their scatter over folds of the view pairs.

    The residuals of one pair's planes (and of pairs that share views)
    are correlated, through the smoothing and the lines' shared pixels, so
    their own scatter (``r² (JᵀJ)⁻¹``) says far less than what the data
    allow. Instead, each fold (pairs whose first view lies in one of
    ``folds`` consecutive blocks) takes one Gauss–Newton step from the
    solution on its own residuals; the spread of those steps over the
    folds, divided by sqrt(folds), is the standard deviation quoted.
    """
    fold = (first_view * folds) // n_views
    steps = []
    for f in range(folds):
        sel = fold == f
        Jf = J[sel]
        if sel.sum() <= J.shape[1]:
            continue
        steps.append(-np.linalg.lstsq(Jf, r[sel], rcond=None)[0])
    if len(steps) < 2:
        return np.full(J.shape[1], np.inf)
    return np.std(np.array(steps), axis=0, ddof=1) / np.sqrt(len(steps))
