"""Numba CPU kernels: forward projection, its exact adjoint, the fused
Jacobian pass (images or reduced per view).

The discrete model
------------------
Work happens in continuous *index* coordinates ``(ix, iy, iz)`` of the voxel
grid (voxel centres at integers).  A ray ``q(t) = s + t d`` is sampled where
it crosses the planes ``i = 0 .. n_a - 1`` of its dominant axis ``a`` (the
axis along which ``|d_a|`` is largest), and on each plane the volume is
interpolated bilinearly in the two other axes (Joseph's method, the scheme of
ASTRA's GPU cone projector).  The line integral is

    P = L * sum_i f~(p_b(i), p_c(i)),   L = |d_world| / |d_a|,

with ``L`` the world length of the ray between two planes.  The interpolant
is the zero-padded one: it falls linearly to zero within one voxel outside
the outer voxel centres, so projections are continuous in the geometry even
when the volume's border is not empty (a sample taller than the field of
view).  Every sample sits exactly on a grid plane, so each ray needs 4
gathers per plane and no more than ``n_a`` samples.  Samples whose four
neighbours are all inside the grid take a fast path (incremental, branch-free,
unsigned offsets so that numba adds no negative-index wrap-around to the
gathers and scatters); the few at the border take a checked one.

Exact Jacobian
--------------
Moving the sample by ``x -> x + tau + omega x (x - c)`` moves each ray the
other way: ``ds = -tau - omega x (s - c)``, ``dd = -omega x d``.  Since
``p_b(i) = s_b + (i - s_a) d_b / d_a``, the derivative of ``P`` needs only
five sums per ray, accumulated in the same pass:
``S0 = sum f~``, ``Sb = sum df~/dp_b``, ``Sc = sum df~/dp_c``,
``Tb = sum t_i df~/dp_b``, ``Tc = sum t_i df~/dp_c`` with
``t_i = (i - s_a) / d_a``; then

    dP = dL S0 + L [Sb (ds_b - ds_a r_b) + Tb (dd_b - dd_a r_b)
                    + Sc (ds_c - ds_a r_c) + Tc (dd_c - dd_a r_c)],

``r_b = d_b / d_a`` and ``dL = -L dd_a / d_a`` (``dd`` is orthogonal to
``d`` for a rotation).  This is the exact derivative of the discrete forward
model (away from the kinks of the bilinear interpolant), checked against
finite differences in the tests.

Exact adjoint without races
---------------------------
The adjoint scatters the same weights.  The volume is cut into slabs of
z-rows and a sample belongs to the slab of its z-cell (the lower of the two
z-rows it touches; planes of z-dominant rays belong to their own row), so
each sample is scattered once.  A slab visits only the detector window its
box projects to and re-clips every ray exactly as the forward does.  Since
a cell also writes the row above it, a slab writes the first row of the next
slab: the even slabs run in parallel, then the odd ones.  No atomics, no
per-thread volume copies, the same arithmetic as the forward (so the
dot-product test holds to float rounding).

Two things make the scatter cheap (issue #13). The forward's interior loop
is vectorised by the compiler (gathers); a scatter loop cannot be, so the
adjoint computes the targets and weights of a chunk of samples in a
vectorised loop and adds them in a scalar one. And a slab accumulates in a
private buffer whose z-rows are padded by a cache line, then adds it to the
volume: in the volume, the two z-rows of a sample's four targets lie a
multiple of 4 KiB apart, and a load that followed a store to the other row
stalled (most likely on the processor's 4K-aliasing check; the padding
removes the cost).
"""

from __future__ import annotations

import math

import numpy as np
from numba import float32, njit, prange, uint64

# Layout of the per-view geometry table (index coordinates, xyz order):
#  0:3  source (cone) or ray direction (parallel)
#  3:6  centre of pixel (0, 0)
#  6:9  step to the next column
#  9:12 step to the next row
# Floating-point licence of the kernels: contraction to FMA, reassociation of
# sums, no signed zeros, reciprocal division. Not "nnan"/"ninf": the ray
# clipping must stay correct for rays parallel to a grid plane.
_FAST = {"contract", "reassoc", "nsz", "arcp"}

# Interior samples of one ray are scattered in chunks of this many: their
# targets and weights are computed first, in a loop that the compiler
# vectorises (every sample independent), then added to the volume in a
# scalar loop (issue #13).
SCATTER_CHUNK = 32
# The adjoint accumulates each slab in a private buffer whose z-rows are this
# many floats (one cache line) longer than a volume plane: in the volume
# itself two z-rows lie a multiple of 4 KiB apart (256³: 256 KiB), and a
# load from one row right after a store to the other stalled, most likely on
# the processor's 4K-aliasing check (256³ x 60 views, Intel Xeon, 2 threads:
# 1.61x -> 1.37x the forward's time).
ROW_PAD = 16

