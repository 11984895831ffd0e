"""Time FDK on the standard benchmark problem and print the figures.

Problem: volume 256^3, voxel 1; circular cone beam SOD 1000, SDD 1500
(ODD 500); detector 256 rows x 384 cols, pitch 1.5; 360 views over 360 deg.
Data: exact projections of a centred uniform ball (radius 100, density 1),
so the run also prints the reconstructed interior mean (should be ~1).
``--size N`` scales every axis by N/256 (volume N^3 of voxel 256/N,
detector N x 1.5N of pitch 1.5*256/N; the same ball and field of view).

Usage::

    python benchmarks/bench_fdk.py [--threads 2] [--repeat 3] [--posed] [--views-per-block 16] [--size 128]

Yardstick (issue #13): the fixed reference forward projector of
``benchmarks/_reference.py`` is timed in alternation with FDK, on the same
geometry and on the ball volume, and the final table gives FDK's time over
the reference's.  The reference runs on ``--ref-views`` views spread over
the orbit (0: all) and its time is scaled to all views.

``--posed`` applies small per-view rigid poses to the geometry (a corrected
geometry: every view tilted, the general back-projection path).
Wall time: median of ``repeat`` runs after one warm-up (which includes the
numba compile or cache load). Peak memory: tracemalloc peak of one run
(NumPy allocations) and the process's peak RSS.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
import tracemalloc

import numba
import numpy as np

from pdvc.geometry import VolumeGeometry, circular_cone
from pdvc.recon import fdk


def ball_projections(geom, radius: float) -> np.ndarray:
    nr, nc = geom.det_shape
    out = np.empty((geom.n_views, nr, nc), np.float32)
    for k in range(geom.n_views):
        pix = geom.pixel_centers(k)
        d = pix - geom.src[k]
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        s = -geom.src[k]
        t = d @ s
        dist2 = s @ s - t * t
        out[k] = 2 * np.sqrt(np.maximum(radius**2 - dist2, 0.0))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--views-per-block", type=int, default=16)
    ap.add_argument("--posed", action="store_true")
    ap.add_argument("--size", type=int, default=256, help="volume N^3 and detector N x 1.5N (standard: 256)")
    ap.add_argument("--ref-views", type=int, default=36, help="views the reference runs on (0: all)")
    args = ap.parse_args()
    numba.set_num_threads(args.threads)
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from _reference import Yardstick, alternate, pin_threads, print_table

    pin_threads(args.threads)
    n = args.size
    angles = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    geom = circular_cone(angles, sod=1000.0, odd=500.0, det_shape=(n, 3 * n // 2), pixel=1.5 * 256 / n)
    vg = VolumeGeometry((n, n, n), 256 / n)
    proj = ball_projections(geom, 100.0)
    if args.posed:
        rng = np.random.default_rng(0)
        geom = geom.apply_poses(rng.normal(0, 2e-3, (360, 3)), rng.normal(0, 0.3, (360, 3)))
    kw = dict(views_per_block=args.views_per_block)

    t0 = time.perf_counter()
    vol = fdk(proj, vg, geom, **kw)
    t_first = time.perf_counter() - t0
    zc, yc, xc = vg.coordinates()
    ball = ((xc[None, None, :] ** 2 + yc[None, :, None] ** 2 + zc[:, None, None] ** 2) <= 100.0**2).astype(np.float32)
    yard = Yardstick(ball, vg, geom, args.ref_views)
    timed = alternate(lambda: fdk(proj, vg, geom, out=vol, **kw), yard, args.repeat, warmup=False)
    times, ref_times = timed["pdvc"], timed["reference"]
    tracemalloc.start()
    fdk(proj, vg, geom, **kw)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    m, h = n // 2, max(2, 10 * n // 256)
    c = vol[m - h : m + h, m - h : m + h, m - h : m + h]
    print(f"geometry: {'posed (general path)' if args.posed else 'nominal circular'}; "
          f"threads {numba.get_num_threads()}; views_per_block {args.views_per_block}")
    print(f"first call (compile or cache load + run): {t_first:.2f} s")
    print(f"fdk wall time, median of {args.repeat}: {np.median(times):.2f} s  (runs: "
          + ", ".join(f"{t:.2f}" for t in times) + ")")
    print(f"voxel-view updates per second: {vg.n_voxels * geom.n_views / np.median(times) / 1e9:.2f} G/s")
    print(f"peak traced memory of one fdk call (tracemalloc): {peak / 2**20:.0f} MiB "
          f"(volume {vol.nbytes / 2**20:.0f} MiB, projections {proj.nbytes / 2**20:.0f} MiB held by caller)")
    print(f"process peak RSS: {rss:.0f} MiB")
    print(f"ball interior mean (expect ~1): {float(c.mean()):.4f}")
    print(f"reference forward, median of {args.repeat}: {np.median(ref_times):.2f} s  (runs: "
          + ", ".join(f"{t:.2f}" for t in ref_times) + ")")
    print_table(
        f"volume {n}^3, 360 views, detector {n}x{3 * n // 2}, {args.threads} threads"
        + (", posed geometry" if args.posed else "") + f"; medians of {args.repeat} alternating runs; bench_fdk.py",
        [("fdk" + (" (posed)" if args.posed else ""), float(np.median(times)), float(np.median(ref_times)))],
        note=yard.describe(),
        threads=args.threads,
    )


if __name__ == "__main__":
    main()
