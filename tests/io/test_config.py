"""Configuration: schema checks, defaults, path resolution, TOML round trip, geometries."""

from __future__ import annotations

import logging
import math
import textwrap

import numpy as np
import pytest

from pdvc.errors import GeometryError
from pdvc.geometry import VolumeGeometry, circular_cone, parallel
from pdvc.io._config import (
    AngleRange,
    ConfigError,
    build_geometry,
    build_volume_geometry,
    check_coverage,
    load_config,
    resolve_angles,
    write_config,
)

CONE = {"type": "cone", "sod": 100.0, "odd": 300.0, "pixel": 0.2}


def _cfg(geometry=None, **sections):
    d = {"data": {"path": "scan"}, "geometry": dict(geometry or CONE)}
    d.update(sections)
    return d


def _write(tmp_path, text, name="run.toml"):
    p = tmp_path / name
    p.write_text(textwrap.dedent(text), encoding="utf-8")
    return p


# -- loading, defaults, paths ------------------------------------------------
def test_minimal_file_gets_defaults_and_absolute_paths(tmp_path):
    p = _write(
        tmp_path,
        """
        [data]
        path = "proj/"
        flats = "flats/*.tif"

        [geometry]
        type = "cone"
        sod = 100
        sdd = 400
        pixel = [0.2, 0.1]
        """,
    )
    cfg = load_config(p)
    assert cfg.data.path == str(tmp_path / "proj")
    assert cfg.data.flats == str(tmp_path / "flats" / "*.tif")
    assert cfg.data.format == "auto" and cfg.data.is_raw == "auto" and cfg.data.sinogram is False
    g = cfg.geometry
    assert (g.sod, g.odd, g.sdd) == (100.0, 300.0, 400.0)
    assert isinstance(g.sod, float)
    assert g.pixel == (0.2, 0.1) and g.det_offset == (0.0, 0.0)
    assert g.angles == "auto"
    assert cfg.volume.offset == (0.0, 0.0, 0.0) and cfg.volume.shape is None
    # the recipe's own model applies: its parameters stay unset until given
    assert cfg.calibration.recipe == "default" and cfg.calibration.scales == "auto" and cfg.calibration.stage is None
    assert cfg.calibration.fixed is None and cfg.calibration.basis is None and cfg.calibration.recipe_parameters() == {}
    assert cfg.output.dir == str(tmp_path / "pdvc_output")
    assert cfg.source == str(p.resolve())


def test_dict_paths_resolve_against_base_dir(tmp_path):
    cfg = load_config(_cfg(output={"dir": "out"}), base_dir=tmp_path)
    assert cfg.data.path == str(tmp_path / "scan")
    assert cfg.output.dir == str(tmp_path / "out")
    abs_cfg = load_config({"data": {"path": "/abs/scan"}, "geometry": CONE}, base_dir=tmp_path)
    assert abs_cfg.data.path == "/abs/scan"


def test_scalar_pixel_and_voxel_become_pairs_and_triples(tmp_path):
    cfg = load_config(_cfg(volume={"voxel_size": 0.05, "shape": [8, 9, 10]}), base_dir=tmp_path)
    assert cfg.geometry.pixel == (0.2, 0.2)
    assert cfg.volume.voxel_size == (0.05, 0.05, 0.05)
    assert cfg.volume.shape == (8, 9, 10)


