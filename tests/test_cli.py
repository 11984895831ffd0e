"""The command line and the calibration pipeline end to end (small scans).

Every scan here is simulated with the analytic ellipsoid projector (not the
voxel projector the engine inverts), with Poisson noise, and judged against
its known true geometry with the gauge-free reprojection error.
"""

import json

import numpy as np
import pytest

import pdvc
from pdvc._demo import run_demo
from pdvc._inputs import load_scan
from pdvc.cli import main
from pdvc.geometry import reprojection_error, sample_points


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """`pdvc simulate` output: a 32^3 scan, 80 views, and its config."""
    out = tmp_path_factory.mktemp("sim")
    assert main(["-q", "simulate", "--out", str(out), "--size", "32", "--views", "80", "--overwrite"]) == 0
    return out


def _err(geom_vectors, true_vectors, det_shape, n):
    vg = pdvc.VolumeGeometry((n, n, n))
    g = pdvc.VectorGeometry(geom_vectors, det_shape, "cone")
    t = pdvc.VectorGeometry(true_vectors, det_shape, "cone")
    return reprojection_error(g, t, sample_points(vg, 5, fraction=0.6)).rms


def test_demo_calibrates_within_a_tenth_of_a_pixel():
    res = run_demo(size=40, n_views=100, seed=1, max_outer=5)
    assert res.nominal_error.rms > 1.0  # the simulated motion is visible
    assert res.recovered_error.rms < 0.1 * res.nominal_error.rms
    cal = res.calibration
    assert np.mean(cal.snr_after) > np.mean(cal.snr_before) + 6
    assert cal.entropy_after < cal.entropy_before
    assert "gauge" in cal.gauge


