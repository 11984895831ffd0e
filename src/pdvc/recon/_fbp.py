"""FDK (cone beam) and FBP (parallel beam) over per-view vector geometry."""

from __future__ import annotations

import logging

import numba
import numpy as np

from ..compute._scheduler import current_session
from ..errors import GeometryError, InputTypeError, ShapeError, ShortScanError
from ..geometry import VectorGeometry, VolumeGeometry
from ._filters import check_filter, check_padding, filter_rows, ramp_filter_response
from ._kernels import backproject_block
from ._weights import ScanWeights, check_center, scan_weights

__all__ = ["fdk", "fbp", "projection_matrices"]

logger = logging.getLogger(__name__)

#: Views filtered and back-projected per pass. Working memory besides the
#: volume: about ``views_per_block * n_rows * n_cols * 32`` bytes (weighted
#: block, zero-padded spectrum and filtered rows, transposed copy): 50 MB for
#: 16 views of 256 x 384.
DEFAULT_VIEWS_PER_BLOCK = 16


# -- checks -------------------------------------------------------------------
def _check_inputs(projections, vol_geom, geom, out, views_per_block):
    if not isinstance(vol_geom, VolumeGeometry):
        raise InputTypeError(f"vol_geom must be a pdvc.VolumeGeometry, got {type(vol_geom).__name__}")
    if not isinstance(geom, VectorGeometry):
        raise InputTypeError(f"geom must be a pdvc.VectorGeometry, got {type(geom).__name__}")
    nr, nc = geom.det_shape
    if nr < 2 or nc < 2:
        raise GeometryError(f"geom.det_shape must be at least (2, 2) for interpolation, got {geom.det_shape}")
    if nr * nc >= 2**32:
        raise GeometryError(f"geom.det_shape must have fewer than 2**32 pixels (32-bit pixel indices), got {geom.det_shape}")
    arr = np.asarray(projections)
    want = (geom.n_views, nr, nc)
    if arr.ndim != 3 or arr.shape != want:
        raise ShapeError(
            f"projections must have shape (n_views, n_rows, n_cols) = {want} to match geom, got {arr.shape}"
        )
    if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise ShapeError(f"projections must be real numbers convertible to float32, got dtype {arr.dtype}")
    if out is not None:
        if (
            not isinstance(out, np.ndarray)
            or out.shape != vol_geom.shape
            or out.dtype != np.float32
            or not out.flags.c_contiguous
            or not out.flags.writeable
        ):
            raise ShapeError(
                f"out must be a writeable C-contiguous float32 array of shape {vol_geom.shape} (nz, ny, nx), "
                f"got {getattr(out, 'dtype', type(out).__name__)} {getattr(out, 'shape', '')}"
            )
        if np.shares_memory(out, arr):
            raise ShapeError("out must not share memory with projections (the input is never modified)")
    if (
        not isinstance(views_per_block, (int, np.integer))
        or isinstance(views_per_block, bool)
        or views_per_block < 1
    ):
        raise ShapeError(f"views_per_block must be a positive int, got {views_per_block!r}")
    return arr


def _coverage_deg(weights: ScanWeights, period: float) -> float:
    """Angular coverage for the log, degrees: the summed quadrature widths of the views.

    Each view stands for its midpoint-rule width (one angular step for evenly
    spaced views): an arc covers its span plus one step, and a scan that
    closes its period covers all of it. So 91 parallel views 2 deg apart,
    -88.2..91.8 deg, cover 180 deg, where ``weights.coverage`` (the period
    minus the largest gap between view azimuths) says 178.
    """
    return float(np.degrees(min(float(np.sum(weights.dtheta)), period)))


# -- geometry -----------------------------------------------------------------
def _source_side_normals(geom: VectorGeometry) -> np.ndarray:
    """Unit detector normals pointing away from the source, ``(n_views, 3)``."""
    n = geom.det_normal
    return n * np.sign(np.einsum("ij,ij->i", geom.det_center - geom.src, n))[:, None]


def _check_center_in_front(geom: VectorGeometry, c: np.ndarray) -> None:
    sod = np.einsum("ij,ij->i", c - geom.src, _source_side_normals(geom))
    bad = np.nonzero(sod <= 0)[0]
    if bad.size:
        raise GeometryError(
            f"center {c.tolist()} must lie in front of the source (on the detector side); "
            f"it does not at views {bad[:10].tolist()}"
        )