# -- round trip --------------------------------------------------------------
ROUND_TRIP_CASES = [
    _cfg(),
    _cfg({"type": "cone", "sod": 50, "sdd": 80.5, "pixel": [0.1, 0.2], "det_offset": [1.5, -2],
          "angles": {"start": 10, "stop": 370, "count": 36, "endpoint": False}, "det_shape": [20, 30]}),
    _cfg({"type": "parallel", "pixel": 0.01, "angles": [0.0, 0.5, 1.25]}),
    _cfg({"type": "parallel", "pixel": 0.01, "angles": "data"}),
    _cfg({"type": "cone", "sod": 1, "odd": 2, "pixel": 0.1, "angles": "angles.txt"}),
    _cfg({"type": "vectors", "vectors": "geom.npy", "beam": "parallel", "det_shape": [4, 5]}),
    _cfg({"type": "nikon", "file": "scan.xtekct", "vendor_angles": "nominal", "vendor_offsets": False}),
    _cfg({"type": "skyscan", "file": "scan.log"}),
    _cfg(
        data={"path": "a.h5", "format": "nxtomo", "dataset": "/entry/data/data", "darks": "d.tif",
              "is_raw": True, "open_beam_columns": [0, 20], "sinogram": True},
        volume={"shape": [10, 11, 12], "voxel_size": [0.1, 0.2, 0.3], "offset": [1, 2, 3]},
        preprocess={"beam_hardening": [1, 0.05, 0.01], "roi_rows": [2, 30], "roi_cols": [0, 40], "bin": 2,
                    "flat_interpolation": "mean", "clip_min": 1e-4},
        calibration={"basis": "fourier:1", "method": "pgd", "frame": "lab", "fixed": ["ty", "rz"],
                     "center": [0, 0, 1], "scales": [8, 2], "max_outer": 3, "tol_px": 0.05, "max_modes": 3,
                     "noise_floor": 1.2, "min_gain": 0.0, "rcond": 1e-5, "fix_scale": False, "backend": "numba"},
        output={"dir": "results", "overwrite": True, "save_initial_volume": True, "volume_format": "npy",
                "exports": False, "report": False},
    ),
]


@pytest.mark.parametrize("raw", ROUND_TRIP_CASES, ids=range(len(ROUND_TRIP_CASES)))
def test_write_then_load_gives_an_equal_config(tmp_path, raw):
    cfg = load_config(raw, base_dir=tmp_path)
    path = write_config(tmp_path / "resolved.toml", cfg)
    again = load_config(path)
    assert again == cfg
    # fully resolved: the written file carries every default
    text = path.read_text()
    for key in ("recipe", "fix_scale", "volume_format", "clip_min", "offset"):
        assert key in text
    # and writing again gives the same text (stable)
    assert write_config(tmp_path / "again.toml", again).read_text() == text


def test_resolved_fills_data_dependent_values_and_round_trips(tmp_path):
    cfg = load_config(_cfg({"type": "cone", "sod": 100, "odd": 300, "pixel": 0.2, "angles": {"stop": 180}}),
                      base_dir=tmp_path)
    geom = build_geometry(cfg, n_views=12, det_shape=(16, 20))
    vol = build_volume_geometry(cfg, geom)
    res = cfg.resolved(n_views=12, det_shape=(16, 20), vol_geom=vol)
    assert res.geometry.angles == AngleRange(0.0, 180.0, 12, False)
    assert res.geometry.det_shape == (16, 20)
    assert res.volume.shape == vol.shape and res.volume.voxel_size == vol.voxel_size
    assert load_config(write_config(tmp_path / "r.toml", res)) == res
    # the resolved config alone rebuilds the same geometry and grid
    assert build_geometry(res) == geom
    assert build_volume_geometry(res, geom) == vol
    with pytest.raises(GeometryError, match="det_shape"):
        res.resolved(det_shape=(16, 21))


def test_resolved_with_explicit_angles_writes_degrees(tmp_path):
    cfg = load_config(_cfg(), base_dir=tmp_path)
    rad = np.linspace(0, np.pi, 7)
    res = cfg.resolved(angles=rad)
    assert res.geometry.angles == tuple(np.rad2deg(rad))
    np.testing.assert_allclose(resolve_angles(res.geometry.angles, 7), rad, rtol=0, atol=1e-15)


def test_the_documented_example_file_loads(tmp_path):
    import pdvc.io._config as mod

    doc = mod.__doc__
    block = doc.split(".. code-block:: toml", 1)[1].split("Default volume", 1)[0]
    p = _write(tmp_path, block)
    cfg = load_config(p)
    assert cfg.geometry.sdd == 1000.0 and cfg.geometry.angles == "auto"
    assert load_config(write_config(tmp_path / "w.toml", cfg)) == cfg


def test_config_equality_ignores_source(tmp_path):
    p = _write(tmp_path, '[data]\npath = "s"\n[geometry]\ntype = "parallel"\npixel = 1\n')
    assert load_config(p) == load_config({"data": {"path": "s"}, "geometry": {"type": "parallel", "pixel": 1}},
                                         base_dir=tmp_path)