N_RED = 38  # 21 (upper triangle of M) + 6 (b) + rss + sum w + sum w s + sum w s^2 + sum w rho + 6 (sum w g)


@njit(inline="always")
def _ray(geo, k, row, col, cone):
    px = geo[k, 3] + col * geo[k, 6] + row * geo[k, 9]
    py = geo[k, 4] + col * geo[k, 7] + row * geo[k, 10]
    pz = geo[k, 5] + col * geo[k, 8] + row * geo[k, 11]
    if cone:
        sx, sy, sz = geo[k, 0], geo[k, 1], geo[k, 2]
        return sx, sy, sz, px - sx, py - sy, pz - sz
    return px, py, pz, geo[k, 0], geo[k, 1], geo[k, 2]


@njit(inline="always")
def _axes(sx, sy, sz, dx, dy, dz, nx, ny, nz):
    """Dominant axis a and the in-plane axes b < c; returns their data.

    Returns (a, sa, sb, sc, da, db, dc, na, nb, nc, sta, stb, stc); strides are
    those of the C-ordered f[z, y, x] raveled.
    """
    ax, ay, az = abs(dx), abs(dy), abs(dz)
    if ax >= ay and ax >= az:
        return 0, sx, sy, sz, dx, dy, dz, nx, ny, nz, 1, nx, nx * ny
    if ay >= az:
        return 1, sy, sx, sz, dy, dx, dz, ny, nx, nz, nx, 1, nx * ny
    return 2, sz, sx, sy, dz, dx, dy, nz, nx, ny, nx * ny, 1, nx


@njit(inline="always")
def _range(sa, sb, sc, da, rb, rc, lo, hi, lob, hib, loc, hic):
    """Inclusive plane range where lob <= p_b <= hib and loc <= p_c <= hic."""
    if rb != 0.0:
        i1 = sa + (lob - sb) / rb
        i2 = sa + (hib - sb) / rb
        if i1 > i2:
            i1, i2 = i2, i1
        lo = max(lo, i1)
        hi = min(hi, i2)
    elif sb < lob or sb > hib:
        return 0, -1
    if rc != 0.0:
        i1 = sa + (loc - sc) / rc
        i2 = sa + (hic - sc) / rc
        if i1 > i2:
            i1, i2 = i2, i1
        lo = max(lo, i1)
        hi = min(hi, i2)
    elif sc < loc or sc > hic:
        return 0, -1
    if hi < lo:
        return 0, -1
    return int(math.ceil(lo)), int(math.floor(hi))


@njit(inline="always")
def _clip(sa, sb, sc, da, rb, rc, na, nb, nc, cone):
    """Plane ranges of one ray: all samples [ilo, ihi] (in-plane support of
    the zero-padded interpolant, (-1, n)) and the interior ones [jlo, jhi]
    whose four neighbours are inside the grid ([0, n-1])."""
    lo = 0.0
    hi = na - 1.0
    if cone:  # half-line from the source: t = (i - sa) / da >= 0
        if da > 0.0:
            lo = max(lo, sa)
        else:
            hi = min(hi, sa)
    ilo, ihi = _range(sa, sb, sc, da, rb, rc, lo, hi, -1.0, float(nb), -1.0, float(nc))
    if nb < 2 or nc < 2:
        # a grid one voxel thick in-plane has no cell with four neighbours
        # inside: every sample takes the checked path (VolumeGeometry asks
        # for >= 2 voxels per axis; the unsigned interior gathers rely on it)
        return ilo, ihi, 0, -1
    jlo, jhi = _range(sa, sb, sc, da, rb, rc, lo, hi, 0.0, nb - 1.0, 0.0, nc - 1.0)
    return ilo, ihi, jlo, jhi


@njit(inline="always")
def _cell(p, n):
    """Clamp p to [0, n-1]; lower cell index (<= n-2) and weight."""
    p = min(max(p, 0.0), n - 1.0)
    i = min(int(p), n - 2)
    return i, p - i


@njit(inline="always")
def _cell_pad(p, n):
    """Border cell of the zero-padded grid: index in [-1, n-1] and weight."""
    p = min(max(p, -1.0), float(n))
    i = min(int(math.floor(p)), n - 1)
    return i, p - i


