"""Command line: ``pdvc demo | calibrate | reconstruct | simulate | inspect``.

The CLI is thin: it parses, calls the library, prints. Long steps report
their progress on stderr; ``-v`` adds the library's log.

Exit codes
----------
0  success
1  a pdvc error: bad input (the message names the parameter, what was
   expected and what came), refused output folder or resume
2  wrong command-line usage
3  the calibration ran but did not succeed (diverged, did not converge, or
   fitted the data worse than the nominal geometry, which is then the one
   returned); every output is written and ``run.json`` says why
130  interrupted (Ctrl-C); every file already written is whole, ``run.json``
   says the run is not complete and ``pdvc calibrate --resume`` continues it
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

from . import __version__
from .errors import PdvcError

log = logging.getLogger("pdvc")

EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_NOT_CALIBRATED, EXIT_INTERRUPTED = 0, 1, 2, 3, 130


class _Progress:
    """One line per stage on stderr (a progress log rather than a bar: it survives pipes and log files)."""

    def __init__(self, stream=sys.stderr, quiet: bool = False):
        self.stream = stream
        self.quiet = quiet
        self.t0 = time.perf_counter()

    def __call__(self, info: dict) -> None:
        if self.quiet:
            return
        event = info.get("event", "")
        el = time.perf_counter() - self.t0
        if event == "init":
            msg = "coarse initialisation (axis offset from opposite views)"
        elif event == "reconstruct":
            msg = f"reconstruction ({info.get('what', '')} geometry, full resolution)"
        elif event == "stage":
            self.stage_rounds, self.round_times = int(info.get("rounds", 0)), []
            msg = (
                f"stage {info['index'] + 1}/{info['n_stages']} '{info['name']}' at scale {info['scale']}: detector "
                f"{info['det_shape'][0]}x{info['det_shape'][1]}, grid {'x'.join(map(str, info['volume']))}, "
                f"{self.stage_rounds} round(s) at most"
            )
        elif event == "round":
            self.round_times = getattr(self, "round_times", []) + [float(info.get("elapsed_s", 0.0))]
            left = max(getattr(self, "stage_rounds", 0) - int(info.get("round", 0)) - 1, 0)
            msg = (
                f"  {info.get('stage')} round {info.get('round')}{' (from extrapolated poses)' if info.get('extrapolated') else ''}: "
                f"chi {info['chi_before']:.4g} -> {info['chi_after']:.4g}, "
                f"increment {info['increment_px']:.3g} px ({self.round_times[-1]:.1f} s"
                + (f"; at most ~{left * np.mean(self.round_times):.0f} s left in this stage)" if left else ")")
            )
        elif event == "resume":
            msg = f"resuming at stage {info.get('stage_index', 0) + 1} after {info.get('rounds')} rounds"
        elif event == "skip":
            msg = f"  {info.get('name')}: skipped, {info.get('why', '')}"
        elif event == "choosing":
            msg = (f"stage {info['index'] + 1}/{info['n_stages']} '{info['name']}' at scale {info['scale']}: comparing the motion "
                   f"models {', '.join(info.get('models', []))}, each fitted on half the views and scored on the other half")
        elif event == "model":
            msg = f"  motion model ({info.get('elapsed_s', 0.0):.1f} s): {info.get('text', '')}"
        elif event == "assess":
            msg = "uncertainty and motion modes at the geometry kept"
        elif event == "second_run" and info.get("basis") == "drift:2":
            msg = ("the precession recipe predicts the views left out worse than the default: it runs once more with a "
                   "precession at one and two cycles per turn")
        elif event == "second_run":
            msg = (f"the default kept a model without the precession: the {info.get('recipe', 'precession')} recipe runs "
                   "as well, and the geometry that predicts the views left out better is kept")
        elif event == "rings":
            msg = (f"a pattern of the detector columns holds {100 * info.get('share', 0.0):.0f}% of the residual: the "
                   "detector's fixed pattern (rings) is subtracted from every view and the scan calibrated again")
        else:
            msg = str(event)
        print(f"[{el:7.1f} s] {msg}", file=self.stream, flush=True)


# ----------------------------------------------------------------------------
# demo
# ----------------------------------------------------------------------------
def _demo(args: argparse.Namespace) -> int:
    from ._demo import run_demo

    print(f"pdvc {__version__} demo: cast-iron rod, volume {args.size}^3, {args.views} views over 360 deg, Poisson noise i0 = 2e4")
    print("  simulated with the analytic ellipsoid projector; motion: axis tilted 0.5 deg and offset, precessing 0.15 deg, drifting")
    res = run_demo(size=args.size, n_views=args.views, seed=args.seed, out_dir=args.out, overwrite=args.overwrite, progress=_Progress(quiet=args.quiet),
                   scheduler=args.scheduler)
    cal = res.calibration
    print(f"  simulation {res.t_simulate:.1f} s, calibration {res.t_calibrate:.1f} s ({cal.message})")
    print()
    print("  reprojection error of sample points vs the true geometry (gauge removed):")
    print(f"    nominal geometry     {res.nominal_error.rms:7.3f} px RMS  (max {res.nominal_error.max:.3f} px)")
    print(f"    calibrated geometry  {res.recovered_error.rms:7.3f} px RMS  (max {res.recovered_error.max:.3f} px)")
    print(f"  mean SNR of the projections: {np.mean(cal.snr_before):.2f} dB -> {np.mean(cal.snr_after):.2f} dB")
    print(f"  entropy of the reconstruction: {cal.entropy_before:.3f} -> {cal.entropy_after:.3f} bits")
    if cal.motion is not None and hasattr(cal.motion, "describe"):
        print("  what moved:")
        for line in cal.motion.describe():
            print(f"    {line}")
    if args.out:
        print(f"  outputs and report.html in {args.out}")
    if not cal.success:
        print(f"pdvc: the demo's calibration did not succeed ({cal.status}): {cal.message}", file=sys.stderr)
        return EXIT_NOT_CALIBRATED
    return EXIT_OK


# ----------------------------------------------------------------------------
# config-driven commands
# ----------------------------------------------------------------------------
def _calibrate(args: argparse.Namespace) -> int:
    from ._calibrate import calibrate
    from ._inputs import load_scan

    scan = load_scan(args.config, out_dir=args.out)
    cfg = _with_scheduler(scan.config, args.scheduler)
    out = args.out or cfg.output.dir
    if out is None:
        raise PdvcError("no output folder: pass --out DIR or set [output] dir in the config")
    _print_scan(scan)
    res = calibrate(
        scan.projections,
        scan.geometry,
        scan.vol_geom,
        out_dir=out,
        overwrite=args.overwrite or cfg.output.overwrite,
        resume=args.resume,
        config=cfg,
        save_initial_volume=cfg.output.save_initial_volume,
        full_resolution_geometry=scan.geometry_unbinned,
        input_notes=scan.notes,
        progress=_Progress(quiet=args.quiet),
        weights=scan.weights,
        scheduler=cfg.compute.scheduler,
        **scan.calibration_options,
    )
    verdict = "calibration succeeded" if res.success else "CALIBRATION DID NOT SUCCEED"
    print(f"{verdict} ({res.status}): {res.message} in {res.elapsed_s:.1f} s")
    print(f"  mean SNR {np.mean(res.snr_before):.2f} -> {np.mean(res.snr_after):.2f} dB; entropy {res.entropy_before:.3f} -> {res.entropy_after:.3f} bits")
    if res.motion is not None and hasattr(res.motion, "describe"):
        for line in res.motion.describe():
            print(f"  {line}")
    print(f"  outputs in {out} (report.html, geometry.npy, motion.csv, result.h5, volume.tif)")
    if not res.success:
        print(f"pdvc: the calibration did not succeed ({res.status}); outputs written, see {out}/run.json", file=sys.stderr)
        return EXIT_NOT_CALIBRATED
    return EXIT_OK


def _reconstruct(args: argparse.Namespace) -> int:
    import tifffile

    from ._inputs import load_scan
    from .calibration import reconstruct
    from .geometry import VectorGeometry
    from .io import atomic_path

    scan = load_scan(args.config)
    geom = scan.geometry
    if args.geometry:
        vec = np.load(args.geometry)
        if vec.shape != (geom.n_views, 12):
            raise PdvcError(f"--geometry must hold ({geom.n_views}, 12) vectors (one row per view), got {vec.shape} from {args.geometry}")
        geom = VectorGeometry(vec, geom.det_shape, geom.kind)
    out = Path(args.out)
    if out.exists() and not args.overwrite:
        raise PdvcError(f"--out {str(out)!r} exists; pass --overwrite to replace it")
    from .compute import use_scheduler

    with use_scheduler(_with_scheduler(scan.config, args.scheduler).compute.scheduler):
        vol = reconstruct(scan.projections, scan.vol_geom, geom)
    with atomic_path(out) as tmp:
        tifffile.imwrite(tmp, vol.astype(np.float32), metadata={"axes": "ZYX"})
    print(f"reconstruction {'x'.join(map(str, vol.shape))} written to {out}")
    return EXIT_OK


def _simulate(args: argparse.Namespace) -> int:
    from ._demo import demo_scan
    from .io import atomic_write_npy, atomic_write_text, prepare_output_dir

    out = prepare_output_dir(args.out, overwrite=args.overwrite)
    scan, vg = demo_scan(size=args.size, n_views=args.views, seed=args.seed)
    atomic_write_npy(out / "projections.npy", scan.projections)
    atomic_write_npy(out / "geometry_nominal.npy", scan.geometry.vectors)
    atomic_write_npy(out / "geometry_true.npy", scan.true_geometry.vectors)
    atomic_write_npy(out / "poses_true.npy", np.hstack([scan.rotvecs, scan.translations]))
    nr, nc = scan.geometry.det_shape
    n = args.size
    config = f"""# pdvc calibrate config.toml  (written by `pdvc simulate`)
