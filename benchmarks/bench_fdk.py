"""Time FDK on the standard benchmark problem and print the figures.

Problem: volume 256^3, voxel 1; circular cone beam SOD 1000, SDD 1500
(ODD 500); detector 256 rows x 384 cols, pitch 1.5; 360 views over 360 deg.
Data: exact projections of a centred uniform ball (radius 100, density 1),
so the run also prints the reconstructed interior mean (should be ~1).

Usage::

    python benchmarks/bench_fdk.py [--threads 2] [--repeat 3] [--posed] [--views-per-block 16]

``--posed`` applies small per-view rigid poses to the geometry (a corrected
geometry: every view tilted, the general back-projection path).
Wall time: median of ``repeat`` runs after one warm-up (which includes the
numba compile or cache load). Peak memory: tracemalloc peak of one run
(NumPy allocations) and the process's peak RSS.
"""

from __future__ import annotations

import argparse
import resource
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
    args = ap.parse_args()
    numba.set_num_threads(args.threads)

    angles = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    geom = circular_cone(angles, sod=1000.0, odd=500.0, det_shape=(256, 384), pixel=1.5)
    vg = VolumeGeometry((256, 256, 256), 1.0)
    proj = ball_projections(geom, 100.0)
    if args.posed:
        rng = np.random.default_rng(0)
        geom = geom.apply_poses(rng.normal(0, 2e-3, (360, 3)), rng.normal(0, 0.3, (360, 3)))
    kw = dict(views_per_block=args.views_per_block)

    t0 = time.perf_counter()
    vol = fdk(proj, vg, geom, **kw)
    t_first = time.perf_counter() - t0
    times = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        fdk(proj, vg, geom, out=vol, **kw)
        times.append(time.perf_counter() - t0)
    tracemalloc.start()
    fdk(proj, vg, geom, **kw)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    c = vol[118:138, 118:138, 118:138]
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


if __name__ == "__main__":
    main()