@njit(inline="always")
def _corners(vf, o, ib, ic, stb, stc, nb, nc, interior):
    """The four neighbours f00, f10 (b+1), f01 (c+1), f11 of a sample; zero outside."""
    if interior:
        # unsigned offsets: all four are inside the array, and numba then
        # drops the negative-index wrap-around of every gather
        ub = uint64(stb)
        uc = uint64(stc)
        oo = uint64(o) + uint64(ib) * ub + uint64(ic) * uc
        return vf[oo], vf[oo + ub], vf[oo + uc], vf[oo + ub + uc]
    b0 = ib >= 0
    b1 = ib + 1 <= nb - 1
    c0 = ic >= 0
    c1 = ic + 1 <= nc - 1
    f00 = vf[o + ib * stb + ic * stc] if (b0 and c0) else 0.0
    f10 = vf[o + (ib + 1) * stb + ic * stc] if (b1 and c0) else 0.0
    f01 = vf[o + ib * stb + (ic + 1) * stc] if (b0 and c1) else 0.0
    f11 = vf[o + (ib + 1) * stb + (ic + 1) * stc] if (b1 and c1) else 0.0
    return f00, f10, f01, f11


@njit(inline="always")
def _sample_cells(sb, sc, rb, rc, sa, i, nb, nc, interior):
    pb = sb + (i - sa) * rb
    pc = sc + (i - sa) * rc
    if interior:
        ib, wb = _cell(pb, nb)
        ic, wc = _cell(pc, nc)
    else:
        ib, wb = _cell_pad(pb, nb)
        ic, wc = _cell_pad(pc, nc)
    return ib, wb, ic, wc


@njit(inline="always")
def _interior(ilo, ihi, jlo, jhi):
    """Interior range clipped into [ilo, ihi]; empty as (ihi + 1, ihi)."""
    jlo = max(jlo, ilo)
    jhi = min(jhi, ihi)
    if jlo > jhi:
        return ihi + 1, ihi
    return jlo, jhi


@njit(inline="always")
def _scatter_checked(buf, o, ib, wb, ic, wc, w, stb, stc, nb, nc, own_lo, own_hi):
    """Scatter one border sample: only targets inside the grid and in owned c-rows."""
    b0 = ib >= 0
    b1 = ib + 1 <= nb - 1
    c0 = ic >= 0 and own_lo <= ic < own_hi
    c1 = ic + 1 <= nc - 1 and own_lo <= ic + 1 < own_hi
    if b0 and c0:
        buf[o + ib * stb + ic * stc] += w * (1.0 - wb) * (1.0 - wc)
    if b1 and c0:
        buf[o + (ib + 1) * stb + ic * stc] += w * wb * (1.0 - wc)
    if b0 and c1:
        buf[o + ib * stb + (ic + 1) * stc] += w * (1.0 - wb) * wc
    if b1 and c1:
        buf[o + (ib + 1) * stb + (ic + 1) * stc] += w * wb * wc


@njit(inline="always")
def _path_length(da, dx, dy, dz, spx, spy, spz):
    wx, wy, wz = dx * spx, dy * spy, dz * spz
    return math.sqrt(wx * wx + wy * wy + wz * wz) / abs(da)


@njit(inline="always")
def _line_integral(vf, sx, sy, sz, dx, dy, dz, nx, ny, nz, spx, spy, spz, cone):
    a, sa, sb, sc, da, db, dc, na, nb, nc, sta, stb, stc = _axes(sx, sy, sz, dx, dy, dz, nx, ny, nz)
    rb = db / da
    rc = dc / da
    ilo, ihi, jlo, jhi = _clip(sa, sb, sc, da, rb, rc, na, nb, nc, cone)
    jlo, jhi = _interior(ilo, ihi, jlo, jhi)
    acc = 0.0
    # border samples before the interior (or all samples if there is none)
    for i in range(ilo, min(jlo, ihi + 1)):
        ib, wb, ic, wc = _sample_cells(sb, sc, rb, rc, sa, i, nb, nc, False)
        f00, f10, f01, f11 = _corners(vf, i * sta, ib, ic, stb, stc, nb, nc, False)
        acc += (1.0 - wc) * (f00 + wb * (f10 - f00)) + wc * (f01 + wb * (f11 - f01))
    # interior: all four neighbours inside, incremental and branch-free.
    # Offsets are unsigned (uint64 throughout: numba would turn a mixed
    # int64/uint64 sum into a float): every gather is inside the array, and
    # signed indices made numba add a negative-index wrap-around to each of
    # the four loads, a quarter of the loop's time (issue #13).
    nb2 = nb - 2
    nc2 = nc - 2
    pb = sb + (jlo - sa) * rb
    pc = sc + (jlo - sa) * rc
    ustb = uint64(stb)
    ustc = uint64(stc)
    usta = uint64(sta)
    o = uint64(max(jlo, 0)) * usta
    for i in range(jlo, jhi + 1):
        ib = min(int(pb), nb2)  # int() truncates: pb >= -eps gives 0
        ic = min(int(pc), nc2)
        wb = pb - ib
        wc = pc - ic
        oo = o + uint64(ib) * ustb + uint64(ic) * ustc
        f00 = vf[oo]
        f10 = vf[oo + ustb]
        f01 = vf[oo + ustc]
        f11 = vf[oo + ustb + ustc]
        acc += (1.0 - wc) * (f00 + wb * (f10 - f00)) + wc * (f01 + wb * (f11 - f01))
        pb += rb
        pc += rc
        o += usta
    for i in range(max(jhi + 1, ilo), ihi + 1):
        ib, wb, ic, wc = _sample_cells(sb, sc, rb, rc, sa, i, nb, nc, False)
        f00, f10, f01, f11 = _corners(vf, i * sta, ib, ic, stb, stc, nb, nc, False)
        acc += (1.0 - wc) * (f00 + wb * (f10 - f00)) + wc * (f01 + wb * (f11 - f01))
    return acc * _path_length(da, dx, dy, dz, spx, spy, spz)


