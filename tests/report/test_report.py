"""Report package: figures, HTML page, motion.csv and result.h5."""

from __future__ import annotations

import csv
import math
import re

import h5py
import numpy as np
import pytest
from matplotlib.collections import PolyCollection
from matplotlib.container import BarContainer
from matplotlib.figure import Figure

from pdvc.errors import InputTypeError, ShapeError
from pdvc.report import (
    MOTION_COLUMNS,
    ReportError,
    axis_trajectory_figure,
    pose_figure,
    read_motion_csv,
    read_result_h5,
    residual_maps_figure,
    slices_figure,
    snr_modes_table,
    snr_per_view_figure,
    spatial_modes_figure,
    temporal_modes_figure,
    write_motion_csv,
    write_report,
    write_result_h5,
)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _leftovers(folder):
    """Temporary files of atomic_path (".<name>.<random>.tmp") left in ``folder``."""
    return [p.name for p in folder.iterdir() if p.name.endswith(".tmp")]


def _images(fig):
    return [im for ax in fig.axes for im in ax.get_images()]


# --------------------------------------------------------------------------- motion.csv


@pytest.fixture
def motion(rng):
    n = 37
    angles = np.linspace(0.0, 360.0, n, endpoint=False)
    # values spanning magnitudes and signs, so that a lossy format would show
    ps = rng.normal(0, 1, (n, 6)) * np.array([3.0, 1e-3, 250.0, 1e-4, 0.02, 1.3])
    pl = rng.normal(0, 1, (n, 6)) * np.array([1e-7, 5.0, 0.3, 2e-3, 1e-6, 0.7])
    std = np.abs(rng.normal(0, 1, (n, 6))) * 1e-3
    return dict(
        angles_deg=angles,
        times=np.cumsum(rng.uniform(0.9, 1.1, n)),
        params_sample=ps,
        params_lab=pl,
        std=std,
        snr_before=rng.uniform(15, 25, n),
        snr_after=rng.uniform(25, 35, n),
    )


def test_motion_csv_round_trip_exact(tmp_path, motion):
    path = write_motion_csv(tmp_path / "motion.csv", **motion)
    assert _leftovers(tmp_path) == []
    with open(path, newline="") as fh:
        header = next(csv.reader(fh))
    assert tuple(header) == MOTION_COLUMNS
    assert {"index", "angle_deg", "time", "tx_sample", "rz_sample_deg", "ty_lab", "rx_lab_deg",
            "std_tz", "std_ry_deg", "snr_before_db", "snr_after_db"} <= set(header)

    got = read_motion_csv(path)
    n = motion["angles_deg"].size
    assert list(got) == list(MOTION_COLUMNS)
    assert got["index"].dtype == np.int64
    np.testing.assert_array_equal(got["index"], np.arange(n))
    np.testing.assert_array_equal(got["angle_deg"], motion["angles_deg"])
    np.testing.assert_array_equal(got["time"], motion["times"])
    for frame, key in (("sample", "params_sample"), ("lab", "params_lab")):
        p = motion[key]
        for j, t in enumerate(("tx", "ty", "tz")):
            np.testing.assert_array_equal(got[f"{t}_{frame}"], p[:, j])  # volume units, unchanged
        for j, r in enumerate(("rx", "ry", "rz")):
            # rad -> deg exactly as np.degrees does it, and repr round-trips the double
            np.testing.assert_array_equal(got[f"{r}_{frame}_deg"], np.degrees(p[:, 3 + j]))
    np.testing.assert_array_equal(got["std_tx"], motion["std"][:, 0])
    np.testing.assert_array_equal(got["std_rz_deg"], np.degrees(motion["std"][:, 5]))
    np.testing.assert_array_equal(got["snr_before_db"], motion["snr_before"])
    np.testing.assert_array_equal(got["snr_after_db"], motion["snr_after"])