def _index_transform(vol_geom: VolumeGeometry) -> np.ndarray:
    """4 x 4 map from voxel index ``(ix, iy, iz, 1)`` to world ``(x, y, z, 1)``."""
    nz, ny, nx = vol_geom.shape
    sx, sy, sz = vol_geom.spacing_xyz
    T = np.diag([sx, sy, sz, 1.0])
    T[:3, 3] = np.asarray(vol_geom.offset) - np.array([(nx - 1) / 2 * sx, (ny - 1) / 2 * sy, (nz - 1) / 2 * sz])
    return T


def projection_matrices(vol_geom: VolumeGeometry, geom: VectorGeometry, center=None):
    """Per-view 3 x 4 projection matrices in voxel-index coordinates.

    For voxel index ``x = (ix, iy, iz, 1)`` and ``w = P[k] @ x``, the voxel
    centre projects on detector pixel ``(row, col) = (w[1] / w[2], w[0] / w[2])``
    (continuous, 0 at the first pixel centre) of view ``k``, exactly
    (homogeneous coordinates, no small-angle approximation).

    Cone beam: with ``M = [u, v, d - src]`` (columns), ``M^{-1} (x - src)``
    gives ``(a, b, 1) * depth / SDD``; rows are offset by the pixel centre
    and the whole matrix scaled so that ``w[2] = depth / SOD_k``, where
    ``depth = (x - src) . n``, ``n`` the detector normal pointing away from
    the source, ``SDD_k = (d - src) . n`` and ``SOD_k = (center - src) . n``.
    Parallel beam: ``w[2] = 1`` and ``(a, b)`` solve
    ``x - d = a u + b v - t ray``.

    Parameters
    ----------
    vol_geom : VolumeGeometry
    geom : VectorGeometry
    center : (3,) array, optional
        Rotation centre for ``SOD_k`` (cone beam; default the origin).

    Returns
    -------
    P : (n_views, 3, 4) float64
    sod : (n_views,) float64
        ``SOD_k`` (cone; ones for parallel), length units.
    sdd : (n_views,) float64
        ``SDD_k`` (cone; ones for parallel), length units.
    """
    vec = geom.vectors
    nr, nc = geom.det_shape
    rc, cc = (nr - 1) / 2, (nc - 1) / 2
    s, d, u, v = vec[:, 0:3], vec[:, 3:6], vec[:, 6:9], vec[:, 9:12]
    n = geom.n_views
    P = np.zeros((n, 3, 4))
    if geom.kind == "cone":
        c = np.zeros(3) if center is None else np.asarray(center, np.float64)
        w = d - s
        uxv = np.cross(u, v)
        det = np.einsum("ij,ij->i", uxv, w)
        qa = np.cross(v, w) / det[:, None]
        qb = np.cross(w, u) / det[:, None]
        qg = uxv / det[:, None]
        nhat = np.sign(det)[:, None] * uxv / np.linalg.norm(uxv, axis=1, keepdims=True)
        sdd = np.einsum("ij,ij->i", w, nhat)
        sod = np.einsum("ij,ij->i", c - s, nhat)
        bad = np.nonzero(sod <= 1e-9 * sdd)[0]
        if bad.size:
            raise GeometryError(
                f"center {c.tolist()} must lie in front of the source (on the detector side); "
                f"it does not at views {bad[:10].tolist()}"
            )
        scale = (sdd / sod)[:, None]
        P[:, 0, :3] = (qa + cc * qg) * scale
        P[:, 1, :3] = (qb + rc * qg) * scale
        P[:, 2, :3] = qg * scale
        P[:, :, 3] = -np.einsum("vij,vj->vi", P[:, :, :3], s)
    else:
        r = geom.ray
        mr = -r
        det = np.einsum("ij,ij->i", u, np.cross(v, mr))
        qa = np.cross(v, mr) / det[:, None]
        qb = np.cross(mr, u) / det[:, None]
        P[:, 0, :3] = qa
        P[:, 1, :3] = qb
        P[:, 0, 3] = cc - np.einsum("ij,ij->i", qa, d)
        P[:, 1, 3] = rc - np.einsum("ij,ij->i", qb, d)
        P[:, 2, 3] = 1.0
        sod = np.ones(n)
        sdd = np.ones(n)
    P = P @ _index_transform(vol_geom)
    return P, sod, sdd


def _z_invariant(P: np.ndarray, vol_geom: VolumeGeometry) -> np.ndarray:
    """Views whose column and weight vary by < 1e-7 pixel / 1e-9 relative over the z range."""
    nz = vol_geom.shape[0]
    w2min = _w2_min(P, vol_geom)
    dcol = np.abs(P[:, 0, 2]) * (nz - 1) / w2min
    dw = np.abs(P[:, 2, 2]) * (nz - 1) / w2min
    return (dcol < 1e-7) & (dw < 1e-9)


