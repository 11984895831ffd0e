"""Benchmark of the CPU operators on the standard problem, with a yardstick (issues #2 §6, #13).

Standard problem (``--size 256``, the default): volume 256³ float32, voxel
1; cone beam SOD 1000, SDD 1500; detector 256 rows x 384 cols, pitch 1.5;
360 views over 360°; 2 threads.  ``--size N`` scales every axis of it by
N/256 (volume N³ of voxel 256/N, detector N x 1.5N of pitch 1.5·256/N, the
same field of view); ``--size 128`` is 8x cheaper and a good quick look.

Each operator runs in a fresh subprocess pinned to ``--threads`` CPUs.  In
it, after a warm-up (numba compile or cache load), pdvc's operator and the
fixed reference forward projector of ``benchmarks/_reference.py`` (and LEAP
where importable) are timed in alternation, ``--repeats`` times each, on
the same volume and geometry; the table gives the medians and the ratio
pdvc / reference.  The adjoint, Jacobian and FDK children also time pdvc's
forward projection in the same rotation: "/forward" is the operator's time
over it (issue #13's targets for the adjoint and the Jacobian pass).  An
absolute time on a shared machine says little; the ratio travels.  Peak
memory: the resident memory the operator's first run adds to the process
(inputs allocated before the baseline is read; LEAP and the forward beside
it not counted).

    python benchmarks/bench_operators.py                 # standard problem (about 15 min on 2 cores)
    python benchmarks/bench_operators.py --size 128      # the same problem at half resolution (~2 min)
    python benchmarks/bench_operators.py --views 36      # fewer views (times x10 printed too)

The reference runs on ``--ref-views`` views spread over the orbit (36 by
default; 0 for all) and its time is scaled to all views: its cost is
linear in the views, and on the full standard problem the plain kernel
takes minutes per run.

LEAP (optional)
---------------
If ``import leapctype`` works, LEAP's CPU forward projector is timed on its
circular cone path (``set_conebeam``) and on its per-view path
(``set_modularbeam``, from the same vectors as pdvc), its back-projection
and its FDK (``FBP``), in the same rotation. A CPU-only build from LEAP's
source tree, as done for the README's figures (github.com/LLNL/LEAP, v1.26,
commit 0c8846f; cmake >= 3.18, a C++17 compiler with OpenMP)::

    git clone https://github.com/LLNL/LEAP.git && cd LEAP
    cp src/cpu_CMakeLists.txt src/CMakeLists.txt    # no CUDA: -D__USE_CPU
    git apply /path/to/pdvc/benchmarks/leap_cpu_only.patch
    mkdir build && cd build && cmake .. -DCMAKE_BUILD_TYPE=Release && cmake --build . -j && cd ..
    SITE=$(/path/to/venv/bin/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
    cp build/lib/libleapct.so src/leapctype.py src/leap_filter_sequence.py \
       src/leap_preprocessing_algorithms.py "$SITE"/
    /path/to/venv/bin/pip install imageio                  # leapctype imports it
    /path/to/venv/bin/python -c "import leapctype; leapctype.tomographicModels().about()"

``leap_cpu_only.patch`` guards three GPU calls in
``filtered_backprojection.cpp`` that the CPU-only build of that commit does
not compile without (``zeroPadForOffsetScan_GPU`` twice, ``cudaFree``); it
changes no CPU code path. ``Release`` compiles with ``-O3``. LEAP's CPU
code runs ``omp_get_num_procs()`` threads; the children here are pinned to
``--threads`` CPUs, which that honours. LEAP's projectors (separable
footprint) are another discretisation and its axis conventions differ:
only times are compared, never values (on the 128³
problem LEAP's circular forward projection of the same volume sums to
pdvc's within 3·10⁻⁶, so both project the same object onto the same
detector).
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


def standard_problem(n: int, views: int):
    """Volume, its geometry, the scan geometry and the angles of the (scaled) standard problem."""
    import numpy as np

    import pdvc

    vg = pdvc.VolumeGeometry((n, n, n), voxel_size=256 / n)
    full = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    angles = np.linspace(0, 2 * np.pi, views, endpoint=False) if views >= 360 else full[:: max(1, 360 // views)][:views]
    det = (n, 3 * n // 2)
    geom = pdvc.circular_cone(angles, sod=1000.0, odd=500.0, det_shape=det, pixel=1.5 * 256 / n)
    rng = np.random.default_rng(0)
    # a textured object filling a cylinder, like a sample
    vol = rng.random(vg.shape, dtype=np.float32)
    zc, yc, xc = vg.coordinates()
    r = 0.45 * 256
    vol *= (xc[None, None, :] ** 2 + yc[None, :, None] ** 2 < r**2).astype(np.float32)
    return vol, vg, geom, angles


def _leap_runs(op, vol, vg, geom, angles, proj):
    """(name, callable) pairs timing LEAP for ``op``; empty when LEAP is not importable.

    Any failure to set LEAP up is reported and LEAP is skipped.
    """
    try:
        from leapctype import tomographicModels
    except Exception:  # noqa: BLE001 - optional dependency, any import failure means "absent"
        return [], "LEAP: not importable (optional; see the docstring to build it CPU-only)"
    import numpy as np

    try:
        n = vg.shape[0]
        nv = geom.n_views
        nr, nc = geom.det_shape
        vec = np.asarray(geom.vectors, np.float64)
        f = np.ascontiguousarray(vol, dtype=np.float32)  # LEAP's default volume order is z, y, x

        def model(kind):
            ct = tomographicModels()
            try:
                ct.set_gpu(-1)  # CPU
            except Exception:  # noqa: BLE001 - a CPU-only build may lack the GPU switch
                pass
            if kind == "circular":
                pix = float(np.linalg.norm(vec[0, 6:9]))
                ct.set_conebeam(nv, nr, nc, pix, pix, 0.5 * (nr - 1), 0.5 * (nc - 1),
                                np.rad2deg(angles).astype(np.float32), 1000.0, 1500.0)
            else:
                u, v = vec[:, 6:9], vec[:, 9:12]
                pw, ph = float(np.linalg.norm(u[0])), float(np.linalg.norm(v[0]))
                ct.set_modularbeam(nv, nr, nc, ph, pw,
                                   np.ascontiguousarray(vec[:, 0:3], np.float32),
                                   np.ascontiguousarray(vec[:, 3:6], np.float32),
                                   np.ascontiguousarray(v / ph, np.float32),
                                   np.ascontiguousarray(u / pw, np.float32))
            ct.set_volume(n, n, n, 256.0 / n, 256.0 / n)
            return ct

        runs = []
        if op == "forward":
            for kind in ("circular", "modular"):
                ct = model(kind)
                g = ct.allocate_projections()
                runs.append((f"LEAP forward ({kind})", lambda ct=ct, g=g: ct.project(g, f)))
        elif op == "adjoint":
            ct = model("circular")
            g = np.ascontiguousarray(proj, dtype=np.float32)
            out = ct.allocate_volume()
            runs.append(("LEAP backproject (circular)", lambda: ct.backproject(g, out)))
        elif op == "fdk":
            ct = model("circular")
            g = np.ascontiguousarray(proj, dtype=np.float32)
            out = ct.allocate_volume()
            runs.append(("LEAP FDK (circular)", lambda: ct.FBP(g, out)))
        return runs, "LEAP: importable, timed in the same rotation"
    except Exception as exc:  # noqa: BLE001
        return [], f"LEAP: importable but failed to set up ({type(exc).__name__}: {exc}); skipped"


def _child(op: str, n: int, views: int, repeats: int, ref_views: int, threads: int) -> dict:
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from _reference import Yardstick, alternate, pin_threads

    pin_threads(threads)
    import numpy as np

    from pdvc.projectors import backproject, forward, reduce_views

    vol, vg, geom, angles = standard_problem(n, views)
    rng = np.random.default_rng(1)
    k = max(1, geom.n_views // 6)
    small = geom[::k]  # a few views spanning the orbit (FDK needs the coverage)
    proj = None
    if op == "forward":
        forward(vol, vg, small)
        run = lambda: forward(vol, vg, geom)  # noqa: E731
    elif op == "adjoint":
        proj = rng.random((geom.n_views,) + geom.det_shape, dtype=np.float32)
        backproject(proj[::k], vg, small)
        run = lambda: backproject(proj, vg, geom)  # noqa: E731
    elif op == "reduced_jacobian":
        meas = forward(vol, vg, geom)
        reduce_views(vol, vg, small, meas[::k])
        run = lambda: reduce_views(vol, vg, geom, meas)  # noqa: E731
    elif op == "fdk":
        from pdvc.recon import fdk

        proj = forward(vol, vg, geom)
        fdk(proj[::k], vg, small)
        run = lambda: fdk(proj, vg, geom)  # noqa: E731
    else:
        raise SystemExit(f"unknown op {op!r}")
    yard = Yardstick(vol, vg, geom, ref_views)
    leap, leap_note = _leap_runs(op, vol, vg, geom, angles, proj)
    # the targets of the adjoint and the Jacobian pass are ratios to pdvc's forward: time it in the same rotation
    fwd = [("pdvc forward", lambda: forward(vol, vg, geom))] if op != "forward" else []
    base = _rss_mib()
    run()  # the operator's own peak, before LEAP or the forward run beside it
    extra_peak = _rss_mib() - base
    times = alternate(run, yard, repeats, others=leap + fwd)
    med = {name: float(np.median(t)) for name, t in times.items()}
    return {
        "op": op,
        "median_s": med["pdvc"],
        "reference_s": med["reference"],
        "forward_s": med.get("pdvc forward", med["pdvc"]),
        "times_s": times,
        "leap_s": {name: med[name] for name, _ in leap},
        "leap_note": leap_note,
        "reference_note": yard.describe(),
        "extra_peak_mib": extra_peak,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=360)
    ap.add_argument("--size", type=int, default=256, help="volume N^3 and detector N x 1.5N (standard: 256)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--ref-views", type=int, default=36, help="views the reference runs on (0: all)")
    ap.add_argument("--ops", default=",".join(OPS))
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(_child(args.child, args.size, args.views, args.repeats, args.ref_views, args.threads)))
        return
    env = dict(os.environ, NUMBA_NUM_THREADS=str(args.threads), OMP_NUM_THREADS="1")
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    os.environ["NUMBA_NUM_THREADS"] = str(args.threads)
    from _reference import machine_line, print_table

    n = args.size
    scale = 360 / args.views
    det = (n, 3 * n // 2)
    title = (f"problem: volume {n}^3, {args.views} views, detector {det[0]}x{det[1]}, {args.threads} threads"
             + ("  (the standard problem)" if n == 256 and args.views == 360 else ""))
    print(title)
    print(machine_line(args.threads))
    print(f"{'operator':18s} {'median s':>9s} {'x360/views':>10s} {'ref s':>8s} {'pdvc/ref':>8s} {'/forward':>8s} {'extra peak MiB':>15s}"
          f"   (volume {n**3 * 4 / 2**20:.0f} MiB, projections {args.views * det[0] * det[1] * 4 / 2**20:.0f} MiB)", flush=True)
    rows, leap_rows, notes = [], [], set()
    t_start = time.perf_counter()
    for op in args.ops.split(","):
        cmd = [sys.executable, os.path.abspath(__file__), "--child", op, "--views", str(args.views), "--size", str(n),
               "--repeats", str(args.repeats), "--ref-views", str(args.ref_views), "--threads", str(args.threads)]
        res = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if res.returncode != 0:
            print(f"{op:18s} failed: {res.stderr.strip().splitlines()[-1] if res.stderr.strip() else res.returncode}")
            continue
        r = json.loads(res.stdout.strip().splitlines()[-1])
        print(f"{op:18s} {r['median_s']:9.2f} {r['median_s'] * scale:10.1f} {r['reference_s']:8.2f} "
              f"{r['median_s'] / r['reference_s']:8.3f} {r['median_s'] / r['forward_s']:8.2f} {r['extra_peak_mib']:15.0f}",
              flush=True)
        rows.append((op, r["median_s"], r["reference_s"]))
        notes.add(r["reference_note"])
        notes.add(r["leap_note"])
        for name, t in r["leap_s"].items():
            leap_rows.append((name, op, t, r["median_s"], r["reference_s"]))
    print_table(
        f"{title}; medians of {args.repeats} alternating runs; bench_operators.py, {time.perf_counter() - t_start:.0f} s in all",
        rows,
        note="\n".join(sorted(notes)),
        threads=args.threads,
    )
    if leap_rows:
        print()
        print(f"{'LEAP operator':30s} {'LEAP s':>9s} {'pdvc s':>9s} {'pdvc/LEAP':>10s} {'LEAP/ref':>9s}")
        for name, _, t, tp, tr in leap_rows:
            print(f"{name:30s} {t:9.3f} {tp:9.3f} {tp / t:10.3f} {t / tr:9.3f}")


if __name__ == "__main__":
    main()
