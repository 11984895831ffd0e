"""End-to-end benchmark of ``pdvc.calibrate`` on simulated scans (issue #11, item 1).

Sizes (voxel 1; cone beam of magnification 1.5 and detector pitch 1.5
unless said otherwise; default recipe; ``--sizes`` picks among them):

* ``small``: the demo's scan size, volume 64³, 150 views, detector 76x89
  (SOD 8n, ODD 4n as in ``pdvc demo``); target <= 60 s;
* ``medium``: volume 128³, 180 views, detector 128x160 (SOD 500, ODD 250);
  target <= 60 s;
* ``standard``: volume 256³, 360 views, detector 256x384 (SOD 1000, ODD 500:
  the standard problem of ``bench_operators.py``); target <= 5 min.  It
  only runs with ``--standard`` (about 5 minutes on 2 cores).  Its default
  schedule is (4, 2), the medium's (2, 1) (``pdvc.calibration.auto_scales``
  caps the finest correlation grid at 256³), so the medium time does not
  project to it;
* ``parallel``: a stand-in for the real synchrotron scan of issue #10/#11
  (not available to the project): parallel beam, 91 views over 180°,
  detector 134x160 of pitch 1, volume 134x160x160; target <= 30 s. The
  motion below puts the axis 6.4 px off centre, as on that scan.

The data are made by the analytic ellipsoid projector (no inverse crime):
``cast_iron_phantom`` (radius 0.36n, height 0.8n, 3n nodules), Poisson noise
i0 = 2e4, motion = ``tilted_axis_poses`` (0.5°, offset 0.04n) followed by
``drift_poses`` (velocity (0.02n, 0, 0.015n) over the scan), as in
``pdvc demo`` without its precession; ``--precession DEG`` adds a
once-per-turn precession of that amplitude (``precession_poses``), which the
default recipe's model choice may answer with the precession model
(``docs/method.md`` §5.12).  The calibration starts from the nominal
geometry with default options.

Each size runs in two fresh subprocesses pinned to ``--threads`` CPUs: one
simulates the scan and saves it (``--keep-data DIR`` keeps it for the next
run), the other loads it, warms up (numba cache load / compile, on a tiny
scan), then times ``pdvc.calibrate``.  Printed per size:

* total seconds (wall clock around ``calibrate``) and the steps pdvc records:
  ``res.timings`` (``init``, each stage, ``final``, ``assess``), the time not
  in them (nominal reconstruction, noise estimate, truncation check, motion
  summary), and, per stage, its rounds, Jacobian passes (``n_iter`` summed
  over ``res.history``) and the time of rounds a guard discarded (stage time
  minus its recorded rounds);
* a finer split measured by wrapping pdvc's functions in the child process
  (no file is changed): reconstructions of the correlation volume,
  Jacobian passes (``reduce_views``), dense solves (``_eig_solve`` and
  ``_assemble``), and coarse-graining, attributed to the step they ran in;
* each round (stage, scale, seconds, passes, χ before -> after, increment,
  and the gauge-free error against the truth of the poses it kept, read
  from ``calibrate(checkpoint=)``; "-" for rounds of a run whose
  checkpoints are not handed out, e.g. a second run's);
* peak memory: the process's peak resident set size (``getrusage``
  ``ru_maxrss``) of the calibrating process, and its value before
  ``calibrate`` (imports, warm-up, projections loaded);
* the final reprojection error against the truth, gauge-free as in
  ``tests/slow/test_accuracy.py`` (125 sample points, RMS detector px, true
  poses in pdvc's gauge, best rigid motion removed), also for the nominal
  geometry;
* status, and the yardstick of ``benchmarks/_reference.py`` (its plain
  forward projector on a fixed problem, 64³ x 36 views, detector 76x89),
  timed 3x before and 3x after ``calibrate``; total / reference is the
  machine-independent figure.

    python benchmarks/bench_calibrate.py                          # small, medium (~3-5 min with simulation)
    python benchmarks/bench_calibrate.py --sizes small            # the demo's size only
    python benchmarks/bench_calibrate.py --sizes parallel         # 91 parallel views, 134x160
    python benchmarks/bench_calibrate.py --sizes parallel --flat 0.69   # with issue #10's flat field (air at 0.69, tilted)
    python benchmarks/bench_calibrate.py --sizes parallel --flat 0.69 --end-point   # over [0, 180 deg], both end views
    python benchmarks/bench_calibrate.py --standard               # small, medium, standard (long)
    python benchmarks/bench_calibrate.py --sizes standard --keep-data /tmp/pdvc_bench   # reuse the simulated scan
    python benchmarks/bench_calibrate.py --sizes medium --precession 0.5   # a precessing axis
    python benchmarks/bench_calibrate.py --sizes parallel --start tilt     # from the true tilted axis (a diagnostic)

``--start tilt`` starts the calibration (``initial_poses``) from the true
tilted, offset axis without the drift, ``--start roll`` from its tilt in the
detector plane alone (and the offset): a diagnostic of which mode the rounds
spend their time on (``docs/method.md`` §5.15), not a calibration a user
could run.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))

# name: (volume edge, views, detector (rows, cols), sod, odd, target s); sod None: parallel beam over 180°
SIZES = {
    "small": (64, 150, (int(1.2 * 64), int(1.4 * 64)), 8.0 * 64, 4.0 * 64, 60.0),
    "medium": (128, 180, (128, 160), 500.0, 250.0, 60.0),
    "standard": (256, 360, (256, 384), 1000.0, 500.0, 300.0),
    "parallel": (160, 91, (134, 160), None, None, 30.0),
}
# the axis of every size: tilted by TILT_DEG toward the azimuth TILT_AZIMUTH (pdvc.simulate.tilted_axis_poses: radians
# from the detector's u at the first view toward +y, away from the source; 0.38 deg in the detector plane and 0.32 deg
# along the beam, a pitch), offset by 0.04 n
TILT_DEG = 0.5
TILT_AZIMUTH = 0.7


def _describe(name: str) -> str:
    n, nv, det, sod, _, _ = SIZES[name]
    if sod is None:
        return f"{det[0]}x{n}x{n}, {nv} par. views/180°, {det[0]}x{det[1]}"
    return f"{n}^3, {nv} views, {det[0]}x{det[1]}"
SEED = 0
MARK = "BENCH_CALIBRATE_JSON "


def _rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _problem(name: str):
    """(nominal geometry, grid, phantom, true rotvecs, true translations) of one size."""
    import numpy as np

    import pdvc
    from pdvc.simulate import cast_iron_phantom, combine_poses, drift_poses, precession_poses, tilted_axis_poses

    n, nv, det, sod, odd, _ = SIZES[name]
    angles = _angles(name)
    if sod is None:  # parallel beam, pixel = voxel, the volume as tall as the detector
        vg = pdvc.VolumeGeometry((det[0], n, n), voxel_size=1.0)
        geom = pdvc.parallel(angles, det_shape=det, pixel=1.0)
    else:
        vg = pdvc.VolumeGeometry((n, n, n), voxel_size=1.0)
        geom = pdvc.circular_cone(angles, sod=sod, odd=odd, det_shape=det, pixel=1.5)
    phantom = cast_iron_phantom(0.36 * n, 0.8 * n, n_nodules=3 * n, seed=SEED)
    rv, t = combine_poses(
        tilted_axis_poses(angles, tilt=np.deg2rad(TILT_DEG), tilt_azimuth=TILT_AZIMUTH, offset=(0.04 * n, 0.0, 0.0)),
        drift_poses(np.linspace(0.0, 1.0, nv), angles, velocity=(0.02 * n, 0.0, 0.015 * n)),
    )
    if _precession_deg():
        rv, t = combine_poses((rv, t), precession_poses(angles, amplitude=np.deg2rad(_precession_deg())))
    return geom, vg, phantom, rv, t


def _angles(name: str):
    """The scan angles of a size: over [0, 180°) in parallel beam ([0, 180°] with ``--end-point``), a full turn in
    cone beam."""
    import numpy as np

    _, nv, _, sod, _, _ = SIZES[name]
    return np.linspace(0, np.pi if sod is None else 2 * np.pi, nv, endpoint=sod is None and _end_point())


def _start_poses(name: str, start: str):
    """``--start``: None (nominal), or the true axis without the drift (``tilt``), or its tilt in the detector plane
    (azimuth 0, ``tilt · cos(azimuth)``) and offset (``roll``)."""
    import numpy as np

    import pdvc
    from pdvc.simulate import tilted_axis_poses

    if start == "nominal":
        return None
    n = SIZES[name][0]
    tilt, az = (TILT_DEG, TILT_AZIMUTH) if start == "tilt" else (TILT_DEG * np.cos(TILT_AZIMUTH), 0.0)
    return pdvc.Poses(*tilted_axis_poses(_angles(name), tilt=np.deg2rad(tilt), tilt_azimuth=az,
                                         offset=(0.04 * n, 0.0, 0.0)))


def _precession_deg() -> float:
    """``--precession``, handed to the child processes through the environment."""
    return float(os.environ.get("PDVC_BENCH_PRECESSION_DEG", "0") or 0)


def _flat() -> float:
    """``--flat``, handed to the child processes through the environment (1: none)."""
    return float(os.environ.get("PDVC_BENCH_FLAT", "1") or 1)


def _end_point() -> bool:
    """``--end-point``, handed to the child processes through the environment."""
    return os.environ.get("PDVC_BENCH_END_POINT", "") == "1"


def _data_path(data_dir: str, name: str) -> str:
    prec = f"_prec{_precession_deg():g}" if _precession_deg() else ""
    flat = f"_flat{_flat():g}" if _flat() != 1.0 else ""
    closed = "_closed" if _end_point() and SIZES[name][3] is None else ""
    return os.path.join(data_dir, f"bench_calibrate_{name}{prec}{flat}{closed}_seed{SEED}.npy")


# --------------------------------------------------------------------------- simulation child


def child_simulate(name: str, path: str) -> int:
    import numpy as np

    from pdvc.simulate import simulate_scan

    geom, vg, phantom, rv, t = _problem(name)
    t0 = time.perf_counter()
    scan = simulate_scan(phantom, geom, rotvecs=rv, translations=t, i0=2e4, seed=SEED, supersampling=2)
    p = scan.projections
    if _flat() != 1.0:
        from bench_accuracy import flat_mismatch  # issue #10's flat field, as bench_accuracy.py --flat makes it

        p = p + flat_mismatch(p.shape, _flat())
    dt = time.perf_counter() - t0
    tmp = path + ".part.npy"
    np.save(tmp, np.asarray(p, np.float32))
    os.replace(tmp, path)
    print(f"  [{name}] simulated in {dt:.1f} s (analytic projector, supersampling 2) -> {path}", flush=True)
    return 0


# --------------------------------------------------------------------------- calibration child


class _Probe:
    """Wraps pdvc functions to time them, attributed to the step (progress event) they run in."""

    def __init__(self):
        self.phase = "setup"
        self.acc: dict = {}  # (phase, kind) -> [seconds, calls]
        self.missing: list = []
        self.live = True

    def wrap(self, module, attr: str, kind: str) -> None:
        fn = getattr(module, attr, None)
        if fn is None or not callable(fn):
            self.missing.append(f"{module.__name__}.{attr}")
            return
        probe = self

        def timed(*a, **kw):
            t0 = time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                rec = probe.acc.setdefault((probe.phase, kind), [0.0, 0])
                rec[0] += time.perf_counter() - t0
                rec[1] += 1

        setattr(module, attr, timed)
        self._restore = getattr(self, "_restore", []) + [(module, attr, fn)]

    def restore(self) -> None:
        for module, attr, fn in getattr(self, "_restore", []):
            setattr(module, attr, fn)

    def progress(self, info: dict) -> None:
        ev = info.get("event")
        if ev == "init":
            self.phase = "init"
        elif ev == "reconstruct":
            self.phase = "nominal" if info.get("what") == "nominal" else "final"
        elif ev in ("stage", "choosing"):  # a stage's model choice runs before its "stage" event, in its time
            self.phase = f"stage {info.get('index')}"
        elif ev == "assess":
            self.phase = "assess"
        if self.live and ev == "round":  # live progress: a long size shows where it is
            print(f"    round {info.get('iteration')}: {info.get('stage')}@{info.get('scale')} {info.get('elapsed_s', 0):.1f} s, "
                  f"{info.get('n_iter')} passes, chi {info.get('chi_before', 0):.4g} -> {info.get('chi_after', 0):.4g}, "
                  f"increment {info.get('increment_px', 0):.3f} px{' (from extrapolated poses)' if info.get('extrapolated') else ''}",
                  flush=True)
        elif self.live and ev == "stage":
            print(f"    stage {info.get('index')}: {info.get('name')}@{info.get('scale')}", flush=True)

    def get(self, phase: str, kind: str) -> tuple:
        s, c = self.acc.get((phase, kind), (0.0, 0))
        return float(s), int(c)


def _install_probe() -> _Probe:
    import importlib

    probe = _Probe()
    drv = importlib.import_module("pdvc.calibration._driver")
    eng = importlib.import_module("pdvc.correlation._engine")
    for attr in ("reconstruct", "cgls", "nonneg_ls", "spline_upsample"):  # the correlation volume and its oversampling
        probe.wrap(drv, attr, "recon")
    probe.wrap(drv, "coarse_grain", "coarse")
    probe.wrap(drv, "correlate", "correlate")
    probe.wrap(eng, "reduce_views", "pass")
    probe.wrap(eng, "reduce_views_background", "pass")  # a pass with a background per view profiled out (--flat)
    probe.wrap(eng, "_eig_solve", "solve")
    probe.wrap(eng, "_assemble", "solve")
    return probe


def _warm_up(parallel: bool = False) -> float:
    """One tiny calibration of the same beam: loads (or compiles) every kernel the timed run uses."""
    import numpy as np

    import pdvc
    from pdvc.simulate import cast_iron_phantom, simulate_scan, tilted_axis_poses

    t0 = time.perf_counter()
    n = 24
    vg = pdvc.VolumeGeometry((n, n, n))
    if parallel:
        angles = np.linspace(0, np.pi, 40, endpoint=False)
        geom = pdvc.parallel(angles, det_shape=(28, 36), pixel=1.0)
    else:
        angles = np.linspace(0, 2 * np.pi, 40, endpoint=False)
        geom = pdvc.circular_cone(angles, sod=8.0 * n, odd=4.0 * n, det_shape=(48, 56), pixel=1.5)
    rv, t = tilted_axis_poses(angles, tilt=np.deg2rad(0.3), offset=(1.0, 0.0, 0.0))
    scan = simulate_scan(cast_iron_phantom(0.36 * n, 0.8 * n, n_nodules=20), geom, rotvecs=rv, translations=t, seed=1)
    import logging

    log = logging.getLogger("pdvc")
    level = log.level
    log.setLevel(logging.CRITICAL)  # the tiny scan's own verdict is not part of the benchmark
    try:
        pdvc.calibrate(scan.projections, scan.geometry, vg, max_outer=2, scales=(2, 1))
    finally:
        log.setLevel(level)
    return time.perf_counter() - t0


def _reference_problem(threads):
    """The fixed yardstick problem: 64³ textured cylinder, 36 cone views, detector 76x89."""
    import numpy as np

    import pdvc

    sys.path.insert(0, HERE)
    from _reference import Yardstick

    n = 64
    vg = pdvc.VolumeGeometry((n, n, n))
    angles = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    geom = pdvc.circular_cone(angles, sod=8.0 * n, odd=4.0 * n, det_shape=(76, 89), pixel=1.5)
    rng = np.random.default_rng(0)
    vol = rng.random(vg.shape, dtype=np.float32)
    zc, yc, xc = vg.coordinates()
    vol *= (xc[None, None, :] ** 2 + yc[None, :, None] ** 2 < (0.45 * n) ** 2).astype(np.float32)
    return Yardstick(vol, vg, geom, ref_views=0)


def child_calibrate(name: str, path: str, threads: int, start: str = "nominal") -> int:
    import numpy as np

    import pdvc
    from pdvc.geometry import fix_gauge, reprojection_error, sample_points

    geom, vg, _, rv_true, t_true = _problem(name)
    yard = _reference_problem(threads)
    t_warm = _warm_up(parallel=SIZES[name][3] is None)
    projections = np.load(path)
    rss_before = _rss_mib()

    ref = [yard() for _ in range(3)]
    kept = {}  # (stage index, round, chi_before) -> the poses that round kept, from the checkpoints

    def checkpoint(state):
        h = state["history"][-1]
        kept[(h["stage_index"], h["round"], h["chi_before"])] = state["poses"]

    initial = _start_poses(name, start)
    probe = _install_probe()
    t0 = time.perf_counter()
    res = pdvc.calibrate(projections, geom, vg, progress=probe.progress, checkpoint=checkpoint, initial_poses=initial)
    total = time.perf_counter() - t0
    probe.restore()
    rss_peak = _rss_mib()
    ref += [yard() for _ in range(3)]
    ref_s = float(np.median(ref))

    points = sample_points(vg, 5, fraction=0.6)
    truth = geom.apply_poses(*fix_gauge(rv_true, t_true, geom, center=vg.offset))
    err = float(reprojection_error(res.geometry, truth, points).rms)
    err_nominal = float(reprojection_error(geom, truth, points).rms)

    # ---- steps: res.timings, plus what is outside them
    tm = dict(res.timings)
    hist = list(res.history)
    steps = []  # (label, seconds, phase key for the probe, rounds, passes)
    if "init" in tm:
        steps.append(("init (axis offset)", tm["init"], "init", None, None))
    stage_keys = [k for k in tm if k.startswith("stage ")]
    for k in stage_keys:
        idx = int(k.split()[1])
        h = [e for e in hist if e.get("stage_index") == idx]
        steps.append((k, tm[k], f"stage {idx}", len(h), sum(int(e["n_iter"]) for e in h)))
    if "zingers" in tm:
        steps.append(("zingers (forward, recon if found)", tm["zingers"], "zingers", None, None))
    steps.append(("final (recon + residuals)", tm.get("final", 0.0), "final", None, None))
    steps.append(("assess", tm.get("assess", 0.0), "assess", None, None))
    known = sum(tm.get(k, 0.0) for k in ["init", "zingers", "stages", "final", "assess"])
    # second_run: the runs not returned (the default's, the precession recipe's, its run with a precession twice a
    # turn) and the comparisons
    twice = "second run (precession twice a turn)" in tm
    returned = None if "first run (default recipe)" not in tm else (
        "second run (precession twice a turn)" if twice else "second run (precession recipe)")
    for key, label in (("first run (default recipe)", "first run, default recipe (not returned)"),
                       ("second run (precession recipe)", "second run, precession recipe (not returned)"),
                       ("second run (precession twice a turn)", "second run, precession twice a turn (not returned)"),
                       ("second run (comparison)", "second run: comparisons")):
        if key in tm and key != returned:
            steps.append((label, tm[key], "second_run", None, None))
            known += tm[key]
    other = res.elapsed_s - known
    steps.append(("other: nominal recon, noise, trunc., motion", other, "nominal", None, None))

    n, nv, det, sod, _, target = SIZES[name]
    print(f"\n[{name}] {_describe(name)}, {'parallel' if sod is None else 'cone'}; stages: "
          + ", ".join(f"{o.name}@{o.scale}" for o in res.stage_outcomes), flush=True)
    print(f"  total {total:.1f} s (res.elapsed_s {res.elapsed_s:.1f}; target {target:.0f} s); warm-up (tiny calibration) {t_warm:.1f} s before")
    print(f"  {'step':42s} {'s':>7s} {'%':>5s} {'rounds':>6s} {'passes':>6s} | {'recon s':>7s} {'pass s':>7s} {'#pass':>5s} {'solve s':>7s} {'coarse s':>8s} {'guard-discarded s':>17s}")
    rows_json = []
    for label, sec, ph, rounds, passes in steps:
        rs, _ = probe.get(ph, "recon")
        ps, pc = probe.get(ph, "pass")
        ss, _ = probe.get(ph, "solve")
        cs, _ = probe.get(ph, "coarse")
        disc = ""
        if ph.startswith("stage "):
            idx = int(ph.split()[1])
            disc = f"{sec - sum(e['elapsed_s'] for e in hist if e.get('stage_index') == idx):.1f}"
        print(f"  {label:42s} {sec:7.1f} {100 * sec / max(total, 1e-9):5.1f} {'' if rounds is None else rounds:>6} "
              f"{'' if passes is None else passes:>6} | {rs:7.1f} {ps:7.1f} {pc:5d} {ss:7.2f} {cs:8.2f} {disc:>17s}")
        rows_json.append(dict(step=label, s=sec, rounds=rounds, passes=passes, recon_s=rs, pass_s=ps, n_pass=pc, solve_s=ss))
    if probe.missing:
        print(f"  (probe: not found, not timed: {', '.join(probe.missing)})")
    for o in res.stage_outcomes:
        print(f"  stage {o.name}@{o.scale}: {_status_name(o.status)}, {o.rounds} rounds, {o.elapsed_s:.1f} s: {o.message}")
    print(f"  rounds: {'it':>3s} {'stage':>8s} {'scale':>5s} {'s':>6s} {'passes':>6s} {'chi before -> after':>22s} {'incr px':>8s} "
          f"{'err px':>7s} engine")
    for e in hist:
        q = kept.get((e["stage_index"], e["round"], e["chi_before"]))
        e_px = "-" if q is None else f"{reprojection_error(geom.apply(q), truth, points).rms:.4f}"
        print(f"          {e['iteration']:3d} {e['stage']:>8s} {e['scale']:5d} {e['elapsed_s']:6.1f} {e['n_iter']:6d} "
              f"{e['chi_before']:10.4g} -> {e['chi_after']:8.4g} {e['increment_px']:8.3f} {e_px:>7s} {e['engine_status']}")
    # a round's cost in forward projections of its correlation grid at its scale (issue #11: ~4 at most)
    from pdvc.calibration import refined_grid

    fwd_s = {}
    for st in res.stages:
        if st.scale in fwd_s:
            continue
        g_s = geom.binned(st.scale) if st.scale > 1 else geom  # the coarse-grained data's geometry
        vg_c = refined_grid(vg if st.scale == 1 else vg.binned(st.scale), st.oversample)
        v = np.ones(vg_c.shape, np.float32)
        pdvc.forward(v, vg_c, g_s)
        t1 = time.perf_counter()
        pdvc.forward(v, vg_c, g_s)
        fwd_s[st.scale] = time.perf_counter() - t1
    for sc in sorted(fwd_s, reverse=True):
        rs = [e["elapsed_s"] / fwd_s[sc] for e in hist if e["scale"] == sc]
        if rs:
            print(f"  scale {sc}: one forward projection of the correlation grid {fwd_s[sc]:.2f} s; a round costs "
                  f"{min(rs):.1f}-{max(rs):.1f} of them (median {float(np.median(rs)):.1f})")
    fine = min(o.scale for o in res.stage_outcomes) if res.stage_outcomes else 1
    fine_ph = [f"stage {int(k.split()[1])}" for k in stage_keys if k.endswith(f"scale {fine})")]
    fine_pass_s = sum(probe.get(ph, "pass")[0] for ph in fine_ph)
    fine_pass_n = sum(probe.get(ph, "pass")[1] for ph in fine_ph)
    n_rounds = len(hist)
    n_passes = sum(int(e["n_iter"]) for e in hist)
    all_pass_s = sum(v[0] for (ph, k), v in probe.acc.items() if k == "pass")
    all_pass_n = sum(v[1] for (ph, k), v in probe.acc.items() if k == "pass")
    print(f"  {n_rounds} rounds, {n_passes} Jacobian passes in the rounds ({all_pass_n} in all, {all_pass_s:.1f} s, "
          f"{all_pass_s / max(all_pass_n, 1):.2f} s each on average over the scales, "
          f"{fine_pass_s / max(fine_pass_n, 1):.2f} s each at the finest scale {fine})")
    print(f"  peak RSS {rss_peak:.0f} MiB (getrusage ru_maxrss of this process; {rss_before:.0f} MiB before calibrate: "
          f"imports, warm-up, projections {projections.nbytes / 2**20:.0f} MiB)")
    print(f"  reprojection error vs truth (gauge-free, 125 points): nominal {err_nominal:.3f} px -> calibrated {err:.4f} px")
    print(f"  status {res.status.name.lower()} (success {res.success}): {res.message}")
    print(f"  motion model: {res.options.get('model', 'n/a')}")
    if _flat() != 1.0:
        print(f"  air: {res.options.get('air', 'n/a')}")
    print(f"  reference (64^3 x 36 views): median {ref_s:.3f} s of {['%.3f' % r for r in ref]} (3 before, 3 after); "
          f"total/reference {total / ref_s:.0f}", flush=True)
    out = dict(
        name=name, total=total, elapsed=res.elapsed_s, rounds=n_rounds, passes=n_passes, all_passes=all_pass_n,
        pass_s=all_pass_s, fine_pass_s=fine_pass_s, fine_pass_n=fine_pass_n, rss_peak=rss_peak, rss_before=rss_before, err=err, err_nominal=err_nominal,
        status=res.status.name.lower(), success=bool(res.success), ref=ref_s, steps=rows_json, warmup=t_warm,
    )
    print(MARK + json.dumps(out), flush=True)
    return 0


def _status_name(s) -> str:
    return getattr(s, "name", str(s)).lower()


# --------------------------------------------------------------------------- parent


def _run_child(argv, env) -> tuple[int, dict | None]:
    proc = subprocess.Popen([sys.executable, os.path.abspath(__file__)] + argv, env=env, stdout=subprocess.PIPE, text=True)
    result = None
    for line in proc.stdout:
        if line.startswith(MARK):
            result = json.loads(line[len(MARK):])
        else:
            print(line, end="", flush=True)
    return proc.wait(), result


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="small,medium", help="comma-separated, among small, medium, standard, parallel")
    ap.add_argument("--standard", action="store_true", help="also run the standard problem (256^3, 360 views; long)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--keep-data", metavar="DIR", help="keep the simulated scans there and reuse them")
    ap.add_argument("--precession", type=float, default=0.0, metavar="DEG",
                    help="add a once-per-turn precession of the axis of this amplitude (default 0: none)")
    ap.add_argument("--flat", type=float, default=1.0, metavar="T",
                    help="issue #10's flat field on the simulated scans: air at a transmission of T, 8%% tilted across "
                         "the columns, 1%% drift over the scan (bench_accuracy.py --flat; default 1: none)")
    ap.add_argument("--end-point", action="store_true",
                    help="parallel scans over [0, 180 deg], both end points included (issue #10's synchrotron list, 91 "
                         "views every 2 deg), instead of [0, 180 deg)")
    ap.add_argument("--start", choices=("nominal", "tilt", "roll"), default="nominal",
                    help="start from the nominal geometry (default), or, as a diagnostic, from the true tilted axis "
                         "without the drift (tilt) or its tilt in the detector plane alone (roll)")
    ap.add_argument("--_child", help=argparse.SUPPRESS)
    ap.add_argument("--_simulate", help=argparse.SUPPRESS)
    ap.add_argument("--_data", help=argparse.SUPPRESS)
    args = ap.parse_args()

    if args._child or args._simulate:
        sys.path.insert(0, HERE)
        from _reference import pin_threads

        pin_threads(args.threads)
        if args._simulate:
            return child_simulate(args._simulate, args._data)
        return child_calibrate(args._child, args._data, args.threads, args.start)

    sizes = [s.strip() for s in args.sizes.split(",") if s.strip()]
    if args.standard and "standard" not in sizes:
        sizes.append("standard")
    bad = [s for s in sizes if s not in SIZES]
    if bad:
        ap.error(f"unknown size(s) {bad}; choose among {list(SIZES)}")

    if args.precession:
        os.environ["PDVC_BENCH_PRECESSION_DEG"] = repr(float(args.precession))
    if not 0.0 < args.flat <= 1.0:
        ap.error("--flat must be a transmission in (0, 1]")
    if args.flat != 1.0:
        os.environ["PDVC_BENCH_FLAT"] = repr(float(args.flat))
    if args.end_point:
        os.environ["PDVC_BENCH_END_POINT"] = "1"
    env = dict(os.environ)
    env["NUMBA_NUM_THREADS"] = str(args.threads)
    env.setdefault("OMP_NUM_THREADS", "1")
    sys.path.insert(0, HERE)
    from _reference import machine_line

    print("bench_calibrate.py: end-to-end pdvc.calibrate on simulated scans (issue #11)")
    print(machine_line(args.threads))
    print(f"command: {sys.executable} {' '.join(sys.argv)}")
    print(f"started {time.strftime('%Y-%m-%d %H:%M:%S')}, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} "
          f"(the machine may be shared: read total/reference)", flush=True)

    data_dir = args.keep_data or tempfile.mkdtemp(prefix="pdvc_bench_calibrate_")
    os.makedirs(data_dir, exist_ok=True)
    results = {}
    t_all = time.perf_counter()
    try:
        for name in sizes:
            path = _data_path(data_dir, name)
            if not os.path.exists(path):
                rc, _ = _run_child(["--_simulate", name, "--_data", path, "--threads", str(args.threads)], env)
                if rc != 0:
                    results[name] = dict(name=name, status=f"simulation failed (rc {rc})")
                    continue
            else:
                print(f"  [{name}] reusing {path}", flush=True)
            rc, res = _run_child(["--_child", name, "--_data", path, "--threads", str(args.threads), "--start", args.start],
                                 env)
            results[name] = res if (rc == 0 and res) else dict(name=name, status=f"failed (rc {rc})")
    finally:
        if not args.keep_data:
            for name in sizes:
                try:
                    os.remove(_data_path(data_dir, name))
                except OSError:
                    pass
            try:
                os.rmdir(data_dir)
            except OSError:
                pass

    # ---- final table
    print()
    print(f"pdvc.calibrate end to end, {args.threads} threads; {machine_line(args.threads)}")
    hdr = (f"{'size':9s} {'problem':30s} {'total s':>8s} {'target':>6s} {'rounds':>6s} {'passes':>6s} {'s/pass':>6s} "
           f"{'peak RSS MiB':>12s} {'err px (nominal)':>17s} {'status':18s} {'ref s':>6s} {'total/ref':>9s}")
    print(hdr)
    print("-" * len(hdr))
    for name in sizes:
        r = results.get(name, {})
        target = SIZES[name][-1]
        prob = _describe(name)
        if "total" not in r:
            print(f"{name:9s} {prob:30s} {r.get('status', 'not run')}")
            continue
        print(f"{name:9s} {prob:30s} {r['total']:8.1f} {target:6.0f} {r['rounds']:6d} {r['passes']:6d} "
              f"{r['fine_pass_s'] / max(r['fine_pass_n'], 1):6.2f} {r['rss_peak']:12.0f} "
              f"{r['err']:7.4f} ({r['err_nominal']:5.2f}) {r['status']:18s} {r['ref']:6.3f} {r['total'] / r['ref']:9.0f}")
    if "standard" not in sizes:
        prob = _describe("standard")
        print(f"{'standard':9s} {prob:30s} not run (--standard)")
    print("s/pass: mean time of one Jacobian pass (reduce_views) at the finest scale; peak RSS: ru_maxrss of the calibrating")
    print("process; err: RMS reprojection error vs the true geometry, gauge-free (nominal in brackets); total/ref: total")
    print(f"over the reference forward projector (64^3 x 36 views) timed in the same process. Wall clock {time.perf_counter() - t_all:.0f} s.")
    return 0 if all("total" in results.get(s, {}) for s in sizes) else 1


if __name__ == "__main__":
    sys.exit(main())
