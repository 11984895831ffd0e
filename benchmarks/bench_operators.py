"""Benchmark of the CPU operators on the standard problem (issue #2 §6).

Volume 256³ float32, voxel 1; cone beam SOD 1000, SDD 1500; detector 256
rows x 384 cols, pitch 1.5; 360 views over 360°; 2 threads.  For each
operator: median wall time of 3 runs after a warm-up run, and the peak
resident memory it adds to the process (each operator runs in a fresh
subprocess; inputs are allocated before the baseline is read).

    python benchmarks/bench_operators.py            # full problem
    python benchmarks/bench_operators.py --views 36 # quick look (times x10 printed too)

Reference anchors (LEAP, CPU OpenMP C++ build, 2 threads, same machine size):
forward 15.7 s (circular-cone path) / 54.4 s (modular vector path),
back-projection 93 s, FDK 108 s.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

OPS = ("forward", "adjoint", "reduced_jacobian", "fdk")


def _rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _child(op: str, n: int, views: int, repeats: int) -> dict:
    import numpy as np

    import pdvc
    from pdvc.projectors import backproject, forward, reduce_views

    vg = pdvc.VolumeGeometry((n, n, n), voxel_size=256 / n)
    angles = np.linspace(0, 2 * np.pi, views, endpoint=False) if views >= 360 else np.linspace(0, 2 * np.pi, 360, endpoint=False)[:: max(1, 360 // views)][:views]
    geom = pdvc.circular_cone(angles, sod=1000.0, odd=500.0, det_shape=(256, 384), pixel=1.5)
    rng = np.random.default_rng(0)
    # a textured object filling a cylinder, like a sample
    vol = rng.random(vg.shape, dtype=np.float32)
    zc, yc, xc = vg.coordinates()
    vol *= (xc[None, None, :] ** 2 + yc[None, :, None] ** 2 < (0.45 * n) ** 2).astype(np.float32)
    small = geom[:: max(1, geom.n_views // 6)]  # a few views spanning the orbit (FDK needs the coverage)
    if op == "forward":
        forward(vol, vg, small)
        run = lambda: forward(vol, vg, geom)  # noqa: E731
    elif op == "adjoint":
        proj = rng.random((geom.n_views, 256, 384), dtype=np.float32)
        backproject(proj[:: max(1, geom.n_views // 6)], vg, small)
        run = lambda: backproject(proj, vg, geom)  # noqa: E731
    elif op == "reduced_jacobian":
        meas = forward(vol, vg, geom)
        reduce_views(vol, vg, small, meas[:: max(1, geom.n_views // 6)])
        run = lambda: reduce_views(vol, vg, geom, meas)  # noqa: E731
    elif op == "fdk":
        from pdvc.recon import fdk

        proj = forward(vol, vg, geom)
        fdk(proj[:: max(1, geom.n_views // 6)], vg, small)
        run = lambda: fdk(proj, vg, geom)  # noqa: E731
    else:
        raise SystemExit(f"unknown op {op!r}")
    base = _rss_mib()
    times = []
    run()  # warm-up at full size
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    return {
        "op": op,
        "median_s": float(np.median(times)),
        "times_s": times,
        "extra_peak_mib": _rss_mib() - base,
        "volume_mib": vol.nbytes / 2**20,
        "projections_mib": geom.n_views * 256 * 384 * 4 / 2**20,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=360)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--ops", default=",".join(OPS))
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(_child(args.child, args.size, args.views, args.repeats)))
        return
    env = dict(os.environ, NUMBA_NUM_THREADS=str(args.threads), OMP_NUM_THREADS="1")
    scale = 360 / args.views
    print(f"standard problem: volume {args.size}^3, {args.views} views, detector 256x384, {args.threads} threads")
    print(f"{'operator':18s} {'median s':>9s} {'x360/views':>10s} {'extra peak MiB':>15s}   (volume {args.size**3 * 4 / 2**20:.0f} MiB, projections {args.views * 256 * 384 * 4 / 2**20:.0f} MiB)")
    for op in args.ops.split(","):
        cmd = [sys.executable, __file__, "--child", op, "--views", str(args.views), "--size", str(args.size), "--repeats", str(args.repeats)]
        res = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if res.returncode != 0:
            print(f"{op:18s} failed: {res.stderr.strip().splitlines()[-1] if res.stderr.strip() else res.returncode}")
            continue
        r = json.loads(res.stdout.strip().splitlines()[-1])
        print(f"{op:18s} {r['median_s']:9.2f} {r['median_s'] * scale:10.1f} {r['extra_peak_mib']:15.0f}")


if __name__ == "__main__":
    main()