@njit(parallel=True, cache=True, fastmath=_FAST)
def forward_kernel(vf, shape_xyz, spacing_xyz, geo, cone, out):
    """out[k, r, c] = line integral of pixel (r, c) of view k."""
    nx, ny, nz = shape_xyz[0], shape_xyz[1], shape_xyz[2]
    spx, spy, spz = spacing_xyz[0], spacing_xyz[1], spacing_xyz[2]
    n_views, n_rows, n_cols = out.shape
    # Row-major walk: a detector row of every view, then the next row. The
    # rays of one row in all views cross the same few z-rows of the volume,
    # which then stay in cache; walking view by view streamed the whole
    # volume from memory once per view (256³: 1.7x slower, issue #13).
    for rk in prange(n_views * n_rows):
        r = rk // n_views
        k = rk - r * n_views
        for c in range(n_cols):
            sx, sy, sz, dx, dy, dz = _ray(geo, k, r, c, cone)
            out[k, r, c] = _line_integral(vf, sx, sy, sz, dx, dy, dz, nx, ny, nz, spx, spy, spz, cone)


@njit(cache=True)
def _window(geo, k, cone, box_lo, box_hi, n_rows, n_cols):
    """Detector window [r0, r1] x [c0, c1] that the index box projects to.

    Exact bounding box of the projected corners (the image of a box in front
    of the source is the hull of its corners' images); the full detector if
    the source is inside or beside the box.
    """
    # detector frame: pixel (row, col) centre = p00 + col U + row V
    ux, uy, uz = geo[k, 6], geo[k, 7], geo[k, 8]
    vx, vy, vz = geo[k, 9], geo[k, 10], geo[k, 11]
    nxn = uy * vz - uz * vy
    nyn = uz * vx - ux * vz
    nzn = ux * vy - uy * vx
    uu = ux * ux + uy * uy + uz * uz
    vv = vx * vx + vy * vy + vz * vz
    uv = ux * vx + uy * vy + uz * vz
    det = uu * vv - uv * uv
    rmin, rmax, cmin, cmax = 1e300, -1e300, 1e300, -1e300
    for corner in range(8):
        x = box_hi[0] if corner & 1 else box_lo[0]
        y = box_hi[1] if corner & 2 else box_lo[1]
        z = box_hi[2] if corner & 4 else box_lo[2]
        if cone:
            ox, oy, oz = geo[k, 0], geo[k, 1], geo[k, 2]
            dx, dy, dz = x - ox, y - oy, z - oz
        else:
            ox, oy, oz = x, y, z
            dx, dy, dz = geo[k, 0], geo[k, 1], geo[k, 2]
        den = dx * nxn + dy * nyn + dz * nzn
        num = (geo[k, 3] - ox) * nxn + (geo[k, 4] - oy) * nyn + (geo[k, 5] - oz) * nzn
        if den == 0.0:
            return 0, n_rows - 1, 0, n_cols - 1
        t = num / den
        if cone and t <= 0.0:
            return 0, n_rows - 1, 0, n_cols - 1
        hx = ox + t * dx - geo[k, 3]
        hy = oy + t * dy - geo[k, 4]
        hz = oz + t * dz - geo[k, 5]
        hu = hx * ux + hy * uy + hz * uz
        hv = hx * vx + hy * vy + hz * vz
        col = (hu * vv - hv * uv) / det
        row = (hv * uu - hu * uv) / det
        rmin = min(rmin, row)
        rmax = max(rmax, row)
        cmin = min(cmin, col)
        cmax = max(cmax, col)
    r0 = max(0, int(math.floor(rmin)) - 1)
    r1 = min(n_rows - 1, int(math.ceil(rmax)) + 1)
    c0 = max(0, int(math.floor(cmin)) - 1)
    c1 = min(n_cols - 1, int(math.ceil(cmax)) + 1)
    return r0, r1, c0, c1