def test_motion_csv_optional_columns_are_nan(tmp_path, motion):
    path = write_motion_csv(
        tmp_path / "m.csv",
        angles_deg=motion["angles_deg"],
        times=None,
        params_sample=motion["params_sample"],
        params_lab=motion["params_lab"],
    )
    got = read_motion_csv(path)
    assert list(got) == list(MOTION_COLUMNS)  # same columns whatever was given
    for name in ("time", "std_tx", "std_rz_deg", "snr_before_db", "snr_after_db"):
        assert np.isnan(got[name]).all(), name
    np.testing.assert_array_equal(got["tz_sample"], motion["params_sample"][:, 2])


def test_motion_csv_shape_errors_leave_no_file(tmp_path, motion):
    bad = dict(motion, params_lab=motion["params_lab"][:, :5])
    with pytest.raises(ShapeError, match="params_lab"):
        write_motion_csv(tmp_path / "m.csv", **bad)
    bad = dict(motion, snr_after=motion["snr_after"][:-1])
    with pytest.raises(ShapeError, match="snr_after"):
        write_motion_csv(tmp_path / "m.csv", **bad)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- result.h5


def test_result_h5_round_trip_nested(tmp_path, rng):
    big = rng.normal(size=(40, 6)).astype(np.float32)  # 240 elements
    huge = rng.normal(size=(30, 50))  # 1500 > 1000 -> gzip
    tree = {
        "version": "0.1.0",
        "gauge": "zero mean pose over the views",
        "chi": 1.0234,
        "n_modes": 3,
        "converged": True,
        "skipped": None,
        "poses": {"sample": big, "lab": huge, "frame": "lab", "labels": ["tx", "ty", "tz"]},
        "history": [0.5, 0.25, 0.125],
        "matrix": [[1, 2], [3, 4]],
        "modes": [
            {"spatial": np.arange(6.0), "chi": 1.5, "basis": "fourier"},
            {"spatial": np.ones(6), "chi": 1.1, "basis": "dirac", "extra": {"cond": 12.5}},
        ],
        "empty": {},
        "scalar64": np.float64(2.5),
        "count": np.int32(7),
    }
    path = write_result_h5(tmp_path / "result.h5", tree)
    assert _leftovers(tmp_path) == []
    got = read_result_h5(path)

    assert "skipped" not in got
    assert got["version"] == "0.1.0" and isinstance(got["version"], str)
    assert got["gauge"] == tree["gauge"]
    assert got["chi"] == 1.0234
    assert got["n_modes"] == 3 and isinstance(got["n_modes"], int)
    assert got["converged"] is True
    assert got["scalar64"] == 2.5
    assert got["count"] == 7
    np.testing.assert_array_equal(got["poses"]["sample"], big)
    assert got["poses"]["sample"].dtype == np.float32
    np.testing.assert_array_equal(got["poses"]["lab"], huge)
    assert got["poses"]["frame"] == "lab"
    assert list(got["poses"]["labels"]) == ["tx", "ty", "tz"]
    np.testing.assert_array_equal(got["history"], [0.5, 0.25, 0.125])
    assert isinstance(got["history"], np.ndarray)
    np.testing.assert_array_equal(got["matrix"], [[1, 2], [3, 4]])
    assert isinstance(got["modes"], list) and len(got["modes"]) == 2
    np.testing.assert_array_equal(got["modes"][0]["spatial"], np.arange(6.0))
    assert got["modes"][0]["basis"] == "fourier"
    assert got["modes"][1]["extra"] == {"cond": 12.5}
    assert got["empty"] == {}

    with h5py.File(path, "r") as fh:
        assert fh["poses/lab"].compression == "gzip"
        assert fh["poses/sample"].compression is None
        assert set(fh["modes"].keys()) == {"0", "1"}
        assert fh.attrs["version"] == "0.1.0"


def test_result_h5_long_string_and_list_with_none(tmp_path):
    text = "x" * 40_000 + "<end>"
    tree = {"config": text, "steps": [{"a": 1}, None, {"b": 2.0}]}
    got = read_result_h5(write_result_h5(tmp_path / "r.h5", tree))
    assert got["config"] == text
    assert got["steps"] == [{"a": 1}, None, {"b": 2.0}]


