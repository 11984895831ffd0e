"""Scan analysis for filtered back-projection: rotation axis, centre, angular weights.

Everything is estimated from the per-view vectors, so a corrected geometry
(views moved and tilted slightly) gets weights that match it.

* Rotation axis ``a`` (unit): cone beam, the normal of the least-squares
  plane through the source positions; parallel beam, the normal of the
  plane spanned by the ray directions. When that plane is undefined (fewer
  than 3 views, or sources on a line) the mean detector row step ``v`` is
  used instead. Only the line matters, not its sign: azimuths, fan angles
  and Parker weights are all measured counter-clockwise about the same
  ``a``, which makes them independent of the direction of rotation.
* Rotation centre ``c`` (cone beam): the centre of the least-squares
  (Kasa) circle through the sources, projected in that plane; the volume
  frame origin when the fit is degenerate.
* Angular weights: each view's azimuth ``phi_k`` about ``a`` (cone: of
  ``src - c``; parallel: of the ray direction, modulo pi). The views are
  sorted by azimuth (so view order, interleaving and several turns do not
  matter), and each view gets the width ``dtheta_k`` = half the gap to its
  neighbours (a midpoint rule, exact for irregular spacing).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..errors import GeometryError, ShortScanError
from ..geometry import VectorGeometry

logger = logging.getLogger(__name__)

#: A scan is "full" (closes the circle) when its largest angular gap is at
#: most this many times the second largest: a short scan has one gap (the
#: missing arc) far larger than all others, while irregular sampling, random
#: angles and several (even coincident) turns have no single outstanding gap.
FULL_SCAN_GAP_RATIO = 3.0


@dataclass(frozen=True)
class ScanWeights:
    """What :func:`scan_weights` found (angles in radians).

    Attributes
    ----------
    axis : (3,) float64
        Unit rotation-axis direction used.
    center : (3,) float64
        Rotation centre used (cone beam), or the origin (parallel beam).
    dtheta : (n_views,) float64
        Angular quadrature width of each view.
    redundancy : (n_views, n_cols) float64
        Redundancy weight per view and detector column (1/2 for a full
        cone-beam scan, Parker weights for a short scan, 1 for parallel).
    full : bool
        Whether the scan was treated as closing its period (2 pi cone, pi parallel).
    coverage : float
        Angular range covered: the period minus the largest gap.
    kind : str
        ``"full"``, ``"short"`` (Parker) or ``"partial"`` (no redundancy weighting).
    """

    axis: np.ndarray
    center: np.ndarray
    dtheta: np.ndarray
    redundancy: np.ndarray
    full: bool
    coverage: float
    kind: str


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _plane_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal ``e1, e2`` with ``e1 x e2 = axis``."""
    trial = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = _unit(trial - (trial @ axis) * axis)
    e2 = np.cross(axis, e1)
    return e1, e2


def check_axis(axis) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.linalg.norm(a) == 0:
        raise GeometryError(f"axis must be a non-zero finite (x, y, z) direction, got {axis!r}")
    return _unit(a)


def check_center(center) -> np.ndarray:
    c = np.asarray(center, dtype=np.float64)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise GeometryError(f"center must be a finite (x, y, z) point, got {center!r}")
    return c


def estimate_axis(geom: VectorGeometry) -> np.ndarray:
    """Unit rotation-axis direction estimated from the vectors (see module notes)."""
    if geom.kind == "cone":
        pts = geom.src - geom.src.mean(axis=0)
    else:
        pts = geom.ray / np.linalg.norm(geom.ray, axis=1, keepdims=True)
    fallback = _unit(np.mean(geom.v / np.linalg.norm(geom.v, axis=1, keepdims=True), axis=0))
    if geom.n_views < 3 and geom.kind == "cone":
        return fallback
    _, s, vt = np.linalg.svd(pts, full_matrices=True)
    # plane well defined: the two in-plane singular values clearly above the third
    s = np.concatenate([s, np.zeros(3 - s.size)])
    if s[1] <= 1e-6 * s[0]:
        return fallback
    a = vt[2]
    # orient like the detector rows (cosmetic: keeps +z for nominal scans)
    return a if a @ fallback >= 0 else -a


def estimate_center(geom: VectorGeometry, axis: np.ndarray) -> np.ndarray:
    """Rotation centre of a cone-beam scan: centre of the source circle (see module notes)."""
    src = geom.src
    mean = src.mean(axis=0)
    if geom.n_views < 3:
        return np.zeros(3)
    e1, e2 = _plane_basis(axis)
    x, y = (src - mean) @ e1, (src - mean) @ e2
    A = np.stack([x, y, np.ones_like(x)], axis=1)
    rhs = -(x * x + y * y)
    sol, _, rank, sv = np.linalg.lstsq(A, rhs, rcond=None)
    if rank < 3 or sv[-1] <= 1e-9 * sv[0]:
        return np.zeros(3)
    cx, cy = -sol[0] / 2, -sol[1] / 2
    return mean + cx * e1 + cy * e2


