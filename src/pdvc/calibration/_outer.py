"""``self_calibrate``: a warm-up and a model stage on the data as given (no scales, no coarse initialisation).

The lower-level entry point of the calibration, for studies and tests: it
builds the stage list of :func:`pdvc.calibration.recipe_stages` at scale 1
(or takes one), runs :func:`pdvc.calibration.run_stages` and reconstructs
the final volume. :func:`pdvc.calibrate` adds the scales, the coarse
initialisation, the metrics, the check against the nominal geometry and
the outputs. The method and the reasons for each default: ``docs/method.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional

import numpy as np

from ..correlation import CorrelationResult, drift_basis, estimate_noise_variance
from ..errors import PdvcError, ShapeError
from ..geometry import Poses, VectorGeometry, VolumeGeometry
from ..status import Status
from ._driver import PosesResult, reconstruct, refined_grid, run_stages
from ._stages import StageError, recipe_stages

__all__ = ["self_calibrate", "OuterResult", "OuterError", "drift_basis", "refined_grid", "gauge_text"]


class OuterError(PdvcError, ValueError):
    """Bad options for :func:`self_calibrate`."""


def gauge_text(kind: str, scale: bool) -> str:
    """How the unobservable global motion is fixed, in words (every output states it)."""
    text = (
        "poses relative to the geometry given; gauge: zero mean rigid pose over the views "
        "(mean rotation = identity, mean position of the volume centre unchanged)"
    )
    if kind == "cone" and scale:
        text += " and zero mean magnification change (the nominal source-object distance is the mean one)"
    return text


@dataclass(frozen=True)
class OuterResult(PosesResult):
    """Outcome of :func:`self_calibrate`.

    Attributes
    ----------
    poses : Poses
        The poses kept, relative to the geometry given, gauge fixed.
    geometry : VectorGeometry
        ``geom.apply(poses)``.
    gauge : str
    result : CorrelationResult or None
        The measurement whose poses were kept.
    history : tuple of dict
        One dict per round (:class:`pdvc.calibration.DriverResult`).
    stages : tuple of StageOutcome
    volume : (nz, ny, nx) float32
        FDK/FBP (or the stage's callable) with ``geometry`` on ``vol_geom``.
    vol_geom, corr_vol_geom : VolumeGeometry
        The grid given and the (oversampled) grid of the last correlation.
    status : Status
    message : str
    model_choice : ModelChoice or None
        The motion model the stages with candidates chose (:class:`pdvc.calibration.DriverResult`).
    """

    poses: Poses
    geometry: VectorGeometry
    gauge: str
    result: Optional[CorrelationResult]
    history: tuple
    stages: tuple
    volume: np.ndarray
    vol_geom: VolumeGeometry
    corr_vol_geom: VolumeGeometry
    status: Status
    message: str
    model_choice: Optional[Any] = None

    @property
    def n_outer(self) -> int:
        return len(self.history)

    @property
    def chi_before(self) -> np.ndarray:
        return np.array([h["chi_before"] for h in self.history])

    @property
    def increments_px(self) -> np.ndarray:
        return np.array([h["increment_px"] for h in self.history])


def self_calibrate(
    projections,
    geom: VectorGeometry,
    vol_geom: VolumeGeometry,
    *,
    stages=None,
    recipe: str = "default",
    max_outer: Optional[int] = None,
    warmup: int = 1,
    guard: Optional[str] = None,
    weights=None,
    noise_variance: Optional[float] = None,
    fix_scale: bool = True,
    initial_poses: Optional[Poses] = None,
    angles=None,
    times=None,
    center=None,
    backend: str = "auto",
    callback: Optional[Callable[[dict], object]] = None,
    checkpoint: Optional[Callable[[dict], object]] = None,
    **model,
) -> OuterResult:
    """Calibrate the per-view geometry by rounds of reconstruction and P-DVC, at the data's own scale.

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) array
        Measured line integrals; not modified.
    geom : VectorGeometry
        The geometry given; the poses returned are relative to it.
    vol_geom : VolumeGeometry
        Grid of the final volume (correlation grids are ``oversample`` x finer).
    stages : sequence of Stage, optional
        The stage list to run; default ``recipe_stages(recipe, scales=(1,), ...)``.
    recipe, max_outer, warmup
        See :func:`pdvc.calibration.recipe_stages` (``max_outer``: rounds at
        most, warm-up included).
    guard : None or "entropy"
        Add the entropy guard to the model stage (the consistency guard is
        always on).
    **model
        Fields of the model stage (:class:`Stage`): ``basis``, ``frame``,
        ``fixed``, ``method``, ``reconstruct``, ``oversample``, ``tol_px``,
        ``stall_ratio``, ``diverge_tol``, ``entropy_tol``, ``max_iter``,
        ``max_modes``, ...
    noise_variance : float, optional
        γ² of the projections; estimated from them if not given.
    initial_poses : Poses, optional
        Where to start (relative to ``geom``); gauge fixed first.
    callback : callable, optional
        Called with the history dict of every round.
    checkpoint : callable, optional
        Called after every round with the driver's state (``run_stages``).

    Returns
    -------
    OuterResult
    """
    p = _check(projections, geom, vol_geom)
    if guard not in (None, "entropy"):
        raise OuterError(f"guard must be None or 'entropy', got {guard!r}")
    try:
        if stages is None:
            if guard == "entropy":
                model["guards"] = ("consistency", "entropy")
            stages = recipe_stages(recipe, geom.det_shape, scales=(1,), max_outer=max_outer, warmup=warmup, **model)
        elif model or guard is not None:
            raise OuterError(f"stages= is given: set {sorted(model) or ['guard']} in the stages instead")
        stages = tuple(stages)
    except StageError as exc:
        raise OuterError(str(exc)) from None
    gamma2 = float(noise_variance) if noise_variance is not None else estimate_noise_variance(p)
    start = None
    if initial_poses is not None:
        start = initial_poses.gauge_fixed(geom, center=vol_geom.offset, scale=fix_scale)
    progress = None if callback is None else (lambda info: callback({k: v for k, v in info.items() if k != "event"}) if info["event"] == "round" else None)
    drv = run_stages(
        p, geom, vol_geom, stages, poses=start, noise_variance=gamma2, weights=weights, fix_scale=fix_scale,
        angles=angles, times=times, center=center, backend=backend, checkpoint=checkpoint, progress=progress,
    )
    geometry = geom.apply(drv.poses)
    volume = None
    if drv.guard_volume is not None and drv.guard_volume[0] is drv.poses and drv.guard_volume[1] == 1:
        volume = drv.guard_volume[2]  # the entropy guard already made it
    if volume is None:
        last = stages[-1]
        rec = last.reconstruct if callable(last.reconstruct) else reconstruct
        volume = rec(p, vol_geom, geometry)
    return OuterResult(
        poses=drv.poses, geometry=geometry, gauge=gauge_text(geom.kind, fix_scale), result=drv.correlation,
        history=drv.history, stages=drv.stages, volume=np.asarray(volume, np.float32), vol_geom=vol_geom,
        corr_vol_geom=refined_grid(vol_geom, stages[-1].oversample), status=drv.status, message=drv.message,
        model_choice=drv.model_choice,
    )


def _check(projections, geom, vol_geom):
    if not isinstance(geom, VectorGeometry):
        raise OuterError(f"geom must be a VectorGeometry, got {type(geom).__name__}")
    if not isinstance(vol_geom, VolumeGeometry):
        raise OuterError(f"vol_geom must be a VolumeGeometry, got {type(vol_geom).__name__}")
    p = np.asarray(projections, dtype=np.float32)
    if p.shape != (geom.n_views,) + tuple(geom.det_shape):
        raise ShapeError(f"projections must have shape {(geom.n_views,) + tuple(geom.det_shape)}, got {p.shape}")
    return p