def test_result_h5_bad_value_leaves_no_file(tmp_path):
    with pytest.raises(InputTypeError, match="/a/bad"):
        write_result_h5(tmp_path / "r.h5", {"a": {"ok": 1.0, "bad": object()}})
    with pytest.raises(InputTypeError, match="key"):
        write_result_h5(tmp_path / "r.h5", {"a/b": 1.0})
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- figures


def test_snr_per_view_figure_legend_gives_means():
    ang = np.linspace(0, 360, 72, endpoint=False)
    before = 20 + 2 * np.sin(np.radians(ang))
    after = 28 + 0.5 * np.cos(np.radians(3 * ang))
    before[5] = np.nan  # a view without a value must not turn the mean into NaN
    fig = snr_per_view_figure(ang, before, after)
    assert isinstance(fig, Figure)
    assert len(fig.axes) == 1
    ax = fig.axes[0]
    assert len(ax.get_lines()) == 2
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    assert f"{np.nanmean(before):.2f}" in texts[0] and "before" in texts[0]
    assert f"{after.mean():.2f}" in texts[1] and "after" in texts[1]
    np.testing.assert_array_equal(ax.get_lines()[1].get_ydata(), after)
    with pytest.raises(ShapeError, match="snr_after"):
        snr_per_view_figure(ang, before, after[:-1])


def test_temporal_modes_figure_panels_and_free_dots():
    n_views = 50
    x = np.arange(n_views)
    alphas = np.stack([np.sin(x / 8), np.cos(x / 5), x / x.max()])
    free = alphas + 0.05
    free[2] = np.nan  # mode 3 has no free history
    fig = temporal_modes_figure(x, alphas, free, xlabel="angle (deg)")
    assert len(fig.axes) == 3
    for l, ax in enumerate(fig.axes):
        lines = [ln for ln in ax.get_lines() if ln.get_linestyle() == "-" and ln.get_label() == "constrained"]
        dots = [ln for ln in ax.get_lines() if ln.get_marker() == "."]
        assert len(lines) == 1
        np.testing.assert_array_equal(lines[0].get_ydata(), alphas[l])
        assert len(dots) == (0 if l == 2 else 1)
    assert fig.axes[-1].get_xlabel() == "angle (deg)"
    with pytest.raises(ShapeError, match="alphas_free"):
        temporal_modes_figure(x, alphas, free[:2])
    assert len(temporal_modes_figure(None, np.zeros((0, n_views))).axes) == 1


def test_spatial_modes_figure_bars_in_degrees():
    spatial = np.array([[1.0, -2.0, 0.5, 0.01, 0.0, -0.02], [0.1, 0.2, 0.3, 0.001, 0.002, 0.003]])
    fig = spatial_modes_figure(spatial)
    assert len(fig.axes) == 2
    ax_t, ax_r = fig.axes
    bars_t = [c for c in ax_t.containers if isinstance(c, BarContainer)]
    bars_r = [c for c in ax_r.containers if isinstance(c, BarContainer)]
    assert len(bars_t) == len(bars_r) == 2  # one group member per mode
    np.testing.assert_allclose([b.get_height() for b in bars_t[0]], spatial[0, :3])
    np.testing.assert_allclose([b.get_height() for b in bars_r[1]], np.degrees(spatial[1, 3:]))
    assert [t.get_text() for t in ax_r.get_xticklabels()] == ["rx", "ry", "rz"]
    assert [t.get_text() for t in ax_r.get_legend().get_texts()] == ["mode 1", "mode 2"]


def test_pose_figure_degrees_and_bands(rng):
    n = 30
    params = rng.normal(0, 1, (n, 6)) * [1, 1, 1, 0.01, 0.01, 0.01]
    std = np.full((n, 6), 0.1) * [1, 1, 1, 0.001, 0.001, 0.001]
    fig = pose_figure(np.arange(n), params, std, frame="sample")
    assert len(fig.axes) == 6
    for j, ax in enumerate(fig.axes):
        y = ax.get_lines()[0].get_ydata()
        np.testing.assert_allclose(y, params[:, j] if j < 3 else np.degrees(params[:, j]))
        assert sum(isinstance(c, PolyCollection) for c in ax.collections) == 1
    assert fig.axes[3].get_title().endswith("(deg)")
    plain = pose_figure(None, params)
    assert all(len(ax.collections) == 0 for ax in plain.axes)
    with pytest.raises(ValueError, match="frame"):
        pose_figure(None, params, frame="detector")