def _w2_min(P: np.ndarray, vol_geom: VolumeGeometry) -> np.ndarray:
    nz, ny, nx = vol_geom.shape
    corners = np.array(
        [[ix, iy, iz, 1.0] for ix in (0, nx - 1) for iy in (0, ny - 1) for iz in (0, nz - 1)]
    )
    return (P[:, 2, :] @ corners.T).min(axis=1)


def _cosine_weights(vec, sdd, red, jj, ii) -> np.ndarray:
    """``red * SDD_k / |p_ij - src_k|`` for a block of views, ``(b, n_rows, n_cols)`` float32."""
    s, d, u, v = vec[:, 0:3], vec[:, 3:6], vec[:, 6:9], vec[:, 9:12]
    w = d - s
    dot = lambda x, y: np.einsum("ij,ij->i", x, y)[:, None, None]  # noqa: E731
    a = jj[None, None, :]
    b = ii[None, :, None]
    # |w + a u + b v|^2, split into a column term, a row term and a cross term
    colterm = dot(w, w) + 2 * a * dot(w, u) + a * a * dot(u, u)
    rowterm = 2 * b * dot(w, v) + b * b * dot(v, v)
    out = np.add(colterm.astype(np.float32), rowterm.astype(np.float32))
    uv = dot(u, v)
    if np.any(uv != 0):
        out += (2 * a * b * uv).astype(np.float32)
    np.sqrt(out, out=out)
    np.divide((red * sdd[:, None, None]).astype(np.float32), out, out=out)
    return out


# -- the shared driver --------------------------------------------------------
def _reconstruct(arr, vol_geom, geom, weights: ScanWeights, *, filter, cutoff, out, views_per_block, padding="zero"):
    session = current_session()  # a Dask cluster made current by pdvc.compute.use_scheduler: by slabs of z
    if session is not None:
        return session.reconstruct(
            arr, vol_geom, geom, weights, filter=filter, cutoff=cutoff, out=out, views_per_block=views_per_block,
            padding=padding,
        )
    nr, nc = geom.det_shape
    cone = geom.kind == "cone"
    P, sod, sdd = projection_matrices(vol_geom, geom, center=weights.center if cone else None)
    if cone:
        w2min = _w2_min(P, vol_geom)
        bad = np.nonzero(w2min <= 0)[0]
        if bad.size:
            raise GeometryError(
                "the volume reaches the source plane (voxels at or behind the source) at views "
                f"{bad[:10].tolist()}; shrink or move vol_geom"
            )
    zinv = _z_invariant(P, vol_geom)
    P[zinv, 0, 2] = 0.0
    P[zinv, 2, 2] = 0.0

    # physical sampling of the filtered rows: the pixel pitch magnified to the
    # rotation centre (cone) or projected perpendicular to the ray (parallel)
    u = geom.u
    if cone:
        tau = np.linalg.norm(u, axis=1) * sod / sdd
    else:
        rhat = geom.ray / np.linalg.norm(geom.ray, axis=1, keepdims=True)
        tau = np.linalg.norm(u - np.einsum("ij,ij->i", u, rhat)[:, None] * rhat, axis=1)
    view_scale = weights.dtheta / tau
    response = ramp_filter_response(nc, filter, cutoff)

    if out is None:
        out = np.zeros(vol_geom.shape, np.float32)
    else:
        out[...] = 0.0
    workers = numba.get_num_threads()
    jj = np.arange(nc) - (nc - 1) / 2
    ii = np.arange(nr) - (nr - 1) / 2
    for k0 in range(0, geom.n_views, views_per_block):
        k1 = min(k0 + views_per_block, geom.n_views)
        sl = slice(k0, k1)
        block = np.asarray(arr[sl], dtype=np.float32)  # a view of the caller's data or a converted copy
        red = weights.redundancy[sl, None, :]  # (b, 1, nc)
        if cone:
            weighted = _cosine_weights(geom.vectors[sl], sdd[sl], red, jj, ii)
            np.multiply(weighted, block, out=weighted)  # a new array: the input is never written
        else:
            weighted = block * red.astype(np.float32)
        q = filter_rows(weighted, response, workers=workers, padding=padding)
        q *= view_scale[sl, None, None].astype(np.float32)
        qt = np.ascontiguousarray(q.transpose(0, 2, 1))  # (b, n_cols, n_rows)
        backproject_block(out, qt, np.ascontiguousarray(P[sl]), np.ascontiguousarray(zinv[sl]))
    return out


