"""A fixed, deliberately plain yardstick for the benchmarks (issue #13).

An absolute time on a shared 2-core machine says little; the time of pdvc
divided by the time of a fixed simple kernel measured in the same run, on the
same problem and the same threads, travels between machines much better.

The yardstick is a textbook cone-beam forward projector over per-view
vectors: one ray per detector pixel, marched from where it enters the
zero-padded grid box to where it leaves it, in steps of one voxel (index
units), sampled by trilinear interpolation of the zero-padded volume (each
of the 8 neighbours bounds-checked), the sum times the world length of a
step.  ``prange`` over views, nothing else: no interior fast path, no
incremental indices, no fast-math.

DO NOT OPTIMISE THIS FILE.  Its whole value is that it stays the same, so
that ratios measured in different runs, on different machines and at
different dates stay comparable.  If it ever has to change, say so in the
README next to every ratio measured against the old one.

It is a different discretisation of the same line integrals than
``pdvc.forward`` (trilinear ray-marching against Joseph's plane sampling);
``tests/projectors/test_reference_kernel.py`` checks they agree to a few
per cent on a smooth object.
"""

from __future__ import annotations

import math
import time

import numpy as np
from numba import njit, prange

__all__ = ["reference_table", "reference_forward", "Yardstick", "alternate", "pin_threads", "machine_line", "print_table"]


def reference_table(vol_geom, geom) -> np.ndarray:
    """Per-view (source, pixel (0, 0), column step, row step) in index units, xyz.

    Voxel centres sit at integer index coordinates; index (0, 0, 0) is the
    centre of the first voxel.  Cone beam only.
    """
    if geom.kind != "cone":
        raise ValueError("the reference projector is cone-beam only")
    sp = np.asarray(vol_geom.spacing_xyz, np.float64)
    nx, ny, nz = vol_geom.shape[::-1]
    centre = np.asarray(vol_geom.offset, np.float64)
    origin = centre - (np.array([nx, ny, nz]) - 1) / 2 * sp  # world position of voxel (0, 0, 0)
    nr, nc = geom.det_shape
    vec = np.asarray(geom.vectors, np.float64)
    src, d, u, v = vec[:, 0:3], vec[:, 3:6], vec[:, 6:9], vec[:, 9:12]
    p00 = d - (nc - 1) / 2 * u - (nr - 1) / 2 * v
    return np.hstack([(src - origin) / sp, (p00 - origin) / sp, u / sp, v / sp])


@njit(inline="always")
def _voxel(vol, x, y, z, nx, ny, nz):
    if x < 0 or y < 0 or z < 0 or x >= nx or y >= ny or z >= nz:
        return 0.0
    return vol[z, y, x]


@njit(parallel=True)  # not cached: the file is loaded under several module names
def _reference_kernel(vol, spacing_xyz, table, out):
    nz, ny, nx = vol.shape
    n_views, n_rows, n_cols = out.shape
    for k in prange(n_views):
        sx, sy, sz = table[k, 0], table[k, 1], table[k, 2]
        for r in range(n_rows):
            for c in range(n_cols):
                # ray from the source through the pixel centre, index units
                dx = table[k, 3] + c * table[k, 6] + r * table[k, 9] - sx
                dy = table[k, 4] + c * table[k, 7] + r * table[k, 10] - sy
                dz = table[k, 5] + c * table[k, 8] + r * table[k, 11] - sz
                norm = math.sqrt(dx * dx + dy * dy + dz * dz)
                dx /= norm
                dy /= norm
                dz /= norm
                # world length of one index-unit step along the ray
                step_len = math.sqrt((dx * spacing_xyz[0]) ** 2 + (dy * spacing_xyz[1]) ** 2 + (dz * spacing_xyz[2]) ** 2)
                # entry and exit of the support of the interpolant, the box [-1, n]^3
                t0 = 0.0
                t1 = 1e30
                for s, d, n in ((sx, dx, nx), (sy, dy, ny), (sz, dz, nz)):
                    if d != 0.0:
                        ta = (-1.0 - s) / d
                        tb = (n - s) / d
                        if ta > tb:
                            ta, tb = tb, ta
                        t0 = max(t0, ta)
                        t1 = min(t1, tb)
                    elif s <= -1.0 or s >= n:
                        t1 = -1.0
                acc = 0.0
                if t1 > t0:
                    n_steps = int(math.ceil(t1 - t0))
                    for i in range(n_steps):
                        t = t0 + (i + 0.5) * ((t1 - t0) / n_steps)
                        x = sx + t * dx
                        y = sy + t * dy
                        z = sz + t * dz
                        x0 = int(math.floor(x))
                        y0 = int(math.floor(y))
                        z0 = int(math.floor(z))
                        fx = x - x0
                        fy = y - y0
                        fz = z - z0
                        acc += (
                            (1 - fz) * ((1 - fy) * ((1 - fx) * _voxel(vol, x0, y0, z0, nx, ny, nz) + fx * _voxel(vol, x0 + 1, y0, z0, nx, ny, nz))
                                        + fy * ((1 - fx) * _voxel(vol, x0, y0 + 1, z0, nx, ny, nz) + fx * _voxel(vol, x0 + 1, y0 + 1, z0, nx, ny, nz)))
                            + fz * ((1 - fy) * ((1 - fx) * _voxel(vol, x0, y0, z0 + 1, nx, ny, nz) + fx * _voxel(vol, x0 + 1, y0, z0 + 1, nx, ny, nz))
                                    + fy * ((1 - fx) * _voxel(vol, x0, y0 + 1, z0 + 1, nx, ny, nz) + fx * _voxel(vol, x0 + 1, y0 + 1, z0 + 1, nx, ny, nz)))
                        )
                    acc *= (t1 - t0) / n_steps * step_len
                out[k, r, c] = acc