def _azimuths(geom: VectorGeometry, axis: np.ndarray, center: np.ndarray) -> np.ndarray:
    e1, e2 = _plane_basis(axis)
    if geom.kind == "cone":
        r = geom.src - center
        return np.arctan2(r @ e2, r @ e1)
    r = geom.ray
    return np.arctan2(r @ e2, r @ e1)


#: Sorted neighbours closer than this fraction of the mean angular step are
#: one sampling position (e.g. the same angle in several turns): they share
#: its width equally instead of the middle ones getting almost nothing.
CLUSTER_FRACTION = 0.25


def _widths(sorted_phi: np.ndarray, period: float, circular: bool) -> np.ndarray:
    """Midpoint-rule widths of sorted angles (any spacing).

    ``circular``: the angles close the period (the last gap wraps around);
    otherwise they form an arc whose end views get their inner half gap twice.
    Runs of views closer than ``CLUSTER_FRACTION`` x the mean step are merged
    into one node at their mean angle, and share the node's width.
    """
    n = sorted_phi.size
    if n == 1:
        return np.array([period / 2])
    if circular:
        # rotate so that the wrap-around gap is the largest one (never inside a cluster)
        gaps = np.diff(np.concatenate([sorted_phi, [sorted_phi[0] + period]]))
        start = (int(np.argmax(gaps)) + 1) % n
        phi = np.concatenate([sorted_phi[start:], sorted_phi[:start] + period])
        mean_step = period / n
    else:
        start = 0
        phi = sorted_phi
        mean_step = (phi[-1] - phi[0]) / (n - 1)
    new_node = np.concatenate([[True], np.diff(phi) >= CLUSTER_FRACTION * mean_step])
    node = np.cumsum(new_node) - 1
    count = np.bincount(node)
    centre = np.bincount(node, weights=phi) / count
    m = centre.size
    if m == 1:
        node_w = np.array([period if circular else period / 2])
    else:
        g = np.diff(centre)
        if circular:
            wrap = centre[0] + period - centre[-1]
            g = np.concatenate([[wrap], g, [wrap]])
        else:
            g = np.concatenate([[g[0]], g, [g[-1]]])
        node_w = 0.5 * (g[:-1] + g[1:])
    w = node_w[node] / count[node]
    return np.roll(w, start)


def fan_angles(geom: VectorGeometry, axis: np.ndarray, center: np.ndarray) -> np.ndarray:
    """Fan angle of every detector column, ``(n_views, n_cols)`` radians.

    Angle about ``axis`` (counter-clockwise) from the ray ``src -> center``
    to the ray ``src -> pixel`` through the detector's middle row.
    """
    nc = geom.det_shape[1]
    j = np.arange(nc) - (nc - 1) / 2
    src = geom.src
    pix = geom.det_center[:, None, :] + j[None, :, None] * geom.u[:, None, :]
    e = pix - src[:, None, :]
    r = center - src
    e = e - (e @ axis)[..., None] * axis
    r = r - (r @ axis)[:, None] * axis
    cross = np.cross(r[:, None, :], e) @ axis
    dot = np.einsum("vk,vjk->vj", r, e)
    return np.arctan2(cross, dot)


def parker_weights(beta: np.ndarray, gamma: np.ndarray, delta: float) -> np.ndarray:
    """Parker short-scan weights, generalised to an over-scan ``delta`` (Wesarg et al. 2002).

    Parameters
    ----------
    beta : (n_views, 1) array, radians
        Source angle from the start of the arc, in ``[0, pi + 2 delta]``.
    gamma : (n_views, n_cols) array, radians
        Fan angle, same orientation as ``beta``; clipped to ``|gamma| < delta``.
    delta : float, radians
        Half the over-scan beyond pi (``delta >= `` the half fan angle for
        exact redundancy).

    Returns
    -------
    (n_views, n_cols) float64
        Weights with ``w(b, g) + w(b + pi + 2 g, -g) = 1``.
    """
    g = np.clip(gamma, -delta * (1 - 1e-9), delta * (1 - 1e-9))
    b = np.broadcast_to(beta, g.shape)
    w = np.ones(g.shape)
    rise = b < 2 * (delta - g)
    w[rise] = np.sin(np.pi / 4 * b[rise] / (delta - g[rise])) ** 2
    fall = b > np.pi - 2 * g
    w[fall] = np.sin(np.pi / 4 * np.maximum(np.pi + 2 * delta - b[fall], 0.0) / (delta + g[fall])) ** 2
    return w


