"""The Jacobian pass on a Dask cluster against threads: parallel efficiency and bytes moved (issue #12).

Problem: the standard one of ``bench_operators.py`` (volume 256³, 360 views,
detector 256 x 384, cone beam; ``--size N`` scales it by N/256).  A *round*
of the calibration is one new volume and ``--passes`` fused Jacobian passes
(``reduce_views``) at slightly different poses against the same
projections -- what the correlation engine does between two
reconstructions.  It is timed

* with the threads of this process (``--threads``, 2 by default),
* on a local Dask cluster of 1 worker process and of 2 worker processes,
  1 thread each (``scheduler = "local:1"`` / ``"local:2"``),

in alternation (threads, 1 worker, 2 workers, the yardstick; both clusters
stay up, idle when not timed), after a warm-up round each (numba cache
load in the workers, the projections sent once per scale).  Parallel efficiency = threaded time / cluster time
for the round (issue #12 target: 2 processes >= 0.8 on 2 cores).  Bytes
moved per round are what pdvc's session counted: the volume broadcast to
every worker, the 32 numbers per view coming back; the projections are sent
once per scale and printed apart.  The FDK of a round is measured too: by
slabs of z, each from the band of detector rows it projects onto, against
the bytes a split by views (summing whole volumes) would move.

The yardstick (``benchmarks/_reference.py``, with ``--threads`` threads) is
timed in the same run; ``pdvc/ref`` is the ratio as in the other benchmarks.

    python benchmarks/bench_dask.py --size 128          # a medium problem (about 2 min on 2 cores)
    python benchmarks/bench_dask.py                     # the standard problem (about 10 min on 2 cores)
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time


def _cpu_seconds() -> float:
    """CPU seconds (user + system) of this process so far, all its threads."""
    import psutil

    t = psutil.Process().cpu_times()
    return t.user + t.system


def _round(vol, vg, geom, meas, passes: int, session=None):
    """One round: a new volume object, ``passes`` Jacobian passes at different poses.

    Returns (wall seconds, CPU seconds of this process and of the workers):
    on a shared machine the wall time depends on the others' load, the CPU
    time says what the work and its overheads cost.
    """
    import numpy as np

    from pdvc.projectors import reduce_views

    v = vol.copy()  # a new reconstruction each round: sent again on a cluster
    workers = (lambda: sum(session.client.run(_cpu_seconds).values())) if session is not None else (lambda: 0.0)
    c0, w0 = _cpu_seconds(), workers()
    t0 = time.perf_counter()
    for k in range(passes):
        g = geom.apply_poses(np.zeros(3), [0.01 * k, 0.0, 0.0])
        reduce_views(v, vg, g, meas)
    wall = time.perf_counter() - t0
    return wall, (_cpu_seconds() - c0) + (workers() - w0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=256, help="volume N^3 and detector N x 1.5N (standard: 256)")
    ap.add_argument("--views", type=int, default=360)
    ap.add_argument("--threads", type=int, default=2, help="threads of the threaded run and of the yardstick")
    ap.add_argument("--passes", type=int, default=3, help="Jacobian passes per round")
    ap.add_argument("--repeats", type=int, default=2, help="timed rounds per configuration (median)")
    ap.add_argument("--ref-views", type=int, default=36, help="views the yardstick runs on (0: all)")
    args = ap.parse_args()

    os.environ["NUMBA_NUM_THREADS"] = str(args.threads)
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from _reference import Yardstick, machine_line, pin_threads

    pin_threads(args.threads)  # the worker processes inherit the CPUs
    import numpy as np

    from bench_operators import standard_problem
    from pdvc.compute import use_scheduler
    from pdvc.projectors import forward, reduce_views
    from pdvc.recon import fdk

    n = args.size
    vol, vg, geom, _ = standard_problem(n, args.views)
    meas = forward(vol, vg, geom) + np.random.default_rng(2).normal(0, 0.01, (geom.n_views,) + geom.det_shape).astype(np.float32)
    vbytes, pbytes = vol.nbytes, meas.nbytes
    print(f"problem: volume {n}^3 ({vbytes / 2**20:.0f} MiB), {geom.n_views} views, detector {geom.det_shape[0]}x"
          f"{geom.det_shape[1]} (projections {pbytes / 2**20:.0f} MiB), cone; a round = 1 new volume + {args.passes} "
          f"Jacobian passes" + ("  (the standard problem)" if n == 256 and args.views == 360 else ""))
    print(machine_line(args.threads))

    yard = Yardstick(vol, vg, geom, args.ref_views)
    k = max(1, geom.n_views // 6)
    reduce_views(vol, vg, geom[::k], meas[::k])  # compile / load the cache here
    names = [f"threads ({args.threads})", "local:1 (1 thread each)", "local:2 (1 thread each)"]
    times = {name: [] for name in names}
    cpu = {name: [] for name in names}
    stats, per_scale, t_ref = {}, {}, []
    fdk_stats = None
    with contextlib.ExitStack() as stack:
        sessions = [stack.enter_context(use_scheduler(s)) for s in ("local:1", "local:2")]
        where = dict(zip(names, ["threads"] + sessions))
        for name in names:  # warm-up: workers load the kernels, the projections are sent (once per scale)
            with use_scheduler(where[name]) as session:
                _round(vol, vg, geom, meas, 1)
                if session is not None:
                    per_scale[name] = dict(session.stats)
        for _ in range(args.repeats):  # in alternation: the noise of a shared machine is spread over all
            t_ref.append(yard())
            for name in names:
                with use_scheduler(where[name]) as session:
                    if session is not None:
                        session.reset_stats()
                    wall, cpu_s = _round(vol, vg, geom, meas, args.passes, session)
                    times[name].append(wall)
                    cpu[name].append(cpu_s)
                    if session is not None:
                        stats[name] = dict(session.stats)
        proj = np.ascontiguousarray(meas)
        with use_scheduler("threads"):  # the threaded FDK, for comparison
            fdk(proj, vg, geom)
            t0 = time.perf_counter()
            fdk(proj, vg, geom)
            t_fdk_threads = time.perf_counter() - t0
        with use_scheduler(sessions[1]) as session:
            session.reset_stats()
            t0 = time.perf_counter()
            fdk(proj, vg, geom)
            t_fdk_first = time.perf_counter() - t0
            first = dict(session.stats)
            session.reset_stats()
            t0 = time.perf_counter()
            fdk(proj, vg, geom)
            t_fdk = time.perf_counter() - t0
            fdk_stats = (t_fdk_first, first, t_fdk, dict(session.stats), session.n_workers)
    t_threads = float(np.median(times[names[0]]))
    rows = [(name, float(np.median(times[name])), stats.get(name), per_scale.get(name), w, float(np.median(cpu[name])))
            for name, w in zip(names, (0, 1, 2))]
    cpu_threads = rows[0][5]

    ref = float(np.median(t_ref))
    print()
    print(f"{'scheduler':26s} {'round s':>8s} {'per pass s':>10s} {'efficiency':>10s} {'pdvc/ref':>8s} {'CPU s/pass':>10s} "
          f"{'CPU eff.':>8s} {'sent MiB/round':>14s} {'back MiB/round':>14s} {'projections MiB/scale':>21s}")
    for name, t, st, per_scale, workers, cpu_s in rows:
        eff = t_threads / t
        per_pass = t / args.passes
        sent = "" if st is None else f"{st['sent_bytes'] / 2**20:14.1f}"
        back = "" if st is None else f"{st['received_bytes'] / 2**20:14.3f}"
        # the warm-up round sent the projections (once per scale) and its volume to every worker
        proj = "" if per_scale is None else f"{(per_scale['sent_bytes'] - per_scale['volume_sends'] * vbytes * workers) / 2**20:21.1f}"
        print(f"{name:26s} {t:8.2f} {per_pass:10.2f} {eff:10.2f} {per_pass / ref:8.3f} {cpu_s / args.passes:10.2f} "
              f"{cpu_threads / cpu_s:8.2f} {sent:>14s} {back:>14s} {proj:>21s}")
    print(f"yardstick: {yard.describe()}; median {ref:.2f} s with {args.threads} threads")
    print("efficiency: threaded round time / this round time (1.00 = as fast as the threads of one process);")
    print("CPU s/pass: CPU seconds of this process and the workers per pass; CPU eff.: threaded CPU / this CPU")
    print("(the work and its overheads, whatever else the machine runs)")
    print("pdvc/ref: time of one Jacobian pass over the yardstick's forward projection, as in bench_operators.py")
    if fdk_stats is not None:
        t1, s1, t2, s2, w = fdk_stats
        by_views = pbytes + w * vbytes
        print()
        print(f"FDK with threads ({args.threads}): {t_fdk_threads:.2f} s")
        print(f"FDK on local:2 by slabs of z: {t1:.2f} s the first time (row bands sent {s1['sent_bytes'] / 2**20:.1f} MiB, "
              f"slabs back {s1['received_bytes'] / 2**20:.1f} MiB), {t2:.2f} s with the bands already there "
              f"(sent {s2['sent_bytes'] / 2**20:.1f} MiB, back {s2['received_bytes'] / 2**20:.1f} MiB)")
        print(f"  a split by views with a sum would move {by_views / 2**20:.1f} MiB (projections once + {w} whole volumes back); "
              f"by slabs: {(s1['sent_bytes'] + s1['received_bytes']) / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