@njit(inline="always")
def _scatter_ray(scratch_o, scratch_wb, scratch_w1, buf, base, w, sa, sb, sc, rb, rc, ilo, ihi, flo, fhi,
                 sta, stb, stc, nb, nc, own_lo, own_hi, clo, chi):
    """Scatter ``w`` times the bilinear weights of samples [ilo, ihi] of one ray.

    ``buf`` holds the slab's rows, starting at offset ``base`` of an index
    space whose strides are ``sta``, ``stb``, ``stc`` (the slab's padded
    rows); samples [flo, fhi] (within [ilo, ihi], or empty as
    (ihi + 1, ihi)) have all four targets inside the grid and owned and take
    the unchecked path, their c cell clamped to [clo, chi] (a sample that
    rounding puts a hair outside its owner's cells keeps its weights to
    rounding); the others are checked against the grid and the owned c-rows
    [own_lo, own_hi). ``scratch_*``: the caller's work arrays of
    ``SCATTER_CHUNK`` entries.
    """
    for i in range(ilo, min(flo, ihi + 1)):
        ib, wb, ic, wc = _sample_cells(sb, sc, rb, rc, sa, i, nb, nc, False)
        _scatter_checked(buf, i * sta - base, ib, wb, ic, wc, w, stb, stc, nb, nc, own_lo, own_hi)
    nb2 = nb - 2
    pb = sb + (flo - sa) * rb
    pc = sc + (flo - sa) * rc
    # unsigned offsets, as in the forward: o may be "negative" (flo * sta <
    # base), but the uint64 sums wrap modulo 2^64 to the true offset of an
    # owned target, which is >= 0
    ustb = uint64(stb)
    ustc = uint64(stc)
    usta = uint64(sta)
    o = uint64(max(flo, 0) * sta - base)
    # the weights in float32, the precision of the volume: float64 weights
    # cost a conversion each way on every read-modify-write (8 a sample),
    # float32 ones two a sample; the positions stay float64, as in the
    # forward (measured on 256³ x 360 views, 2 threads: 1.60 -> 1.44x the
    # forward's time)
    w32 = float32(w)
    # Two loops per chunk of SCATTER_CHUNK samples: the first computes each
    # sample's target offset and weights into scratch arrays and is
    # vectorised (as the forward's gather loop is); the second does the four
    # read-modify-writes, which no compiler vectorises (it cannot prove the
    # targets distinct). Measured on 256³ x 60 views (Intel Xeon, 2 threads),
    # in the forward's time: one fused scalar loop 2.0x, the split one 1.65x;
    # with the padded rows (ROW_PAD) 1.97x fused, 1.37x split.
    i0 = flo
    while i0 <= fhi:
        m = min(SCATTER_CHUNK, fhi - i0 + 1)
        for j in range(m):
            ib = min(int(pb), nb2)
            ic = min(max(int(pc), clo), chi)
            scratch_o[j] = o + uint64(ib) * ustb + uint64(ic) * ustc
            scratch_wb[j] = float32(pb - ib)
            scratch_w1[j] = w32 * float32(pc - ic)  # w wc
            pb += rb
            pc += rc
            o += usta
        for j in range(m):
            oo = scratch_o[j]
            wb = scratch_wb[j]
            w1 = scratch_w1[j]
            w0 = w32 - w1  # w (1 - wc)
            v0 = w0 * wb
            v1 = w1 * wb
            o1 = oo + ustb
            o2 = oo + ustc
            o3 = o1 + ustc
            # the four loads before the four stores (measured: 1.43x -> 1.36x)
            f00 = buf[oo]
            f10 = buf[o1]
            f01 = buf[o2]
            f11 = buf[o3]
            buf[oo] = f00 + (w0 - v0)
            buf[o1] = f10 + v0
            buf[o2] = f01 + (w1 - v1)
            buf[o3] = f11 + v1
        i0 += m
    for i in range(max(fhi + 1, ilo), ihi + 1):
        ib, wb, ic, wc = _sample_cells(sb, sc, rb, rc, sa, i, nb, nc, False)
        _scatter_checked(buf, i * sta - base, ib, wb, ic, wc, w, stb, stc, nb, nc, own_lo, own_hi)


@njit(inline="always")
def _plane_range(sa, sc, rc, lo, hi, ilo, ihi):
    """Samples i in [ilo, ihi] with lo <= p_c(i) < hi, p_c(i) = sc + (i - sa) rc.

    The bounds come from t(z) = sa + (z - sc) / rc alone, so two slabs that
    share a boundary z split the samples between them exactly (no sample in
    both, none in neither), whatever the rounding.
    """
    if rc == 0.0:
        if lo <= sc < hi:
            return ilo, ihi
        return ihi + 1, ihi
    tlo = min(max(sa + (lo - sc) / rc, ilo - 1.0), ihi + 1.0)
    thi = min(max(sa + (hi - sc) / rc, ilo - 1.0), ihi + 1.0)
    if rc > 0.0:
        a = int(math.ceil(tlo))
        b = int(math.ceil(thi)) - 1
    else:
        a = int(math.floor(thi)) + 1
        b = int(math.floor(tlo))
    return max(a, ilo), min(b, ihi)


