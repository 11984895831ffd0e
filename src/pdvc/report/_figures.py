"""Figures of a calibration report, one function per figure of the paper.

Every function takes plain NumPy arrays and returns a
:class:`matplotlib.figure.Figure` drawn on an Agg canvas: no pyplot state,
no display.  Parameter order is ``(tx, ty, tz, rx, ry, rz)``; translations
are in volume units, rotations in radians on input and degrees on the axes.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..errors import ShapeError

__all__ = [
    "PARAM_NAMES",
    "snr_per_view_figure",
    "temporal_modes_figure",
    "spatial_modes_figure",
    "pose_figure",
    "residual_maps_figure",
    "axis_trajectory_figure",
    "slices_figure",
    "snr_modes_table",
]

#: Names of the six rigid-body parameters, in the order used everywhere.
PARAM_NAMES = ("tx", "ty", "tz", "rx", "ry", "rz")

_FRAMES = ("lab", "sample")


# --------------------------------------------------------------------------- helpers


def _new_figure(figsize) -> Figure:
    """A Figure on its own Agg canvas, with constrained layout."""
    fig = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _as_1d(name: str, a, n: int | None = None) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 1 or (n is not None and arr.shape[0] != n):
        want = "(n,)" if n is None else f"({n},)"
        raise ShapeError(f"{name} must have shape {want}, got {arr.shape}")
    return arr


def _as_2d(name: str, a, shape: tuple) -> np.ndarray:
    """``a`` as float64 with ``ndim == len(shape)``; ``None`` entries of ``shape`` are free."""
    arr = np.asarray(a, dtype=np.float64)
    ok = arr.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, arr.shape))
    if not ok:
        want = "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"
        raise ShapeError(f"{name} must have shape {want}, got {arr.shape}")
    return arr


def _finite(a: np.ndarray) -> np.ndarray:
    return a[np.isfinite(a)]


def _param_label(j: int, length_unit: str) -> str:
    return f"{PARAM_NAMES[j]} ({length_unit})" if j < 3 else f"{PARAM_NAMES[j]} (deg)"


def _to_display(params: np.ndarray) -> np.ndarray:
    """Copy of ``(..., 6)`` parameters with the rotations converted rad -> deg."""
    out = np.array(params, dtype=np.float64, copy=True)
    out[..., 3:] = np.degrees(out[..., 3:])
    return out


# --------------------------------------------------------------------------- SNR


def snr_per_view_figure(angles_deg, snr_before, snr_after=None) -> Figure:
    """SNR per view before and after calibration (paper Figs 5 and 9).

    Parameters
    ----------
    angles_deg : array_like, shape (n_views,), degrees
        Projection angle of each view.
    snr_before, snr_after : array_like, shape (n_views,), dB
        ``20 log10(std(s_k) / std(ρ_k))`` of each view with the nominal and
        with the calibrated geometry.  ``snr_after`` may be ``None``.

    Returns
    -------
    Figure
        One axes; the legend gives each curve's mean SNR (NaN ignored) with
        two decimals, e.g. ``"before (mean 24.50 dB)"``.
    """
    ang = _as_1d("angles_deg", angles_deg)
    curves = [("before", snr_before, "C3")]
    if snr_after is not None:
        curves.append(("after", snr_after, "C0"))
    fig = _new_figure((7.0, 3.6))
    ax = fig.add_subplot()
    for label, values, colour in curves:
        v = _as_1d(f"snr_{label}", values, ang.size)
        mean = float(np.mean(_finite(v))) if np.isfinite(v).any() else float("nan")
        ax.plot(ang, v, "-", color=colour, lw=1.2, label=f"{label} (mean {mean:.2f} dB)")
    ax.set_xlabel("angle (deg)")
    ax.set_ylabel("SNR (dB)")
    ax.set_title("SNR per view")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best")
    return fig


def snr_modes_table(mode_table) -> tuple[tuple[str, ...], list[tuple[str, ...]]]:
    """Mean SNR as a function of the number of modes (paper Table 1).

    Parameters
    ----------
    mode_table : sequence of (n_modes, chi, snr_db)
        One entry per stage: number of modes identified so far (int), the
        normalised residual χ (1 at the noise floor, dimensionless) and the
        mean SNR in dB.

    Returns
    -------
    header : tuple of str
    rows : list of tuple of str
        Formatted cells, ready for :func:`~pdvc.report.write_report`.
    """
    header = ("modes", "chi", "mean SNR (dB)")
    rows = []
    for i, entry in enumerate(mode_table):
        if len(entry) != 3:
            raise ShapeError(f"mode_table[{i}] must be (n_modes, chi, snr_db), got {entry!r}")
        n, chi, snr = entry
        rows.append((str(int(n)), f"{float(chi):.4g}", f"{float(snr):.2f}"))
    return header, rows


# --------------------------------------------------------------------------- modes


def temporal_modes_figure(x, alphas, alphas_free=None, xlabel: str = "view") -> Figure:
    """Temporal modes α_l, constrained and free (paper Figs 11a–13a).

    Parameters
    ----------
    x : array_like, shape (n_views,) or None
        Abscissa (view index, angle in degrees, time...); ``None`` for the
        view index.
    alphas : array_like, shape (n_modes, n_views), dimensionless
        Constrained temporal modes (``max |α_l| = 1``), drawn as lines.
    alphas_free : array_like, shape (n_modes, n_views), optional
        Free (Dirac) history of each mode, drawn as dots; a row of NaN (or
        ``None`` for all) draws none for that mode.
    xlabel : str
        Label of the abscissa.

    Returns
    -------
    Figure
        One axes per mode (one axes saying so when ``n_modes == 0``).
    """
    a = np.asarray(alphas, dtype=np.float64)
    if a.ndim == 1:
        a = a[None, :]
    if a.ndim != 2:
        raise ShapeError(f"alphas must have shape (n_modes, n_views), got {a.shape}")
    n_modes, n_views = a.shape
    xv = np.arange(n_views, dtype=np.float64) if x is None else _as_1d("x", x, n_views)
    free = None
    if alphas_free is not None:
        free = np.asarray(alphas_free, dtype=np.float64)
        if free.ndim == 1:
            free = free[None, :]
        if free.shape != a.shape:
            raise ShapeError(f"alphas_free must have the shape of alphas {a.shape}, got {free.shape}")
    fig = _new_figure((7.0, 1.0 + 1.9 * max(n_modes, 1)))
    if n_modes == 0:
        ax = fig.add_subplot()
        ax.text(0.5, 0.5, "no mode identified", ha="center", va="center", transform=ax.transAxes)
        ax.set_axis_off()
        return fig
    axs = fig.subplots(n_modes, 1, sharex=True, squeeze=False)[:, 0]
    for l, ax in enumerate(axs):
        ax.plot(xv, a[l], "-", color="k", lw=1.3, label="constrained")
        if free is not None and np.isfinite(free[l]).any():
            ax.plot(xv, free[l], ".", color="C0", ms=4, label="free (Dirac)")
        ax.axhline(0.0, color="0.6", lw=0.6)
        ax.set_ylabel(f"α{l + 1}")
        ax.grid(True, alpha=0.3)
    axs[0].legend(loc="best", fontsize="small")
    axs[-1].set_xlabel(xlabel)
    fig.suptitle("temporal modes")
    return fig


def spatial_modes_figure(spatial, *, length_unit: str = "vol. units") -> Figure:
    """Spatial part of each mode as grouped bars (paper Figs 11b–13b).

    Parameters
    ----------
    spatial : array_like, shape (n_modes, 6)
        Rigid-body amplitudes ``p`` of each mode, order
        ``(tx, ty, tz, rx, ry, rz)``; translations in volume units,
        rotations in radians (displayed in degrees).
    length_unit : str
        Name of the volume unit on the translation axis.

    Returns
    -------
    Figure
        Two axes: translations (tx, ty, tz) and rotations (rx, ry, rz); in
        each, one group of ``n_modes`` bars per parameter, labelled with
        their value.
    """
    p = _as_2d("spatial", spatial, (None, 6))
    n_modes = p.shape[0]
    shown = _to_display(p)
    fig = _new_figure((8.0, 3.4))
    axs = fig.subplots(1, 2)
    width = 0.8 / max(n_modes, 1)
    for ax, cols, unit in ((axs[0], slice(0, 3), length_unit), (axs[1], slice(3, 6), "deg")):
        centres = np.arange(3, dtype=np.float64)
        for l in range(n_modes):
            pos = centres - 0.4 + width * (l + 0.5)
            bars = ax.bar(pos, shown[l, cols], width, color=f"C{l % 10}", label=f"mode {l + 1}")
            ax.bar_label(bars, fmt="%.3g", fontsize="x-small")
        ax.set_xticks(centres, PARAM_NAMES[cols])
        ax.axhline(0.0, color="0.4", lw=0.6)
        ax.set_ylabel(unit)
        ax.grid(True, axis="y", alpha=0.3)
    axs[0].set_title("translations")
    axs[1].set_title("rotations")
    if n_modes:
        axs[1].legend(loc="best", fontsize="small")
    fig.suptitle("spatial modes")
    return fig


# --------------------------------------------------------------------------- poses


def pose_figure(
    x, params, std=None, frame: str = "lab", *, xlabel: str = "view", length_unit: str = "vol. units"
) -> Figure:
    """The six pose parameters per view, with ±1 standard-deviation bands.

    Parameters
    ----------
    x : array_like, shape (n_views,) or None
        Abscissa; ``None`` for the view index.
    params : array_like, shape (n_views, 6)
        ``(tx, ty, tz, rx, ry, rz)`` per view; translations in volume units,
        rotations in radians (displayed in degrees).
    std : array_like, shape (n_views, 6), optional
        Standard deviation of each parameter, same units; drawn as a band.
    frame : {"lab", "sample"}
        Frame the parameters are expressed in (title only).
    xlabel, length_unit : str
        Axis labels.

    Returns
    -------
    Figure
        Six axes, translations on the first row, rotations on the second.
    """
    if frame not in _FRAMES:
        raise ValueError(f"frame must be one of {_FRAMES}, got {frame!r}")
    p = _as_2d("params", params, (None, 6))
    n_views = p.shape[0]
    xv = np.arange(n_views, dtype=np.float64) if x is None else _as_1d("x", x, n_views)
    shown = _to_display(p)
    s = None
    if std is not None:
        s = _to_display(_as_2d("std", std, (n_views, 6)))
    fig = _new_figure((10.0, 5.0))
    axs = fig.subplots(2, 3, sharex=True).ravel()
    for j, ax in enumerate(axs):
        ax.plot(xv, shown[:, j], "-", color="C0", lw=1.2)
        if s is not None:
            ax.fill_between(xv, shown[:, j] - s[:, j], shown[:, j] + s[:, j], color="C0", alpha=0.25, lw=0)
        ax.set_title(_param_label(j, length_unit), fontsize="medium")
        ax.grid(True, alpha=0.3)
        if j >= 3:
            ax.set_xlabel(xlabel)
    fig.suptitle(f"pose per view ({frame} frame)")
    return fig


# --------------------------------------------------------------------------- images


def residual_maps_figure(before, after=None, titles: Sequence[str] | None = None, *, clim=None) -> Figure:
    """Residual images before and after calibration (paper Figs 4, 8, 10).

    Parameters
    ----------
    before : array_like, shape (n_maps, n_rows, n_cols)
        Residuals ``ρ_k = Π_k[f] − s_k`` of a few views (typically two
        angles) with the nominal geometry, projection units.
    after : array_like, shape (n_maps, n_rows, n_cols), optional
        The same views with the calibrated geometry.
    titles : sequence of str, length n_maps, optional
        Column titles, e.g. ``"θ = 90°"``.
    clim : float, optional
        Half-width of the colour scale; default the 99th percentile of
        ``|before|`` (finite values).

    Returns
    -------
    Figure
        ``n_maps`` axes per row (before, then after) and one colour bar; every
        image uses the same symmetric scale ``(-clim, clim)``.
    """
    b = np.asarray(before, dtype=np.float64)
    if b.ndim == 2:
        b = b[None]
    if b.ndim != 3:
        raise ShapeError(f"before must have shape (n_maps, n_rows, n_cols), got {b.shape}")
    rows = [("before", b)]
    if after is not None:
        a = np.asarray(after, dtype=np.float64)
        if a.ndim == 2:
            a = a[None]
        if a.shape != b.shape:
            raise ShapeError(f"after must have the shape of before {b.shape}, got {a.shape}")
        rows.append(("after", a))
    n_maps = b.shape[0]
    if titles is None:
        titles = [f"map {i}" for i in range(n_maps)]
    titles = list(titles)
    if len(titles) != n_maps:
        raise ShapeError(f"titles must have {n_maps} entries (one per map), got {len(titles)}")
    if clim is None:
        vals = _finite(np.abs(b))
        clim = float(np.percentile(vals, 99)) if vals.size else 0.0
        if not clim > 0:
            alls = np.concatenate([_finite(np.abs(r)).ravel() for _, r in rows])
            clim = float(alls.max()) if alls.size and alls.max() > 0 else 1.0
    clim = float(clim)
    aspect = b.shape[2] / b.shape[1]
    fig = _new_figure((1.0 + 3.0 * n_maps * min(max(aspect, 0.5), 2.0), 0.6 + 3.0 * len(rows)))
    axs = fig.subplots(len(rows), n_maps, squeeze=False)
    im = None
    for i, (label, maps) in enumerate(rows):
        for m in range(n_maps):
            ax = axs[i, m]
            im = ax.imshow(maps[m], cmap="RdBu_r", vmin=-clim, vmax=clim, interpolation="nearest")
            ax.set_title(f"{label}: {titles[m]}", fontsize="medium")
            ax.set_xticks([])
            ax.set_yticks([])
    fig.colorbar(im, ax=axs, shrink=0.85, label="residual")
    return fig


def slices_figure(vol_before, vol_after, *, voxel_size=None, percentiles=(0.5, 99.5)) -> Figure:
    """Central axial and vertical slices before and after (paper Figs 7, 15).

    Parameters
    ----------
    vol_before, vol_after : array_like, shape (n_z, n_y, n_x)
        Reconstructions with the nominal and the calibrated geometry.
    voxel_size : (sz, sy, sx), optional
        Voxel size (volume units), for the aspect ratio; default cubic.
    percentiles : (low, high)
        Grey scale: these percentiles of the finite values of ``vol_after``,
        shared by all four images.

    Returns
    -------
    Figure
        Four image axes (rows before/after, columns axial ``z = n_z // 2`` and
        vertical ``y = n_y // 2``) and one colour bar.
    """
    vols = []
    for name, v in (("vol_before", vol_before), ("vol_after", vol_after)):
        arr = np.asarray(v)
        if arr.ndim != 3:
            raise ShapeError(f"{name} must have shape (n_z, n_y, n_x), got {arr.shape}")
        vols.append(arr)
    sz, sy, sx = (1.0, 1.0, 1.0) if voxel_size is None else map(float, voxel_size)
    vals = _finite(np.asarray(vols[1], dtype=np.float64))
    if vals.size:
        vmin, vmax = (float(q) for q in np.percentile(vals, percentiles))
    else:
        vmin, vmax = 0.0, 1.0
    if not vmax > vmin:
        vmin, vmax = vmin - 0.5, vmin + 0.5
    fig = _new_figure((8.0, 7.0))
    axs = fig.subplots(2, 2)
    im = None
    for i, (label, v) in enumerate(zip(("before", "after"), vols)):
        nz, ny, _ = v.shape
        axial = np.asarray(v[nz // 2], dtype=np.float32)
        vertical = np.asarray(v[:, ny // 2, :], dtype=np.float32)
        im = axs[i, 0].imshow(axial, cmap="gray", vmin=vmin, vmax=vmax, origin="lower", aspect=sy / sx)
        axs[i, 0].set_title(f"{label}: axial z = {nz // 2}", fontsize="medium")
        axs[i, 0].set_xlabel("x")
        axs[i, 0].set_ylabel("y")
        axs[i, 1].imshow(vertical, cmap="gray", vmin=vmin, vmax=vmax, origin="lower", aspect=sz / sx)
        axs[i, 1].set_title(f"{label}: vertical y = {ny // 2}", fontsize="medium")
        axs[i, 1].set_xlabel("x")
        axs[i, 1].set_ylabel("z")
    fig.colorbar(im, ax=axs, shrink=0.8, label="attenuation")
    return fig


# --------------------------------------------------------------------------- axis


def axis_trajectory_figure(angles_deg, top, centre, bottom) -> Figure:
    """Displacement of the sample's top, centre and bottom on the detector (Figs 6, 14).

    Parameters
    ----------
    angles_deg : array_like, shape (n_views,), degrees
    top, centre, bottom : array_like, shape (n_views, 2), pixels
        Detector displacement ``(row, col)`` of the projection of three points
        on the rotation axis (top, centre and bottom of the sample) caused by
        the identified motion, per view.

    Returns
    -------
    Figure
        Three axes: column (horizontal) displacement vs angle, row (vertical)
        displacement vs angle, and the trajectory in the detector plane
        (column right, row down) with the mean axis (mean top to mean bottom)
        dashed.
    """
    ang = _as_1d("angles_deg", angles_deg)
    parts = []
    for name, d in (("top", top), ("centre", centre), ("bottom", bottom)):
        parts.append((name, _as_2d(name, d, (ang.size, 2))))
    fig = _new_figure((12.0, 3.8))
    ax_col, ax_row, ax_det = fig.subplots(1, 3)
    for i, (name, d) in enumerate(parts):
        c = f"C{i}"
        ax_col.plot(ang, d[:, 1], "-", color=c, lw=1.2, label=name)
        ax_row.plot(ang, d[:, 0], "-", color=c, lw=1.2, label=name)
        ax_det.plot(d[:, 1], d[:, 0], "-", color=c, lw=1.0, label=name)
    with np.errstate(invalid="ignore"):
        mt = np.nanmean(parts[0][1], axis=0)
        mb = np.nanmean(parts[2][1], axis=0)
    ax_det.plot([mt[1], mb[1]], [mt[0], mb[0]], "--", color="k", lw=1.0, label="mean axis")
    ax_col.set_title("horizontal (column) displacement", fontsize="medium")
    ax_row.set_title("vertical (row) displacement", fontsize="medium")
    ax_det.set_title("trajectory on the detector", fontsize="medium")
    for ax in (ax_col, ax_row):
        ax.set_xlabel("angle (deg)")
        ax.set_ylabel("pixels")
        ax.grid(True, alpha=0.3)
    ax_det.set_xlabel("column displacement (px)")
    ax_det.set_ylabel("row displacement (px, down)")
    ax_det.invert_yaxis()
    ax_det.set_aspect("equal", adjustable="datalim")
    ax_det.grid(True, alpha=0.3)
    ax_col.legend(loc="best", fontsize="small")
    ax_det.legend(loc="best", fontsize="small")
    return fig
