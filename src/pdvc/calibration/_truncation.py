"""Samples larger than the volume: which rays the reconstruction cannot explain, and which case a scan is in.

A reconstruction on ``vol_geom`` re-projects only what lies inside the
volume box. A rod longer than the field of view (the usual in situ sample,
held in grips) also attenuates the rays that leave the box through its top
or bottom face: on those rays the re-projection misses the part of the rod
outside the box, the residual is the sample itself, not noise, and the
correlation pulls the poses to explain it. :func:`truncation_weights` drops
them; :func:`detect_truncation` says from a reconstruction whether the
sample crosses the box's faces (vertical truncation) or its sides (a region
of interest, lateral truncation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputTypeError
from ..geometry import VectorGeometry, VolumeGeometry

__all__ = ["truncation_weights", "detect_truncation", "detect_scan_truncation", "air_to_subtract", "air_columns_span",
           "Truncation", "outside_pattern", "cylinder_window", "field_radius", "field_cover"]


def _rays(geom: VectorGeometry, chunk: int):
    """Chunks of views: ``(slice, a, d)``, every pixel's ray ``a + t d``, ``(views, n_rows, n_cols, 3)`` each."""
    nr, nc = geom.det_shape
    jj, ii = np.meshgrid(np.arange(nc) - (nc - 1) / 2, np.arange(nr) - (nr - 1) / 2)
    for k0 in range(0, geom.n_views, chunk):
        ks = slice(k0, min(k0 + chunk, geom.n_views))
        pix = (geom.det_center[ks, None, None, :] + jj[None, :, :, None] * geom.u[ks, None, None, :]
               + ii[None, :, :, None] * geom.v[ks, None, None, :])
        if geom.kind == "cone":
            a = np.broadcast_to(geom.src[ks, None, None, :], pix.shape)
            yield ks, a, pix - a
        else:
            yield ks, pix, np.broadcast_to(geom.ray[ks, None, None, :], pix.shape)