@njit(cache=True, fastmath=_FAST)
def _adjoint_slab(proj, s, slab_edges, geo, cone, nx, ny, nz, spx, spy, spz, out):
    """Scatter into ``out`` every sample whose z-cell belongs to slab ``s``.

    Compiled on its own, not inlined into the parallel loop: numba hoists
    the allocations of a parallel loop's body out of it, to be reused by all
    the iterations a thread runs, and this function's buffers depend on the
    slab (sized for a thread's first slab, a larger one later would write
    past the end).
    """
    n_views, n_rows, n_cols = proj.shape
    n_slabs = slab_edges.shape[0] - 1
    plane = nx * ny
    zlo = slab_edges[s]
    zhi = slab_edges[s + 1]
    # cells [zlo, zhi) (and the zero-padded border cells at the grid's ends)
    # belong to the slab; a cell writes its rows ic and ic + 1, so the slab
    # writes rows [zlo, zhi]: its own and the next slab's first
    clo = -2.0 if s == 0 else float(zlo)
    chi = float(nz + 1) if s == n_slabs - 1 else float(zhi)
    row_hi = min(zhi + 1, nz)
    # the slab's rows [zlo, row_hi) in a private buffer of padded rows (see
    # ROW_PAD), added to the volume at the end
    stride = plane + ROW_PAD
    n_own = row_hi - zlo
    buf = np.zeros(n_own * stride, np.float32)
    base = zlo * stride
    scratch_o = np.empty(SCATTER_CHUNK, np.uint64)
    scratch_wb = np.empty(SCATTER_CHUNK, np.float32)
    scratch_w1 = np.empty(SCATTER_CHUNK, np.float32)
    box_lo = np.array([-1.0, -1.0, max(clo, -1.0)])
    box_hi = np.array([float(nx), float(ny), min(chi, float(nz))])
    for k in range(n_views):
        row0, row1, col0, col1 = _window(geo, k, cone, box_lo, box_hi, n_rows, n_cols)
        for r in range(row0, row1 + 1):
            for c in range(col0, col1 + 1):
                val = proj[k, r, c]
                if val == 0.0:
                    continue
                sx, sy, sz, dx, dy, dz = _ray(geo, k, r, c, cone)
                a, sa, sb, sc, da, db, dc, na, nb, nc, sta, stb, stc = _axes(sx, sy, sz, dx, dy, dz, nx, ny, nz)
                rb = db / da
                rc = dc / da
                if a == 2:
                    # planes are z-rows: the slab's planes, every in-plane row
                    sta = stride
                    plo, phi = zlo, zhi - 1
                    own_lo, own_hi, c_lo, c_hi = -2, nc + 2, 0, nc - 2
                else:
                    # z is the in-plane axis c: the samples whose z-cell is the
                    # slab's; a ray that misses the slab is left before its clip
                    stc = stride
                    plo, phi = _plane_range(sa, sc, rc, clo, chi, 0, na - 1)
                    if plo > phi:
                        continue
                    own_lo, own_hi = zlo, row_hi
                    c_lo, c_hi = max(zlo, 0), min(zhi - 1, nc - 2)
                ilo, ihi, jlo, jhi = _clip(sa, sb, sc, da, rb, rc, na, nb, nc, cone)
                ilo = max(ilo, plo)
                ihi = min(ihi, phi)
                if ilo > ihi:
                    continue
                w = val * _path_length(da, dx, dy, dz, spx, spy, spz)
                flo, fhi = _interior(ilo, ihi, jlo, jhi)
                _scatter_ray(scratch_o, scratch_wb, scratch_w1, buf, base, w, sa, sb, sc, rb, rc, ilo, ihi,
                             flo, fhi, sta, stb, stc, nb, nc, own_lo, own_hi, c_lo, c_hi)
    for q in range(n_own):
        row = out[(zlo + q) * plane : (zlo + q + 1) * plane]
        acc = buf[q * stride : q * stride + plane]
        for e in range(plane):
            row[e] += acc[e]