def test_cli_simulate_inspect_calibrate_reconstruct(simulated, tmp_path, capsys):
    cfg = simulated / "config.toml"
    assert main(["inspect", str(cfg)]) == 0
    text = capsys.readouterr().out
    assert "80 views" in text and "cone beam" in text
    assert "sample and volume: the sample lies inside the volume" in text
    out = tmp_path / "cal"
    assert main(["-q", "calibrate", str(cfg), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "axis offset" in text
    run = json.loads((out / "run.json").read_text())
    assert run["status"] == "complete" and "gauge" in run["gauge"]
    log_text = (out / "pdvc.log").read_text()
    assert "calibration done" in log_text and "INFO" in log_text
    # what was read and assumed of the data (the notes `pdvc inspect` prints) is kept in the output folder
    notes = list(load_scan(cfg).notes)
    assert any(n.startswith("read ") for n in notes)
    assert run["inputs"] == notes
    assert all(f"input: {n}" in log_text for n in notes)
    for name in ("geometry.npy", "geometry_nominal.npy", "geometry_astra.json", "geometry_tigre.json", "motion.csv",
                 "result.h5", "volume.tif", "report.html", "config.toml", "snr_per_view.png", "residuals.png"):
        assert (out / name).is_file(), name
    assert not list(out.glob(".*.tmp"))
    vec = np.load(out / "geometry.npy")
    true = np.load(simulated / "geometry_true.npy")
    nominal = np.load(simulated / "geometry_nominal.npy")
    proj = np.load(simulated / "projections.npy")
    det = proj.shape[1:]
    e_cal, e_nom = _err(vec, true, det, 32), _err(nominal, true, det, 32)
    assert e_cal < 0.25 * e_nom, (e_cal, e_nom)
    html = (out / "report.html").read_text()
    assert "snr_per_view.png" in html and "entropy" in html
    import html as _html

    inputs = html.split("Inputs: what was read and assumed", 1)[1].split("</section>", 1)[0]
    assert all(f"<li>{_html.escape(n)}</li>" in inputs for n in notes)
    assert "zingers, hot and dead pixels" in html and "air level (what the rays that miss the sample read)" in html
    assert ("before the background per view" in html) == ("a plane per view fitted" in html)
    assert "background per view" in html and "background = &#x27;auto&#x27;" in html.replace("&#39;", "&#x27;")
    # the written config reruns: it is the fully resolved one
    cfg2 = pdvc.io.load_config(out / "config.toml")
    assert cfg2.volume.shape == (32, 32, 32)
    # a non-empty output folder is refused
    assert main(["-q", "calibrate", str(cfg), "--out", str(out)]) == 1
    assert "not empty" in capsys.readouterr().err
    # reconstruct with the calibrated geometry
    vol_path = tmp_path / "vol.tif"
    assert main(["reconstruct", str(cfg), "--geometry", str(out / "geometry.npy"), "--out", str(vol_path)]) == 0
    import tifffile

    assert tifffile.imread(vol_path).shape == (32, 32, 32)
    # a geometry file of the wrong shape is named in the error
    bad = tmp_path / "bad.npy"
    np.save(bad, vec[:10])
    assert main(["reconstruct", str(cfg), "--geometry", str(bad), "--out", str(tmp_path / "v2.tif")]) == 1
    assert "--geometry" in capsys.readouterr().err


def test_interrupted_run_leaves_whole_files_and_resumes(simulated, tmp_path):
    proj = np.load(simulated / "projections.npy")
    nominal = np.load(simulated / "geometry_nominal.npy")
    geom = pdvc.VectorGeometry(nominal, proj.shape[1:], "cone")
    vg = pdvc.VolumeGeometry((32, 32, 32))
    out = tmp_path / "run"

    def stop_at_fine_scale(info):
        if info.get("event") == "stage" and info.get("scale") == 1:
            raise KeyboardInterrupt

    opts = dict(scales=(2, 1), max_outer=2, second_run="off")  # the resumed run's own stages, no second recipe
    with pytest.raises(KeyboardInterrupt):
        pdvc.calibrate(proj, geom, vg, out_dir=out, progress=stop_at_fine_scale, **opts)
    assert json.loads((out / "run.json").read_text())["status"] == "running"
    assert (out / "checkpoint.npz").is_file() and not list(out.glob(".*.tmp"))
    assert not (out / "geometry.npy").exists()
    seen = []
    res = pdvc.calibrate(proj, geom, vg, out_dir=out, resume=True, progress=seen.append, **opts)
    assert seen[0]["event"] == "resume"
    # the stages at scale 2 (warm-up and model) were not redone: those at scale 1 ran (no warm-up at a finer scale)
    assert [(s["name"], s["scale"]) for s in seen if s.get("event") == "stage"] == [("model", 1), ("jolts", 1)]
    assert {h["scale"] for h in res.history} == {2, 1}
    assert json.loads((out / "run.json").read_text())["status"] == "complete"


def test_interrupted_within_a_scale_resumes_after_the_last_round(simulated, tmp_path):
    proj = np.load(simulated / "projections.npy")
    geom = pdvc.VectorGeometry(np.load(simulated / "geometry_nominal.npy"), proj.shape[1:], "cone")
    vg = pdvc.VolumeGeometry((32, 32, 32))
    out = tmp_path / "run"

    def stop_after_second_round(info):
        if info.get("event") == "round" and info.get("iteration") == 1:
            raise KeyboardInterrupt

    opts = dict(scales=(1,), max_outer=4, tol_px=1e-9, oversample=1, second_run="off")
    with pytest.raises(KeyboardInterrupt):
        pdvc.calibrate(proj, geom, vg, out_dir=out, progress=stop_after_second_round, **opts)
    with np.load(out / "checkpoint.npz") as z:  # the warm-up's round and the model's first
        assert int(z["stage_index"]) == 1 and int(z["rounds_done"]) == 1
    seen = []
    res = pdvc.calibrate(proj, geom, vg, out_dir=out, resume=True, progress=seen.append, **opts)
    rounds = [s for s in seen if s.get("event") == "round"]
    assert len(rounds) <= 2  # only the model's rounds left of max_outer = 4 (1 warm-up + 3)
    assert all(r["stage"] == "model" and r["round"] >= 1 for r in rounds)
    assert len(res.history) == 2 + len(rounds)


def test_a_resumed_run_keeps_the_background_its_first_round_decided(simulated, tmp_path, caplog):
    proj = np.load(simulated / "projections.npy")
    geom = pdvc.VectorGeometry(np.load(simulated / "geometry_nominal.npy"), proj.shape[1:], "cone")
    vg = pdvc.VolumeGeometry((32, 32, 32))
    drifted = proj + np.linspace(0.0, 0.3, proj.shape[0], dtype=np.float32)[:, None, None]  # an air level that drifts
    out = tmp_path / "run"

    def stop_after_first_round(info):
        if info.get("event") == "round" and info.get("iteration") == 0:
            raise KeyboardInterrupt

    # air = "off": the engine's background decides here (air = "auto" would subtract the drift before the rounds)
    opts = dict(scales=(1,), max_outer=3, tol_px=1e-9, oversample=1, air="off", second_run="off")
    with pytest.raises(KeyboardInterrupt), caplog.at_level("INFO", logger="pdvc.calibration"):
        pdvc.calibrate(drifted, geom, vg, out_dir=out, progress=stop_after_first_round, **opts)
    assert "measured again" in caplog.text  # decided in the first round
    caplog.clear()
    with caplog.at_level("INFO", logger="pdvc.calibration"):
        res = pdvc.calibrate(drifted, geom, vg, out_dir=out, resume=True, **opts)
    assert "measured again" not in caplog.text  # read from the history, not decided again
    assert len(res.history) == 3 and all(h["background"] == 1 for h in res.history)
    assert res.options["background"].startswith("a plane per view")


def test_input_notes_must_be_strings_and_a_bad_one_writes_nothing(simulated, tmp_path):
    proj = np.load(simulated / "projections.npy")
    scan = load_scan(simulated / "config.toml")
    for bad in ("read a file", [1, 2]):
        with pytest.raises(pdvc.InputTypeError, match="input_notes"):
            pdvc.calibrate(proj, scan.geometry, scan.vol_geom, out_dir=tmp_path / "o", input_notes=bad)
    assert not (tmp_path / "o").exists()


def test_pipeline_bad_input_is_named(simulated):
    proj = np.load(simulated / "projections.npy")
    geom = pdvc.VectorGeometry(np.load(simulated / "geometry_nominal.npy"), proj.shape[1:], "cone")
    vg = pdvc.VolumeGeometry((32, 32, 32))
    bad = proj.copy()
    bad[3, 2, 2] = np.nan
    with pytest.raises(pdvc.PdvcError, match="NaN/Inf.*view 3"):
        pdvc.calibrate(bad, geom, vg)
    assert np.isfinite(proj).all()  # the input was not touched
    with pytest.raises(pdvc.ShapeError, match="projections must have shape"):
        pdvc.calibrate(proj[:, :-1], geom, vg)
    with pytest.raises(pdvc.PdvcError, match="weights"):
        pdvc.calibrate(proj, geom, vg, weights=np.zeros(proj.shape[1:]))
    with pytest.raises(pdvc.PdvcError, match="scales"):
        pdvc.calibrate(proj, geom, vg, scales=(2, 0))
    with pytest.raises(pdvc.PdvcError, match="init"):
        pdvc.calibrate(proj, geom, vg, init="guess")


def test_motion_too_large_for_the_linearisation_is_reported(simulated):
    """A 12-px axis offset, no coarse initialisation, one scale: told to start coarser."""
    from pdvc.calibration import offset_poses

    proj = np.load(simulated / "projections.npy")
    geom = pdvc.VectorGeometry(np.load(simulated / "geometry_nominal.npy"), proj.shape[1:], "cone")
    vg = pdvc.VolumeGeometry((32, 32, 32))
    rv, t = offset_poses(geom, 12.0)
    shifted = pdvc.VectorGeometry(geom.apply_poses(rv, t).vectors, geom.det_shape, "cone")
    data = pdvc.forward(pdvc.fdk(proj, vg, shifted), vg, shifted)
    res = pdvc.calibrate(data, geom, vg, init="none", scales=(1,), max_outer=2, oversample=1)
    assert not res.success
    assert "coarser scale" in res.message


def test_cli_usage_errors(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--size", "4"])
    assert exc.value.code == 2
    with pytest.raises(SystemExit) as exc:
        main([])
    assert exc.value.code == 2
    for cmd in ("demo", "calibrate", "reconstruct", "simulate", "inspect"):
        with pytest.raises(SystemExit) as exc:
            main([cmd, "--help"])
        assert exc.value.code == 0
    assert "Exit codes" in pdvc.cli.build_parser().format_help()


def test_cli_missing_config_is_a_clear_error(tmp_path, capsys):
    assert main(["calibrate", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "nope.toml" in err


def test_noise_from_counts_matches_the_simulated_photon_statistics(tmp_path):
    """Raw counts with flats (gain 1): γ² from Poisson statistics ≈ the empirical variance of the noise."""
    from pdvc._inputs import load_scan
    from pdvc.simulate import cast_iron_phantom, simulate_scan

    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    geom = pdvc.circular_cone(angles, sod=200.0, odd=100.0, det_shape=(20, 24), pixel=1.5)
    scan = simulate_scan(cast_iron_phantom(6.0, 12.0, n_nodules=10, seed=1), geom, i0=5e3, seed=2, supersampling=1)
    np.save(tmp_path / "counts.npy", scan.counts.astype(np.float32))
    np.save(tmp_path / "flats.npy", scan.flats.astype(np.float32))
    np.save(tmp_path / "darks.npy", scan.darks.astype(np.float32))
    (tmp_path / "c.toml").write_text(
        '[data]\npath = "counts.npy"\nflats = "flats.npy"\ndarks = "darks.npy"\nis_raw = true\n'
        '[geometry]\ntype = "cone"\nsod = 200.0\nodd = 100.0\npixel = 1.5\nangles = { start = 0, stop = 360, count = 24 }\n'
        '[volume]\nshape = [16, 16, 16]\nvoxel_size = 1.0\n[calibration]\nnoise = "counts"\n'
    )
    s = load_scan(tmp_path / "c.toml")
    g2 = s.calibration_options["noise_variance"]
    empirical = float(np.var(s.projections - scan.clean))
    assert g2 == pytest.approx(empirical, rel=0.15)
    assert g2 == pytest.approx(float(np.mean(scan.noise_variance())), rel=0.15)


def test_resume_with_changed_data_is_refused(simulated, tmp_path):
    proj = np.load(simulated / "projections.npy")
    geom = pdvc.VectorGeometry(np.load(simulated / "geometry_nominal.npy"), proj.shape[1:], "cone")
    vg = pdvc.VolumeGeometry((32, 32, 32))
    out = tmp_path / "run"

    def stop_after_first_round(info):
        if info.get("event") == "round":
            raise KeyboardInterrupt

    opts = dict(scales=(1,), max_outer=3, oversample=1)
    with pytest.raises(KeyboardInterrupt):
        pdvc.calibrate(proj, geom, vg, out_dir=out, progress=stop_after_first_round, **opts)
    changed = proj.copy()
    changed[5, 3, 3] += 0.01
    with pytest.raises(pdvc.PdvcError, match="projections differ"):
        pdvc.calibrate(changed, geom, vg, out_dir=out, resume=True, **opts)
    with pytest.raises(pdvc.PdvcError, match="settings differ"):
        pdvc.calibrate(proj, geom, vg, out_dir=out, resume=True, scales=(1,), max_outer=4, oversample=1)
    assert json.loads((out / "run.json").read_text())["status"] == "running"  # the refused resumes changed nothing


def test_cli_exit_code_says_a_calibration_did_not_succeed(simulated, tmp_path, monkeypatch, capsys):
    # a calibration made to end worse than nominal (the driver is broken on purpose: every other view shifted, which
    # no global motion of the sample takes back): exit 3, outputs written
    import dataclasses

    from pdvc.calibration import _pipeline
    from pdvc.geometry import Poses

    real = _pipeline.run_stages

    def broken(*a, **kw):
        out = real(*a, **kw)
        n = out.poses.n_views
        shift = np.tile([4.0, 0.0, 2.0], (n, 1)) * (np.arange(n) % 2)[:, None]
        return dataclasses.replace(out, poses=Poses(np.zeros((n, 3)), shift))

    monkeypatch.setattr(_pipeline, "run_stages", broken)
    cfg = simulated / "config.toml"
    text = cfg.read_text() + '\n[calibration]\nmax_outer = 1\nscales = [1]\noversample = 1\n'
    (tmp_path / "c.toml").write_text(text.replace('path = "projections.npy"', f'path = "{simulated / "projections.npy"}"'))
    code = main(["-q", "calibrate", str(tmp_path / "c.toml"), "--out", str(tmp_path / "o")])
    assert code == 3
    run = json.loads((tmp_path / "o" / "run.json").read_text())
    assert run["status"] == "complete" and run["success"] is False and run["status_name"] == "worse_than_nominal"
    assert (tmp_path / "o" / "geometry.npy").is_file() and (tmp_path / "o" / "report.html").is_file()
    assert "did not succeed" in capsys.readouterr().err


def test_binned_calibration_writes_the_geometry_for_the_full_detector(simulated, tmp_path):
    # the poses do not depend on the pixel size: calibrated on a 2x2-binned copy, they are applied
    # to the unbinned nominal geometry; that geometry binned is the calibrated one of the binned run
    text = (simulated / "config.toml").read_text().replace('path = "projections.npy"', f'path = "{simulated / "projections.npy"}"')
    text += "\n[preprocess]\nbin = 2\n\n[calibration]\nmax_outer = 2\nscales = [1]\noversample = 1\n"
    (tmp_path / "c.toml").write_text(text)
    out = tmp_path / "o"
    assert main(["-q", "calibrate", str(tmp_path / "c.toml"), "--out", str(out)]) in (0, 3)
    full = np.load(out / "geometry_full_resolution.npy")
    binned = np.load(out / "geometry.npy")
    proj = np.load(simulated / "projections.npy")
    g_full = pdvc.VectorGeometry(full, proj.shape[1:], "cone")
    np.testing.assert_allclose(g_full.binned(2).vectors, binned, rtol=1e-9, atol=1e-9)
    assert not np.allclose(full, np.load(simulated / "geometry_nominal.npy"))


def test_a_config_schedule_caps_the_correlation_grid_of_its_volume(tmp_path):
    """``scales = "auto"`` from a config sees the [volume] grid: 256³ on 256x384 runs (4, 2); 128³ keeps (2, 1)."""
    from pdvc._inputs import load_scan

    np.save(tmp_path / "p.npy", np.zeros((8, 256, 384), np.float32))
    for n, scales in ((256, [4, 4, 2, 2]), (128, [2, 2, 1, 1])):
        (tmp_path / "c.toml").write_text(
            '[data]\npath = "p.npy"\nis_raw = false\n'
            '[geometry]\ntype = "cone"\nsod = 1000.0\nodd = 500.0\npixel = 1.5\nangles = { start = 0, stop = 360, count = 8 }\n'
            f'[volume]\nshape = [{n}, {n}, {n}]\nvoxel_size = {256 / n}\n'
        )
        s = load_scan(tmp_path / "c.toml")
        assert [st.scale for st in s.calibration_options["stages"]] == scales