def test_residual_maps_share_one_symmetric_scale(rng):
    before = rng.normal(0, 1.0, (2, 24, 32))
    after = rng.normal(0, 0.1, (2, 24, 32))
    fig = residual_maps_figure(before, after, ["θ = 90°", "θ = 330°"])
    ims = _images(fig)
    assert len(ims) == 4
    assert len(fig.axes) == 5  # 4 images + 1 colour bar
    clims = {im.get_clim() for im in ims}
    assert len(clims) == 1  # exactly the same limits everywhere
    lo, hi = clims.pop()
    assert lo == -hi
    assert hi == pytest.approx(np.percentile(np.abs(before), 99))
    titles = [ax.get_title() for ax in fig.axes[:4]]
    assert "before: θ = 90°" in titles and "after: θ = 330°" in titles
    with pytest.raises(ShapeError, match="titles"):
        residual_maps_figure(before, after, ["one"])
    with pytest.raises(ShapeError, match="after"):
        residual_maps_figure(before, after[:, :10])


def test_slices_share_grey_scale_of_after(rng):
    vb = rng.normal(0, 1.0, (12, 14, 16)).astype(np.float32)
    va = rng.normal(0.5, 0.2, (12, 14, 16)).astype(np.float32)
    fig = slices_figure(vb, va)
    ims = _images(fig)
    assert len(ims) == 4
    clims = {im.get_clim() for im in ims}
    assert len(clims) == 1
    lo, hi = clims.pop()
    elo, ehi = np.percentile(va.astype(np.float64), (0.5, 99.5))
    assert (lo, hi) == pytest.approx((elo, ehi))
    np.testing.assert_array_equal(ims[0].get_array(), vb[6])  # axial z = nz // 2 of 'before'
    np.testing.assert_array_equal(ims[3].get_array(), va[:, 7, :])  # vertical y = ny // 2 of 'after'
    with pytest.raises(ShapeError, match="vol_after"):
        slices_figure(vb, va[0])


def test_axis_trajectory_figure():
    ang = np.linspace(0, 360, 40, endpoint=False)
    t = np.radians(ang)
    top = np.stack([0.1 * np.sin(t), 2.0 * np.cos(t)], axis=1)
    centre = np.zeros((40, 2))
    bottom = -top
    fig = axis_trajectory_figure(ang, top, centre, bottom)
    assert len(fig.axes) == 3
    ax_col, ax_row, ax_det = fig.axes
    np.testing.assert_array_equal(ax_col.get_lines()[0].get_ydata(), top[:, 1])
    np.testing.assert_array_equal(ax_row.get_lines()[2].get_ydata(), bottom[:, 0])
    np.testing.assert_array_equal(ax_det.get_lines()[0].get_xdata(), top[:, 1])
    np.testing.assert_array_equal(ax_det.get_lines()[0].get_ydata(), top[:, 0])
    assert ax_det.yaxis_inverted()  # rows go down, as in the images
    with pytest.raises(ShapeError, match="centre"):
        axis_trajectory_figure(ang, top, centre[:, :1], bottom)


def test_snr_modes_table():
    header, rows = snr_modes_table([(0, 3.2, 24.5), (1, 1.8, 29.04), (3, 1.02, 31.456)])
    assert header == ("modes", "chi", "mean SNR (dB)")
    assert rows == [("0", "3.2", "24.50"), ("1", "1.8", "29.04"), ("3", "1.02", "31.46")]
    with pytest.raises(ShapeError):
        snr_modes_table([(1, 2.0)])


# --------------------------------------------------------------------------- HTML


