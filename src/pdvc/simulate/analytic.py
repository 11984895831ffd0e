"""Exact line integrals of ellipsoid phantoms for any per-view vector geometry.

This is the reference the voxel projectors are judged against, so it is
written for correctness first: the chord of a ray through an ellipsoid is
solved in closed form (the quadratic of the ray in the ellipsoid's unit-ball
frame), in float64, and the only approximation is the optional averaging of
sub-rays over the pixel area.

Speed comes from culling: for each view and ellipsoid the detector box of the
ellipsoid's bounding sphere is computed exactly (the tangent cone from the
source for cone beam, the sphere's oblique shadow for parallel beam) and only
pixels in it are visited. When the tangent cone reaches the plane through the
source parallel to the detector (the sphere beside or around the source) the
whole detector is visited instead.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..errors import InputTypeError
from ..geometry import VectorGeometry
from ._checks import as_int
from .phantoms import EllipsoidPhantom

__all__ = ["project_analytic"]

# The culling box is widened by this many pixels on each side (round-off in
# the box computation; the chord at the box edge is zero anyway).
_BOX_MARGIN_PX = 1e-6
# Relative inflation of bounding-sphere radii for the same reason.
_RADIUS_INFLATION = 1e-7
# Views are processed in chunks so that the per (view, ellipsoid) work arrays stay small.
_WORK_BYTES = 64 * 2**20


@numba.njit(cache=True)
def _cross(a0, a1, a2, b0, b1, b2):  # pragma: no cover - compiled
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@numba.njit(parallel=True, cache=True)
def _prepare_kernel(vectors, is_cone, nr, nc, M, C, rad, cull, boxes, pre):  # pragma: no cover - compiled
    """Per (view, ellipsoid): detector box of the bounding sphere and the
    ray quantities in the ellipsoid's unit-ball frame.

    boxes[k, e] = (row0, row1, col0, col1), inclusive; row0 > row1 when empty.
    pre[k, e] (cone)     = M(src - c), M(d - src), M u, M v
    pre[k, e] (parallel) = M(d - c),   M ray,     M u, M v
    """
    n_views = vectors.shape[0]
    n_ell = C.shape[0]
    for k in numba.prange(n_views):
        s0, s1, s2 = vectors[k, 0], vectors[k, 1], vectors[k, 2]
        d0, d1, d2 = vectors[k, 3], vectors[k, 4], vectors[k, 5]
        u0, u1, u2 = vectors[k, 6], vectors[k, 7], vectors[k, 8]
        v0, v1, v2 = vectors[k, 9], vectors[k, 10], vectors[k, 11]
        n0, n1, n2 = _cross(u0, u1, u2, v0, v1, v2)
        nn = n0 * n0 + n1 * n1 + n2 * n2
        # dual vectors: hit - d = a u + b v  <=>  a = (hit - d).ut, b = (hit - d).vt
        a0, a1, a2 = _cross(v0, v1, v2, n0, n1, n2)
        ut0, ut1, ut2 = a0 / nn, a1 / nn, a2 / nn
        b0, b1, b2 = _cross(n0, n1, n2, u0, u1, u2)
        vt0, vt1, vt2 = b0 / nn, b1 / nn, b2 / nn
        utut = ut0 * ut0 + ut1 * ut1 + ut2 * ut2
        vtvt = vt0 * vt0 + vt1 * vt1 + vt2 * vt2
        for e in range(n_ell):
            c0, c1, c2 = C[e, 0], C[e, 1], C[e, 2]
            # -- unit-frame quantities ------------------------------------------
            if is_cone:
                x0, x1, x2 = s0 - c0, s1 - c1, s2 - c2
                y0, y1, y2 = d0 - s0, d1 - s1, d2 - s2
            else:
                x0, x1, x2 = d0 - c0, d1 - c1, d2 - c2
                y0, y1, y2 = s0, s1, s2
            for i in range(3):
                pre[k, e, i] = M[e, i, 0] * x0 + M[e, i, 1] * x1 + M[e, i, 2] * x2
                pre[k, e, 3 + i] = M[e, i, 0] * y0 + M[e, i, 1] * y1 + M[e, i, 2] * y2
                pre[k, e, 6 + i] = M[e, i, 0] * u0 + M[e, i, 1] * u1 + M[e, i, 2] * u2
                pre[k, e, 9 + i] = M[e, i, 0] * v0 + M[e, i, 1] * v1 + M[e, i, 2] * v2
            # -- detector box of the bounding sphere ----------------------------
            full = not cull
            cmin = 0.0
            cmax = 0.0
            rmin = 0.0
            rmax = 0.0
            rho = rad[e] * (1.0 + _RADIUS_INFLATION)
            if not full and is_cone:
                e0, e1, e2 = c0 - s0, c1 - s1, c2 - s2
                dist = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
                if dist <= rho * (1.0 + 1e-6):
                    full = True  # source inside (or on) the bounding sphere
                else:
                    e0, e1, e2 = e0 / dist, e1 / dist, e2 / dist
                    sin_a = rho / dist
                    s2a = sin_a * sin_a
                    ne = n0 * e0 + n1 * e1 + n2 * e2
                    A = ne * ne - s2a * nn
                    if A <= 1e-9 * nn:
                        full = True  # tangent cone reaches the plane through the source
                    else:
                        # column a(w) = a_src + L (w.ut)/(w.n) over the tangent cone
                        # of half-angle alpha about e; the extremes of the ratio are
                        # where the plane w.(ut - k n) = 0 is tangent to the cone.
                        L = n0 * (d0 - s0) + n1 * (d1 - s1) + n2 * (d2 - s2)
                        a_src = (s0 - d0) * ut0 + (s1 - d1) * ut1 + (s2 - d2) * ut2
                        b_src = (s0 - d0) * vt0 + (s1 - d1) * vt1 + (s2 - d2) * vt2
                        ue = ut0 * e0 + ut1 * e1 + ut2 * e2
                        ve = vt0 * e0 + vt1 * e1 + vt2 * e2
                        hw = sin_a * math.sqrt(max(ue * ue * nn + utut * A, 0.0)) / A
                        kc = ue * ne / A
                        ka, kb = L * (kc - hw), L * (kc + hw)
                        cmin, cmax = a_src + min(ka, kb), a_src + max(ka, kb)
                        hw = sin_a * math.sqrt(max(ve * ve * nn + vtvt * A, 0.0)) / A
                        kc = ve * ne / A
                        ka, kb = L * (kc - hw), L * (kc + hw)
                        rmin, rmax = b_src + min(ka, kb), b_src + max(ka, kb)
            elif not full:
                # parallel: a(x) = ((x - d) - (n.(x - d))/(n.r) r).ut is affine in x
                nr_ = n0 * s0 + n1 * s1 + n2 * s2
                x0, x1, x2 = c0 - d0, c1 - d1, c2 - d2
                tt = (n0 * x0 + n1 * x1 + n2 * x2) / nr_
                h0, h1, h2 = x0 - tt * s0, x1 - tt * s1, x2 - tt * s2
                ac = h0 * ut0 + h1 * ut1 + h2 * ut2
                bc = h0 * vt0 + h1 * vt1 + h2 * vt2
                ru = (s0 * ut0 + s1 * ut1 + s2 * ut2) / nr_
                rv = (s0 * vt0 + s1 * vt1 + s2 * vt2) / nr_
                g0, g1, g2 = ut0 - n0 * ru, ut1 - n1 * ru, ut2 - n2 * ru
                ga = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
                g0, g1, g2 = vt0 - n0 * rv, vt1 - n1 * rv, vt2 - n2 * rv
                gb = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
                cmin, cmax = ac - rho * ga, ac + rho * ga
                rmin, rmax = bc - rho * gb, bc + rho * gb
            if not full and not (
                math.isfinite(cmin) and math.isfinite(cmax) and math.isfinite(rmin) and math.isfinite(rmax)
            ):
                full = True
            if full:
                boxes[k, e, 0] = 0
                boxes[k, e, 1] = nr - 1
                boxes[k, e, 2] = 0
                boxes[k, e, 3] = nc - 1
                continue
            # pixel j covers columns [j - 0.5, j + 0.5] around its centre
            fc0 = np.ceil(cmin + (nc - 1) / 2.0 - 0.5 - _BOX_MARGIN_PX)
            fc1 = np.floor(cmax + (nc - 1) / 2.0 + 0.5 + _BOX_MARGIN_PX)
            fr0 = np.ceil(rmin + (nr - 1) / 2.0 - 0.5 - _BOX_MARGIN_PX)
            fr1 = np.floor(rmax + (nr - 1) / 2.0 + 0.5 + _BOX_MARGIN_PX)
            if fc1 < 0 or fr1 < 0 or fc0 > nc - 1 or fr0 > nr - 1:
                boxes[k, e, 0] = 1
                boxes[k, e, 1] = 0
                boxes[k, e, 2] = 1
                boxes[k, e, 3] = 0
                continue
            # clamp as floats first: the unclamped values may not fit an int
            boxes[k, e, 0] = int(max(0.0, fr0))
            boxes[k, e, 1] = int(min(nr - 1.0, fr1))
            boxes[k, e, 2] = int(max(0.0, fc0))
            boxes[k, e, 3] = int(min(nc - 1.0, fc1))


@numba.njit(parallel=True, cache=True)
def _project_kernel(vectors, is_cone, nr, nc, ss, dens, boxes, pre, out):  # pragma: no cover - compiled
    n_views = vectors.shape[0]
    n_ell = dens.shape[0]
    offs = np.empty(ss)
    for a in range(ss):
        offs[a] = (a + 0.5) / ss - 0.5
    inv_ss2 = 1.0 / (ss * ss)
    cc = (nc - 1) / 2.0
    rc = (nr - 1) / 2.0
    for idx in numba.prange(n_views * nr):
        k = idx // nr
        i = idx - k * nr
        row = np.zeros(nc)
        s0, s1, s2 = vectors[k, 0], vectors[k, 1], vectors[k, 2]
        d0, d1, d2 = vectors[k, 3], vectors[k, 4], vectors[k, 5]
        u0, u1, u2 = vectors[k, 6], vectors[k, 7], vectors[k, 8]
        v0, v1, v2 = vectors[k, 9], vectors[k, 10], vectors[k, 11]
        rnorm = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
        for e in range(n_ell):
            if boxes[k, e, 0] > i or boxes[k, e, 1] < i:
                continue
            j0 = boxes[k, e, 2]
            j1 = boxes[k, e, 3]
            p0, p1, p2 = pre[k, e, 0], pre[k, e, 1], pre[k, e, 2]
            q0, q1, q2 = pre[k, e, 3], pre[k, e, 4], pre[k, e, 5]
            qu0, qu1, qu2 = pre[k, e, 6], pre[k, e, 7], pre[k, e, 8]
            qv0, qv1, qv2 = pre[k, e, 9], pre[k, e, 10], pre[k, e, 11]
            de = dens[e]
            for j in range(j0, j1 + 1):
                acc = 0.0
                for sr in range(ss):
                    beta = i - rc + offs[sr]
                    for sc in range(ss):
                        alpha = j - cc + offs[sc]
                        if is_cone:
                            # ray src + t w, w = (d + alpha u + beta v) - src; unit frame p + t q
                            a0 = q0 + alpha * qu0 + beta * qv0
                            a1 = q1 + alpha * qu1 + beta * qv1
                            a2 = q2 + alpha * qu2 + beta * qv2
                            qq = a0 * a0 + a1 * a1 + a2 * a2
                            t0 = -(p0 * a0 + p1 * a1 + p2 * a2) / qq
                            c0 = p0 + t0 * a0
                            c1 = p1 + t0 * a1
                            c2 = p2 + t0 * a2
                            h2 = (1.0 - (c0 * c0 + c1 * c1 + c2 * c2)) / qq
                            if h2 <= 0.0:
                                continue
                            h = math.sqrt(h2)
                            t_hi = t0 + h
                            if t_hi <= 0.0:
                                continue  # behind the source
                            t_lo = t0 - h
                            if t_lo < 0.0:
                                t_lo = 0.0
                            w0 = d0 - s0 + alpha * u0 + beta * v0
                            w1 = d1 - s1 + alpha * u1 + beta * v1
                            w2 = d2 - s2 + alpha * u2 + beta * v2
                            acc += (t_hi - t_lo) * math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
                        else:
                            # line x(alpha, beta) + t ray; unit frame p + t q
                            b0 = p0 + alpha * qu0 + beta * qv0
                            b1 = p1 + alpha * qu1 + beta * qv1
                            b2 = p2 + alpha * qu2 + beta * qv2
                            qq = q0 * q0 + q1 * q1 + q2 * q2
                            t0 = -(b0 * q0 + b1 * q1 + b2 * q2) / qq
                            c0 = b0 + t0 * q0
                            c1 = b1 + t0 * q1
                            c2 = b2 + t0 * q2
                            h2 = (1.0 - (c0 * c0 + c1 * c1 + c2 * c2)) / qq
                            if h2 <= 0.0:
                                continue
                            acc += 2.0 * math.sqrt(h2) * rnorm
                row[j] += de * acc * inv_ss2
        for j in range(nc):
            out[k, i, j] = row[j]


def project_analytic(
    phantom: EllipsoidPhantom, geom: VectorGeometry, *, supersampling: int = 1, _cull: bool = True
) -> np.ndarray:
    """Exact line integrals of an ellipsoid phantom.

    For every pixel the line integral ``Σ_n density_n · chord_n`` of the
    ray through the pixel centre, ``d + (j - (n_cols-1)/2) u + (i -
    (n_rows-1)/2) v`` (``DESIGN.md`` §1):

    * cone beam: the half-line from the source through the pixel (matter
      behind the source does not count; the line is not cut at the
      detector, which is assumed to lie beyond the object);
    * parallel beam: the whole line through the pixel along ``ray``.

    Parameters
    ----------
    phantom : EllipsoidPhantom
    geom : VectorGeometry
        Per-view vectors of any orientation, cone or parallel.
    supersampling : int, >= 1
        ``s``: each pixel is the mean over ``s x s`` sub-rays through the
        points ``d + (j - (n_cols-1)/2 + o_a) u + (i - (n_rows-1)/2 + o_b) v``
        with ``o = (k + 0.5)/s - 0.5`` (uniform over the pixel area): the
        detector's area integration, to second order in the pixel size.

    Returns
    -------
    (n_views, n_rows, n_cols) float32, dimensionless
        Line integrals (attenuation in 1/length times length). Computed in
        float64 and rounded once.

    Notes
    -----
    Work is O(views x pixels covered x ellipsoids x s²): pixels outside an
    ellipsoid's bounding-sphere shadow are never visited. Parallel over
    (view, row) pairs with numba.
    """
    if not isinstance(phantom, EllipsoidPhantom):
        raise InputTypeError(f"phantom must be an EllipsoidPhantom, got {type(phantom).__name__}")
    if not isinstance(geom, VectorGeometry):
        raise InputTypeError(f"geom must be a VectorGeometry, got {type(geom).__name__}")
    ss = as_int(supersampling, "supersampling", minimum=1)
    nr, nc = geom.det_shape
    n_views, n_ell = geom.n_views, phantom.n_ellipsoids
    out = np.zeros((n_views, nr, nc), dtype=np.float32)
    if n_ell == 0:
        return out
    # writable C-ordered float64 copies: one compiled signature for every call
    vectors = np.array(geom.vectors, dtype=np.float64, order="C")
    is_cone = geom.kind == "cone"
    maps = np.array(phantom.unit_maps(), dtype=np.float64, order="C")
    centers = np.array(phantom.center, dtype=np.float64, order="C")
    radii = np.array(phantom.bounding_radius, dtype=np.float64, order="C")
    dens = np.array(phantom.density, dtype=np.float64, order="C")
    # per (view, ellipsoid) work arrays take 128 bytes; keep them under ~64 MB
    chunk = max(1, min(n_views, _WORK_BYTES // (128 * n_ell)))
    for v0 in range(0, n_views, chunk):
        vec = vectors[v0 : v0 + chunk]
        boxes = np.empty((vec.shape[0], n_ell, 4), dtype=np.int64)
        pre = np.empty((vec.shape[0], n_ell, 12), dtype=np.float64)
        _prepare_kernel(vec, is_cone, nr, nc, maps, centers, radii, bool(_cull), boxes, pre)
        _project_kernel(vec, is_cone, nr, nc, ss, dens, boxes, pre, out[v0 : v0 + chunk])
    return out
