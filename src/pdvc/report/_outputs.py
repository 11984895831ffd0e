"""The output folder of a calibration run (the edge layer: reads a CalibrationResult, writes files).

Layout (every file written atomically: a reader, or a run interrupted with
Ctrl-C, never sees a half-written file)::

    run.json               status ("running" / "complete"), pdvc version, times, gauge
    checkpoint.npz         poses + history after every outer iteration (for --resume)
    geometry.npy           calibrated per-view vectors (n_views, 12), DESIGN.md convention
    geometry_nominal.npy   the nominal ones
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

from ..correlation import lab_frames, view_angles
from ..correlation._engine import _rt_to_params
from ..io import atomic_path, atomic_write_npy, atomic_write_text, prepare_output_dir

log = logging.getLogger("pdvc.report")

__all__ = ["OutputWriter", "RUN_FILE"]

RUN_FILE = "run.json"
CHECKPOINT = "checkpoint.npz"


def _version() -> str:
    try:
        from .. import __version__

        return str(__version__)
    except Exception:  # pragma: no cover
        return "unknown"


class OutputWriter:
    """Writes the outputs of :func:`pdvc.calibrate` into one folder."""

    def __init__(self, out_dir, *, overwrite: bool = False, resume: bool = False):
        self.out = prepare_output_dir(out_dir, overwrite=overwrite or resume)
        self.started = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        if not resume or not (self.out / RUN_FILE).exists():
            self._run_file("running")

    # -- status and checkpoint -------------------------------------------------
    def _run_file(self, status: str, **extra) -> None:
        info = dict(status=status, pdvc_version=_version(), started=self.started)
        info["updated"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        info.update(extra)
        atomic_write_text(self.out / RUN_FILE, json.dumps(info, indent=2, default=str) + "\n")

    def save_checkpoint(self, rotvecs, translations, history, scale_index: int, offset_px, rounds_done: int = 0) -> None:
        with atomic_path(self.out / CHECKPOINT) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(
                    fh,
                    rotvecs=np.asarray(rotvecs, float),
                    translations=np.asarray(translations, float),
                    history=np.array(json.dumps(list(history), default=float)),
                    scale_index=np.array(int(scale_index)),
                    rounds_done=np.array(int(rounds_done)),
                    offset_px=np.array(np.nan if offset_px is None else float(offset_px)),
                )

    def load_checkpoint(self):
        path = self.out / CHECKPOINT
        if not path.exists():
            return None
        with np.load(path) as z:
            off = float(z["offset_px"])
            return dict(
                rotvecs=z["rotvecs"].copy(),
                translations=z["translations"].copy(),
                history=json.loads(str(z["history"])),
                scale_index=int(z["scale_index"]),
                rounds_done=int(z["rounds_done"]) if "rounds_done" in z else 0,
                offset_px=None if np.isnan(off) else off,
            )

    # -- final outputs ---------------------------------------------------------
    def write(self, result, *, projections, geom_fine, config=None, save_initial_volume=True) -> None:
        from ._tables import write_motion_csv, write_result_h5

        out = self.out
        oc = getattr(config, "output", None)
        want = lambda name, default=True: bool(getattr(oc, name, default))  # noqa: E731
        vol_format = getattr(oc, "volume_format", "tiff")
        atomic_write_npy(out / "geometry.npy", result.geometry.vectors)
        atomic_write_npy(out / "geometry_nominal.npy", result.nominal.vectors)
        if want("exports"):
            from ..io._export import write_exports

            write_exports(out, result.geometry, result.vol_geom)

        eng = result.engine
        n = result.nominal.n_views
        F = lab_frames(result.nominal)
        angles = view_angles(result.nominal)
        params = _rt_to_params(result.rotvecs, result.translations, np.asarray(result.vol_geom.offset, float))
        params_lab = np.hstack([np.einsum("kji,kj->ki", F, params[:, :3]), np.einsum("kji,kj->ki", F, params[:, 3:])])
        times = np.arange(n, dtype=float)
        write_motion_csv(
            out / "motion.csv",
            angles_deg=np.rad2deg(angles),
            times=times,
            params_sample=params,
            params_lab=params_lab,
            std=None if eng is None else eng.std,
            snr_before=result.snr_before,
            snr_after=result.snr_after,
        )
        for stem, vol in (("volume", result.volume if want("save_final_volume") else None), ("volume_initial", result.volume_initial if save_initial_volume else None)):
            if vol is not None:
                _write_volume(out, stem, np.asarray(vol, np.float32), vol_format, result.vol_geom)
        tree = _result_tree(result, params, params_lab, angles, config)
        write_result_h5(out / "result.h5", tree)
        if config is not None:
            from ..io._config import write_config

            write_config(out / "config.toml", config)
        from ._calibration import build_report

        if want("report"):
            build_report(out, result, projections=projections, geom_fine=geom_fine, angles=angles, params_lab=params_lab)
        self._run_file(
            "complete",
            gauge=result.gauge,
            status_code=result.status,
            message=result.message,
            elapsed_s=round(result.elapsed_s, 2),
            snr_before_db=float(np.mean(result.snr_before)),
            snr_after_db=float(np.mean(result.snr_after)),
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
    eng = result.engine
    tree = {
        "gauge": result.gauge,
        "status": result.status,
        "message": result.message,
        "elapsed_s": result.elapsed_s,
        "options": {k: (v if not isinstance(v, (list, tuple)) else np.asarray(v) if all(isinstance(x, (int, float)) for x in v) else ", ".join(map(str, v))) for k, v in result.options.items()},
        "geometry": {"calibrated": result.geometry.vectors, "nominal": result.nominal.vectors, "kind": result.nominal.kind, "det_shape": np.asarray(result.nominal.det_shape)},
        "volume_grid": {"shape": np.asarray(result.vol_geom.shape), "voxel_size": np.asarray(result.vol_geom.voxel_size), "offset": np.asarray(result.vol_geom.offset)},
        "poses": {"rotvecs": result.rotvecs, "translations": result.translations, "params_sample": params, "params_lab": params_lab, "angles_rad": angles, "parameter_order": "tx, ty, tz, rx, ry, rz about the volume centre"},
        "metrics": {"snr_before_db": result.snr_before, "snr_after_db": result.snr_after, "entropy_before": result.entropy_before, "entropy_after": result.entropy_after},
        "history": {k: np.asarray([h.get(k, np.nan) for h in result.history], float) for k in ("scale", "iteration", "chi_before", "chi_after", "snr", "increment_px")},
        "initial_offset_px": np.nan if result.initial_offset_px is None else result.initial_offset_px,
    }
    if eng is not None:
        tree["engine"] = {
            "method": eng.method,
            "frame": eng.frame,
            "basis": getattr(eng.basis, "name", str(eng.basis.kind)),
            "std_sample": eng.std,
            "chi_history": eng.chi_history,
            "snr_history": eng.snr_history,
            "noise_variance": eng.noise_variance,
            "status": eng.status,
            "message": eng.message,
            "observability": "\n".join(eng.observability.describe()) if hasattr(eng.observability, "describe") else "",
            "mode_table": np.asarray(eng.mode_table, float).reshape(-1, 3) if eng.mode_table else np.zeros((0, 3)),
            "modes": [
                {"spatial": m.spatial, "coefficients": m.coefficients, "alpha": m.alpha, "alpha_free": m.alpha_free, "chi": m.chi}
                for m in eng.modes
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