def _small_figures():
    ang = np.linspace(0, 360, 20, endpoint=False)
    rng = np.random.default_rng(3)
    return {
        "snr_per_view": snr_per_view_figure(ang, 20 + 0 * ang, 25 + 0 * ang),
        "residuals": residual_maps_figure(rng.normal(size=(2, 8, 8)), rng.normal(size=(2, 8, 8)), ["a", "b"]),
        "pose_lab": pose_figure(None, rng.normal(size=(20, 6)) * 0.01),
    }


def test_write_report_page_and_pngs(tmp_path):
    figs = _small_figures()
    header, rows = snr_modes_table([(0, 3.2, 24.5), (3, 1.02, 31.25)])
    out = tmp_path / "report"
    path = write_report(
        out,
        title="Scan <A> & B",
        summary={"chi after": 1.0234567, "mean SNR before (dB)": 24.5, "gauge": "zero mean pose", "views": 720},
        figures=figs,
        tables={"snr_modes": (header, rows)},
        sections=["pose_lab", "snr_modes"],
        notes=["translation along the beam is unobservable: 1 < 2"],
    )
    assert path == out / "report.html"
    text = path.read_text(encoding="utf-8")
    for name in figs:
        assert f'<img src="{name}.png">' in text
        data = (out / f"{name}.png").read_bytes()
        assert data.startswith(PNG_SIGNATURE)
        assert len(data) > 1000
    # summary first, with its values
    assert text.index("chi after") < text.index("<img")
    assert "1.02346" in text and "24.5" in text and "zero mean pose" in text and ">720<" in text
    # text is escaped
    assert "1 &lt; 2" in text and "1 < 2" not in text
    assert "Scan &lt;A&gt; &amp; B" in text
    # sections in the asked order, the rest after
    assert text.index('<img src="pose_lab.png">') < text.index("31.25") < text.index('<img src="snr_per_view.png">')
    assert text.index('<img src="snr_per_view.png">') < text.index('<img src="residuals.png">')
    assert "pdvc 0.1.0" in text or re.search(r"pdvc \d", text)
    assert re.search(r"generated \d{4}-\d{2}-\d{2}T", text)
    # figures are closed (cleared) after saving
    assert all(len(f.axes) == 0 for f in figs.values())
    assert _leftovers(out) == []


def test_write_report_failed_save_leaves_no_partial_file(tmp_path, monkeypatch):
    figs = _small_figures()
    real_savefig = Figure.savefig
    calls = []

    def failing_savefig(self, fname, *args, **kwargs):
        calls.append(fname)
        if len(calls) == 2:
            with open(fname, "wb") as fh:  # a partial PNG, then the failure
                fh.write(PNG_SIGNATURE + b"\x00" * 10)
            raise RuntimeError("disk full")
        return real_savefig(self, fname, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", failing_savefig)
    out = tmp_path / "r"
    with pytest.raises(RuntimeError, match="disk full"):
        write_report(out, title="t", summary={}, figures=figs)
    names = sorted(p.name for p in out.iterdir())
    assert names == ["snr_per_view.png"]  # the first, complete; no partial second, no page
    assert not (out / "residuals.png").exists()
    assert not (out / "report.html").exists()
    assert _leftovers(out) == []
    assert all(len(f.axes) == 0 for f in figs.values())  # closed even on failure


def test_write_report_rejects_bad_names(tmp_path):
    fig = snr_per_view_figure([0.0, 1.0], [1.0, 2.0])
    with pytest.raises(ReportError, match="names"):
        write_report(tmp_path, title="t", summary={}, figures={"../evil": fig})
    with pytest.raises(ReportError, match="section"):
        write_report(tmp_path, title="t", summary={}, figures={"ok": fig}, sections=["missing"])
    assert list(tmp_path.iterdir()) == []


def test_write_report_summary_formats_nan_and_ints(tmp_path):
    path = write_report(tmp_path, title="t", summary={"a": math.nan, "b": np.int64(3), "c": np.float32(0.5)},
                        figures={})
    text = path.read_text()
    assert ">nan<" in text and ">3<" in text and ">0.5<" in text