# -- public -------------------------------------------------------------------
def fdk(
    projections,
    vol_geom: VolumeGeometry,
    geom: VectorGeometry,
    *,
    filter: str = "ram-lak",
    cutoff: float = 1.0,
    short_scan="auto",
    center=None,
    axis=None,
    views_per_block: int = DEFAULT_VIEWS_PER_BLOCK,
    out=None,
    padding: str = "zero",
) -> np.ndarray:
    """FDK reconstruction of (near-)circular cone-beam projections with per-view vectors.

    Each view is used with its own source, detector position and tilt, so a
    corrected (calibrated) geometry reconstructs without resampling.

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) array
        Line integrals (attenuation x length), real numbers; read only
        (filtered into new arrays, one block of views at a time, so a
        ``np.memmap`` is streamed). NaN or Inf are not checked and spread.
    vol_geom : VolumeGeometry
        The grid to reconstruct.
    geom : VectorGeometry
        Cone-beam vectors (``kind="cone"``), at least 2 views.
    filter : {"ram-lak", "shepp-logan", "cosine", "hamming", "hann"}
        Window of the ramp filter (see :func:`ramp_filter_response`).
    cutoff : float in (0, 1]
        Filter cut-off as a fraction of the Nyquist frequency.
    short_scan : {"auto", True, False}
        Redundancy weighting. "auto": a scan whose source azimuths close
        the circle (no gap more than 3 x the second largest, none over
        180 deg) is a full scan, weight 1/2 per ray pair; otherwise it is a
        short scan and gets Parker weights, generalised to the available
        over-scan (Wesarg et al. 2002). A short scan must cover at least
        180 deg + the fan angle, else :class:`~pdvc.errors.GeometryError`.
        True forces Parker weights (also on a full turn); False uses 1/2
        everywhere (an incomplete arc then gives limited-angle errors).
    center : (3,) array, optional
        Rotation centre (x, y, z), length units. Default: the centre of the
        least-squares circle through the source positions (the volume frame
        origin if that fit is degenerate).
    axis : (3,) array, optional
        Rotation-axis direction. Default: normal of the least-squares plane
        through the source positions.
    views_per_block : int
        Views filtered and back-projected per pass (memory vs. passes over
        the volume).
    out : (nz, ny, nx) float32 array, optional
        Overwritten with the result and returned.
    padding : {"zero", "edge"}
        How the rows are extended for the ramp filter. "zero" for an object
        inside the field of view; "edge" carries each row's end values
        outward (:func:`pdvc.recon._filters.filter_rows`), for an object
        wider than the detector (a region-of-interest scan): no bright rim
        at the edge of the field of view, much less cupping.

    Returns
    -------
    (nz, ny, nx) float32
        Attenuation per length unit, ``f[z, y, x]``.

    Notes
    -----
    For view ``k`` with source ``s``, detector centre ``d``, steps ``u, v``
    and unit detector normal ``n`` (pointing away from the source),
    ``SDD_k = (d - s) . n`` and ``SOD_k = (c - s) . n`` (``c`` the centre):

    1. pre-weight pixel ``(i, j)`` by ``SDD_k / |p_ij - s|`` (cosine) times
       the redundancy weight (1/2, or Parker's ``w(beta, gamma)``);
    2. ramp-filter every row (along ``u``), zero padded to a power of two
       >= ``2 n_cols``, with sample pitch ``tau_k = |u| SOD_k / SDD_k``
       (the pixel magnified to the rotation centre): ``q = (g * p) / tau_k``;
    3. back-project voxel by voxel:
       ``f(x) = sum_k dtheta_k (SOD_k / depth_k(x))^2 q_k(row_k(x), col_k(x))``
       with ``depth_k(x) = (x - s) . n``, bilinear interpolation (zero outside
       the detector) and ``dtheta_k`` the midpoint-rule width of the view's
       source azimuth about the rotation axis (irregular spacing, any view
       order and several turns are fine).

    This is the Feldkamp-Davis-Kress formula, exact in the source plane for a
    circular orbit; a uniform ball of density mu reconstructs to mu (tested
    within 2 %). The rotation axis and centre are estimated from the source
    positions unless given; ``dtheta_k`` and the Parker angles are measured
    about them. An object wider than the detector is reconstructed inside
    the field of view with ``padding="edge"``; half-detector (offset
    detector) scans are not handled.

    Examples
    --------
    >>> import numpy as np
    >>> from pdvc.geometry import VolumeGeometry, circular_cone
    >>> geom = circular_cone(np.linspace(0, 2 * np.pi, 90, endpoint=False), sod=200.0, odd=100.0,
    ...                      det_shape=(40, 60), pixel=1.5)
    >>> vol = fdk(np.zeros((90, 40, 60), np.float32), VolumeGeometry((32, 32, 32)), geom)
    >>> vol.shape, vol.dtype
    ((32, 32, 32), dtype('float32'))
    """
    arr = _check_inputs(projections, vol_geom, geom, out, views_per_block)
    if geom.kind != "cone":
        raise GeometryError(
            "fdk needs a cone-beam geometry, got geom.kind='parallel'; use pdvc.recon.fbp for parallel beam"
        )
    check_filter(filter, cutoff)
    check_padding(padding)
    if center is not None:
        _check_center_in_front(geom, check_center(center))
    weights = scan_weights(geom, axis=axis, center=center, short_scan=short_scan)
    logger.info(
        "fdk: %s scan of %d views, coverage %.1f of 360 deg (each view covers its angular step), axis %s, centre %s",
        weights.kind,
        geom.n_views,
        _coverage_deg(weights, 2 * np.pi),
        np.round(weights.axis, 6).tolist(),
        np.round(weights.center, 6).tolist(),
    )
    return _reconstruct(
        arr, vol_geom, geom, weights, filter=filter, cutoff=cutoff, out=out,
        views_per_block=int(views_per_block), padding=padding,
    )


