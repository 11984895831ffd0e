"""Command line: ``pdvc demo`` (more sub-commands come with the pipeline).

Exit codes: 0 success; 1 a pdvc error (bad input, refused output folder);
2 wrong command-line usage; 130 interrupted.
"""

from __future__ import annotations

import argparse
import logging
import sys

from . import __version__
from .errors import PdvcError

log = logging.getLogger("pdvc")


def _demo(args: argparse.Namespace) -> int:
    from ._demo import run_demo
    from .io import atomic_write_npy, prepare_output_dir

    out = prepare_output_dir(args.out, overwrite=args.overwrite) if args.out else None
    res = run_demo(size=args.size, n_views=args.views, seed=args.seed)
    n = args.size
    print(f"pdvc {__version__} demo: cast-iron rod, volume {n}^3, {args.views} views, detector {res.det_shape[0]}x{res.det_shape[1]}")
    print("  motion: axis tilted 0.5 deg and offset, precessing 0.15 deg, drifting; Poisson noise i0 = 2e4")
    print(f"  simulated with the analytic ellipsoid projector in {res.t_simulate:.1f} s")
    print(
        f"  the nominal geometry misplaces the sample by {res.nominal_error.rms:.2f} px RMS "
        f"(max {res.nominal_error.max:.2f} px) on the detector, gauge removed"
    )
    print()
    print(f"  {'reconstruction with':18s} {'RMSE/range':>10s} {'entropy':>8s} {'SNR dB':>7s} {'FDK s':>6s} {'Jacobian pass s':>15s}")
    for r in res.rows:
        print(f"  {r.label:18s} {r.rmse:10.4f} {r.entropy:8.3f} {r.snr_db:7.2f} {r.t_fdk:6.2f} {r.t_jacobian:15.2f}")
    print()
    print("  (the P-DVC engine that finds the true geometry from the data is issue #3; see README)")
    if out is not None:
        atomic_write_npy(out / "geometry_nominal.npy", res.scan.geometry.vectors)
        atomic_write_npy(out / "geometry_true.npy", res.scan.true_geometry.vectors)
        atomic_write_npy(out / "projections.npy", res.scan.projections)
        for r in res.rows:
            atomic_write_npy(out / f"volume_{r.label.replace(' ', '_')}.npy", r.volume)
        print(f"  wrote geometries, projections and volumes (.npy) to {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pdvc", description="Self-calibration of lab micro-CT scans by projection-based DVC.")
    parser.add_argument("--version", action="version", version=f"pdvc {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="simulate a drifting scan, reconstruct it, print figures")
    demo.add_argument("--out", help="folder for the outputs (.npy); nothing is written if absent")
    demo.add_argument("--overwrite", action="store_true", help="allow a non-empty --out folder")
    demo.add_argument("--size", type=int, default=96, help="volume edge in voxels (default 96)")
    demo.add_argument("--views", type=int, default=180, help="number of projections over 360 deg (default 180)")
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(func=_demo)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if getattr(args, "size", 16) < 16 or getattr(args, "views", 16) < 8:
        parser.error("--size must be >= 16 and --views >= 8")
    try:
        return args.func(args)
    except PdvcError as exc:
        print(f"pdvc: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("pdvc: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