@njit(parallel=True, cache=True, fastmath=_FAST)
def adjoint_kernel(proj, shape_xyz, spacing_xyz, geo, cone, slab_edges, out):
    """out (raveled f[z, y, x]) = exact transpose of forward_kernel applied to proj.

    Slabs of z-rows (``slab_edges``, each at least 2 rows) own the samples
    whose z-cell lies in them, so every sample is scattered once. A slab
    also writes the first row of the next one: the even slabs run in
    parallel, then the odd ones, so that no two running slabs share a row.
    """
    nx, ny, nz = shape_xyz[0], shape_xyz[1], shape_xyz[2]
    spx, spy, spz = spacing_xyz[0], spacing_xyz[1], spacing_xyz[2]
    n_slabs = slab_edges.shape[0] - 1
    plane = nx * ny
    for s in prange(n_slabs):
        out[slab_edges[s] * plane : slab_edges[s + 1] * plane] = 0.0
    for phase in range(2):
        for j in prange((n_slabs - phase + 1) // 2):
            _adjoint_slab(proj, 2 * j + phase, slab_edges, geo, cone, nx, ny, nz, spx, spy, spz, out)


@njit(inline="always")
def _ray_sums(vf, sx, sy, sz, dx, dy, dz, nx, ny, nz, cone):
    """Plane-sampled sums along one ray (see module docstring)."""
    a, sa, sb, sc, da, db, dc, na, nb, nc, sta, stb, stc = _axes(sx, sy, sz, dx, dy, dz, nx, ny, nz)
    rb = db / da
    rc = dc / da
    ilo, ihi, jlo, jhi = _clip(sa, sb, sc, da, rb, rc, na, nb, nc, cone)
    s0 = 0.0
    s_b = 0.0
    s_c = 0.0
    t_b = 0.0
    t_c = 0.0
    inv_da = 1.0 / da
    jlo, jhi = _interior(ilo, ihi, jlo, jhi)
    for part in range(3):
        if part == 0:
            i0, i1 = ilo, min(jlo, ihi + 1)
        elif part == 1:
            i0, i1 = jlo, jhi + 1
        else:
            i0, i1 = max(jhi + 1, ilo), ihi + 1
        interior = part == 1
        pb = sb + (i0 - sa) * rb
        pc = sc + (i0 - sa) * rc
        ti = (i0 - sa) * inv_da
        for i in range(i0, i1):
            if interior:
                ib = min(int(pb), nb - 2)
                ic = min(int(pc), nc - 2)
                wb = pb - ib
                wc = pc - ic
            else:
                ib, wb, ic, wc = _sample_cells(sb, sc, rb, rc, sa, i, nb, nc, False)
            f00, f10, f01, f11 = _corners(vf, i * sta, ib, ic, stb, stc, nb, nc, interior)
            d0 = f10 - f00
            d1 = f11 - f01
            s0 += (1.0 - wc) * (f00 + wb * d0) + wc * (f01 + wb * d1)
            gb = (1.0 - wc) * d0 + wc * d1
            gc = (1.0 - wb) * (f01 - f00) + wb * (f11 - f10)
            s_b += gb
            s_c += gc
            t_b += ti * gb
            t_c += ti * gc
            pb += rb
            pc += rc
            ti += inv_da
    return a, s0, s_b, s_c, t_b, t_c


@njit(inline="always")
def _pick(a, x, y, z):
    """(value along a, along b, along c) of an xyz triple, b < c the other axes."""
    if a == 0:
        return x, y, z
    if a == 1:
        return y, x, z
    return z, x, y


@njit(inline="always")
def _sensitivities(g, vf, sx, sy, sz, dx, dy, dz, nx, ny, nz, spx, spy, spz, ox, oy, oz, cx, cy, cz, cone):
    """Line integral and its 6 derivatives (tx, ty, tz, rx, ry, rz) into g[0:6].

    Translations in world units, rotations in radians about the world point
    (cx, cy, cz); (ox, oy, oz) is the world position of index (0, 0, 0).
    """
    a, s0, s_b, s_c, t_b, t_c = _ray_sums(vf, sx, sy, sz, dx, dy, dz, nx, ny, nz, cone)
    da, db, dc = _pick(a, dx, dy, dz)
    L = _path_length(da, dx, dy, dz, spx, spy, spz)
    rb = db / da
    rc = dc / da
    # world position relative to c and world direction
    wsx = ox + sx * spx - cx
    wsy = oy + sy * spy - cy
    wsz = oz + sz * spz - cz
    wdx, wdy, wdz = dx * spx, dy * spy, dz * spz
    for j in range(6):
        # world perturbation of ray point (ps) and direction (pd) for mode j
        psx = psy = psz = 0.0
        pdx = pdy = pdz = 0.0
        if j == 0:
            psx = -1.0
        elif j == 1:
            psy = -1.0
        elif j == 2:
            psz = -1.0
        elif j == 3:  # -e_x x w = (0, w_z, -w_y)
            psy, psz = wsz, -wsy
            pdy, pdz = wdz, -wdy
        elif j == 4:  # -e_y x w = (-w_z, 0, w_x)
            psx, psz = -wsz, wsx
            pdx, pdz = -wdz, wdx
        else:  # -e_z x w = (w_y, -w_x, 0)
            psx, psy = wsy, -wsx
            pdx, pdy = wdy, -wdx
        # to index coordinates
        qa, qb, qc = _pick(a, psx / spx, psy / spy, psz / spz)
        ea, eb, ec = _pick(a, pdx / spx, pdy / spy, pdz / spz)
        dlog = -ea / da  # dL / L
        g[j] = L * (
            dlog * s0
            + s_b * (qb - qa * rb)
            + t_b * (eb - ea * rb)
            + s_c * (qc - qa * rc)
            + t_c * (ec - ea * rc)
        )
    return L * s0


@njit(parallel=True, cache=True, fastmath=_FAST)
def jacobian_images_kernel(vf, shape_xyz, spacing_xyz, origin_xyz, center_xyz, geo, cone, out_proj, out_sens):
    nx, ny, nz = shape_xyz[0], shape_xyz[1], shape_xyz[2]
    spx, spy, spz = spacing_xyz[0], spacing_xyz[1], spacing_xyz[2]
    ox, oy, oz = origin_xyz[0], origin_xyz[1], origin_xyz[2]
    cx, cy, cz = center_xyz[0], center_xyz[1], center_xyz[2]
    n_views, n_rows, n_cols = out_proj.shape
    for rk in prange(n_views * n_rows):
        r = rk // n_views  # row-major: see forward_kernel
        k = rk - r * n_views
        g = np.empty(6)
        for c in range(n_cols):
            sx, sy, sz, dx, dy, dz = _ray(geo, k, r, c, cone)
            p = _sensitivities(g, vf, sx, sy, sz, dx, dy, dz, nx, ny, nz, spx, spy, spz, ox, oy, oz, cx, cy, cz, cone)
            out_proj[k, r, c] = p
            for j in range(6):
                out_sens[k, j, r, c] = g[j]


@njit(parallel=True, cache=True, fastmath=_FAST)
def jacobian_reduce_kernel(
    vf, shape_xyz, spacing_xyz, origin_xyz, center_xyz, geo, cone, meas, weights, cut, shift, partial
):
    """Per (view, row): sums of w g gᵀ (upper triangle), w g ρ, w ρ², w, w s, w s², w ρ, w g.

    ρ = s - P (measured minus projected), so that M⁻¹ b is the Gauss-Newton
    step of one view.  ``weights`` has 1 or n_views leading entries.

    ``cut > 0``: Huber weights on ``e = ρ - shift[k]`` (iteratively
    reweighted least squares, the weights of this pass's residual): every
    sum above uses ``w min(1, cut / |e|)`` and ``e`` in place of ``w`` and
    ``ρ``, except ``Σ w s``, ``Σ w s²`` (the data's) and the residual slot,
    which holds Huber's loss ``Σ w L(e)`` (``L(e) = e²`` inside the cut,
    ``2 cut |e| - cut²`` outside).
    """
    nx, ny, nz = shape_xyz[0], shape_xyz[1], shape_xyz[2]
    spx, spy, spz = spacing_xyz[0], spacing_xyz[1], spacing_xyz[2]
    ox, oy, oz = origin_xyz[0], origin_xyz[1], origin_xyz[2]
    cx, cy, cz = center_xyz[0], center_xyz[1], center_xyz[2]
    n_views, n_rows, n_cols = meas.shape
    per_view_w = weights.shape[0] > 1
    robust = cut > 0.0
    for rk in prange(n_views * n_rows):
        r = rk // n_views  # row-major: see forward_kernel
        k = rk - r * n_views
        kr = k * n_rows + r
        kw = k if per_view_w else 0
        g = np.empty(6)
        acc = np.zeros(N_RED)
        for c in range(n_cols):
            w0 = weights[kw, r, c]
            if w0 == 0.0:
                continue
            sx, sy, sz, dx, dy, dz = _ray(geo, k, r, c, cone)
            p = _sensitivities(g, vf, sx, sy, sz, dx, dy, dz, nx, ny, nz, spx, spy, spz, ox, oy, oz, cx, cy, cz, cone)
            s = meas[k, r, c]
            rho = s - p
            w = w0
            loss = rho * rho
            if robust:
                rho = rho - shift[k]
                a = abs(rho)
                if a > cut:
                    w = w0 * cut / a
                    loss = 2.0 * cut * a - cut * cut
                else:
                    loss = rho * rho
            q = 0
            for i in range(6):
                wgi = w * g[i]
                for j in range(i, 6):
                    acc[q] += wgi * g[j]
                    q += 1
                acc[21 + i] += wgi * rho
                acc[32 + i] += wgi
            acc[27] += w0 * loss
            acc[28] += w
            acc[29] += w0 * s
            acc[30] += w0 * s * s
            acc[31] += w * rho
        for q in range(N_RED):
            partial[kr, q] = acc[q]