def truncation_weights(geom: VectorGeometry, vol_geom: VolumeGeometry, *, margin_voxels: float = 2.0, chunk: int = 16) -> np.ndarray:
    """Detector weights that drop the rays leaving the volume through its top or bottom face.

    A ray is kept (weight 1) when, over the part of it above the volume's
    footprint in x and y, its z stays within the box (shrunk by
    ``margin_voxels`` at each face), or when it misses the footprint. A
    sample that crosses the top or bottom face can lie on the dropped rays
    outside the box, where no reconstruction on ``vol_geom`` puts it. The
    margin keeps off the rays that graze the end layers, where the
    interpolating projector meets the box's zero padding (measured on a
    cone-beam rod 3x longer than the volume, tilted 0.6° and offset 2.3 px:
    default recipe, seeds 0 / 1 / 2: 0.168 / 0.063 / 0.104 px with a 2-voxel
    margin; seed 0 without weights 0.333 px, with a 1-voxel margin 0.146 px).

    Returns
    -------
    (n_views, n_rows, n_cols) float32 of 0 and 1
    """
    if not isinstance(geom, VectorGeometry) or not isinstance(vol_geom, VolumeGeometry):
        raise InputTypeError("truncation_weights needs a VectorGeometry and a VolumeGeometry")
    c = np.asarray(vol_geom.offset, float)
    half = 0.5 * np.asarray(vol_geom.extent_xyz, float)
    lo, hi = c - half, c + half
    # a thin slab (a few slices) keeps at least its middle half
    dz = min(float(margin_voxels), 0.25 * vol_geom.shape[0]) * float(vol_geom.voxel_size[0])
    z_lo, z_hi = lo[2] + dz, hi[2] - dz
    out = np.empty((geom.n_views, *geom.det_shape), np.float32)
    for ks, a, d in _rays(geom, chunk):
        s0 = np.full(d.shape[:3], -np.inf)
        s1 = np.full(d.shape[:3], np.inf)
        for ax in (0, 1):  # slab intersection with the footprint in x and y
            da = d[..., ax]
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = (lo[ax] - a[..., ax]) / da
                t2 = (hi[ax] - a[..., ax]) / da
            inside = (a[..., ax] >= lo[ax]) & (a[..., ax] <= hi[ax])
            near = np.where(da == 0, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
            far = np.where(da == 0, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
            s0 = np.maximum(s0, near)
            s1 = np.minimum(s1, far)
        hits = s1 > s0
        za = a[..., 2] + np.where(hits, s0, 0.0) * d[..., 2]
        zb = a[..., 2] + np.where(hits, s1, 0.0) * d[..., 2]
        leaves = hits & ((np.maximum(za, zb) > z_hi) | (np.minimum(za, zb) < z_lo))
        out[ks] = ~leaves
    return out


@dataclass(frozen=True)
class Truncation:
    """Whether the sample reaches past the volume box, read off a reconstruction.

    Attributes
    ----------
    vertical : bool
        Material in the top or bottom slices (the sample crosses the faces).
    lateral : bool
        Material at the edge of the slices (a region-of-interest scan).
    top_bottom_ratio, edge_ratio : float
        Mean value of those regions over that of the central region.
    """

    vertical: bool
    lateral: bool
    top_bottom_ratio: float
    edge_ratio: float

    def describe(self) -> str:
        parts = []
        if self.vertical:
            parts.append(
                f"the sample crosses the volume's top or bottom face (end slices hold {100 * self.top_bottom_ratio:.0f}% "
                "of the central ones): rays leaving the volume there are dropped"
            )
        if self.lateral:
            parts.append(
                f"the sample reaches the sides of the volume (edge ring holds {100 * self.edge_ratio:.0f}% of the centre): "
                "a region-of-interest scan; roi = 'auto' subtracts the average of what the material outside the "
                "volume adds when the volume is as wide as the field of view (docs/method.md §5.17)"
            )
        return "; ".join(parts) if parts else "the sample lies inside the volume"


def detect_truncation(volume, vol_geom: VolumeGeometry, *, threshold: float = 0.2) -> Truncation:
    """Read off a reconstruction whether the sample reaches past the box's faces or sides.

    The mean value of the two end slices (top and bottom 5 %, at least one
    slice each) and of the outer ring of the slices (beyond 90 % of the
    inscribed radius) are compared with that of the central region (middle
    third in z, inside half the radius): above ``threshold`` the sample is
    taken to reach there. Means, not mean absolute values: the noise of a
    reconstruction averages out in air, material does not.
    """
    v = np.asarray(volume, np.float32)
    nz, ny, nx = v.shape
    if nz < 8:  # a stack of a few slices has no end slices to tell from its middle
        vertical_possible = False
    else:
        vertical_possible = True
    y, x = np.meshgrid(np.linspace(-1, 1, ny), np.linspace(-1, 1, nx), indexing="ij")
    r = np.hypot(x, y)
    centre = float(v[nz // 3: max(2 * nz // 3, nz // 3 + 1)][:, r < 0.5].mean())
    if not centre > 0:
        return Truncation(False, False, 0.0, 0.0)
    m = max(1, int(round(0.05 * nz)))
    ends = float(np.concatenate([v[:m], v[-m:]])[:, r < 0.9].mean()) / centre
    ring = (r > 0.9) & (r <= 1.0)
    edge = float(v[nz // 4: max(3 * nz // 4, nz // 4 + 1)][:, ring].mean()) / centre
    return Truncation(vertical_possible and ends > threshold, edge > threshold, ends, edge)


# what the pixels taken as air may hold at most: a share of the pixels examined (a sample must be in the field), and a
# spread about the fitted air in units of the data's noise std (air is flat up to the noise; the thinnest rays through
# a sample wider than the field are not)
AIR_MAX_FRACTION = 0.9
AIR_MAX_SPREAD = 2.0
# ... and the columns where it was measured: on both sides of the detector (a column within AIR_EDGE_COLUMNS of the
# columns from each end), so that the degree-2 profile is interpolated under a sample that covers the middle columns
# in every view (a rod longer than the field), not extrapolated beyond one side; and in at least AIR_MIN_COLUMNS of
# the columns. Until session 43 the rule asked for 90 % of the columns: a rod's air, measured in 30 of 56 columns on
# both sides of it, was left in the data and issue #10's flat field (0.37, 0.30 .. 0.46 across the columns) took the
# rods 0.3-1.3 px farther than nominal (docs/method.md §5.41)
AIR_MIN_COLUMNS = 0.25
AIR_EDGE_COLUMNS = 0.1


def air_columns_span(profile) -> bool:
    """Whether the columns where the air was measured (the finite values of ``profile``) span the detector: at least
    ``AIR_MIN_COLUMNS`` of them, and one within ``AIR_EDGE_COLUMNS`` of the columns from each end."""
    measured = np.flatnonzero(np.isfinite(np.asarray(profile)))
    n = np.size(profile)
    if n == 0 or measured.size < AIR_MIN_COLUMNS * n:
        return False
    edge = max(1, int(np.ceil(AIR_EDGE_COLUMNS * n)))
    return bool(measured[0] < edge and measured[-1] >= n - edge)


def air_to_subtract(air, projections) -> bool:
    """Whether an air estimate is an air level to subtract: measurably off 0 (``AirEstimate.significant``), and air.

    A sample wider than the field of view (a region-of-interest scan) has no
    air; the rays through the least material then look like an air level
    with a profile. They are told apart by what air is: at most
    ``AIR_MAX_FRACTION`` of the pixels (a sample is in the field), and flat
    up to the noise (the spread of the pixels taken as air within
    ``AIR_MAX_SPREAD`` times the data's noise std, Immerkær's estimate).
    Its profile across the columns must also have been measured on both
    sides of the detector (:func:`air_columns_span`): under a sample that
    covers the middle columns in every view the degree-2 profile is then
    interpolated between the two sides, not extrapolated beyond one.
    Measured: a foam twice as wide as the field, 99.9 % of its pixels taken
    as air with a spread of 4.2 noise std; the 180° stand-in of
    ``bench_calibrate.py`` with an air level of 0.37, 49 % and 0.6.
    """
    from ..correlation import estimate_noise_variance

    if not (air.significant and air.air_fraction <= AIR_MAX_FRACTION and air_columns_span(air.profile)):
        return False
    return bool(air.noise_std <= AIR_MAX_SPREAD * np.sqrt(estimate_noise_variance(projections)))


def detect_scan_truncation(projections, vol_geom: VolumeGeometry, geom: VectorGeometry, volume=None):
    """:func:`detect_truncation` on the nominal reconstruction of a scan, its air level removed first.

    Rays that miss the sample should read 0. An air level left by an
    imperfect flat field (:func:`pdvc.io.estimate_air`) adds a constant
    to every ray, and FBP turns that into a bright rim at the edge of the
    field: a sample inside the volume would then look like a
    region-of-interest scan. When the air is measurably off 0
    and is air (:func:`air_to_subtract`), the fitted air (per-view offsets and
    tilts, the column profile and the rows': :func:`pdvc.io.subtract_air`)
    is subtracted and the scan reconstructed again
    for the test. Otherwise ``volume`` (the nominal reconstruction of
    ``projections``, if the caller has it) is used as it is. A scan whose
    sample covers the detector has no air to measure, and is also tested
    as it is.

    Returns
    -------
    (Truncation, AirEstimate)
    """
    from ..io import estimate_air, subtract_air
    from ..recon import analytic

    air = estimate_air(projections)
    if air_to_subtract(air, projections):
        volume = analytic(subtract_air(projections, air)[0], vol_geom, geom)
    elif volume is None:
        volume = analytic(projections, vol_geom, geom)
    return detect_truncation(volume, vol_geom), air


def cylinder_window(vol_geom: VolumeGeometry, *, taper: float = 0.2) -> np.ndarray:
    """A soft cylinder about the volume's z axis: 1 inside ``(1 - taper)`` of the inscribed radius, 0 outside it.

    ``(ny, nx)`` float32, falling linearly to zero between the two radii. The
    re-projection of a volume multiplied by it has the same support, and
    (about a centred axis) the same profile, in every view: no square corner
    of the box comes and goes with the angle.
    """
    nz, ny, nx = vol_geom.shape
    sy, sx = float(vol_geom.voxel_size[1]), float(vol_geom.voxel_size[2])
    y = (np.arange(ny) - (ny - 1) / 2) * sy
    x = (np.arange(nx) - (nx - 1) / 2) * sx
    r = np.hypot(y[:, None], x[None, :]) / (0.5 * min(ny * sy, nx * sx))
    return np.clip((1.0 - r) / taper, 0.0, 1.0).astype(np.float32)


def outside_pattern(projections, vol_geom: VolumeGeometry, geom: VectorGeometry, *, taper: float = 0.2) -> np.ndarray:
    """What a sample wider than the volume adds to every view: the mean over the views of the data minus the
    re-projection of its reconstruction inside the volume's inscribed cylinder, ``(n_rows, n_cols)`` float32.

    A region-of-interest scan sees the sample outside the field of view on
    every ray. About the rotation axis that part is nearly the same in every
    view, so its mean over the views, subtracted, leaves the projections of
    the cylinder alone (its structure outside the cylinder, less its mean,
    stays as noise). The reconstruction carries the rows' edge values outward
    for the ramp filter (``padding="edge"``), which keeps the bright rim of a
    truncated reconstruction out of the cylinder.
    """
    from ..projectors import forward
    from ..recon import analytic

    vol = analytic(projections, vol_geom, geom, padding="edge")
    vol *= cylinder_window(vol_geom, taper=taper)[None]
    q = forward(vol, vol_geom, geom)
    out = np.zeros(geom.det_shape, np.float64)
    for k0 in range(0, geom.n_views, 64):
        out += (np.asarray(projections[k0:k0 + 64], np.float64) - q[k0:k0 + 64]).sum(axis=0)
    return (out / geom.n_views).astype(np.float32)


def field_radius(geom: VectorGeometry, vol_geom: VolumeGeometry) -> float:
    """Radius of the field of view about the volume's z axis: the median over the views of the distance, in the xy
    plane, from that axis to the nearer of the rays through the two outer columns of the middle row (length units)."""
    nr, nc = geom.det_shape
    mid = (nr - 1) / 2
    c = np.asarray(vol_geom.offset, float)
    out = []
    for j in (0, nc - 1):
        pix = geom.det_center + (j - (nc - 1) / 2) * geom.u + (mid - (nr - 1) / 2) * geom.v
        a, d = (geom.src, pix - geom.src) if geom.kind == "cone" else (pix, geom.ray)
        norm = np.hypot(d[:, 0], d[:, 1])
        dist = np.abs(d[:, 0] * (c[1] - a[:, 1]) - d[:, 1] * (c[0] - a[:, 0])) / np.where(norm > 0, norm, np.inf)
        out.append(dist)
    return float(np.median(np.minimum(*out)))


def field_cover(geom: VectorGeometry, vol_geom: VolumeGeometry) -> float:
    """The volume's inscribed radius (in x and y) over the field of view's (:func:`field_radius`)."""
    return 0.5 * min(vol_geom.extent_xyz[0], vol_geom.extent_xyz[1]) / field_radius(geom, vol_geom)