# -- errors ------------------------------------------------------------------
def test_unknown_key_lists_the_allowed_ones(tmp_path):
    with pytest.raises(ConfigError) as err:
        load_config(_cfg({**CONE, "sdo": 5}), base_dir=tmp_path)
    msg = str(err.value)
    assert "'sdo'" in msg and "[geometry]" in msg and "sod" in msg and "pixel" in msg


def test_unknown_section_is_an_error(tmp_path):
    with pytest.raises(ConfigError, match=r"unknown section \[geometri\].*\[geometry\]"):
        load_config({**_cfg(), "geometri": {}}, base_dir=tmp_path)


def test_key_of_another_geometry_type_is_named(tmp_path):
    with pytest.raises(ConfigError, match=r"geometry\.sod is not used with type = 'nikon'.*file"):
        load_config(_cfg({"type": "nikon", "file": "a.xtekct", "sod": 3}), base_dir=tmp_path)


@pytest.mark.parametrize(
    "section, key, value, pattern",
    [
        ("geometry", "sod", "100", r"geometry\.sod must be a number, got '100' \(string\)"),
        ("geometry", "pixel", [0.1, 0.2, 0.3], r"geometry\.pixel must be a number or a pair \[row, col\]"),
        ("geometry", "det_offset", True, r"geometry\.det_offset must be a pair"),
        ("data", "sinogram", "no", r"data\.sinogram must be true or false, got 'no' \(string\)"),
        ("data", "format", "tif", r"data\.format must be one of 'auto', 'tiff-folder'"),
        ("data", "is_raw", "yes", r"data\.is_raw must be true, false or \"auto\""),
        ("preprocess", "bin", 1.5, r"preprocess\.bin must be an integer, got 1\.5 \(float\)"),
        ("preprocess", "roi_rows", [5, 2], r"preprocess\.roi_rows must be a range \[a, b\)"),
        ("preprocess", "clip_min", 1.0, r"preprocess\.clip_min must be below 1"),
        ("calibration", "basis", "fourier", r"calibration\.basis must be one of 'dirac'"),
        ("calibration", "fixed", ["tx", "yaw"], r"calibration\.fixed\[1\] must be one of 'tx'"),
        ("calibration", "scales", [2, 4], r"calibration\.scales must be strictly decreasing"),
        ("calibration", "max_outer", 0, r"calibration\.max_outer must be an integer >= 1, got 0"),
        ("calibration", "oversample_by", "zoom", r"calibration\.oversample_by must be one of 'spline', 'reconstruction'"),
        ("calibration", "accelerate", "yes", r"calibration\.accelerate must be true or false, got 'yes' \(string\)"),
        ("calibration", "extrapolate", 1, r"calibration\.extrapolate must be true or false, got 1 \(integer\)"),
        ("volume", "shape", [1, 10, 10], r"volume\.shape\[0\] must be an integer >= 2"),
        ("volume", "voxel_size", -0.1, r"volume\.voxel_size\[0\] must be positive"),
        ("output", "volume_format", "raw", r"output\.volume_format must be one of"),
    ],
)
def test_type_and_range_errors_name_key_expected_and_got(tmp_path, section, key, value, pattern):
    raw = _cfg()
    raw.setdefault(section, {})
    raw[section] = {**raw[section], key: value}
    with pytest.raises(ConfigError, match=pattern):
        load_config(raw, base_dir=tmp_path)


def test_required_keys(tmp_path):
    with pytest.raises(ConfigError, match=r"data\.path is required"):
        load_config({"data": {}, "geometry": CONE}, base_dir=tmp_path)
    with pytest.raises(ConfigError, match=r"geometry\.type is required"):
        load_config({"data": {"path": "x"}, "geometry": {}}, base_dir=tmp_path)
    with pytest.raises(ConfigError, match=r"\[geometry\] is required"):
        load_config({"data": {"path": "x"}}, base_dir=tmp_path)
    with pytest.raises(ConfigError, match=r"geometry\.pixel is required"):
        load_config(_cfg({"type": "cone", "sod": 1, "odd": 1}), base_dir=tmp_path)
    with pytest.raises(ConfigError, match="not both"):
        load_config(_cfg({**CONE, "sdd": 400}), base_dir=tmp_path)