def fbp(
    projections,
    vol_geom: VolumeGeometry,
    geom: VectorGeometry,
    *,
    filter: str = "ram-lak",
    cutoff: float = 1.0,
    axis=None,
    views_per_block: int = DEFAULT_VIEWS_PER_BLOCK,
    out=None,
    padding: str = "zero",
) -> np.ndarray:
    """Filtered back-projection of parallel-beam projections with per-view vectors.

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) array
        Line integrals (attenuation x length); read only.
    vol_geom : VolumeGeometry
    geom : VectorGeometry
        Parallel-beam vectors (``kind="parallel"``), at least 2 views.
    filter, cutoff, views_per_block, out, padding
        As in :func:`fdk`.
    axis : (3,) array, optional
        Rotation-axis direction; default the normal of the plane spanned by
        the ray directions.

    Returns
    -------
    (nz, ny, nx) float32
        Attenuation per length unit.

    Notes
    -----
    ``f(x) = sum_k dtheta_k q_k(row_k(x), col_k(x))`` with ``q = (g * p) / tau``,
    ``tau = |u|`` projected perpendicular to the ray, and ``dtheta_k`` the
    midpoint-rule width of the ray azimuths taken modulo pi: a 180 deg scan
    integrates over pi, a 360 deg scan counts every direction twice at half
    weight, irregular and partly doubled coverage are weighted consistently.
    Less than 180 deg is reconstructed with a logged warning (limited angle).
    """
    arr = _check_inputs(projections, vol_geom, geom, out, views_per_block)
    if geom.kind != "parallel":
        raise GeometryError(
            "fbp needs a parallel-beam geometry, got geom.kind='cone'; use pdvc.recon.fdk for cone beam"
        )
    check_filter(filter, cutoff)
    check_padding(padding)
    weights = scan_weights(geom, axis=axis)
    logger.info(
        "fbp: %s scan of %d views, coverage %.1f of 180 deg (each view covers its angular step)",
        weights.kind,
        geom.n_views,
        _coverage_deg(weights, np.pi),
    )
    return _reconstruct(
        arr, vol_geom, geom, weights, filter=filter, cutoff=cutoff, out=out,
        views_per_block=int(views_per_block), padding=padding,
    )


def analytic(projections, vol_geom: VolumeGeometry, geom: VectorGeometry, **kw) -> np.ndarray:
    """FDK (cone beam) or FBP (parallel beam), for reconstructions made inside a calibration.

    A cone-beam short scan whose arc falls short of 180° plus the fan
    angle (:class:`pdvc.errors.ShortScanError` from :func:`fdk`; a
    calibration's poses can shorten the arc seen about the moved axis by a
    degree or two) is reconstructed without redundancy weights, with a
    warning, instead of stopping the run.
    """
    if geom.kind != "cone":
        return fbp(projections, vol_geom, geom, **kw)
    try:
        return fdk(projections, vol_geom, geom, **kw)
    except ShortScanError as exc:
        if kw.get("short_scan", "auto") is True:
            raise  # Parker weights asked for explicitly
        logger.warning("%s: reconstructed with short_scan=False (no redundancy weights) instead", exc)
        return fdk(projections, vol_geom, geom, **dict(kw, short_scan=False))
