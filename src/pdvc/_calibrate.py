"""``pdvc.calibrate``: the calibration pipeline plus, optionally, its output folder."""

from __future__ import annotations

import logging

import numpy as np

from .calibration import CalibrationResult
from .calibration import calibrate as _calibrate

log = logging.getLogger("pdvc")

__all__ = ["calibrate"]


def calibrate(
    projections,
    geom,
    vol_geom,
    *,
    out_dir=None,
    overwrite: bool = False,
    resume: bool = False,
    config=None,
    save_initial_volume: bool = True,
    **options,
) -> CalibrationResult:
    """Calibrate a scan from its own projections; write the outputs if ``out_dir``.

    Parameters
    ----------
    projections : (n_views, n_rows, n_cols) array
        Line integrals; not modified.
    geom : VectorGeometry
        Nominal geometry.
    vol_geom : VolumeGeometry
        Reconstruction grid.
    out_dir : path, optional
        Output folder (layout in :mod:`pdvc.report._outputs`): refused when
        not empty unless ``overwrite`` or ``resume``. A checkpoint is written
        after every outer iteration; ``run.json`` says "complete" only at the end.
    resume : bool
        Continue an interrupted run from the checkpoint in ``out_dir``.
    config : Config or dict, optional
        The resolved configuration, written as ``config.toml``.
    **options
        Passed to :func:`pdvc.calibration.calibrate` (basis, method, frame,
        fixed, scales, oversample, n_outer, tol_px, init, weights, ...).

    Returns
    -------
    CalibrationResult
    """
    if out_dir is None:
        if resume:
            raise ValueError("resume=True needs out_dir (the folder of the interrupted run)")
        return _calibrate(projections, geom, vol_geom, **options)
    from .report._outputs import OutputWriter

    writer = OutputWriter(out_dir, overwrite=overwrite, resume=resume)
    # the run's log (INFO and above of every pdvc module), appended on --resume
    handler = logging.FileHandler(writer.out / "pdvc.log", mode="a" if resume else "w", encoding="utf-8")
    handler.setLevel(logging.INFO)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger("pdvc")
    old_level = root.level
    root.addHandler(handler)
    if root.getEffectiveLevel() > logging.INFO:
        root.setLevel(logging.INFO)
    try:
        state = writer.load_checkpoint() if resume else None
        if resume and state is None:
            log.warning("no checkpoint in %s: starting from the beginning", writer.out)
        res = _calibrate(projections, geom, vol_geom, checkpoint=lambda st: writer.save_checkpoint(**st), resume=state, **options)
        s = int(res.scales[-1])
        p_fine = np.asarray(projections, np.float32) if s == 1 else res.projections_fine
        writer.write(res, projections=p_fine, geom_fine=geom if s == 1 else geom.binned(s), config=config, save_initial_volume=save_initial_volume)
    finally:
        root.removeHandler(handler)
        root.setLevel(old_level)
        handler.close()
    return res