@pytest.mark.parametrize(
    "geometry, pattern",
    [
        ({**CONE, "sod": 0}, r"geometry\.sod must be positive"),
        ({**CONE, "sod": -5}, r"geometry\.sod must be positive"),
        ({**CONE, "pixel": 0}, r"geometry\.pixel\[0\] must be positive"),
        ({**CONE, "pixel": [0.1, -0.1]}, r"geometry\.pixel\[1\] must be positive"),
        ({"type": "cone", "sod": 100, "sdd": 100, "pixel": 1}, r"sdd .* must exceed geometry\.sod"),
        ({"type": "cone", "sod": 100, "sdd": 50, "pixel": 1}, r"must exceed"),
        ({"type": "cone", "sod": 100, "odd": -150, "pixel": 1}, r"source would be on or behind the detector"),
        ({"type": "cone", "sod": 100, "odd": 0, "pixel": 1}, r"geometry\.odd must be positive"),
        ({**CONE, "angles": []}, r"at least one angle"),
    ],
)
def test_degenerate_geometry_is_a_geometry_error(tmp_path, geometry, pattern):
    with pytest.raises(GeometryError, match=pattern) as err:
        load_config(_cfg(geometry), base_dir=tmp_path)
    assert isinstance(err.value, ConfigError)


def test_invalid_toml_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(_write(tmp_path, "[data\npath = 1\n"))
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "nope.toml")


# -- angles and geometry -----------------------------------------------------
def test_angle_range_count_and_endpoint():
    np.testing.assert_allclose(np.rad2deg(resolve_angles(AngleRange(0, 360, 4))), [0, 90, 180, 270])
    np.testing.assert_allclose(np.rad2deg(resolve_angles(AngleRange(0, 180, 3, True))), [0, 90, 180])
    np.testing.assert_allclose(np.rad2deg(resolve_angles(AngleRange(10, 20), n_views=2)), [10, 15])
    with pytest.raises(GeometryError, match="without count"):
        resolve_angles(AngleRange(0, 360))


def test_auto_and_data_angles():
    data = np.array([0.1, 0.2, 0.4])
    np.testing.assert_array_equal(resolve_angles("auto", 3, data_angles=data), data)
    np.testing.assert_array_equal(resolve_angles("data", 3, data_angles=data), data)
    np.testing.assert_allclose(resolve_angles("auto", 4), np.deg2rad([0, 90, 180, 270]))
    np.testing.assert_allclose(resolve_angles("auto", 4, kind="parallel"), np.deg2rad([0, 45, 90, 135]))
    with pytest.raises(GeometryError, match="carry no angles"):
        resolve_angles("data", 3)
    with pytest.raises(GeometryError, match="carry 3 angles but there are 4"):
        resolve_angles("auto", 4, data_angles=data)


def test_angles_from_text_and_npy_files(tmp_path):
    (tmp_path / "a.txt").write_text("# degrees\n0\n1.5\n3.0\n")
    np.save(tmp_path / "a.npy", np.array([0.0, 1.5, 3.0]))
    for name in ("a.txt", "a.npy"):
        cfg = load_config(_cfg({**CONE, "angles": name}), base_dir=tmp_path)
        np.testing.assert_allclose(resolve_angles(cfg.geometry.angles, 3), np.deg2rad([0, 1.5, 3.0]))
    (tmp_path / "b.txt").write_text("0 1\n2 3\n")
    with pytest.raises(ConfigError, match="one angle per projection"):
        resolve_angles(str(tmp_path / "b.txt"))


def test_cone_config_builds_the_nominal_circular_scan(tmp_path):
    cfg = load_config(_cfg({"type": "cone", "sod": 100, "sdd": 400, "pixel": [0.3, 0.2], "det_offset": [1, -2],
                            "angles": {"start": 0, "stop": 360}}), base_dir=tmp_path)
    g = build_geometry(cfg, n_views=8, det_shape=(10, 12))
    th = np.deg2rad(np.arange(8) * 45.0)
    ref = circular_cone(th, sod=100, odd=300, det_shape=(10, 12), pixel=(0.3, 0.2), det_offset=(1, -2))
    assert g == ref
    # DESIGN §1 at view 1 (45 deg): src = (SOD sin, -SOD cos, 0)
    np.testing.assert_allclose(g.src[1], [100 * math.sin(th[1]), -100 * math.cos(th[1]), 0], atol=1e-12)


