"""A smooth background per view, estimated with the motion and profiled out of the normal equations.

What a rigid motion of the sample cannot explain but a few smooth numbers
per view can: an air level left by an imperfect flat field (a constant per
view, drifting in time), a gain ramp across the detector, the slowly varying
attenuation of material outside the reconstructed box (a region-of-interest
scan). The measured view is modelled as ``s = Π f + Φ c``, ``Φ`` the
monomials ``u^a v^b`` (``a + b ≤ degree``) of the detector coordinates
scaled to [-1, 1], ``c`` free per view. Eliminating ``c`` (variable
projection) leaves the rigid problem with

    M' = M - C A⁻¹ Cᵀ,   b' = b - C A⁻¹ e,   rss' = rss - eᵀ A⁻¹ e,

``A = Φ W Φᵀ``, ``C = G W Φᵀ``, ``e = Φ W ρ`` (``G`` the six
sensitivities, ``ρ`` the residual): exactly the normal equations, step and
χ of the joint problem minimised over ``c``. Everything downstream (the
Gauss–Newton and PGD solves, χ, the per-view SNR) uses them unchanged.
An offset (degree 0) needs only ``Σ w g`` besides what the fused pass
already sums (:func:`profile_offset`): no extra cost. Degrees 1 and 2 compute
the sensitivity images (:func:`pdvc.projectors.jacobian`, threaded, chunks
of views of ~256 MiB) instead of the fused reduction: 1.1 × its time at one
thread.
"""

from __future__ import annotations

import numpy as np

from ..projectors import ViewReduction, jacobian, reduce_views

__all__ = ["background_basis", "without_background", "reduce_views_background", "profile_offset", "view_offset", "auto_background",
           "BACKGROUND_DEGREES", "AUTO_OFFSET_SIGMA", "AUTO_DEGREE"]

BACKGROUND_DEGREES = (0, 1, 2)
# The calibration's background = "auto" fits a background of degree AUTO_DEGREE (and measures its first round again
# with it) when the per-view offsets of the first round's residual, at the poses that round measured, vary from view
# to view by AUTO_OFFSET_SIGMA noise standard deviations of the full-resolution projections or more (RMS about their
# mean; docs/method.md §5.10). Tuning cases: clean ≤ 0.046, an air level drifting by 0.05 ≥ 0.297. At the poses
# measured, not at the start: a translation along a cone beam changes the magnification and with it the projected
# mass, so a large motion still to be found shows as a per-view offset too.
AUTO_OFFSET_SIGMA = 0.12
AUTO_DEGREE = 1
_CHUNK_BYTES = 256 * 2**20


def background_basis(det_shape, degree: int) -> np.ndarray:
    """``(K, n_rows, n_cols)`` monomials ``u^a v^b``, ``a + b ≤ degree``, u and v in [-1, 1] across the detector."""
    if degree not in BACKGROUND_DEGREES:
        raise ValueError(f"background degree must be one of {BACKGROUND_DEGREES}, got {degree!r}")
    nr, nc = det_shape
    v = np.linspace(-1.0, 1.0, nr) if nr > 1 else np.zeros(1)
    u = np.linspace(-1.0, 1.0, nc) if nc > 1 else np.zeros(1)
    vv, uu = np.meshgrid(v, u, indexing="ij")
    return np.stack([uu**a * vv**b for d in range(degree + 1) for b in range(d + 1) for a in (d - b,)])


def without_background(residual, degree: int, weights=None) -> np.ndarray:
    """``residual`` (views, rows, cols) less, view by view, the polynomial of ``degree`` in the detector coordinates
    (:func:`background_basis`) that fits it best by least squares weighted by ``weights`` (broadcastable to it;
    pixels of weight 0 do not count). Float64."""
    d = np.asarray(residual, np.float64)
    n = d.shape[0]
    phi = background_basis(d.shape[1:], degree).reshape(-1, d[0].size)
    flat = d.reshape(n, -1)
    w = np.broadcast_to(np.ones(1) if weights is None else np.asarray(weights, np.float64), d.shape).reshape(n, -1)
    out = np.empty_like(flat)
    for k in range(n):
        pw = phi * w[k]
        c = np.linalg.lstsq(pw @ phi.T, pw @ flat[k], rcond=1e-12)[0]  # singular only where a view has no weight
        out[k] = flat[k] - c @ phi
    return out.reshape(d.shape)


def profile_offset(red: ViewReduction) -> ViewReduction:
    """Degree 0 from a fused reduction: an offset per view eliminated with ``Σ w g``, ``Σ w ρ`` and ``Σ w``.

    ``A = Σ w``, ``C = Σ w g``, ``e = Σ w ρ``: no image is stored, the pass
    costs what the fused one costs, and it runs wherever that one runs (a
    Dask cluster included).
    """
    if red.grad_sum is None:
        raise ValueError("the reduction carries no grad_sum (Σ w g): made by reduce_views of an older backend?")
    a = np.where(red.weight_sum > 0, red.weight_sum, np.inf)
    c = red.grad_sum
    e = red.resid_sum
    return ViewReduction(
        M=red.M - np.einsum("ki,kj->kij", c, c) / a[:, None, None],
        b=red.b - c * (e / a)[:, None],
        rss=np.maximum(red.rss - e**2 / a, 0.0),
        weight_sum=red.weight_sum, meas_sum=red.meas_sum, meas_sq_sum=red.meas_sq_sum,
        resid_sum=np.zeros_like(red.resid_sum), center=red.center, grad_sum=np.zeros_like(c),
    )


