"""The precision of the weak modes (Cramér–Rao from the Hessian) against what the calibration reaches (issue #10, item 7).

A cone-beam scan is simulated with the analytic projector (a cast-iron rod
phantom inside the volume, Poisson noise; never the engine's own
projector) with an axis offset, a tilted axis and a once-per-turn
precession. For each mode of the set-up, the data's own precision is the
Cramér–Rao bound ``γ² H⁻¹`` of its amplitude:

* ``H = Σ_k D_kᵀ M_k D_k`` with ``M_k`` the Gauss–Newton matrix of view k
  (one Jacobian pass, ``reduce_views``) at the **true** geometry against
  the FDK volume made at the true geometry on the calibration's 2x grid,
  and ``D_k`` the lab-frame ``drift:2`` model that the precession
  candidate fits ({1, t, t², cos θ, sin θ, cos 2θ, sin 2θ} x five lab
  parameters; the rotation about the axis fixed): the mode is estimated
  jointly with everything else that model frees;
* ``γ²`` the noise variance the calibration estimates from the data
  (Immerkær);
* the mode's shape is taken from the simulator's own generators
  (``tilted_axis_poses``, ``precession_poses`` at a small amplitude),
  projected on the model, and its bound converted into the RMS
  displacement of sample points on the detector (px).

Two more bounds for the mode alone (every other unknown known): with the
volume known, ``γ / |J m|`` (``J m`` the change of the projections along
the mode), and with the volume re-made by the loop's own reconstruction,
``γ / |J m − Π FDK(J m)|`` (FDK is linear): what is left of the mode's
signature once the reconstruction has taken its share, the information
the reconstruct–correlate loop can use. A mode whose signature the
reconstruction absorbs is near-gauge: its second bound is far above its
first. (A least-squares re-solve, CGLS, absorbs more with every
iteration, 6x then 20x the first bound at 30 and 100 iterations: no limit
to quote, so FDK, the loop's own step, is used.)

The default calibration (``pdvc.calibrate``) is then run on the scan; its
pose error against the truth (both in the gauge of ``fix_gauge``) is
fitted by the same model and read along each mode. A ratio far above 1
says that the error is not noise: it is the bias of the
reconstruct–correlate loop along that mode (``docs/method.md`` §5.4).

    python benchmarks/bench_modes.py             # 48³, 180 views (about a minute on 2 cores)
    python benchmarks/bench_modes.py --n 64 --seed 1 --sod 2   # a wider cone
    python benchmarks/bench_modes.py --ecc       # and the epipolar consistency of the views beside it

``--ecc`` adds a criterion that does not go through the reconstruction:
the epipolar consistency of cone-beam view pairs
(:func:`pdvc.calibration.epipolar_refine`), its precision on each mode at
the truth and the error along each mode once it has refined the five modes
from the calibrated poses (``docs/method.md`` §5.21).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np


def _modes(angles, eps):
    """name -> (rv, t) of a mode of the set-up at amplitude ``eps`` (radians or length), from the simulator."""
    from pdvc.simulate import precession_poses, tilted_axis_poses

    return {
        "axis offset across the beam": tilted_axis_poses(angles, tilt=0.0, offset=(eps, 0.0, 0.0)),
        "axis tilt in the detector plane (roll)": tilted_axis_poses(angles, tilt=eps, tilt_azimuth=0.0),
        "axis tilt toward the source (pitch)": tilted_axis_poses(angles, tilt=eps, tilt_azimuth=np.pi / 2),
        "precession 1/turn, phase 0": precession_poses(angles, amplitude=eps),
        "precession 1/turn, phase 90 deg": precession_poses(angles, amplitude=eps, phase=np.pi / 2),
    }


def _design(geom, center, angles, times):
    """(n_views, 6, n_cols): the lab-frame drift:2 model in sample parameters about ``center`` (rz fixed)."""
    from pdvc.correlation import lab_to_sample_map, make_basis

    S = make_basis("drift:2", angles=angles, times=times).matrix  # (n_views, n_funcs)
    T = lab_to_sample_map(geom, center=center)  # lab -> sample, (n_views, 6, 6)
    cols = [T[:, :, p] * S[:, j][:, None] for j in range(S.shape[1]) for p in range(5)]  # tx ty tz rx ry
    return np.stack(cols, axis=-1)


def _epipolar_rows(p, geom, truth, calibrated, ref, angles, c, points, amplitude, modes, eps):
    """Epipolar consistency on the five modes: its precision at the truth, and where it takes the calibrated poses."""
    from pdvc.calibration import epipolar_refine, epipolar_views, view_pairs
    from pdvc.geometry import Poses, fix_gauge, reprojection_error

    names = list(modes)
    fields = [Poses(*modes[k]).to_params(c) / eps for k in names]
    px = np.array([reprojection_error(geom.apply(Poses(*modes[k])), geom, points).rms / eps for k in names])
    steps = 0.05 / px  # finite differences of 0.05 px on the detector
    t0 = time.perf_counter()
    views, pairs = epipolar_views(p, geom), view_pairs(angles)
    at_truth = epipolar_refine(p, geom, truth, fields, center=c, angles=angles, views=views, pairs=pairs, steps=steps,
                               max_iter=0)
    fit = epipolar_refine(p, geom, calibrated, fields, center=c, angles=angles, views=views, pairs=pairs, steps=steps)
    est = Poses(*fix_gauge(fit.poses.rotvecs, fit.poses.translations, geom, center=c))
    err = est.to_params(c) - ref.to_params(c)
    total = reprojection_error(geom.apply(est), geom.apply(ref), points).rms
    print(f"\nepipolar consistency ({fit.n_pairs} view pairs, {fit.n_planes} planes; {time.perf_counter() - t0:.1f} s): "
          f"residual RMS {at_truth.rms_before:.4g} at the truth, {fit.rms_before:.4g} at the calibrated poses, "
          f"{fit.rms_after:.4g} after refining the five modes from them (gauge-free error {total:.4f} px)")
    print(f"{'mode':40s} {'ECC std at truth':>16s} {'ECC reached':>12s}   (px)")
    for q, name in enumerate(names):
        reached = abs(amplitude(err, fields[q])) * px[q]
        print(f"{name:40s} {at_truth.std[q] * px[q]:16.5f} {reached:12.5f}", flush=True)
    print("ECC std at truth: the standard deviation of each mode's amplitude (the five modes fitted jointly, nothing "
          "else free), from the spread of what 8 folds of the view pairs give on their own; ECC reached: the error along the mode after the five "
          "modes were refined by epipolar consistency from the calibrated poses (everything else as calibrated).")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=48, help="volume edge in voxels (default 48)")
    ap.add_argument("--views", type=int, default=180, help="views over 360 degrees (default 180)")
    ap.add_argument("--i0", type=float, default=2e4, help="photons per pixel (default 2e4)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sod", type=float, default=8.0, help="source-axis distance in volume edges (default 8; 2: a wider cone)")
    ap.add_argument("--tilt", type=float, default=0.5, help="axis tilt, degrees (default 0.5)")
    ap.add_argument("--precession", type=float, default=0.3, help="precession amplitude, degrees (default 0.3)")
    ap.add_argument("--recipe", default="default", help="pdvc.calibrate's recipe (default: the default one)")
    ap.add_argument("--ecc", action="store_true",
                    help="also the epipolar consistency of the views (a criterion without reconstruction): its precision "
                         "on each mode at the truth, and the error after it refines the five modes from the calibration")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    os.environ.setdefault("NUMBA_NUM_THREADS", str(args.threads))

    import pdvc
    from pdvc.calibration import refined_grid
    from pdvc.correlation import estimate_noise_variance
    from pdvc.geometry import Poses, fix_gauge, reprojection_error, sample_points
    from pdvc.projectors import jacobian, reduce_views
    from pdvc.simulate import cast_iron_phantom, combine_poses, precession_poses, simulate_scan, tilted_axis_poses

    n = args.n
    vg = pdvc.VolumeGeometry((n, n, n))
    angles = np.linspace(0, 2 * np.pi, args.views, endpoint=False)
    times = np.linspace(0.0, 1.0, args.views)
    sod, odd = args.sod * n, args.sod / 2 * n
    geom = pdvc.circular_cone(angles, sod=sod, odd=odd, det_shape=(int(1.2 * n), int(1.4 * n)), pixel=(sod + odd) / sod)
    phantom = cast_iron_phantom(0.36 * n, 0.8 * n, n_nodules=3 * n, seed=args.seed)
    rv, t = combine_poses(
        tilted_axis_poses(angles, tilt=np.deg2rad(args.tilt), tilt_azimuth=0.7, offset=(2.0, 0.0, 0.0)),
        precession_poses(angles, amplitude=np.deg2rad(args.precession)),
    )
    t0 = time.perf_counter()
    scan = simulate_scan(phantom, geom, rotvecs=rv, translations=t, i0=args.i0, seed=args.seed, supersampling=2)
    p = scan.projections
    c = np.asarray(vg.offset, float)
    points = sample_points(vg, 5, fraction=0.6)
    print(f"scan: {n}^3, {args.views} views, cone {np.rad2deg(np.arctan(0.7 * n / sod)):.1f} deg "
          f"half-angle, i0 {args.i0:g}; axis tilt {args.tilt} deg, offset 2 voxels, precession {args.precession} deg "
          f"({time.perf_counter() - t0:.1f} s)", flush=True)

    # --- the bound: one Jacobian pass at the truth, against the FDK at the truth on the 2x grid
    gamma2 = estimate_noise_variance(p)
    truth = Poses(rv, t)
    g_true = geom.apply(truth)
    vg_c = refined_grid(vg, 2)
    vol = pdvc.fdk(p, vg_c, g_true)
    red = reduce_views(vol, vg_c, g_true, p, center=c)
    D = _design(geom, c, angles, times)  # (n, 6, m)
    H = np.einsum("kim,kij,kjl->ml", D, red.M, D)
    s = 1.0 / np.sqrt(np.maximum(np.diag(H), 1e-300))  # column scaling: the eigenvalue cut is scale-free
    Hs = H * s[:, None] * s[None, :]
    w, V = np.linalg.eigh(Hs)
    keep = w > 1e-6 * w.max()
    cov = gamma2 * (s[:, None] * ((V[:, keep] / w[keep]) @ V[:, keep].T) * s[None, :])

    eps = 1e-4
    m_cols = D.shape[2]
    wrow = np.tile([1.0, 1.0, 1.0, n / 2, n / 2, n / 2], geom.n_views)  # rotations x the half-size: length units
    Dw = D.reshape(-1, m_cols) * wrow[:, None]

    def coefficients(params_k):
        """The model's coefficients that fit a per-view (n, 6) pattern of sample parameters best."""
        return np.linalg.lstsq(Dw, params_k.reshape(-1) * wrow, rcond=None)[0]

    def amplitude(params_k, pattern):
        """The amplitude along ``pattern`` (per unit) of what the model fits of ``params_k``, as for "reached" below."""
        m = pattern.reshape(-1) * wrow
        return float((Dw.T @ m / float(m @ m)) @ coefficients(params_k))

    # --- what the calibration reaches
    t1 = time.perf_counter()
    res = pdvc.calibrate(p, geom, vg, recipe=args.recipe)
    t_cal = time.perf_counter() - t1
    est = Poses(*fix_gauge(res.poses.rotvecs, res.poses.translations, geom, center=c))
    ref = Poses(*fix_gauge(rv, t, geom, center=c))
    err = est.to_params(c) - ref.to_params(c)
    total = reprojection_error(geom.apply(est), geom.apply(ref), points).rms
    print(f"calibration ({args.recipe}): {res.status.name.lower()}, gauge-free error {total:.4f} px (nominal "
          f"{reprojection_error(geom, geom.apply(ref), points).rms:.3f} px), {t_cal:.1f} s; noise std {np.sqrt(gamma2):.4g}\n")

    print(f"{'mode':40s} {'bound, model':>12s} {'bound, alone':>12s} {'FDK re-solved':>14s} {'reached':>9s}   (px)")
    rows = []
    c_err = coefficients(err)
    _, sens = jacobian(vol, vg_c, g_true, center=c)  # (n, 6, rows, cols): d(projection)/d(pose) at the truth
    for name, (mrv, mt) in _modes(angles, eps).items():
        pattern = Poses(mrv, mt).to_params(c) / eps  # per unit amplitude, sample parameters about c
        m = pattern.reshape(-1) * wrow
        fit = np.linalg.norm(Dw @ coefficients(pattern) - m) / max(np.linalg.norm(m), 1e-300)
        # the amplitude along the mode of what the model fits: a = <D c, m> / <m, m>, a linear functional g of c
        g = Dw.T @ m / float(m @ m)
        px_per_unit = reprojection_error(geom.apply(Poses(mrv, mt)), geom, points).rms / eps
        bound = np.sqrt(max(float(g @ cov @ g), 0.0)) * px_per_unit
        # the mode alone: its data signature J m with the volume known, and what is left of it once the loop's own
        # reconstruction (FDK, linear) has taken its share, J m - Π FDK(J m): the information the loop keeps
        jm = np.einsum("kirc,ki->krc", sens, pattern).astype(np.float32)
        alone = px_per_unit / np.sqrt(float(np.sum(jm.astype(float) ** 2)) / gamma2)
        left = jm - pdvc.forward(pdvc.fdk(jm, vg_c, g_true), vg_c, g_true)
        resolved = px_per_unit / np.sqrt(max(float(np.sum(left.astype(float) ** 2)), 1e-300) / gamma2)
        reached = abs(float(g @ c_err)) * px_per_unit
        rows.append((name, bound, alone, resolved, reached, fit))
        print(f"{name:40s} {bound:12.5f} {alone:12.5f} {resolved:14.5f} {reached:9.5f}", flush=True)
    if args.ecc:
        _epipolar_rows(p, geom, truth, res.poses, ref, angles, c, points, amplitude, _modes(angles, eps), eps)
    print(f"\nmodel fit of the modes' shapes: worst residual {100 * max(r[5] for r in rows):.1g} %")
    print("bound, model: the Cramér–Rao std of the mode's amplitude with the volume known (the FDK at the truth) and "
          "the other unknowns of the lab drift:2 model free (γ² H⁻¹); bound, alone: the same with nothing else free; "
          "FDK re-solved: the mode alone with what the FDK of its data signature explains taken out (what the "
          "reconstruct-correlate loop can still see of it); reached: the calibrated geometry's error along the mode "
          "(gauge fixed, fitted by the same model). All as RMS displacement of sample points on the detector, px.")
    return rows


if __name__ == "__main__":
    main()
