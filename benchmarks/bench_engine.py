"""Benchmark of the P-DVC engine on the standard problem (issue #2 §6).

Volume 256³ float32, voxel 1; cone beam SOD 1000, SDD 1500; detector 256
rows x 384 cols, pitch 1.5; 180 views (every other view of the 360-view
orbit; ``--views 360`` for all), 2 threads. The data are the projections of
a textured cylinder after a small known motion (0.2° tilted axis, 0.5 voxel
offset) plus 1 % Gaussian noise; the engine starts from the nominal geometry.

Printed figures (one run each after a small warm-up that compiles the kernels):

* ``reduce pass``: one fused Jacobian pass (``reduce_views``: M_k, b_k, χ² of
  every view): the cost unit of the engine;
* ``solve``: the dense solves of one Gauss–Newton iteration (full
  identification with the ``fourier:1`` basis, and the per-view 6x6 solves of
  the free basis), from M_k, b_k;
* ``GN iteration``: ``correlate(max_iter=2)`` minus ``correlate(max_iter=1)``,
  i.e. one solve plus the pass at the new poses that checks χ and gives the
  next M_k, b_k (``correlate`` also makes one pass at the start);
* ``PGD, 3 modes``: ``correlate(method="pgd", max_modes=3)`` (fourier:1), with
  its number of passes;
* memory: the peak of numpy/Python allocations (``tracemalloc``) during each
  step, and the process's peak resident size.

Yardstick (issue #13): the fixed reference forward projector of
``benchmarks/_reference.py`` is timed on the same volume and geometry, in
alternation with ``--repeats`` extra reduce passes (on ``--ref-views`` views
spread over the orbit, 0 for all, its time scaled to all views); the final
table gives every step's time over the reference's.  ``--size N`` scales
every axis of the problem by N/256 (volume N^3, detector N x 1.5N).

    python benchmarks/bench_engine.py              # 180 views (a few minutes on 2 cores)
    python benchmarks/bench_engine.py --views 36   # quick look
    python benchmarks/bench_engine.py --size 128   # half resolution in every axis
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
import tracemalloc


def _rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _timed(label, fn, results):
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    t0 = time.perf_counter()
    out = fn()
    dt = time.perf_counter() - t0
    peak = (tracemalloc.get_traced_memory()[1] - base) / 2**20
    results.append((label, dt, peak))
    print(f"{label:34s} {dt:9.3f} s   peak alloc {peak:8.0f} MiB   (process peak RSS {_rss_mib():.0f} MiB)", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=180)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--modes", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=3, help="reduce passes timed in alternation with the reference")
    ap.add_argument("--ref-views", type=int, default=36, help="views the reference runs on (0: all)")
    args = ap.parse_args()
    os.environ.setdefault("NUMBA_NUM_THREADS", str(args.threads))
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from _reference import Yardstick, alternate, pin_threads, print_table

    pin_threads(args.threads)

    import numpy as np

    import pdvc
    from pdvc.correlation import correlate, estimate_noise_variance, make_basis
    from pdvc.correlation._engine import _assemble, _eig_solve
    from pdvc.projectors import forward, reduce_views
    from pdvc.simulate import tilted_axis_poses

    n = args.size
    vg = pdvc.VolumeGeometry((n, n, n), voxel_size=256 / n)
    full = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    angles = full if args.views >= 360 else full[:: max(1, 360 // args.views)][: args.views]
    det = (n, 3 * n // 2)
    geom = pdvc.circular_cone(angles, sod=1000.0, odd=500.0, det_shape=det, pixel=1.5 * 256 / n)
    nv = geom.n_views
    title = f"problem: volume {n}^3, {nv} views, detector {det[0]}x{det[1]}, {os.environ['NUMBA_NUM_THREADS']} threads"
    print(title)
    print(f"  volume {vg.n_voxels * 4 / 2**20:.0f} MiB, projections {nv * det[0] * det[1] * 4 / 2**20:.0f} MiB")

    rng = np.random.default_rng(0)
    vol = rng.random(vg.shape, dtype=np.float32)
    zc, yc, xc = vg.coordinates()
    vol *= (xc[None, None, :] ** 2 + yc[None, :, None] ** 2 < (0.45 * n * vg.voxel_size[2]) ** 2).astype(np.float32)
    rv, t = tilted_axis_poses(angles, tilt=np.deg2rad(0.2), tilt_azimuth=0.3, offset=(0.5, 0.0, 0.0))
    data = forward(vol, vg, geom.apply_poses(rv, t))
    data += rng.normal(0, 0.01 * float(data.std()), data.shape).astype(np.float32)

    # warm-up: compile the kernels on a few views
    small = slice(0, nv, max(1, nv // 6))
    reduce_views(vol, vg, geom[small], data[small])
    correlate(vol, vg, data[small], geom[small], basis="constant", max_iter=1)
    yard = Yardstick(vol, vg, geom, args.ref_views)

    tracemalloc.start()
    base_rss = _rss_mib()
    results: list = []
    red = _timed("reduce pass (M_k, b_k, all views)", lambda: reduce_views(vol, vg, geom, data), results)
    basis = make_basis("fourier:1", angles=angles)

    def solve_full():
        H, h = _assemble(basis.matrix, red.M, red.b)
        return _eig_solve(H, h, 1e-6, 0.0)

    _timed("solve, full identification (f:1)", solve_full, results)
    _timed("solve, free basis (6x6 per view)", lambda: _eig_solve(red.M, red.b, 1e-6, 0.0), results)
    gamma2 = estimate_noise_variance(data)
    kw = dict(basis="fourier:1", noise_variance=gamma2)
    res1 = _timed("correlate(max_iter=1)", lambda: correlate(vol, vg, data, geom, max_iter=1, **kw), results)
    res2 = _timed("correlate(max_iter=2)", lambda: correlate(vol, vg, data, geom, max_iter=2, **kw), results)
    gn = results[-1][1] - results[-2][1]
    print(
        f"{'=> one Gauss-Newton iteration':34s} {gn:9.2f} s   (passes: {res1.n_iter} and {res2.n_iter}; "
        f"chi {res2.chi_history[0]:.3g} -> {res2.chi:.3g})"
    )
    pgd = _timed(
        f"PGD, {args.modes} modes (fourier:1)",
        lambda: correlate(vol, vg, data, geom, method="pgd", max_modes=args.modes, noise_floor=0.0, min_gain=0.0, **kw),
        results,
    )
    print(
        f"  PGD: {len(pgd.modes)} modes, {pgd.n_iter} passes ({results[-1][1] / max(pgd.n_iter, 1):.2f} s/pass), "
        f"SNR per mode {[round(float(s), 2) for _, _, s in pgd.mode_table]} dB, {pgd.message}"
    )
    print(f"process peak RSS {_rss_mib():.0f} MiB (before the timed steps {base_rss:.0f} MiB)")
    tracemalloc.stop()
    # the yardstick, in alternation with more reduce passes (after all the timed steps,
    # so that their memory figures are unchanged)
    timed = alternate(lambda: reduce_views(vol, vg, geom, data), yard, args.repeats, warmup=False)
    ref = float(np.median(timed["reference"]))
    red_med = float(np.median(timed["pdvc"] + [results[0][1]]))
    rows = [(f"reduce pass (median of {args.repeats + 1})", red_med, ref)]
    rows += [(label, dt, ref) for label, dt, _ in results[1:]]
    rows.insert(5, ("one Gauss-Newton iteration", gn, ref))
    print_table(
        f"{title}; bench_engine.py; reference: median of {args.repeats} runs alternating with reduce passes",
        rows,
        note=yard.describe(),
    )
    if nv != 360:
        f = 360 / nv
        print(
            f"x{f:.1f} for 360 views (scaling with views): reduce pass ~{results[0][1] * f:.1f} s, "
            f"GN iteration ~{gn * f:.1f} s, PGD ~{results[-1][1] * f:.0f} s"
        )


if __name__ == "__main__":
    sys.exit(main())
