"""Ramp filters for filtered back-projection (FDK and FBP).

The ramp is built in the spatial domain (the band-limited Ram-Lak kernel of
Kak & Slaney, eq. 3.29, sampled at the detector pitch and wrapped on the
zero-padded length), then transformed; this keeps the correct, non-zero DC
term that a sampled ``|f|`` would lose. A window then tapers the high
frequencies.
"""

from __future__ import annotations

import numpy as np
import scipy.fft

from ..errors import ShapeError

__all__ = ["FILTERS", "ramp_filter_response", "padded_length"]

#: Names accepted by ``filter=`` in :func:`pdvc.recon.fdk` and :func:`pdvc.recon.fbp`.
FILTERS = ("ram-lak", "shepp-logan", "cosine", "hamming", "hann")


def check_filter(filter: str, cutoff: float) -> tuple[str, float]:
    """Validate ``filter`` and ``cutoff``; return them normalised."""
    name = filter.lower() if isinstance(filter, str) else filter
    if name not in FILTERS:
        raise ShapeError(f"filter must be one of {FILTERS}, got {filter!r}")
    try:
        c = float(cutoff)
    except (TypeError, ValueError):
        c = float("nan")
    if not (0.0 < c <= 1.0):
        raise ShapeError(f"cutoff must be a fraction of the Nyquist frequency in (0, 1], got {cutoff!r}")
    return name, c


PADDINGS = ("zero", "edge")


def check_padding(padding: str) -> str:
    """Validate the ramp filter's ``padding`` (``"zero"`` or ``"edge"``)."""
    if padding not in PADDINGS:
        raise ShapeError(f"padding must be one of {PADDINGS}, got {padding!r}")
    return padding


def padded_length(n_cols: int) -> int:
    """Zero-padded filtering length: the smallest power of two >= ``2 * n_cols`` (at least 64)."""
    return max(64, 1 << int(np.ceil(np.log2(2 * int(n_cols)))))


def ramp_filter_response(n_cols: int, filter: str = "ram-lak", cutoff: float = 1.0) -> np.ndarray:
    """Frequency response of the windowed ramp filter, in detector-pixel units.

    Parameters
    ----------
    n_cols : int
        Number of detector columns; the response is for the zero-padded
        length ``n = padded_length(n_cols)`` (power of two >= ``2 n_cols``).
    filter : {"ram-lak", "shepp-logan", "cosine", "hamming", "hann"}
        Window applied to the ramp. With ``x = f / (cutoff f_N)`` (``f_N``
        = 0.5 cycle/pixel the Nyquist frequency), for ``x <= 1``: ram-lak 1,
        shepp-logan ``sinc(x/2)``, cosine ``cos(pi x/2)``, hamming
        ``0.54 + 0.46 cos(pi x)``, hann ``0.5 + 0.5 cos(pi x)``; 0 for ``x > 1``.
        With ``cutoff=1`` these are the windows of scikit-image's ``iradon``.
    cutoff : float in (0, 1]
        Cut-off frequency as a fraction of Nyquist.

    Returns
    -------
    (n // 2 + 1,) float64
        Response for ``scipy.fft.rfft`` bins of the padded rows. Convolving a
        row of unit pitch with it and dividing by the physical pitch ``tau``
        (length units) gives the ramp-filtered projection in 1/length.

    Examples
    --------
    >>> h = ramp_filter_response(100)
    >>> h.shape, round(float(h[-1]), 2)   # |f| = 1/2 cycle/pixel at Nyquist
    ((129,), 0.5)
    """
    name, c = check_filter(filter, cutoff)
    n = padded_length(n_cols)
    k = np.concatenate([np.arange(0, n // 2 + 1), np.arange(-(n // 2) + 1, 0)]).astype(np.float64)
    h = np.zeros(n)
    h[0] = 0.25
    odd = (k % 2) != 0
    h[odd] = -1.0 / (np.pi * k[odd]) ** 2
    resp = np.real(scipy.fft.rfft(h))
    f = np.arange(n // 2 + 1) / n  # cycles per pixel, 0 ... 0.5
    x = f / (0.5 * c)
    if name == "ram-lak":
        win = np.ones_like(x)
    elif name == "shepp-logan":
        win = np.sinc(x / 2)  # numpy sinc(t) = sin(pi t)/(pi t)
    elif name == "cosine":
        win = np.cos(np.pi * x / 2)
    elif name == "hamming":
        win = 0.54 + 0.46 * np.cos(np.pi * x)
    else:  # hann
        win = 0.5 + 0.5 * np.cos(np.pi * x)
    win = np.where(x <= 1.0 + 1e-12, win, 0.0)
    return resp * win


#: Pixels averaged at each end of a row for the value that ``padding="edge"`` carries outward.
EDGE_PIXELS = 3


def filter_rows(weighted: np.ndarray, response: np.ndarray, *, workers: int | None = None,
                padding: str = "zero") -> np.ndarray:
    """Convolve every detector row (last axis) with ``response``.

    ``weighted`` is float32 ``(..., n_cols)``; returns a new float32 array of
    the same shape. The padded length is ``2 * (len(response) - 1)``.
    ``padding="zero"`` pads with zeros (the object lies inside the field of
    view); ``"edge"`` carries the mean of the ``EDGE_PIXELS`` outer pixels of
    each end outward, half of the padding each side (the padded row is
    circular): a row cut by the detector's edge (an object wider than the
    field of view) then has no step for the ramp filter to turn into the
    bright rim and the cupping of a truncated reconstruction.
    """
    n = 2 * (response.shape[0] - 1)
    nc = weighted.shape[-1]
    if padding == "edge" and n > nc:
        m = min(EDGE_PIXELS, nc)
        row = np.empty(weighted.shape[:-1] + (n,), np.float32)
        row[..., :nc] = weighted
        half = nc + (n - nc) // 2
        row[..., nc:half] = weighted[..., nc - m:].mean(axis=-1, keepdims=True)
        row[..., half:] = weighted[..., :m].mean(axis=-1, keepdims=True)
        spec = scipy.fft.rfft(row, axis=-1, workers=workers)
    else:
        check_padding(padding)
        spec = scipy.fft.rfft(weighted, n=n, axis=-1, workers=workers)
    spec *= response.astype(np.float32)
    return scipy.fft.irfft(spec, n=n, axis=-1, workers=workers)[..., :nc]
