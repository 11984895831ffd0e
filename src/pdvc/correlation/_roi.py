"""Region of interest Ξ on the detector (``DESIGN.md`` §2, paper eq. 1 and §3).

The cost sums over the pixels of a region of interest only: the paper
drops the detector rows at the top and bottom whose rays leave the
reconstructed volume through its top or bottom face, where cone-beam
reconstructions carry artefacts (and the sample may go on outside the
volume) that no rigid motion explains. :func:`cone_artifact_rows` finds
those rows from the geometry; :func:`detector_weights` turns row and column
ranges and an optional mask into the weight image passed to
:func:`pdvc.projectors.reduce_views` (``weights=``).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputTypeError, PdvcError, ShapeError
from ..geometry import check_det_shape
from ..geometry import VectorGeometry, VolumeGeometry

__all__ = ["RoiError", "detector_weights", "cone_artifact_rows"]


class RoiError(PdvcError, ValueError):
    """A region of interest that keeps no pixel, or ranges outside the detector."""


def _det_shape(det_shape) -> tuple[int, int]:
    return check_det_shape(det_shape)


def _range(value, n: int, name: str) -> tuple[int, int]:
    if value is None:
        return 0, n
    try:
        a, b = value
    except (TypeError, ValueError):
        raise RoiError(f"{name} must be a (start, stop) pair of ints (half-open), got {value!r}") from None
    a = 0 if a is None else a
    b = n if b is None else b
    for x in (a, b):
        if not isinstance(x, (int, np.integer)) or isinstance(x, bool):
            raise RoiError(f"{name} must be a (start, stop) pair of ints (half-open), got {value!r}")
    if not 0 <= a <= b <= n:
        raise RoiError(f"{name} must satisfy 0 <= start <= stop <= {n}, got {value!r}")
    return int(a), int(b)


def detector_weights(det_shape, *, rows=None, cols=None, mask=None, margin: int = 0) -> np.ndarray:
    """Pixel weights of a detector region of interest.

    Parameters
    ----------
    det_shape : (n_rows, n_cols)
    rows, cols : (start, stop), optional
        Half-open ranges of detector rows / columns kept (``None`` for
        either end means the detector edge; default the whole axis), e.g.
        ``rows=cone_artifact_rows(geom, vol_geom)``.
    mask : (n_rows, n_cols) array, optional
        Boolean, or weights in ``[0, 1]``, multiplied in (e.g. 0 on dead
        pixels or on a sample holder).
    margin : int, >= 0
        Pixels dropped at each of the four detector edges (on top of
        ``rows`` / ``cols``).

    Returns
    -------
    (n_rows, n_cols) float32
        1 inside the ranges (times ``mask``), 0 outside.

    Raises
    ------
    RoiError
        If no pixel keeps a positive weight: ``"ROI is empty: rows=(…),
        cols=(…)…"``, or a range lies outside the detector.
    """
    nr, nc = _det_shape(det_shape)
    r0, r1 = _range(rows, nr, "rows")
    c0, c1 = _range(cols, nc, "cols")
    if not isinstance(margin, (int, np.integer)) or isinstance(margin, bool) or margin < 0:
        raise RoiError(f"margin must be a non-negative int (pixels), got {margin!r}")
    m = int(margin)
    rr0, rr1 = max(r0, m), min(r1, nr - m)
    cc0, cc1 = max(c0, m), min(c1, nc - m)
    w = np.zeros((nr, nc), np.float32)
    if rr1 > rr0 and cc1 > cc0:
        w[rr0:rr1, cc0:cc1] = 1.0
    if mask is not None:
        mk = np.asarray(mask)
        if mk.shape != (nr, nc):
            raise ShapeError(f"mask must have shape {(nr, nc)} (n_rows, n_cols), got {mk.shape}")
        if mk.dtype != bool:
            if not np.issubdtype(mk.dtype, np.number) or np.iscomplexobj(mk):
                raise InputTypeError(f"mask must be boolean or real weights in [0, 1], got dtype {mk.dtype}")
            if not np.all(np.isfinite(mk)) or mk.min() < 0 or mk.max() > 1:
                raise RoiError("mask must hold finite weights in [0, 1]")
        w *= mk.astype(np.float32)
    if not np.any(w > 0):
        raise RoiError(
            f"ROI is empty: rows=({r0}, {r1}), cols=({c0}, {c1}), margin={m} on a detector "
            f"of {(nr, nc)}" + (", and the mask keeps none of those pixels" if mask is not None else "")
        )
    return w


def cone_artifact_rows(geom: VectorGeometry, vol_geom: VolumeGeometry, *, margin_px: int = 2) -> tuple[int, int]:
    """Detector rows whose rays cross the volume only through its sides.

    A row is kept when, at every view, every ray through one of its pixel
    centres stays within the volume's z-extent ``[z_min, z_max]`` (voxel
    edges) over the whole stretch where it crosses the volume's footprint,
    the ``x-y`` rectangle of the grid: such a ray enters and leaves through
    the side faces, never through the top or bottom face. Rows whose rays
    cut the top or bottom face see matter outside the reconstructed volume
    and the cone-beam artefacts there (paper §3); they are excluded. Rays
    that miss the footprint do not constrain their row. The longest run of
    kept rows, shrunk by ``margin_px`` at each end, is returned.

    Parameters
    ----------
    geom : VectorGeometry
        Cone beam (rays are half-lines from the source through the pixel
        centres) or parallel beam (whole lines along ``ray``; for the
        nominal scan the rows whose centres lie within the volume's
        z-extent).
    vol_geom : VolumeGeometry
    margin_px : int, >= 0
        Rows dropped at each end of the run (pixel footprint, interpolation
        near the faces).

    Returns
    -------
    (start, stop) : tuple of int
        Half-open range of rows, for :func:`detector_weights` ``rows=``.

    Raises
    ------
    RoiError
        If no row qualifies (e.g. a volume thinner than the cone's spread).

    Notes
    -----
    The test uses the volume frame's z axis as "top/bottom": the grid's z
    faces. Work is ``O(n_views · n_rows · n_cols)``: a few ms per view at
    the coarse scales; for a large full-resolution scan pass a subset of
    views, e.g. ``geom[::10]`` (the rows change slowly with the angle).
    """
    if not isinstance(geom, VectorGeometry):
        raise InputTypeError(f"geom must be a pdvc.VectorGeometry, got {type(geom).__name__}")
    if not isinstance(vol_geom, VolumeGeometry):
        raise InputTypeError(f"vol_geom must be a pdvc.VolumeGeometry, got {type(vol_geom).__name__}")
    if not isinstance(margin_px, (int, np.integer)) or isinstance(margin_px, bool) or margin_px < 0:
        raise RoiError(f"margin_px must be a non-negative int (rows), got {margin_px!r}")
    nr, nc = geom.det_shape
    half = vol_geom.extent_xyz / 2
    lo = np.asarray(vol_geom.offset) - half
    hi = np.asarray(vol_geom.offset) + half
    ok = np.ones(nr, bool)
    ii = (np.arange(nr) - (nr - 1) / 2)[:, None, None]
    jj = (np.arange(nc) - (nc - 1) / 2)[None, :, None]
    for k in range(geom.n_views):
        vec = geom.vectors[k]
        pix = vec[3:6] + jj * vec[6:9] + ii * vec[9:12]  # (nr, nc, 3)
        if geom.kind == "cone":
            origin = np.broadcast_to(vec[0:3], pix.shape)
            direction = pix - vec[0:3]
            t_lo, t_hi = 0.0, np.inf  # half-line from the source
        else:
            origin = pix
            direction = np.broadcast_to(vec[0:3], pix.shape)
            t_lo, t_hi = -np.inf, np.inf
        t0 = np.full((nr, nc), t_lo)
        t1 = np.full((nr, nc), t_hi)
        hits = np.ones((nr, nc), bool)
        for ax in (0, 1):  # slab intersection with the x and y faces: the footprint prism
            o, d = origin[..., ax], direction[..., ax]
            para = np.abs(d) < 1e-300
            with np.errstate(divide="ignore", invalid="ignore"):
                ta = (lo[ax] - o) / d
                tb = (hi[ax] - o) / d
            tmin = np.where(para, -np.inf, np.minimum(ta, tb))
            tmax = np.where(para, np.inf, np.maximum(ta, tb))
            hits &= ~para | ((o >= lo[ax]) & (o <= hi[ax]))
            t0 = np.maximum(t0, tmin)
            t1 = np.minimum(t1, tmax)
        hits &= t1 > t0
        oz, dz = origin[..., 2], direction[..., 2]
        inside = np.ones((nr, nc), bool)
        for t in (t0, t1):
            with np.errstate(invalid="ignore"):
                z = np.where(np.isfinite(t), oz + t * dz, np.where(dz == 0, oz, np.sign(t) * np.sign(dz) * np.inf))
            inside &= (z >= lo[2]) & (z <= hi[2])
        ok &= np.all(inside | ~hits, axis=1)
    if not np.any(ok):
        raise RoiError(
            f"ROI is empty: no detector row has all its rays inside the volume's z-extent "
            f"[{lo[2]:g}, {hi[2]:g}] across its footprint"
        )
    # longest run of kept rows
    edges = np.diff(np.concatenate([[0], ok.astype(np.int8), [0]]))
    starts, stops = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
    best = int(np.argmax(stops - starts))
    a, b = int(starts[best]) + int(margin_px), int(stops[best]) - int(margin_px)
    if b <= a:
        raise RoiError(
            f"ROI is empty: rows=({a}, {b}) after a margin of {margin_px} on the run "
            f"({int(starts[best])}, {int(stops[best])}) of rows inside the volume"
        )
    return a, b
