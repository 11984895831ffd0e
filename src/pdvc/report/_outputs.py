"""The output folder of a calibration run (the edge layer: reads a CalibrationResult, writes files).

Layout (every file written atomically: a reader, or a run interrupted with
Ctrl-C, never sees a half-written file)::

    run.json               status ("running" / "complete"), pdvc version, times, gauge, what was assumed of the inputs
    checkpoint.npz         poses + history after every outer iteration (for --resume)
    geometry.npy           calibrated per-view vectors (n_views, 12), DESIGN.md convention
    geometry_nominal.npy   the nominal ones
    geometry_full_resolution.npy  the calibrated vectors of the unbinned detector (when the data were binned)
    geometry_astra.json, geometry_tigre.json, geometry_leap.json, geometry_cil.json
    motion.csv             per view: poses (sample and lab frames), SNR before/after, std
    result.h5              everything (options, poses, histories, modes, SNR, motion summary)
    volume.tif             corrected reconstruction, float32 (z, y, x)
    volume_initial.tif     reconstruction with the nominal geometry (optional)
    report.html + *.png    the figures of the paper
    config.toml            the fully resolved configuration (CLI runs)

``run.json`` is written first with status "running" and rewritten last with
"complete": a folder whose ``run.json`` does not say "complete" holds the
files of an interrupted run (each of them whole), and ``--resume`` continues
from its checkpoint.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
from pathlib import Path

import numpy as np

from ..correlation import view_angles
from ..status import Status
from ..errors import PdvcError
from ..io import atomic_path, atomic_write_npy, atomic_write_text, prepare_output_dir

log = logging.getLogger("pdvc.report")

__all__ = ["OutputWriter", "OWNED_OUTPUTS", "RUN_FILE", "ResumeMismatchError", "check_resume_fingerprint", "remove_owned_outputs"]

RUN_FILE = "run.json"
CHECKPOINT = "checkpoint.npz"

#: PNG figures of the report (stems given by :func:`pdvc.report._calibration.build_report`)
REPORT_FIGURES = ("snr_per_view", "poses_lab", "temporal_modes", "spatial_modes", "residuals", "axis_trajectory", "slices")

#: Every file a calibration run may write into its folder; ``--overwrite``
#: removes these (and the stale ``.<name>.*.tmp`` files of interrupted atomic
#: writes) and nothing else, so files the user put there are kept.
OWNED_OUTPUTS = (
    RUN_FILE,
    CHECKPOINT,
    "pdvc.log",
    "geometry.npy",
    "geometry_nominal.npy",
    "geometry_full_resolution.npy",
    "geometry_astra.json",
    "geometry_tigre.json",
    "geometry_leap.json",
    "geometry_cil.json",
    "motion.csv",
    "result.h5",
    *(f"{stem}.{ext}" for stem in ("volume", "volume_initial") for ext in ("tif", "npy", "h5")),
    "report.html",
    "config.toml",
    *(f"{name}.png" for name in REPORT_FIGURES),
)

_FINGERPRINT_PARTS = {
    "data": "the projections differ from those of the checkpoint",
    "geometry": "the geometry or volume grid differs from that of the checkpoint",
    "settings": "the calibration settings differ from those of the checkpoint",
}


class ResumeMismatchError(PdvcError, ValueError):
    """``--resume`` on a folder whose run used other data, geometry or settings."""


def _is_owned(name: str) -> bool:
    if name in OWNED_OUTPUTS:
        return True
    # a temporary file of atomic_path: ".<name>.<random>.tmp"
    if name.startswith(".") and name.endswith(".tmp"):
        return any(name.startswith(f".{owned}.") for owned in OWNED_OUTPUTS)
    return False


def remove_owned_outputs(folder, keep=()) -> list[str]:
    """Remove the files pdvc owns (:data:`OWNED_OUTPUTS`, stale ``.<name>.*.tmp``) from ``folder``.

    Anything else (files the user put there, sub-folders) is kept, and so is
    every path in ``keep`` (the run's inputs, e.g. a ``config.toml`` that
    ``pdvc simulate`` wrote there). Returns the names removed, sorted; logs
    them at INFO.
    """
    out = Path(folder)
    if not out.is_dir():
        return []
    kept = {Path(k).resolve() for k in keep if k}
    removed = []
    for p in sorted(out.iterdir()):
        if _is_owned(p.name) and (p.is_file() or p.is_symlink()) and p.resolve() not in kept:
            p.unlink()
            removed.append(p.name)
    if removed:
        log.info("--overwrite: removed %d earlier output(s) from %s: %s", len(removed), out, ", ".join(removed))
    return removed


def check_resume_fingerprint(folder, fingerprint: dict | None) -> None:
    """Refuse to resume when the folder's ``run.json`` fingerprint differs from ``fingerprint``.

    Raises :class:`ResumeMismatchError` naming what changed. A ``run.json``
    without a fingerprint (an older pdvc) is accepted with a warning; with
    no ``run.json`` or no new fingerprint there is nothing to compare.
    """
    path = Path(folder) / RUN_FILE
    if fingerprint is None or not path.exists():
        return
    try:
        old = json.loads(path.read_text(encoding="utf-8")).get("fingerprint")
    except (OSError, ValueError, AttributeError) as exc:
        raise ResumeMismatchError(
            f"cannot resume: {str(path)!r} is unreadable ({exc}); rerun without --resume, with --overwrite or another --out"
        ) from None
    if not isinstance(old, dict):
        log.warning("%s has no fingerprint (written by an older pdvc): cannot check that the data and settings are those of the checkpoint", path)
        return
    changed = [k for k in sorted(set(old) | set(fingerprint)) if old.get(k) != fingerprint.get(k)]
    if changed:
        what = "; ".join(_FINGERPRINT_PARTS.get(k, f"the {k} fingerprint differs") for k in changed)
        raise ResumeMismatchError(
            f"cannot resume the run in {str(Path(folder))!r}: {what}. "
            "Rerun without --resume to start again (with --overwrite to replace its outputs), or choose another --out."
        )


def _version() -> str:
    try:
        from .. import __version__

        return str(__version__)
    except Exception:  # pragma: no cover
        return "unknown"


class OutputWriter:
    """Writes the outputs of :func:`pdvc.calibrate` into one folder."""

    def __init__(self, out_dir, *, overwrite: bool = False, resume: bool = False, fingerprint: dict | None = None, keep=()):
        self.out = prepare_output_dir(out_dir, overwrite=overwrite or resume)
        self.started = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        self.fingerprint = None if fingerprint is None else dict(fingerprint)
        if resume:
            check_resume_fingerprint(self.out, self.fingerprint)
        elif overwrite:
            remove_owned_outputs(self.out, keep)
        if not resume or not (self.out / RUN_FILE).exists():
            self._run_file("running")

    # -- status and checkpoint -------------------------------------------------
    def _run_file(self, status: str, **extra) -> None:
        info = dict(status=status, pdvc_version=_version(), started=self.started)
        info["updated"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        info.update(extra)
        if getattr(self, "fingerprint", None) is not None:
            info["fingerprint"] = self.fingerprint
        atomic_write_text(self.out / RUN_FILE, json.dumps(info, indent=2, default=str) + "\n")

    def save_checkpoint(self, state: dict) -> None:
        """The driver's state after a round (poses, history, stage index, rounds done, coarse offset, rings removed,
        parameters held)."""
        poses = state["poses"]
        offset_px = state.get("offset_px")
        with atomic_path(self.out / CHECKPOINT) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(
                    fh,
                    rotvecs=np.asarray(poses.rotvecs, float),
                    translations=np.asarray(poses.translations, float),
                    history=np.array(json.dumps(list(state["history"]), default=float)),
                    stage_index=np.array(int(state["stage_index"])),
                    rounds_done=np.array(int(state.get("rounds_done", 0))),
                    offset_px=np.array(np.nan if offset_px is None else float(offset_px)),
                    rings=np.array(str(state.get("rings", ""))),
                    held=np.array(",".join(state.get("held", ()))),
                )

    def load_checkpoint(self):
        """The state :meth:`save_checkpoint` wrote, or None when the folder has no checkpoint."""
        from ..geometry import Poses

        path = self.out / CHECKPOINT
        if not path.exists():
            return None
        with np.load(path) as z:
            if "stage_index" not in z:
                raise ResumeMismatchError(f"{path} was written by an older pdvc (no stage index): rerun without --resume")
            off = float(z["offset_px"])
            return dict(
                poses=Poses(z["rotvecs"], z["translations"]),
                history=json.loads(str(z["history"])),
                stage_index=int(z["stage_index"]),
                rounds_done=int(z["rounds_done"]),
                offset_px=None if np.isnan(off) else off,
                rings=str(z["rings"]) if "rings" in z else "",
                held=tuple(h for h in str(z["held"]).split(",") if h) if "held" in z else (),
            )

    # -- final outputs ---------------------------------------------------------
    def write(self, result, *, projections, config=None, save_initial_volume=True, full_resolution_geometry=None,
              input_notes=()) -> None:
        """Every output of ``result`` (a CalibrationResult); ``run.json`` last, with the status.

        ``full_resolution_geometry``: the nominal geometry of the unbinned
        detector; the poses applied to it go to ``geometry_full_resolution.npy``.
        ``input_notes``: what was read and assumed about the data
        (``Scan.notes``), in the report and in ``run.json`` (``inputs``).
        """
        from ._tables import write_motion_csv, write_result_h5

        out = self.out
        oc = getattr(config, "output", None)
        want = lambda name, default=True: bool(getattr(oc, name, default))  # noqa: E731
        vol_format = getattr(oc, "volume_format", "tiff")
        atomic_write_npy(out / "geometry.npy", result.geometry.vectors)
        atomic_write_npy(out / "geometry_nominal.npy", result.nominal.vectors)
        if full_resolution_geometry is not None:
            atomic_write_npy(out / "geometry_full_resolution.npy", full_resolution_geometry.apply(result.poses).vectors)
        if want("exports"):
            from ..io import write_exports

            write_exports(out, result.geometry, result.vol_geom)

        n = result.nominal.n_views
        angles = view_angles(result.nominal)
        center = np.asarray(result.vol_geom.offset, float)
        params = result.poses.to_params(center)
        params_lab = result.poses.lab_params(result.nominal, center)
        asm = result.assessment
        write_motion_csv(
            out / "motion.csv",
            angles_deg=np.rad2deg(angles),
            times=np.arange(n, dtype=float),
            params_sample=params,
            params_lab=params_lab,
            std=None if asm is None else asm.std,
            snr_before=result.snr_before,
            snr_after=result.snr_after,
        )
        for stem, vol in (("volume", result.volume if want("save_final_volume") else None), ("volume_initial", result.volume_initial if save_initial_volume else None)):
            if vol is not None:
                _write_volume(out, stem, np.asarray(vol, np.float32), vol_format, result.vol_geom)
        write_result_h5(out / "result.h5", _result_tree(result, params, params_lab, angles, config))
        if config is not None:
            from ..io import write_config

            write_config(out / "config.toml", config)
        from ._calibration import build_report

        if want("report"):
            build_report(out, result, projections=projections, angles=angles, params_lab=params_lab, inputs=input_notes)
        status = Status(result.status)
        self._run_file(
            "complete",
            gauge=result.gauge,
            success=status.success,
            status_name=status.name.lower(),
            status_code=int(status),
            message=result.message,
            stages=[dict(name=o.name, scale=o.scale, status=Status(o.status).name.lower(), rounds=o.rounds,
                         elapsed_s=round(o.elapsed_s, 2)) for o in result.stage_outcomes],
            timings_s={k: round(float(v), 2) for k, v in result.timings.items()},
            elapsed_s=round(result.elapsed_s, 2),
            snr_before_db=float(np.mean(result.snr_before)),
            snr_after_db=float(np.mean(result.snr_after)),
            inputs=[str(n) for n in input_notes],
        )
        log.info("outputs written to %s", out)


def _write_volume(out: Path, stem: str, vol: np.ndarray, fmt: str, vol_geom) -> None:
    """``<stem>.tif`` (float32, ZYX), ``.npy`` or ``.h5`` (dataset ``volume`` with its grid)."""
    if fmt == "npy":
        atomic_write_npy(out / f"{stem}.npy", vol)
    elif fmt == "hdf5":
        import h5py

        with atomic_path(out / f"{stem}.h5") as tmp:
            with h5py.File(tmp, "w") as f:
                d = f.create_dataset("volume", data=vol, chunks=True, compression="gzip")
                d.attrs["axes"] = "ZYX"
                d.attrs["voxel_size_zyx"] = np.asarray(vol_geom.voxel_size, float)
                d.attrs["offset_xyz"] = np.asarray(vol_geom.offset, float)
    else:
        import tifffile

        with atomic_path(out / f"{stem}.tif") as tmp:
            tifffile.imwrite(tmp, vol, metadata={"axes": "ZYX"})


def _result_tree(result, params, params_lab, angles, config) -> dict:
    hist_keys = ("stage_index", "scale", "iteration", "round", "chi_before", "chi_after", "snr", "increment_px", "elapsed_s",
                 "row_sums_misfit")
    tree = {
        "gauge": result.gauge,
        "status": int(result.status),
        "status_name": Status(result.status).name.lower(),
        "success": int(Status(result.status).success),
        "message": result.message,
        "elapsed_s": result.elapsed_s,
        "options": {k: (v if not isinstance(v, (list, tuple)) else np.asarray(v) if all(isinstance(x, (int, float)) for x in v) else "\n".join(map(str, v))) for k, v in result.options.items()},
        "geometry": {"calibrated": result.geometry.vectors, "nominal": result.nominal.vectors, "kind": result.nominal.kind, "det_shape": np.asarray(result.nominal.det_shape)},
        "volume_grid": {"shape": np.asarray(result.vol_geom.shape), "voxel_size": np.asarray(result.vol_geom.voxel_size), "offset": np.asarray(result.vol_geom.offset)},
        "poses": {"rotvecs": result.rotvecs, "translations": result.translations, "params_sample": params, "params_lab": params_lab, "angles_rad": angles, "parameter_order": "tx, ty, tz, rx, ry, rz about the volume centre"},
        "metrics": {"snr_before_db": result.snr_before, "snr_after_db": result.snr_after, "entropy_before": result.entropy_before, "entropy_after": result.entropy_after},
        "history": {k: np.asarray([h.get(k, np.nan) for h in result.history], float) for k in hist_keys},
        "history_stage": "\n".join(str(h.get("stage", "")) for h in result.history),
        "initial_offset_px": np.nan if result.initial_offset_px is None else result.initial_offset_px,
    }
    asm = result.assessment
    if asm is not None:
        tree["assessment"] = {
            "what": "the measurement at the poses returned: uncertainty (gamma^2 H^-1), unobservable directions, modes of the total motion",
            "frame": asm.frame,
            "basis": ", ".join(asm.basis_names),
            "std_sample": asm.std,
            "chi": asm.chi,
            "observability": "\n".join(asm.observability.describe()),
            "modes": [
                {"spatial": m.spatial, "coefficients": m.coefficients, "alpha": m.alpha, "alpha_free": m.alpha_free}
                for m in asm.modes
            ],
        }
    if result.motion is not None and hasattr(result.motion, "as_dict"):
        tree["motion"] = result.motion.as_dict()
    if config is not None:
        try:
            tree["config_toml"] = _config_text(config)
        except Exception:  # pragma: no cover
            pass
    return tree


def _config_text(config) -> str:
    import tomli_w

    d = config.to_dict() if hasattr(config, "to_dict") else dict(config)
    return tomli_w.dumps(_plain(d))


def _plain(x):
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items() if v is not None}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, Path):
        return str(x)
    if isinstance(x, np.generic):
        return x.item()
    return x