def view_offset(red: ViewReduction, noise_variance: float) -> float:
    """The RMS of the per-view offsets of the residual about their mean, in noise standard deviations.

    The offset of view k is ``m_k = Σ w ρ / Σ w``; what varies from view to view (``m_k - m̄``, ``m̄`` their mean
    weighted by ``Σ w``) is counted, with weight ``Σ w``: an offset that is the same in every view (a mass the
    reconstruction and the data do not share, e.g. FDK's cone-beam loss, 0.95 σ of the 128³ benchmark scan at its
    true geometry, the same in every view to 0.18 σ) is not an air level that drifts. From any reduction.
    """
    a = np.asarray(red.weight_sum, float)
    e = np.asarray(red.resid_sum, float)
    total_w = float(a.sum())
    if not (total_w > 0 and noise_variance > 0):
        return 0.0
    ok = a > 0
    m = np.where(ok, e / np.where(ok, a, 1.0), 0.0)
    mean = float(np.sum(a * m) / total_w)
    energy = float(np.sum(np.where(ok, a * (m - mean) ** 2, 0.0)))
    return float(np.sqrt(energy / (total_w * noise_variance)))


def auto_background(offset_sigma: float):
    """The degree ``background = "auto"`` fits for per-view offsets varying by ``offset_sigma`` (RMS, in noise std of
    the full-resolution projections) from view to view (None: none)."""
    return AUTO_DEGREE if offset_sigma >= AUTO_OFFSET_SIGMA else None


def reduce_views_background(volume, vol_geom, geom, measured, *, degree: int, weights=None, center=None,
                            backend="auto", robust=None) -> ViewReduction:
    """:func:`pdvc.projectors.reduce_views` with a smooth background per view profiled out (module docstring).

    Degree 0 goes through the fused pass (:func:`profile_offset`); degrees 1
    and 2 through the sensitivity images. ``robust``: ``reduce_views``'s
    Huber weights ``(cut, shift)``, taken on the residual before the
    background is profiled out.
    """
    if degree == 0:
        return profile_offset(reduce_views(volume, vol_geom, geom, measured, weights=weights, center=center, backend=backend,
                                           robust=robust))
    return _by_images(volume, vol_geom, geom, measured, degree=degree, weights=weights, center=center, backend=backend,
                      robust=robust)


def _by_images(volume, vol_geom, geom, measured, *, degree: int, weights=None, center=None, backend="auto",
               robust=None) -> ViewReduction:
    """The profiled reduction from the sensitivity images, view by view (any degree)."""
    s = np.asarray(measured, np.float32)
    nv = geom.n_views
    nr, nc = geom.det_shape
    chunk = max(1, int(_CHUNK_BYTES // (7 * 4 * nr * nc)))  # views per images pass: ~256 MiB of images at a time
    phi = background_basis((nr, nc), degree).reshape(-1, nr * nc)  # (K, P)
    if weights is None:
        w = np.ones((1, nr * nc))
    else:
        w = np.asarray(weights, np.float64).reshape(-1, nr * nc)
    M = np.empty((nv, 6, 6))
    b = np.empty((nv, 6))
    rss = np.empty(nv)
    wsum = np.empty(nv)
    msum = np.empty(nv)
    m2sum = np.empty(nv)
    for k in range(nv):  # one view at a time: a few (6 + K) x P arrays
        if k % chunk == 0:
            proj, sens = jacobian(volume, vol_geom, geom[k:k + chunk], center=center, backend=backend)
        w0 = w[k if w.shape[0] > 1 else 0]
        G = sens[k % chunk].reshape(6, -1).astype(np.float64)
        sk = s[k].reshape(-1).astype(np.float64)
        rho = sk - proj[k % chunk].reshape(-1)
        if robust is None:
            wk, loss = w0, float(w0 @ rho**2)
        else:  # the fused kernel's Huber weights (pdvc.projectors.reduce_views)
            cut = robust[0]
            rho = rho - robust[1][k]
            a = np.abs(rho)
            wk = w0 * np.minimum(1.0, cut / np.maximum(a, 1e-300))
            loss = float(w0 @ np.where(a > cut, 2 * cut * a - cut * cut, rho**2))
        Gw = G * wk
        Pw = phi * wk
        A = Pw @ phi.T
        C = Gw @ phi.T
        e = Pw @ rho
        sol = np.linalg.lstsq(A, np.column_stack([C.T, e]), rcond=1e-12)[0]  # A⁻¹ [Cᵀ e]; A is singular with no weight
        M[k] = Gw @ G.T - C @ sol[:, :6]
        b[k] = Gw @ rho - C @ sol[:, 6]
        rss[k] = max(loss - float(e @ sol[:, 6]), 0.0)
        wsum[k] = float(wk.sum())
        msum[k] = float(w0 @ sk)
        m2sum[k] = float(w0 @ sk**2)
    return ViewReduction(M=M, b=b, rss=rss, weight_sum=wsum, meas_sum=msum, meas_sq_sum=m2sum,
                         resid_sum=np.zeros(nv), center=np.asarray(center, float))