def scan_weights(geom: VectorGeometry, *, axis=None, center=None, short_scan="auto") -> ScanWeights:
    """Axis, centre, per-view angular widths and redundancy weights of a scan.

    Parameters
    ----------
    geom : VectorGeometry
        Cone or parallel beam, at least 2 views.
    axis : (3,) array, optional
        Rotation-axis direction; estimated from the vectors if None.
    center : (3,) array, optional
        Rotation centre (cone beam), length units; estimated if None.
    short_scan : {"auto", True, False}
        Cone beam only. "auto": a full scan (weight 1/2) when the largest gap
        between the sorted view azimuths is at most ``FULL_SCAN_GAP_RATIO``
        times the second largest and below half the period; otherwise
        Parker weights over the arc that ends at the largest gap. True:
        always Parker. False: never (an incomplete arc then reconstructs
        with limited-angle errors).

    Returns
    -------
    ScanWeights
    """
    if geom.n_views < 2:
        raise GeometryError(f"geom must have at least 2 views for filtered back-projection, got {geom.n_views}")
    if short_scan not in ("auto", True, False):
        raise GeometryError(f"short_scan must be 'auto', True or False, got {short_scan!r}")
    a = estimate_axis(geom) if axis is None else check_axis(axis)
    nc = geom.det_shape[1]
    cone = geom.kind == "cone"
    if cone:
        c = estimate_center(geom, a) if center is None else check_center(center)
    else:
        c = np.zeros(3)
    period = 2 * np.pi if cone else np.pi
    phi = np.mod(_azimuths(geom, a, c), period)
    order = np.argsort(phi, kind="stable")
    sphi = phi[order]
    gaps = np.diff(np.concatenate([sphi, [sphi[0] + period]]))
    i_big = int(np.argmax(gaps))
    big = float(gaps[i_big])
    second = float(np.partition(gaps, -2)[-2])
    closes = big <= FULL_SCAN_GAP_RATIO * second and big < period / 2
    coverage = period - big
    dtheta = np.empty(geom.n_views)
    if not cone:
        full = bool(closes)
        if not full:
            logger.warning(
                "parallel scan covers %.1f deg of the 180 deg needed: limited-angle reconstruction",
                np.degrees(coverage),
            )
        arc = np.roll(sphi, -(i_big + 1))
        arc_order = np.roll(order, -(i_big + 1))
        if full:
            dtheta[order] = _widths(sphi, period, True)
        else:
            arc = np.mod(arc - arc[0], period)
            dtheta[arc_order] = _widths(arc, period, False)
        red = np.ones((geom.n_views, nc))
        return ScanWeights(a, c, dtheta, red, full, coverage, "full" if full else "partial")

    use_parker = (short_scan == "auto" and not closes) or short_scan is True
    if not use_parker:
        if closes:
            dtheta[order] = _widths(sphi, period, True)
            kind = "full"
        else:
            arc_order = np.roll(order, -(i_big + 1))
            arc = np.mod(np.roll(sphi, -(i_big + 1)) - sphi[(i_big + 1) % sphi.size], period)
            dtheta[arc_order] = _widths(arc, period, False)
            kind = "partial"
            logger.warning(
                "cone scan covers %.1f deg, not a full turn, and short_scan=False: "
                "no redundancy weighting, expect limited-angle errors",
                np.degrees(coverage),
            )
        red = np.full((geom.n_views, nc), 0.5)
        return ScanWeights(a, c, dtheta, red, kind == "full", coverage, kind)

    # Parker short scan over the arc that starts after the largest gap
    start = sphi[(i_big + 1) % sphi.size]
    beta = np.mod(phi - start, period)
    arc_order = np.argsort(beta, kind="stable")
    dtheta[arc_order] = _widths(beta[arc_order], period, False)
    span = float(beta.max())
    gamma = fan_angles(geom, a, c)
    half_fan = float(np.max(np.abs(gamma)))
    delta = (span - np.pi) / 2
    step = span / max(geom.n_views - 1, 1)
    if delta < half_fan - step:  # one angular step of tolerance; gamma is clipped to delta
        raise ShortScanError(
            f"short scan covers {np.degrees(span):.1f} deg but a short scan needs at least 180 deg + fan angle "
            f"= {np.degrees(np.pi + 2 * half_fan):.1f} deg; pass short_scan=False to back-project the "
            "incomplete data without redundancy weights (limited-angle errors)"
        )
    delta = max(delta, 1e-6)
    red = parker_weights(beta[:, None], gamma, delta)
    logger.info(
        "short scan of %.1f deg (fan %.1f deg): Parker weights with delta %.2f deg",
        np.degrees(span),
        np.degrees(2 * half_fan),
        np.degrees(delta),
    )
    return ScanWeights(a, c, dtheta, red, False, coverage, "short")
