"""Image-quality measures of the paper (§2.4): SNR of residuals, volume entropy."""

from __future__ import annotations

import numpy as np

from ..errors import ShapeError

__all__ = ["snr_db", "shannon_entropy"]


def snr_db(signal, residual, *, axis=None) -> np.ndarray | float:
    """Signal-to-noise ratio ``20 log10(std(s) / std(ρ))`` in dB.

    Parameters
    ----------
    signal, residual : arrays of the same shape
        Measured projections ``s`` and residual ``ρ``.
    axis : None or int or tuple
        ``None`` for one overall figure; e.g. ``(1, 2)`` on
        ``(n_views, n_rows, n_cols)`` for one figure per view.
    """
    s = np.asarray(signal, dtype=np.float64)
    r = np.asarray(residual, dtype=np.float64)
    if s.shape != r.shape:
        raise ShapeError(f"signal and residual must have the same shape, got {s.shape} and {r.shape}")
    with np.errstate(divide="ignore"):
        return 20.0 * np.log10(np.std(s, axis=axis) / np.std(r, axis=axis))


def shannon_entropy(volume, *, bins: int = 256, value_range=None, mask=None) -> float:
    """Shannon entropy (bits) of the gray-level histogram of a volume.

    A sharper reconstruction of the same sample concentrates its histogram
    on its phases, so its entropy is lower (paper §2.4). Compare volumes
    with the same ``value_range`` (default: the first volume's 0.1–99.9 %
    percentiles, passed explicitly to the second).
    """
    v = np.asarray(volume)
    if mask is not None:
        v = v[np.asarray(mask, bool)]
    v = v[np.isfinite(v)].ravel()
    if v.size == 0:
        raise ShapeError("volume holds no finite value to histogram")
    if value_range is None:
        value_range = tuple(np.percentile(v, [0.1, 99.9]))
    hist, _ = np.histogram(v, bins=bins, range=value_range)
    p = hist[hist > 0] / hist.sum()
    return float(-(p * np.log2(p)).sum())