def reference_forward(volume, vol_geom, geom, out=None) -> np.ndarray:
    """Line integrals of ``volume`` (nz, ny, nx) for the cone-beam ``geom``; float32."""
    vol = np.ascontiguousarray(volume, dtype=np.float32)
    table = reference_table(vol_geom, geom)
    shape = (geom.n_views,) + tuple(geom.det_shape)
    if out is None:
        out = np.empty(shape, np.float32)
    _reference_kernel(vol, np.asarray(vol_geom.spacing_xyz, np.float64), table, out)
    return out


class Yardstick:
    """The reference forward projection of one benchmark problem, ready to time.

    ``ref_views``: the reference runs on every k-th view of ``geom`` (about
    ``ref_views`` views spread over the whole orbit) and its time is scaled by
    ``n_views / n_ref_views``: its cost is linear in the views, and a plain
    kernel on the full standard problem would take minutes per run.  Pass
    ``ref_views=0`` for all views.
    """

    def __init__(self, volume, vol_geom, geom, ref_views: int = 36):
        self.volume = np.ascontiguousarray(volume, dtype=np.float32)
        self.vol_geom = vol_geom
        step = 1 if ref_views <= 0 else max(1, geom.n_views // ref_views)
        self.geom = geom[::step]
        self.scale = geom.n_views / self.geom.n_views
        self.out = np.empty((self.geom.n_views,) + tuple(self.geom.det_shape), np.float32)
        reference_forward(self.volume, vol_geom, self.geom[:1])  # compile (not cached)

    def describe(self) -> str:
        return (
            f"reference: plain trilinear ray-marching cone forward projector (benchmarks/_reference.py) on "
            f"{self.geom.n_views} views spread over the orbit, time scaled x{self.scale:.2f} to all views"
        )

    def __call__(self) -> float:
        """Seconds of one reference run, scaled to all views of the problem."""
        t0 = time.perf_counter()
        reference_forward(self.volume, self.vol_geom, self.geom, self.out)
        return (time.perf_counter() - t0) * self.scale


def alternate(run_pdvc, yardstick, repeats: int, others=(), warmup: bool = True):
    """Time ``run_pdvc`` and the yardstick in alternation, after one warm-up each.

    ``others``: extra (name, callable) timed in the same rotation (LEAP).
    Returns a dict name -> list of seconds, with keys "pdvc", "reference"
    and the names of ``others``.  Report the ratio of the medians:
    alternating spreads the noise of a shared machine over all of them.
    """
    if warmup:
        yardstick()
        run_pdvc()
        for _, fn in others:
            fn()
    times = {"pdvc": [], "reference": []}
    times.update({name: [] for name, _ in others})
    for _ in range(repeats):
        times["reference"].append(yardstick())
        t0 = time.perf_counter()
        run_pdvc()
        times["pdvc"].append(time.perf_counter() - t0)
        for name, fn in others:
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    return times


def pin_threads(threads: int) -> None:
    """Restrict this process to ``threads`` CPUs when the machine has more.

    numba uses NUMBA_NUM_THREADS anyway; LEAP's OpenMP code asks for
    omp_get_num_procs() threads, which honours the affinity mask.
    """
    import os

    try:
        cpus = sorted(os.sched_getaffinity(0))
        if 0 < threads < len(cpus):
            os.sched_setaffinity(0, cpus[:threads])
    except (AttributeError, OSError):
        pass


def machine_line(threads=None) -> str:
    """CPU model, cores, numba version and threads, date: the header of every result table."""
    import datetime
    import os
    import platform

    import numba

    model = platform.processor() or "unknown CPU"
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        layer = numba.threading_layer()  # known once a parallel kernel has run in this process
    except ValueError:
        layer = numba.config.THREADING_LAYER
    return (
        f"machine: {model}, {os.cpu_count()} logical CPUs; numba {numba.__version__} "
        f"(threads {threads or numba.get_num_threads()}, threading layer {layer}); numpy {np.__version__}; "
        f"date {datetime.date.today().isoformat()}"
    )


def print_table(title: str, rows, note: str = "", threads=None) -> None:
    """rows: (operator, pdvc s, reference s).  Prints the ratio too, and the machine."""
    print()
    print(title)
    print(machine_line(threads))
    if note:
        print(note)
    print(f"{'operator':34s} {'pdvc s':>9s} {'reference s':>12s} {'pdvc/ref':>9s}")
    for name, tp, tr in rows:
        ratio = tp / tr if tr > 0 else float("nan")
        print(f"{name:34s} {tp:9.3f} {tr:12.3f} {ratio:9.3f}")
    print("pdvc/ref: pdvc's time over the time of the fixed reference forward projector on the same volume")
    print("and geometry, both measured in this run (medians; alternating where there are repeats).")
