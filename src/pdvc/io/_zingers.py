"""Zingers, hot and dead pixels: isolated pixels that the reconstruction does not explain, replaced by a median.

A zinger (a cosmic ray or a scattered photon hitting the detector) or a hot
pixel is one pixel of one view that reads far brighter than its neighbours;
in line integrals it is a deep, isolated dip (a dead pixel, an isolated
peak). Rigid-motion correlation weighs every pixel by its squared residual:
a fraction of a percent of such pixels is enough to steer the poses
(``benchmarks/bench_accuracy.py --zingers``).

They are found on the residual ``r = p - Π f`` of a reconstruction ``f``
of the scan (FDK at the nominal geometry is enough): what the sample
explains is gone, a misplaced edge is a line of large residual, a zinger is
alone. Photon noise grows behind the sample (the variance of a line
integral is ``exp(p) / i0``), so ``r`` minus its median per view is scaled
by ``exp(-Π f / 2)`` before its robust standard deviation σ (1.4826 MAD) is
taken over the scan. A pixel is a zinger when its scaled residual is above
``k`` σ, none of its four neighbours is above 3 σ or 1/2.5 of it (the ramp
filter of the reconstruction spreads a little of a zinger to its
neighbours), and the view before or after does not hold a residual of the
same sign within a pixel (the sample's own structure, misplaced, does);
a pixel alone in half the views or more is a hot or dead pixel and is
replaced in every view. A zinger whose light the scintillator spread over
a few pixels (as in neutron imaging) is a bright spot of 2–9 pixels:
:func:`outlier_blobs` finds those, and the same test of the views before
and after decides. A zinger is replaced by the median of its eight
neighbours in the same view that are not replaced themselves. Tomography toolkits remove
outliers with a median filter and a threshold on the data alone (e.g.
TomoPy's ``remove_outlier``): on fine structure (the 1–2 px struts of the
benchmark's foams) that flags 300–1600 pixels of a clean 40³ scan and
misses a quarter of the zingers; the residual flags none of the former.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter

from ..errors import ShapeError
from ._preprocess import _robust_std

__all__ = ["ZingerReport", "isolated_outliers", "outlier_blobs", "remove_zingers", "ZINGER_SIGMA", "BLOB_SIZE"]

ZINGER_SIGMA = 6.0
"""A zinger's residual is at least this many robust standard deviations."""

BLOB_SIZE = 3
"""A zinger's light spreads over at most a square of this side (pixels)."""

_RIM = 0.2  # a blob's rim: its group's pixels next to the core beyond this fraction of the peak (the spot's faint
# edge; it also takes the reconstruction's spread of the spot along the rows, up to a third of it on 48-60 views)

_NEIGHBOUR_SIGMA = 3.0
_NEIGHBOUR_RATIO = 2.5  # a zinger's neighbours hold at most this fraction of its residual (the FDK's ramp spreads a little)
_SAMPLE = 2_000_000  # pixels the robust σ is taken on (evenly strided)
_CHUNK = 32 * 2**20  # bytes of views filtered at a time


@dataclass(frozen=True)
class ZingerReport:
    """What :func:`remove_zingers` found: the count, the fraction of pixels, the views touched and σ."""

    count: int
    fraction: float
    views: int
    sigma: float
    threshold: float
    every: int = 1  # checked on every k-th view only
    blobs: int = 0  # of them in groups of 2 or more pixels (a zinger's light spread over a few pixels)

    def describe(self, replaced: bool = True) -> str:
        """One line; ``replaced``: say that they were replaced (False: only what was found)."""
        if not self.count:
            where = f" on every {self.every}th view" if self.every > 1 else ""
            return (f"none found{where} (no isolated pixel or bright spot {self.threshold:g} robust std or more from the "
                    "reprojection)")
        what = f"pixel(s) isolated or in {self.blobs} spot(s) of 2-{BLOB_SIZE ** 2} px" if self.blobs else \
            "isolated pixel(s)"
        return (f"{self.count} {what} ({100 * self.fraction:.3g}% of the pixels, in {self.views} view(s)) "
                f"{self.threshold:g} robust std or more from the reprojection (zingers, hot or dead pixels)"
                + (", replaced by the median of their neighbours" if replaced else ""))


