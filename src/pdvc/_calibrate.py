"""``pdvc.calibrate``: the calibration pipeline plus, optionally, its output folder."""

from __future__ import annotations

import logging

from .calibration import CalibrationResult
from .calibration import calibrate as _calibrate
from .errors import InputTypeError

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
    full_resolution_geometry=None,
    input_notes=(),
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
        after every round; ``run.json`` says "complete" only at the end, with
        ``success``, the status and the message. Every output is written even
        when the calibration did not succeed.
    resume : bool
        Continue an interrupted run from the checkpoint in ``out_dir``.
    config : Config or dict, optional
        The resolved configuration, written as ``config.toml``.
    full_resolution_geometry : VectorGeometry, optional
        The nominal geometry of the detector before binning, when the
        projections given are a binned copy: the poses found (which do not
        depend on the pixel size) are applied to it and written as
        ``geometry_full_resolution.npy``, for the full-size reconstruction.
    input_notes : sequence of str
        What was read and assumed about the data (``Scan.notes`` of
        :func:`pdvc._inputs.load_scan`: the data kind and why, flats, air level, bad
        pixels, binning, the schedule's scales): with ``out_dir``, written to
        ``pdvc.log``, ``run.json`` (``inputs``) and the report, so that the
        output folder says what the calibration assumed.
    **options
        Passed to :func:`pdvc.calibration.calibrate` (recipe, stages, scales,
        max_outer, basis, method, frame, fixed, init, weights, ...).

    Returns
    -------
    CalibrationResult
    """
    notes = None if isinstance(input_notes, (str, bytes)) else list(input_notes or ())
    if notes is None or not all(isinstance(n, str) for n in notes):
        raise InputTypeError(f"input_notes must be a sequence of str (one note per item), got {input_notes!r:.80}")
    if out_dir is None:
        if resume:
            raise ValueError("resume=True needs out_dir (the folder of the interrupted run)")
        return _calibrate(projections, geom, vol_geom, **options)
    from .report._outputs import OutputWriter

    inputs = () if config is None else (getattr(config, "source", None), getattr(getattr(config, "data", None), "path", None))
    writer = OutputWriter(
        out_dir, overwrite=overwrite, resume=resume, fingerprint=_fingerprint(projections, geom, vol_geom, options, config),
        keep=inputs,
    )
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
        for note in notes:
            log.info("input: %s", note)
        state = writer.load_checkpoint() if resume else None
        if resume and state is None:
            log.warning("no checkpoint in %s: starting from the beginning", writer.out)
        res = _calibrate(projections, geom, vol_geom, checkpoint=writer.save_checkpoint, resume=state, **options)
        writer.write(
            res, projections=projections, config=config, save_initial_volume=save_initial_volume,
            full_resolution_geometry=full_resolution_geometry, input_notes=notes,
        )
    finally:
        root.removeHandler(handler)
        root.setLevel(old_level)
        handler.close()
    return res


def _fingerprint(projections, geom, vol_geom, options: dict, config) -> dict:
    """What ``--resume`` checks: data, geometry and settings (callables left out; arrays such as weights by their hash)."""
    from .io import run_fingerprint

    # where it runs (scheduler, [compute]) does not change the result: a run may resume on another
    settings = {"options": {k: v for k, v in options.items() if not callable(v) and k != "scheduler"}}
    if config is not None:
        d = config.to_dict() if hasattr(config, "to_dict") else dict(config)
        # [data] is left out: where the projections are read from may move; what they hold is the data hash
        settings["config"] = {k: v for k, v in d.items() if k not in ("output", "data", "compute")}
    return run_fingerprint(projections, geom, vol_geom, settings)