def test_parallel_config_and_angle_count_mismatch(tmp_path):
    cfg = load_config(_cfg({"type": "parallel", "pixel": 0.5, "angles": [0, 30, 60]}), base_dir=tmp_path)
    g = build_geometry(cfg, n_views=3, det_shape=(4, 6))
    assert g == parallel(np.deg2rad([0, 30, 60]), det_shape=(4, 6), pixel=0.5)
    with pytest.raises(GeometryError, match="gives 3 angles but there are 4 projections"):
        build_geometry(cfg, n_views=4, det_shape=(4, 6))
    with pytest.raises(GeometryError, match="needs the detector shape"):
        build_geometry(cfg, n_views=3)


def test_det_shape_in_config_is_checked_against_the_data(tmp_path):
    cfg = load_config(_cfg({**CONE, "det_shape": [10, 12]}), base_dir=tmp_path)
    assert build_geometry(cfg, n_views=5).det_shape == (10, 12)
    with pytest.raises(GeometryError, match=r"det_shape is \[10, 12\] but the projections are \[10, 13\]"):
        build_geometry(cfg, n_views=5, det_shape=(10, 13))


def test_vectors_config_from_npy_and_text(tmp_path):
    ref = circular_cone(np.linspace(0, 1, 4), sod=10, odd=20, det_shape=(3, 5), pixel=0.1)
    np.save(tmp_path / "g.npy", ref.vectors)
    np.savetxt(tmp_path / "g.txt", ref.vectors, fmt="%.17g")
    for name in ("g.npy", "g.txt"):
        cfg = load_config(_cfg({"type": "vectors", "vectors": name, "det_shape": [3, 5]}), base_dir=tmp_path)
        assert build_geometry(cfg, n_views=4) == ref
    with pytest.raises(GeometryError, match="holds 4 views but there are 5"):
        build_geometry(cfg, n_views=5)
    np.save(tmp_path / "bad.npy", np.zeros((4, 9)))
    bad = load_config(_cfg({"type": "vectors", "vectors": "bad.npy"}), base_dir=tmp_path)
    with pytest.raises(ConfigError, match=r"\(n_views, 12\)"):
        build_geometry(bad, det_shape=(3, 5))


# -- volume ------------------------------------------------------------------
def test_default_volume_is_magnified_pixel_and_detector_shape(tmp_path):
    cfg = load_config(_cfg({"type": "cone", "sod": 100, "odd": 300, "pixel": [0.4, 0.2]}), base_dir=tmp_path)
    g = build_geometry(cfg, n_views=6, det_shape=(10, 14))
    vol = build_volume_geometry(cfg, g)
    assert vol.shape == (10, 14, 14)
    np.testing.assert_allclose(vol.voxel_size, (0.4 / 4, 0.2 / 4, 0.2 / 4), rtol=1e-12)
    assert vol.offset == (0.0, 0.0, 0.0)


def test_default_volume_parallel_and_explicit_values(tmp_path):
    cfg = load_config(_cfg({"type": "parallel", "pixel": 0.3}, volume={"offset": [1, 2, 3]}), base_dir=tmp_path)
    g = build_geometry(cfg, n_views=4, det_shape=(5, 7))
    vol = build_volume_geometry(cfg, g)
    assert vol.voxel_size == (0.3, 0.3, 0.3) and vol.shape == (5, 7, 7) and vol.offset == (1.0, 2.0, 3.0)
    cfg2 = load_config(_cfg({"type": "parallel", "pixel": 0.3}, volume={"shape": [4, 5, 6], "voxel_size": [1, 2, 3]}),
                       base_dir=tmp_path)
    vol2 = build_volume_geometry(cfg2, g)
    assert vol2 == VolumeGeometry((4, 5, 6), (1.0, 2.0, 3.0))
    dflt = VolumeGeometry((8, 8, 8), 0.7)
    assert build_volume_geometry(cfg.volume, g, defaults=dflt).voxel_size == (0.7, 0.7, 0.7)


def test_default_voxel_follows_magnification_of_moved_views(tmp_path):
    # Detector moved 100 mm further away in every view: magnification 5 instead of 4.
    g = circular_cone(np.linspace(0, 6, 9), sod=100, odd=400, det_shape=(8, 8), pixel=0.5)
    vol = build_volume_geometry(load_config(_cfg(), base_dir=tmp_path).volume, g)
    np.testing.assert_allclose(vol.voxel_size, (0.1, 0.1, 0.1), rtol=1e-12)


