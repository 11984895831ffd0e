"""What dominates a residual that is far above the noise: offsets, detector patterns, outliers or structure.

When χ stays far above 1 the rigid-motion model is not what limits the fit.
:func:`diagnose_residual` splits the energy of the residual
``s - Π f`` into parts that name their usual cause, so that the log and the
report can say it (an air level left by the flat field, a fixed pattern of
the detector, zingers and dead pixels, noise, and what remains: motion the
model does not hold, or a sample the volume does not hold).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ShapeError
from ..io._rings import mean_of_views
from ..io._zingers import isolated_outliers, outlier_blobs

__all__ = ["diagnose_residual", "ResidualDiagnosis", "sample_outline"]


@dataclass(frozen=True)
class ResidualDiagnosis:
    """Shares of the residual's energy (they add up to 1).

    Attributes
    ----------
    chi : float
        RMS residual over the noise standard deviation.
    view_offset : float
        A constant per view (an air level, a drifting flat field or dose).
    column_pattern : float
        A pattern of the detector columns that stays over views and rows
        (flat-field error, rings, a dead column).
    row_pattern : float
        A pattern of the detector rows that stays over views and columns.
    outliers : float
        Isolated pixels beyond 6 robust standard deviations, alone or in bright groups
        of a few pixels (zingers, hot or dead pixels).
        A residual dominated by motion (the nominal geometry of a misaligned
        scan) puts its edges in ``structure`` and, for a constant offset of
        the axis, in ``column_pattern``: read the parts after calibration.
    noise : float
        What γ² accounts for.
    structure : float
        The rest: the sample's own structure, i.e. motion the model does not
        hold, or material the volume does not hold.
    column_pattern_off_outline : float or None
        The column pattern's share of the residual in the columns away from
        the sample's outline (:func:`sample_outline`), where a detector's
        fixed pattern stays and the reconstruction's model error at the
        sample's edge does not; None when the data were not given or too
        few columns are away from the outline.
    """

    chi: float
    view_offset: float
    column_pattern: float
    row_pattern: float
    outliers: float
    noise: float
    structure: float
    column_pattern_off_outline: float | None = None

    def describe(self) -> str:
        parts = [
            ("a constant per view (air level, flat field or dose drift)", self.view_offset),
            ("a fixed pattern of the detector columns (flat field, rings, dead columns)", self.column_pattern),
            ("a fixed pattern of the detector rows", self.row_pattern),
            ("outlier pixels (zingers, dead or hot pixels)", self.outliers),
            ("noise", self.noise),
            ("structure of the sample (motion or material the model does not hold)", self.structure),
        ]
        parts.sort(key=lambda x: -x[1])
        return f"residual chi {self.chi:.3g}: " + ", ".join(f"{100 * v:.0f}% {name}" for name, v in parts if v >= 0.005)


def _sum_squares(a) -> float:
    """Σ a² accumulated in float64, a view at a time (no full-size temporary)."""
    a = np.asarray(a)
    rows = a.reshape(a.shape[0], -1) if a.ndim >= 2 else a.reshape(1, -1)
    return float(sum(np.einsum("i,i->", x, x, dtype=np.float64) for x in rows))


#: sample_outline: a column is inside the sample's shadow where the views' mean profile rises above this fraction of its
#: range; the outline is where that changes, widened by OUTLINE_MARGIN columns each side (docs/method.md §5.40)
OUTLINE_FRACTION = 0.1
OUTLINE_MARGIN = 3
#: column_pattern_off_outline is measured only where at least this fraction of the columns is away from the outline
OFF_OUTLINE_MIN = 0.25


def sample_outline(data, *, fraction: float = OUTLINE_FRACTION, margin: int = OUTLINE_MARGIN) -> np.ndarray:
    """The detector columns ``(n_cols,)`` bool at the outline of the sample's shadow in the mean of the views.

    ``data`` (n_views, n_rows, n_cols) line integrals, read in chunks of
    views, not modified. The mean over views and rows (a running median over
    5 columns) is inside the shadow where it rises above ``fraction`` of its
    range; the columns where inside turns to outside, and ``margin``
    columns each side, are the outline. A sample centred on the axis keeps
    its edge at those columns in every view, and with it what the
    reconstruction does not reproduce of a sharp edge: a pattern of the
    columns that is not the detector's.
    """
    from scipy.ndimage import binary_dilation, median_filter

    d = data
    if getattr(d, "ndim", 0) != 3:
        raise ShapeError(f"data must be (n_views, n_rows, n_cols), got shape {getattr(d, 'shape', None)}")
    prof = median_filter(mean_of_views(d).mean(axis=0), size=5, mode="nearest")
    lo, hi = float(prof.min()), float(prof.max())
    if not hi > lo:
        return np.zeros(d.shape[2], bool)
    inside = prof - lo > fraction * (hi - lo)
    turn = np.zeros_like(inside)
    change = inside[1:] != inside[:-1]
    turn[1:] |= change
    turn[:-1] |= change
    return binary_dilation(turn, iterations=margin) if margin > 0 and turn.any() else turn


def diagnose_residual(residual, noise_variance: float, weights=None, data=None) -> ResidualDiagnosis:
    """Split the residual ``(n_views, n_rows, n_cols)`` into the parts of :class:`ResidualDiagnosis`.

    The parts are taken one after the other from what is left: the mean of
    each view, then the mean of each column over views and rows, then of
    each row, then the isolated pixels beyond 6 robust σ (1.4826 MAD; no
    4-neighbour beyond 3σ: a zinger is alone, the edge of a misplaced sample
    is a line) and the bright groups within 3 x 3 px with nothing beyond 3σ
    around them (a zinger whose light spread); the noise is
    ``n γ²`` (capped at what is left), the structure the rest. Pixels with
    zero weight are left out. With ``data`` (the line integrals the residual
    is of), also the column pattern's share in the columns away from the
    sample's outline (``column_pattern_off_outline``).
    """
    # one float32 copy, changed in place (a scan's residual is the size of its data: no float64 or temporary copies),
    # sums accumulated in float64
    r = np.array(residual, dtype=np.float32)
    w = np.ones(r.shape, bool) if weights is None else np.broadcast_to(np.asarray(weights) > 0, r.shape)
    off = ~w
    r[off] = 0.0
    n_w = max(int(w.sum()), 1)
    total = _sum_squares(r)
    if not total > 0:
        return ResidualDiagnosis(0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0)
    away = None
    if data is not None:
        if getattr(data, "shape", None) != r.shape:
            raise ShapeError(f"data must have the residual's shape {r.shape}, got {getattr(data, 'shape', None)}")
        away = ~sample_outline(data)
        if away.mean() < OFF_OUTLINE_MIN:
            away = None
        else:
            # each column's energy, a view at a time (no full-size temporary)
            e_cols = sum(np.einsum("ij,ij->j", x, x, dtype=np.float64) for x in r)
    cnt_v = np.maximum(w.sum(axis=(1, 2)), 1)
    m = r.sum(axis=(1, 2), dtype=np.float64) / cnt_v
    e_view = float(np.sum(m**2 * cnt_v))
    r -= m[:, None, None].astype(np.float32)
    r[off] = 0.0
    cnt_c = np.maximum(w.sum(axis=(0, 1)), 1)
    c = r.sum(axis=(0, 1), dtype=np.float64) / cnt_c
    e_col = float(np.sum(c**2 * cnt_c))
    e_away = float(e_cols[away].sum()) if away is not None else 0.0
    col_away = float(np.sum((c**2 * cnt_c)[away]) / e_away) if e_away > 0 else None
    r -= c[None, None, :].astype(np.float32)
    r[off] = 0.0
    cnt_r = np.maximum(w.sum(axis=(0, 2)), 1)
    rw = r.sum(axis=(0, 2), dtype=np.float64) / cnt_r
    e_row = float(np.sum(rw**2 * cnt_r))
    r -= rw[None, :, None].astype(np.float32)
    r[off] = 0.0
    del off
    vals = r[w]
    if vals.size:
        vals -= np.median(vals)
        sigma = 1.4826 * float(np.median(np.abs(vals, out=vals)))
    else:
        sigma = 0.0
    del vals
    # isolated: no 4-neighbour beyond 3 sigma (the edges of a misplaced sample are lines), or a bright group within
    # 3 x 3 px with nothing beyond 3 sigma around it (a zinger whose light spread)
    out = np.zeros(r.shape, bool)
    if sigma > 0:
        out = w & (isolated_outliers(r, sigma, 6.0, ratio=np.inf)
                   | (outlier_blobs(r, sigma, 6.0, ratio=np.inf, quiet=True)[0] > 0))
    e_out = _sum_squares(r[out])
    rest = max(total - e_view - e_col - e_row - e_out, 0.0)
    e_noise = min(n_w * float(noise_variance), rest)
    shares = np.array([e_view, e_col, e_row, e_out, e_noise, rest - e_noise]) / total
    return ResidualDiagnosis(float(np.sqrt(total / (n_w * noise_variance))), *map(float, shares), col_away)