# A cone-beam scan simulated with the analytic ellipsoid projector and known motion:
# geometry_true.npy is the answer, poses_true.npy the poses (rotation vector, translation).
[data]
path = "projections.npy"
is_raw = false

[geometry]
type = "cone"
sod = {8.0 * n}
odd = {4.0 * n}
pixel = 1.5
det_shape = [{nr}, {nc}]
angles = {{ start = 0.0, stop = 360.0, count = {args.views} }}

[volume]
shape = [{n}, {n}, {n}]
voxel_size = 1.0

[output]
dir = "calibrated"
"""
    atomic_write_text(out / "config.toml", config)
    print(f"simulated {args.views} views of {nr}x{nc} px into {out}: projections.npy, geometry_nominal.npy, geometry_true.npy, config.toml")
    print(f"calibrate it with:  pdvc calibrate {out / 'config.toml'}")
    return EXIT_OK


def _inspect(args: argparse.Namespace) -> int:
    from ._inputs import inspect_scan

    lines, problems = inspect_scan(args.config)
    for line in lines:
        print(line)
    if problems:
        print("problems:")
        for p in problems:
            print(f"  - {p}")
        return EXIT_ERROR
    print("no inconsistency found")
    return EXIT_OK


def _with_scheduler(cfg, scheduler):
    """The config with ``--scheduler`` in ``[compute]`` when given (it overrides the file)."""
    if scheduler is None:
        return cfg
    import dataclasses

    return dataclasses.replace(cfg, compute=dataclasses.replace(cfg.compute, scheduler=scheduler))


def _scheduler_arg(text: str) -> str:
    from .compute import SchedulerError, parse_scheduler

    try:
        parse_scheduler(text)
    except SchedulerError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text.strip()


_SCHEDULER_HELP = (
    "where the projection passes and reconstructions run: 'threads' (default), 'local:N' (a local Dask cluster "
    "of N worker processes) or 'tcp://host:port' (a running Dask cluster); overrides [compute] scheduler"
)


def _print_scan(scan) -> None:
    g = scan.geometry
    print(f"data: {scan.projections.shape[0]} views of {g.det_shape[0]}x{g.det_shape[1]} px ({g.kind} beam), grid {'x'.join(map(str, scan.vol_geom.shape))}")
    for line in scan.notes:
        print(f"  {line}")


# ----------------------------------------------------------------------------
# parser
# ----------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pdvc",
        description="Self-calibration of lab micro-CT scans by projection-based DVC.",
        epilog="Exit codes: 0 success, 1 pdvc error (bad input, refused output), 2 usage, "
        "3 calibration did not succeed (outputs written), 130 interrupted.",
    )
    parser.add_argument("--version", action="version", version=f"pdvc {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress lines on stderr")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="simulate a drifting, precessing scan, calibrate it, print the errors")
    demo.add_argument("--out", help="folder for the outputs and report.html; nothing is written if absent")
    demo.add_argument("--overwrite", action="store_true", help="allow a non-empty --out folder")
    demo.add_argument("--size", type=int, default=64, help="volume edge in voxels (default 64)")
    demo.add_argument("--views", type=int, default=150, help="projections over 360 deg (default 150)")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--scheduler", type=_scheduler_arg, help=_SCHEDULER_HELP)
    demo.set_defaults(func=_demo)

    cal = sub.add_parser("calibrate", help="calibrate a scan described by a TOML config")
    cal.add_argument("config", help="TOML configuration (see the user guide)")
    cal.add_argument("--out", help="output folder (default: [output] dir of the config)")
    cal.add_argument("--overwrite", action="store_true", help="allow a non-empty output folder")
    cal.add_argument("--resume", action="store_true", help="continue an interrupted run in the output folder")
    cal.add_argument("--scheduler", type=_scheduler_arg, help=_SCHEDULER_HELP)
    cal.set_defaults(func=_calibrate)

    rec = sub.add_parser("reconstruct", help="reconstruct a scan (FDK / FBP) with its nominal or a calibrated geometry")
    rec.add_argument("config", help="TOML configuration")
    rec.add_argument("--geometry", help="per-view vectors (.npy, (n_views, 12)), e.g. geometry.npy of a calibration")
    rec.add_argument("--out", default="volume.tif", help="output TIFF (default volume.tif)")
    rec.add_argument("--overwrite", action="store_true")
    rec.add_argument("--scheduler", type=_scheduler_arg, help=_SCHEDULER_HELP)
    rec.set_defaults(func=_reconstruct)

    sim = sub.add_parser("simulate", help="write a simulated scan with known motion, its true geometry and a config")
    sim.add_argument("--out", required=True, help="output folder")
    sim.add_argument("--overwrite", action="store_true")
    sim.add_argument("--size", type=int, default=64)
    sim.add_argument("--views", type=int, default=150)
    sim.add_argument("--seed", type=int, default=0)
    sim.set_defaults(func=_simulate)

    ins = sub.add_parser("inspect", help="summarise the data and geometry of a config, flag inconsistencies")
    ins.add_argument("config", help="TOML configuration")
    ins.set_defaults(func=_inspect)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.INFO if args.verbose else logging.WARNING
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    for h in logging.getLogger().handlers:  # the output folder's pdvc.log gets INFO; the terminal only this
        h.setLevel(level)
    if getattr(args, "size", 16) < 16 or getattr(args, "views", 16) < 8:
        parser.error("--size must be >= 16 and --views >= 8")
    try:
        return args.func(args)
    except PdvcError as exc:
        print(f"pdvc: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("pdvc: interrupted; files already written are whole (see run.json); `--resume` continues", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
