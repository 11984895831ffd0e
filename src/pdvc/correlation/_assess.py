"""What the data say about a set of poses: uncertainties, unobservable directions and the modes of the motion.

:func:`assess` makes one Jacobian pass at given poses (the ones a
calibration kept) and reports, for a motion model (basis, frame, fixed
parameters): the standard deviation of every pose parameter (γ² H⁻¹), the
directions the data cannot determine, and the space-time modes of the
*total* motion (the paper's Figs 11–13: spatial modes, and each mode's
history constrained by the motion found and free, view by view).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..geometry import Poses
from ._engine import Mode, Observability, _full_step, _overall_snr, _problem, _std_sample

__all__ = ["assess", "Assessment"]


@dataclass(frozen=True)
class Assessment:
    """The measurement of :func:`assess` at given poses.

    Attributes
    ----------
    poses : Poses
    params, params_lab : (n_views, 6)
        The poses as ``(tx, ty, tz, rx, ry, rz)`` about ``center``, sample and lab frame.
    std : (n_views, 6)
        Standard deviation of ``params`` (sample frame) for the model; NaN
        along unobservable directions, 0 for fixed parameters.
    observability : Observability
    modes : tuple of Mode
        Space-time modes of the total motion, largest first: ``spatial``
        (the six parameters at max |α| = 1, in ``frame``), ``alpha`` (the
        history of the motion kept), ``alpha_free`` (the same spatial mode
        measured view by view at these poses), ``coefficients`` (``alpha``
        on the basis), ``chi``.
    chi : float
    snr_per_view : (n_views,) float, dB
    frame : str
    basis_names : tuple of str
    center : (3,)
    """

    poses: Poses
    params: np.ndarray
    params_lab: np.ndarray
    std: np.ndarray
    observability: Observability
    modes: tuple
    chi: float
    snr: float
    snr_per_view: np.ndarray
    frame: str
    basis_names: tuple
    center: np.ndarray


def assess(
    volume,
    vol_geom,
    projections,
    geom,
    poses: Poses,
    *,
    basis="fourier:1",
    frame: str = "sample",
    fixed=(),
    center=None,
    weights=None,
    noise_variance: Optional[float] = None,
    angles=None,
    times=None,
    n_modes: int = 3,
    rcond: float = 1e-6,
    backend: str = "auto",
    background: Optional[int] = None,
) -> Assessment:
    """Uncertainty, observability and motion modes of ``poses`` (relative to ``geom``).

    One reduced Jacobian pass over ``projections`` with ``geom.apply(poses)``
    against ``volume``. The modes are the singular vectors of the total
    motion (parameters in ``frame``, free ones only, rotations scaled by the
    volume's half-size so that both count in length units).
    """
    prob, basis_obj = _problem(volume, vol_geom, projections, geom, basis, frame, center, fixed, weights, noise_variance, angles, times, backend,
                               background)
    red = prob.reduce(poses.rotvecs, poses.translations)
    _, obs, var = _full_step(prob, basis_obj, red, poses.rotvecs, rcond, 0.0)
    params = poses.to_params(prob.center)
    params_lab = poses.lab_params(geom, prob.center)
    q = params_lab if frame == "lab" else params
    X = (q / prob.scale[None, :])[:, prob.free]
    M, b = prob.framed(red, poses.rotvecs)
    modes = []
    if np.any(X):
        U, S, Vt = np.linalg.svd(X, full_matrices=False)
        Smat = basis_obj.matrix
        for i in range(min(int(n_modes), int(np.sum(S > 1e-3 * S[0])))):
            alpha = U[:, i] * S[i]
            j = int(np.argmax(np.abs(alpha)))
            amp = alpha[j]
            alpha, p = alpha / amp, Vt[i] * amp  # max |α| = 1 with α > 0 there; the amplitude goes to the spatial mode
            qf = np.einsum("i,kij,j->k", p, M, p)
            rf = np.einsum("ki,i->k", b, p)
            free = alpha + np.where(qf > 0, rf / np.where(qf > 0, qf, 1.0), np.nan)
            spatial = np.zeros(6)
            spatial[prob.free] = p
            coeffs = np.linalg.lstsq(Smat, alpha, rcond=None)[0]
            modes.append(Mode(spatial=spatial * prob.scale, coefficients=coeffs, alpha=alpha, alpha_free=free, chi=prob.chi(red)))
    return Assessment(
        poses=poses, params=params, params_lab=params_lab, std=_std_sample(prob, var, poses.rotvecs), observability=obs,
        modes=tuple(modes), chi=prob.chi(red), snr=_overall_snr(red), snr_per_view=red.snr_db(), frame=frame,
        basis_names=tuple(basis_obj.names), center=prob.center,
    )