# -- coverage ----------------------------------------------------------------
def _scan():
    return circular_cone(np.linspace(0, 2 * np.pi, 12, endpoint=False), sod=100, odd=100, det_shape=(40, 40), pixel=0.5)


def test_coverage_full_partial_and_warning(caplog):
    g = _scan()  # magnification 2: the detector sees a 10 mm wide field at the axis
    assert check_coverage(g, VolumeGeometry((10, 10, 10), 0.5)) == pytest.approx(1.0)
    with caplog.at_level(logging.WARNING):
        frac = check_coverage(g, VolumeGeometry((10, 30, 30), 1.0))
    assert 0 < frac < 0.5
    assert "mostly outside the detector" in caplog.text


def test_coverage_errors_when_the_volume_misses_or_holds_the_source():
    g = _scan()
    with pytest.raises(GeometryError, match="misses the detector completely"):
        check_coverage(g, VolumeGeometry((4, 4, 4), 0.5, offset=(0.0, 0.0, 60.0)))
    with pytest.raises(GeometryError, match="reaches the source plane"):
        check_coverage(g, VolumeGeometry((10, 10, 10), 25.0))


def test_coverage_partial_fraction_is_the_overlap_ratio():
    # parallel beam, a box twice as tall as the detector, fully inside horizontally
    g = parallel([0.0, 0.5], det_shape=(10, 20), pixel=1.0)
    frac = check_coverage(g, VolumeGeometry((20, 4, 4), 1.0))
    assert frac == pytest.approx(0.5, rel=1e-9)


def test_extrapolate_reaches_the_model_stage(tmp_path):
    from pdvc.calibration import recipe_stages

    raw = _cfg()
    raw["calibration"] = {"extrapolate": True}
    cfg = load_config(raw, base_dir=tmp_path)
    assert cfg.calibration.recipe_parameters() == {"extrapolate": True}
    stages = recipe_stages(det_shape=(64, 64), **cfg.calibration.recipe_parameters())
    assert [s.extrapolate for s in stages if s.name == "model"] == [True]


def test_roi_is_read_defaults_to_auto_and_reaches_calibrate(tmp_path):
    from pdvc._inputs import calibration_options

    assert load_config(_cfg(), base_dir=tmp_path).calibration.roi == "auto"
    cfg = load_config(_cfg(calibration={"roi": "on"}), base_dir=tmp_path)
    assert cfg.calibration.roi == "on"
    assert calibration_options(cfg.calibration, (64, 64))["roi"] == "on"
    with pytest.raises(ConfigError, match="roi"):
        load_config(_cfg(calibration={"roi": "yes"}), base_dir=tmp_path)


def test_robust_reaches_every_stage_and_zero_turns_it_off(tmp_path):
    from pdvc.calibration import Stage, StageError, recipe_stages

    assert Stage().robust is None  # least squares by default
    raw = _cfg()
    raw["calibration"] = {"robust": 5}
    cfg = load_config(raw, base_dir=tmp_path)
    assert cfg.calibration.recipe_parameters() == {"robust": 5.0}
    stages = recipe_stages(det_shape=(64, 64), **cfg.calibration.recipe_parameters())
    assert {s.robust for s in stages} == {5.0}  # warm-up and jolts too
    raw["calibration"] = {"robust": 0}
    stages = recipe_stages(det_shape=(64, 64), **load_config(raw, base_dir=tmp_path).calibration.recipe_parameters())
    assert {s.robust for s in stages} == {None}
    assert {s.robust for s in recipe_stages(det_shape=(64, 64))} == {None}
    # a stage list round-trips through its TOML tables (0 for none)
    for r in (None, 2.5):
        st = Stage(robust=r)
        assert Stage.from_dict(st.to_dict()).robust == r
    for bad in (-1, "4", True, float("nan")):
        with pytest.raises(StageError, match="robust"):
            Stage(robust=bad)
    raw["calibration"] = {"robust": -1}
    with pytest.raises(ConfigError, match=r"calibration\.robust must be zero or positive"):
        load_config(raw, base_dir=tmp_path)
    raw["calibration"] = {"robust": "huber"}
    with pytest.raises(ConfigError, match=r"calibration\.robust must be a number"):
        load_config(raw, base_dir=tmp_path)