def isolated_outliers(z, sigma: float, k: float = ZINGER_SIGMA, ratio: float = _NEIGHBOUR_RATIO) -> np.ndarray:
    """Pixels of ``z`` ``(n, rows, cols)`` beyond ``k σ`` whose four neighbours (same view) are all below
    ``max(3 σ, |z| / ratio)``: alone, not on a line or a blob."""
    a = np.abs(np.asarray(z))
    out = a > k * sigma
    if out.any():
        nb = np.zeros(a.shape, a.dtype)
        np.maximum(nb[:, 1:, :], a[:, :-1, :], out=nb[:, 1:, :])
        np.maximum(nb[:, :-1, :], a[:, 1:, :], out=nb[:, :-1, :])
        np.maximum(nb[:, :, 1:], a[:, :, :-1], out=nb[:, :, 1:])
        np.maximum(nb[:, :, :-1], a[:, :, 1:], out=nb[:, :, :-1])
        out &= nb < np.maximum(_NEIGHBOUR_SIGMA * sigma, a / ratio)
    return out


def outlier_blobs(z, sigma: float, k: float = ZINGER_SIGMA, ratio: float = _NEIGHBOUR_RATIO,
                  size: int = BLOB_SIZE, quiet: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Blobs of ``z`` ``(n, rows, cols)``: zingers whose light spread over a few pixels.

    A blob's core is the part of a group of pixels below ``-3 σ`` (brighter than the reprojection; 8-connected,
    in one view) beyond ``m / ratio``, ``m`` the group's peak: the ramp filter of the reconstruction spreads a
    strong zinger beyond 3 σ around it. The core must have two pixels or more (one is a single zinger,
    :func:`isolated_outliers`), fit in a ``size x size`` square and peak beyond ``k σ``; the blob is the core
    and the pixels of its group next to it beyond a fifth of ``m`` (the spot's faint edge). A misplaced edge is
    a line longer than ``size``. A misplaced small feature is a compact bright group too, next to a dark one:
    :func:`remove_zingers` tells it by the next views, where it is still there. Without that check, ``quiet``
    also asks that nothing around the core goes beyond ``max(3 σ, m / ratio)`` (which misses a spot next to an
    edge of the sample or of the field of view). A group that reads dark is a defect of the detector (in every
    view) or the streak a zinger leaves through the reconstruction, and is never a blob.

    Returns ``(labels, peaks)``: one positive label per blob (0 elsewhere), and each blob's peak pixel.
    """
    from scipy import ndimage

    s = -np.asarray(z)
    shape = s.shape
    structure = np.zeros((3, 3, 3), bool)
    structure[1] = True  # 8-connected within a view, never across views
    labels, peaks = np.zeros(shape, np.int64), np.zeros(shape, bool)
    group, n = ndimage.label(s > _NEIGHBOUR_SIGMA * sigma, structure)
    at = np.flatnonzero(group)  # what follows runs on these pixels only (noise puts ~0.1 % of them beyond 3 σ)
    if not at.size:
        return labels, peaks
    val, grp = s.ravel()[at], group.ravel()[at]
    peak = np.zeros(n + 1)
    np.maximum.at(peak, grp, val)
    core_at = at[val > peak[grp] / ratio]
    core = np.zeros(shape, bool)
    core.ravel()[core_at] = True
    lab, n = ndimage.label(core, structure)
    c_lab, c_val = lab.ravel()[core_at], s.ravel()[core_at]
    _, r, c = np.unravel_index(core_at, shape)
    peak = np.zeros(n + 1)
    np.maximum.at(peak, c_lab, c_val)
    lo_r, hi_r, lo_c, hi_c = (np.full(n + 1, v) for v in (shape[1], -1, shape[2], -1))
    np.minimum.at(lo_r, c_lab, r), np.maximum.at(hi_r, c_lab, r)
    np.minimum.at(lo_c, c_lab, c), np.maximum.at(hi_c, c_lab, c)
    keep = ((np.bincount(c_lab, minlength=n + 1) >= 2) & (peak > k * sigma)
            & (hi_r - lo_r < size) & (hi_c - lo_c < size))
    keep[0] = False
    if quiet and keep.any():
        around = ndimage.maximum(maximum_filter(np.where(lab > 0, 0.0, np.abs(s)), size=(1, 3, 3), mode="nearest"),
                                 lab, np.arange(n + 1))
        keep &= around < np.maximum(_NEIGHBOUR_SIGMA * sigma, peak / ratio)
    if not keep.any():
        return labels, peaks
    new = np.zeros(n + 1, np.int64)
    new[keep] = 1 + np.arange(int(keep.sum()))
    labels.ravel()[core_at] = new[c_lab]
    peaks.ravel()[core_at] = (new[c_lab] > 0) & (c_val == peak[c_lab])
    # the rim: pixels of a blob's group next to its core, beyond a fifth of its peak (the spot's faint edge)
    rim_at = at[labels.ravel()[at] == 0]
    v, r, c = np.unravel_index(rim_at, shape)
    near = np.zeros(rim_at.size, np.int64)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                near = np.maximum(near, labels[v, np.clip(r + dr, 0, shape[1] - 1), np.clip(c + dc, 0, shape[2] - 1)])
    blob_peak = np.concatenate([[np.inf], peak[keep]])
    rim = near > 0
    rim[rim] = s.ravel()[rim_at[rim]] > _RIM * blob_peak[near[rim]]
    labels.ravel()[rim_at[rim]] = near[rim]
    return labels, peaks


def _scaled_residual(p, q) -> np.ndarray:
    """The residual ``p - q`` of views, less its median per view, over the photon noise's ``exp(q / 2)``."""
    r = np.asarray(p, np.float32) - np.asarray(q, np.float32)
    r -= np.median(r.reshape(r.shape[0], -1), axis=1)[:, None, None]
    return r * np.exp(-0.5 * np.clip(np.asarray(q, np.float32), -5.0, 20.0))


def _seen_nearby(z: np.ndarray, sigma: float, first: int, count: int, alone: np.ndarray) -> np.ndarray:
    """For views ``first .. first + count`` of ``z``: whether the sample's structure is there too in the next
    views: within a pixel, a residual of the same sign above ``max(3 σ, |z| / ratio)`` in the view before or
    after that is not itself alone (``alone``, a zinger there), or in both views (a misplaced small feature)."""
    out = np.zeros((count,) + z.shape[1:], bool)
    z_na = np.where(alone, 0.0, z)
    filt = {name: maximum_filter(sign * arr, size=(1, 3, 3), mode="nearest")
            for name, sign, arr in (("p", 1, z), ("n", -1, z), ("p_na", 1, z_na), ("n_na", -1, z_na))}
    n = z.shape[0]
    for j in range(count):
        v = first + j
        c = z[v]
        lim = np.maximum(_NEIGHBOUR_SIGMA * sigma, np.abs(c) / _NEIGHBOUR_RATIO)
        both = np.ones(c.shape, bool)
        for w in (v - 1, v + 1):
            if not 0 <= w < n:
                both[:] = False
                continue
            out[j] |= np.where(c > 0, filt["p_na"][w], filt["n_na"][w]) > lim
            both &= np.where(c > 0, filt["p"][w], filt["n"][w]) > lim
        out[j] |= both
    return out


def _fill_from_neighbours(block: np.ndarray, hit: np.ndarray) -> None:
    """Replace the pixels of ``hit`` in ``block`` (in place) by the median of their eight neighbours (same view,
    edges clamped) that are not hit; a pixel all of whose neighbours are hit (inside a blob) waits for them, from
    the blob's rim inwards."""
    todo = hit.copy()
    nr, nc = block.shape[1:]
    while todo.any():
        v, r, c = np.nonzero(todo)
        vals, ok = [], []
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                if dr or dc:
                    rr, cc = np.clip(r + dr, 0, nr - 1), np.clip(c + dc, 0, nc - 1)
                    vals.append(block[v, rr, cc])
                    ok.append(~todo[v, rr, cc])
        vals, ok = np.stack(vals, axis=1), np.stack(ok, axis=1)
        ready = ok.any(axis=1)
        if not ready.any():  # a whole view hit: nothing to take a median of
            break
        med = np.nanmedian(np.where(ok[ready], vals[ready], np.nan), axis=1)
        block[v[ready], r[ready], c[ready]] = med
        todo[v[ready], r[ready], c[ready]] = False


def remove_zingers(projections, reprojection, *, k: float = ZINGER_SIGMA) -> tuple[np.ndarray, ZingerReport]:
    """Find zingers, hot and dead pixels in line integrals and replace them (module docstring).

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) array
        Line integrals; not modified.
    reprojection : array of the same shape
        ``Π f``: the forward projection of a reconstruction of them.
    k : float
        Threshold in robust standard deviations (default 6).

    Returns
    -------
    (projections, ZingerReport)
        ``projections`` itself when nothing was found, else a float32 copy
        with each zinger replaced by the median of its eight neighbours.
    """
    p = np.asarray(projections)
    q = np.asarray(reprojection)
    if p.ndim != 3:
        raise ShapeError(f"projections must have shape (n_views, n_rows, n_cols), got {p.shape}")
    if q.shape != p.shape:
        raise ShapeError(f"reprojection must have the projections' shape {p.shape}, got {q.shape}")
    if not (k > _NEIGHBOUR_SIGMA):
        raise ValueError(f"k must be above {_NEIGHBOUR_SIGMA} (the neighbours' threshold), got {k!r}")
    n = p.shape[0]
    step = max(1, int(_CHUNK // max(1, 4 * p.shape[1] * p.shape[2])))
    pick = np.unique(np.linspace(0, n - 1, min(n, max(1, _SAMPLE // max(1, p.shape[1] * p.shape[2]))), dtype=int))
    sigma = _robust_std(_scaled_residual(p[pick], q[pick]), _SAMPLE)
    if not sigma > 0:
        return p, ZingerReport(0, 0.0, 0, 0.0, float(k))
    # pass 1: pixels alone in their view; a pixel alone in half the views or more is hot or dead (all views)
    alone = np.zeros(p.shape, bool)
    for s in range(0, n, step):
        alone[s:s + step] = isolated_outliers(_scaled_residual(p[s:s + step], q[s:s + step]), sigma, k)
    hot = alone.mean(axis=0) >= 0.5
    # pass 2: a zinger is in one view only; the sample's own structure, which a misaligned reconstruction leaves
    # as isolated spikes too, is still there in the next view, within a pixel (for a blob: next to its peak)
    out, count, views, blobs = None, 0, 0, 0
    for s in range(0, n, step):
        lo, hi, m = max(s - 1, 0), min(s + step + 1, n), min(step, n - s)
        z = _scaled_residual(p[lo:hi], q[lo:hi])
        seen = _seen_nearby(z, sigma, s - lo, m, alone[lo:hi])
        hit = alone[s:s + step] & ~hot[None] & ~seen
        labels, peaks = outlier_blobs(z[s - lo:s - lo + m], sigma, k)
        spread = (labels > 0) & ~np.isin(labels, labels[peaks & seen]) & ~hot[None]
        blobs += int(np.unique(labels[spread]).size)
        hit |= spread | hot[None]
        if hit.any():
            if out is None:
                out = np.array(p, dtype=np.float32, copy=True)
            _fill_from_neighbours(out[s:s + step], hit)
            count += int(hit.sum())
            views += int(hit.any(axis=(1, 2)).sum())
    rep = ZingerReport(count, count / float(p.size), views, sigma, float(k), blobs=blobs)
    return (p if out is None else out), rep
