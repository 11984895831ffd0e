"""The axis pdvc finds on the real scans, against an established centre-of-rotation finder (issue #10).

Issue #10 asks that on real scans "the axis must agree with established
centre-finding tools". This bench calibrates each real scan of
``../shared/data`` with its example config (``examples/*/config.toml``, as
``pdvc calibrate`` runs it) and sets beside pdvc's axis the centre that
algotom finds on the same line integrals (the config's binning, the same
preprocessing, read by :func:`pdvc._inputs.load_scan`):

* Vo's method (``algotom.prep.calculation.find_center_vo``: the Fourier
  metric of the sinogram joined to its mirror) on the views of a half
  turn (on a full turn each half on its own), rows spread over the
  detector (the median, and the spread over the rows);
* phase correlation of the view at 0° with the mirrored view at 180°
  (``find_center_based_phase_correlation``), where both exist and the
  detector has 8 rows or more.

Both are offsets of the axis from the detector's centre column, in the
config's pixels, the column pdvc's ``describe_motion`` reports
(``motion/offset_px``): positive to the right. pdvc's also follows the
axis's tilt and the per-view motion; the finders assume one vertical axis,
so they are compared at the rows they were measured on (pdvc's offset is
at the volume's centre row). Neither is ground truth; a difference of a
few tenths of a pixel is what two methods of this kind give.

algotom is not a dependency of pdvc: ``pip install -e ".[peers]"``.

    python benchmarks/bench_centre.py              # the three real scans (about 2 minutes on 2 cores)
    python benchmarks/bench_centre.py --scans tooth
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import re
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"

# example -> {config key: path under DATA}
SCANS = {
    "tooth": {"path": "tomopy-tooth/tooth.h5"},
    "neutron360": {"path": "sarepy-neutron360/sinogram_360_neutron_image.tif"},
    "psi-neutron360": {"path": "psi-neutron360/projections", "flats": "psi-neutron360/flats", "darks": "psi-neutron360/darks"},
}


def _config(name: str, folder: Path) -> Path:
    """The example's config with its data paths pointed at ``DATA``."""
    text = (ROOT / "examples" / name / "config.toml").read_text()
    for key, rel in SCANS[name].items():
        text = re.sub(rf'^{key} = ".*"$', f'{key} = "{(DATA / rel).as_posix()}"', text, count=1, flags=re.M)
    cfg = folder / f"{name}.toml"
    cfg.write_text(text)
    return cfg


def _finders(p: np.ndarray, angles: np.ndarray) -> dict:
    """Axis offsets (px from the centre column) by algotom's finders on line integrals ``(views, rows, cols)``."""
    from algotom.prep.calculation import find_center_based_phase_correlation, find_center_vo

    n_rows, n_cols = p.shape[1:]
    centre = (n_cols - 1) / 2
    deg = np.rad2deg(np.asarray(angles, float) - float(angles[0]))
    step = float(np.median(np.diff(deg)))
    rows = np.unique(np.linspace(0, n_rows - 1, min(n_rows, 9)).round().astype(int))
    out = {}
    halves = [("", deg <= 180.0 + 0.5 * step)]  # the first half turn, its end view included
    if deg[-1] >= 360.0 - 1.5 * step:  # a full turn: the second half turn too (the finder's own scatter)
        halves = [(", 1st half turn", halves[0][1]), (", 2nd half turn", deg >= 180.0 - 0.5 * step)]
    for label, half in halves:
        vo = [float(find_center_vo(p[half, r, :].astype(np.float32), step=0.1, ncore=1)) - centre for r in rows]
        out[f"Vo (algotom){label}"] = (float(np.median(vo)), float(np.ptp(vo)) if len(vo) > 1 else 0.0)
    j180 = int(np.argmin(np.abs(deg - 180.0)))
    if abs(deg[j180] - 180.0) < 0.5 * step and n_rows >= 8:  # a 2D match needs more than a row or two
        c = float(find_center_based_phase_correlation(p[0].astype(np.float32), p[j180].astype(np.float32))) - centre
        out["phase correlation 0/180 (algotom)"] = (c, 0.0)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scans", nargs="+", choices=sorted(SCANS), default=sorted(SCANS))
    args = ap.parse_args(argv)
    if importlib.util.find_spec("algotom") is None:
        ap.error('algotom is not installed: pip install -e ".[peers]"')
    from pdvc._inputs import load_scan
    from pdvc.cli import main as pdvc_main
    from pdvc.report import read_result_h5

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for name in args.scans:
            if not (DATA / SCANS[name]["path"]).exists():
                print(f"{name}: data not found under {DATA}; skipped", flush=True)
                continue
            cfg = _config(name, folder)
            t0 = time.perf_counter()
            with contextlib.redirect_stdout(io.StringIO()):  # pdvc's summary: the figures below are read from result.h5
                rc = pdvc_main(["-q", "calibrate", str(cfg), "--out", str(folder / name)])
            t_pdvc = time.perf_counter() - t0
            if rc != 0:
                print(f"{name}: pdvc calibrate exited {rc}", flush=True)
                continue
            res = read_result_h5(folder / name / "result.h5")
            offset = float(res["motion"]["offset_px"])
            snr = (float(res["metrics"]["snr_before_db"].mean()), float(res["metrics"]["snr_after_db"].mean()))
            scan = load_scan(cfg)
            from pdvc.correlation import view_angles

            t1 = time.perf_counter()
            found = _finders(np.asarray(scan.projections), view_angles(scan.geometry))
            t_peer = time.perf_counter() - t1
            shape = np.shape(scan.projections)
            print(f"\n{name}: {shape[0]} views of {shape[1]} x {shape[2]} px (as calibrated); pdvc {t_pdvc:.1f} s, "
                  f"SNR {snr[0]:.2f} -> {snr[1]:.2f} dB; algotom {t_peer:.1f} s", flush=True)
            print(f"  {'pdvc (calibrated axis, centre row)':40s} {offset:+8.3f} px")
            for method, (c, spread) in found.items():
                extra = f"  (rows spread {spread:.2f} px)" if spread else ""
                print(f"  {method:40s} {c:+8.3f} px   pdvc - it {offset - c:+.3f} px{extra}")
                rows.append((name, method, offset, c))
    for method in sorted({r[1].split(",")[0] for r in rows}):
        d = np.array([r[2] - r[3] for r in rows if r[1].split(",")[0] == method])
        print(f"pdvc against {method}: largest difference {np.abs(d).max():.3f} px, median {np.median(np.abs(d)):.3f} px "
              f"over {d.size} comparisons (offsets from the centre column, in the pixels each config calibrates)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
