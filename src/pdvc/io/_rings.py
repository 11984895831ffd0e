"""Rings: a fixed pattern of the detector, the same in every view, removed from the line integrals.

A flat field that is wrong at some pixels (a defect of the scintillator, a
flat taken before the beam settled, a column that responds differently)
adds the same offset to those pixels' line integrals in every view:
stripes in the sinograms, rings about the axis in the reconstruction. The
reconstruction holds the rings in the sample's frame; when the poses move
the sample its re-projection moves them too, while the detector's pattern
stays where it is, so the rings pull the poses back toward the nominal
geometry (``benchmarks/bench_accuracy.py --rings``; ``docs/method.md``
§5.13).

The pattern is estimated from the data, as the sinogram-based ring filters
of tomography toolkits do: the mean of all views, minus its running median
over ``width`` columns along each detector row. A detector pattern changes
from one pixel to the next and is in every view, so it is all in the mean;
so is part of the sample's own structure, which the estimate also takes
(on the 57-column detectors of the accuracy benchmark as much as a pattern
of 0.04 RMS, more than the rings measured there). That part is the same in
every view too: the reconstruction absorbs it and the poses do not move,
but it is why :func:`pdvc.calibrate` removes the pattern only when the
residual at the calibrated geometry shows one (``rings = "auto"``). What the
running median keeps (patterns wider than about half the window, a smooth
air level) is left to the background per view and the air-level checks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import median_filter

from ..errors import PdvcError, ShapeError

__all__ = ["RingReport", "ring_pattern", "remove_rings", "RING_WIDTH"]

RING_WIDTH = 21
"""Columns of the running median (patterns up to about 10 columns wide are taken)."""

_CHUNK = 32 * 2**20  # bytes of views summed at a time


@dataclass(frozen=True)
class RingReport:
    """What :func:`remove_rings` subtracted.

    Attributes
    ----------
    amplitude : float
        RMS of the fixed pattern over the detector (line-integral units).
    peak : float
        Its largest absolute value.
    noise : float
        RMS that the noise alone leaves in the mean of the views (σ / √n):
        the pattern's own noise.
    width : int
        Columns of the running median.
    """

    amplitude: float
    peak: float
    noise: float
    width: int = RING_WIDTH

    def describe(self) -> str:
        ratio = f"{self.amplitude / self.noise:.1f}x" if self.noise > 0 else "far above"
        return (f"a fixed pattern of the detector of RMS {self.amplitude:.3g} (peak {self.peak:.3g}; {ratio} what the noise "
                f"leaves in the mean of the views) subtracted from every view")

    def to_dict(self) -> dict:
        return dict(amplitude=self.amplitude, peak=self.peak, noise=self.noise, width=self.width)


def _check_width(width) -> int:
    if not (isinstance(width, (int, np.integer)) and not isinstance(width, bool) and width >= 3 and width % 2 == 1):
        raise PdvcError(f"width must be an odd int >= 3, got {width!r}")
    return int(width)


def ring_pattern(projections, *, width: int = RING_WIDTH) -> np.ndarray:
    """The fixed pattern ``(n_rows, n_cols)`` float32: the mean of the views minus its running median over ``width`` columns.

    ``projections`` (n_views, n_rows, n_cols) line integrals, not modified;
    a memory map is read in chunks of views.
    """
    w = _check_width(width)
    p = projections
    if getattr(p, "ndim", 0) != 3:
        raise ShapeError(f"projections must be (n_views, n_rows, n_cols), got shape {getattr(p, 'shape', None)}")
    n, nr, nc = p.shape
    if nc < w:
        raise ShapeError(f"projections have {nc} columns, fewer than the ring filter's width {w}")
    mean = mean_of_views(p)
    return (mean - median_filter(mean, size=(1, w), mode="reflect")).astype(np.float32)


def mean_of_views(projections) -> np.ndarray:
    """The mean over views ``(n_rows, n_cols)`` float64 of ``(n_views, n_rows, n_cols)`` projections, summed in chunks
    of views (a memory map is never read whole)."""
    n, nr, nc = projections.shape
    step = max(1, _CHUNK // max(nr * nc * 4, 1))
    total = np.zeros((nr, nc), np.float64)
    for k in range(0, n, step):
        total += np.asarray(projections[k:k + step], np.float64).sum(axis=0)
    return total / n


def remove_rings(projections, *, noise_variance: float = 0.0, width: int = RING_WIDTH) -> tuple[np.ndarray, RingReport]:
    """Subtract the detector's fixed pattern (:func:`ring_pattern`) from every view.

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) array
        Line integrals; not modified.
    noise_variance : float
        γ² of one pixel of one view, for the report (the pattern's own noise).
    width : int
        Columns of the running median (odd).

    Returns
    -------
    (projections, RingReport)
        A float32 copy with the pattern subtracted, and what it was.
    """
    if not (np.isfinite(noise_variance) and noise_variance >= 0):
        raise PdvcError(f"noise_variance must be a finite float >= 0, got {noise_variance!r}")
    pattern = ring_pattern(projections, width=width)
    amp = float(np.sqrt(np.mean(pattern.astype(np.float64) ** 2)))
    rep = RingReport(amp, float(np.abs(pattern).max()), float(np.sqrt(noise_variance / projections.shape[0])), int(width))
    return np.asarray(projections, np.float32) - pattern[None], rep
