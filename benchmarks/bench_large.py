"""A 2k lab scan calibrated on a binned copy, read and binned in chunks (issue #11, item 3).

The scan: a uint16 TIFF folder of ``--views`` views of ``--det`` x ``--det``
pixels (default 1440 views of 2048 x 2048: 12 GB on disk, 24 GB as float32),
with 10 flats and 10 darks. It is made by upsampling a smaller simulated
scan (``--det / 4`` pixels, block repeat x4): ``cast_iron_phantom`` in a
``--size``³ grid (default 128), cone beam (magnification 1.5), projected by
the analytic ellipsoid projector (no inverse crime) with a known motion
(``tilted_axis_poses`` 0.5°, offset 0.04 n, plus a drift), converted to
counts with Poisson noise (i0 = 2e4) by ``pdvc.simulate.simulate_scan``.
Making it is not timed.

Timed, in a fresh child process pinned to ``--threads`` CPUs, as
``pdvc calibrate`` runs it: ``load_scan`` of a config with
``[preprocess] bin = --bin`` (default 4: reading, normalising, binning in
chunks), then ``pdvc.calibrate`` on the binned copy with default options,
writing ``geometry_full_resolution.npy``. Printed: read + bin time (and
MB/s), the calibration split (``res.timings``), total, the child's peak
resident memory (``ru_maxrss`` from ``os.wait4``), the yardstick ratio
(``benchmarks/_reference.py``, timed 3x after the calibration, as in
``bench_calibrate.py``) and the RMS reprojection error of the geometry
written for the full-resolution detector against the injected motion
(125 points, gauge removed, full-resolution pixels), also for the nominal
geometry. Targets (issue #11): <= 15 min and <= 8 GiB peak.

    python benchmarks/bench_large.py                       # 2048² x 1440 (~12 GB of TIFFs in a temp dir)
    python benchmarks/bench_large.py --quick               # 256² x 180, a minute
    python benchmarks/bench_large.py --views 360 --det 1024
    python benchmarks/bench_large.py --keep-data /tmp/big  # keep (and reuse) the TIFFs
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
MARK = "BENCH_LARGE_JSON "
SEED = 0
UP = 4  # upsampling of the simulated scan


def _problem(size: int, n_views: int, det: int):
    """(small nominal geometry, full nominal geometry, grid, phantom, true rotvecs, true translations)."""
    import numpy as np

    import pdvc
    from pdvc.simulate import cast_iron_phantom, combine_poses, drift_poses, tilted_axis_poses

    n = size
    small = det // UP
    sod, odd = 4.0 * n, 2.0 * n
    pixel = 1.5 * 1.25 * n / small  # the detector sees 1.25 n at the sample (magnification 1.5)
    vg = pdvc.VolumeGeometry((n, n, n), voxel_size=1.0)
    angles = np.linspace(0, 2 * np.pi, n_views, endpoint=False)
    geom_s = pdvc.circular_cone(angles, sod=sod, odd=odd, det_shape=(small, small), pixel=pixel)
    geom_f = pdvc.circular_cone(angles, sod=sod, odd=odd, det_shape=(small * UP, small * UP), pixel=pixel / UP)
    phantom = cast_iron_phantom(0.36 * n, 0.8 * n, n_nodules=n // 2, seed=SEED)
    rv, t = combine_poses(
        tilted_axis_poses(angles, tilt=np.deg2rad(0.5), tilt_azimuth=0.7, offset=(0.04 * n, 0.0, 0.0)),
        drift_poses(np.linspace(0.0, 1.0, n_views), angles, velocity=(0.02 * n, 0.0, 0.015 * n)),
    )
    return geom_s, geom_f, vg, phantom, rv, t, dict(sod=sod, odd=odd, pixel=pixel / UP)


def _tag(args) -> str:
    return f"bench_large_n{args.size}_v{args.views}_d{args.det}_seed{SEED}"


def child_make(args, folder: str) -> int:
    """Simulate at det / 4 and write the x4 upsampled uint16 TIFF folder (proj/, flats/, darks/)."""
    import numpy as np
    import tifffile

    from pdvc.simulate import simulate_scan

    geom_s, _, _, phantom, rv, t, _ = _problem(args.size, args.views, args.det)
    t0 = time.perf_counter()
    scan = simulate_scan(phantom, geom_s, rotvecs=rv, translations=t, i0=2e4, seed=SEED, supersampling=1)
    t_sim = time.perf_counter() - t0

    def up(img):
        return np.clip(np.rint(img), 0, 65535).astype(np.uint16).repeat(UP, axis=0).repeat(UP, axis=1)

    t0 = time.perf_counter()
    for sub, frames in (("proj", scan.counts), ("flats", scan.flats), ("darks", scan.darks)):
        os.makedirs(os.path.join(folder, sub), exist_ok=True)
        for k, img in enumerate(frames):
            tifffile.imwrite(os.path.join(folder, sub, f"{sub}_{k:05d}.tif"), up(img))
    open(os.path.join(folder, "COMPLETE"), "w").write("ok\n")
    print(f"  simulated {args.views} views of {args.det // UP}^2 in {t_sim:.1f} s; wrote {args.det}^2 uint16 TIFFs in "
          f"{time.perf_counter() - t0:.1f} s -> {folder}", flush=True)
    return 0


def _config(args, folder: str, out: str) -> str:
    n, small = args.size, args.det // UP
    g = dict(sod=4.0 * n, odd=2.0 * n, pixel=1.5 * 1.25 * n / small / UP)  # as _problem, without simulating
    text = (
        f'[data]\npath = "{folder}/proj"\nflats = "{folder}/flats"\ndarks = "{folder}/darks"\n'
        f'[geometry]\ntype = "cone"\nsod = {g["sod"]}\nodd = {g["odd"]}\npixel = {g["pixel"]}\n'
        f"angles = {{ start = 0, stop = 360, count = {args.views} }}\n"
        f"[volume]\nshape = [{args.size}, {args.size}, {args.size}]\nvoxel_size = 1.0\n"
        f"[preprocess]\nbin = {args.bin}\n"
    )
    path = os.path.join(out, "config.toml")
    with open(path, "w") as f:
        f.write(text)
    return path


def child_calibrate(args, folder: str, out: str) -> int:
    import numpy as np

    import pdvc
    from pdvc._inputs import load_scan
    from pdvc.geometry import fix_gauge, reprojection_error, sample_points

    import logging

    sys.path.insert(0, HERE)
    from bench_calibrate import _reference_problem, _warm_up

    io_log = logging.getLogger("pdvc.io")  # the reader's progress lines, while reading
    handler = logging.StreamHandler(sys.stdout)
    handler.setFormatter(logging.Formatter("    %(message)s"))
    io_log.addHandler(handler)
    io_log.setLevel(logging.INFO)
    yard = _reference_problem(args.threads)
    _warm_up()
    cfg = _config(args, folder, out)
    t0 = time.perf_counter()
    scan = load_scan(cfg, out_dir=os.path.join(out, "cal"))
    t_read = time.perf_counter() - t0
    rss_read = _rss_mib()
    io_log.removeHandler(handler)
    t1 = time.perf_counter()
    res = pdvc.calibrate(
        scan.projections, scan.geometry, scan.vol_geom, out_dir=os.path.join(out, "cal"), overwrite=True,
        config=scan.config, full_resolution_geometry=scan.geometry_unbinned, **scan.calibration_options,
    )
    t_cal = time.perf_counter() - t1
    total = time.perf_counter() - t0
    ref = float(np.median([yard() for _ in range(3)]))

    _, geom_f, vg, _, rv, t, _ = _problem(args.size, args.views, args.det)
    truth = geom_f.apply_poses(*fix_gauge(rv, t, geom_f, center=vg.offset))
    written = os.path.join(out, "cal", "geometry_full_resolution.npy")
    points = sample_points(vg, 5, fraction=0.6)
    err = nominal = float("nan")
    if os.path.exists(written):
        g = pdvc.VectorGeometry(np.load(written), geom_f.det_shape, "cone")
        err = float(reprojection_error(g, truth, points).rms)
        nominal = float(reprojection_error(geom_f, truth, points).rms)
    notes = [n for n in scan.notes if n.startswith("read in chunks")]
    out_d = dict(
        read_s=t_read, cal_s=t_cal, total_s=total, ref_s=ref, rss_read_mib=rss_read,
        timings={k: float(v) for k, v in (getattr(res, "timings", None) or {}).items()},
        status=str(res.status), success=bool(res.success), err_px=err, nominal_px=nominal,
        binned=list(scan.projections.shape), chunk_note=notes[0] if notes else "",
    )
    print(MARK + json.dumps(out_d), flush=True)
    return 0


def _rss_mib() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _run_child(argv: list) -> tuple[int, str, float]:
    """Run this script as a child; its return code, stdout, and its peak RSS (MiB) from os.wait4."""
    proc = subprocess.Popen([sys.executable, os.path.abspath(__file__)] + argv, stdout=subprocess.PIPE, text=True)
    lines = []
    for line in proc.stdout:
        if not line.startswith(MARK):
            print(line, end="", flush=True)
        lines.append(line)
    _, status, ru = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, "".join(lines), ru.ru_maxrss / 1024.0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, default=1440)
    ap.add_argument("--det", type=int, default=2048, help="detector rows = columns (a multiple of 4)")
    ap.add_argument("--size", type=int, default=128, help="edge of the simulated volume, voxels")
    ap.add_argument("--bin", type=int, default=4, help="[preprocess] bin")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="256^2 detector, 180 views, 64^3 volume")
    ap.add_argument("--keep-data", metavar="DIR", help="keep (and reuse) the TIFF folder here")
    ap.add_argument("--child", choices=("make", "calibrate"), help=argparse.SUPPRESS)
    ap.add_argument("--folder", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.quick:
        args.views, args.det, args.size = 180, 256, 64
    if args.det % UP or args.det // UP < 8:
        ap.error(f"--det must be a multiple of {UP} and at least {8 * UP}, got {args.det}")
    if args.child:
        sys.path.insert(0, HERE)
        from _reference import pin_threads

        pin_threads(args.threads)
        return child_make(args, args.folder) if args.child == "make" else child_calibrate(args, args.folder, args.out)

    sys.path.insert(0, HERE)
    from _reference import machine_line

    common = ["--views", str(args.views), "--det", str(args.det), "--size", str(args.size), "--bin", str(args.bin),
              "--threads", str(args.threads)]
    tmp = tempfile.mkdtemp(prefix="pdvc_bench_large_")
    base = args.keep_data or tmp
    folder = os.path.join(base, _tag(args))
    gb = args.views * args.det**2 * 2 / 1e9
    print(f"bench_large: {args.views} views of {args.det}x{args.det} uint16 ({gb:.1f} GB as read, {2 * gb:.1f} GB as "
          f"float32), bin {args.bin}, volume {args.size}^3; {machine_line(args.threads)}", flush=True)
    try:
        if not os.path.exists(os.path.join(folder, "COMPLETE")):
            shutil.rmtree(folder, ignore_errors=True)
            rc, _, _ = _run_child(common + ["--child", "make", "--folder", folder])
            if rc:
                return rc
        else:
            print(f"  reusing {folder}")
        rc, text, rss = _run_child(common + ["--child", "calibrate", "--folder", folder, "--out", tmp])
        if rc:
            return rc
        r = json.loads([ln for ln in text.splitlines() if ln.startswith(MARK)][-1][len(MARK):])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if not args.keep_data:
            shutil.rmtree(folder, ignore_errors=True)
    print(f"  {r['chunk_note']}")
    print(f"read + normalise + bin : {r['read_s']:8.1f} s ({gb * 1e3 / max(r['read_s'], 1e-9):.0f} MB/s of uint16) "
          f"-> binned {r['binned']}; peak RSS after it {r['rss_read_mib'] / 1024:.2f} GiB")
    split = ", ".join(f"{k} {v:.1f}" for k, v in r["timings"].items())
    print(f"calibration            : {r['cal_s']:8.1f} s ({split})")
    print(f"total                  : {r['total_s']:8.1f} s (target <= 900 s)  status {r['status']}")
    print(f"peak RSS (child)       : {rss / 1024:8.2f} GiB (target <= 8 GiB)")
    print(f"yardstick              : {r['ref_s']:8.3f} s; total / reference = {r['total_s'] / r['ref_s']:.0f}")
    print(f"full-resolution geometry vs injected motion: RMS reprojection error {r['err_px']:.3f} px "
          f"(nominal {r['nominal_px']:.3f} px), full-resolution pixels")
    return 0 if r["success"] else 3


if __name__ == "__main__":
    sys.exit(main())
