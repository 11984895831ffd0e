"""Reading, normalising and binning a scan in chunks of views (issue #11, item 3).

Known answers: the chunked path gives the in-memory path's projections,
geometry, air estimate and notes (float tolerance: the only difference is
where float32 rounding happens), for TIFF folders, multi-page TIFF, HDF5
(NXtomo with flats before and after, interpolated per view) and .npy, with
flats/darks and without; and the binned geometry maps onto the full
detector (each coarse pixel centre is the centre of its fine block).
"""

import logging

import h5py
import numpy as np
import pytest
import tifffile

import pdvc
from pdvc._inputs import load_scan
from pdvc.errors import PdvcError
from pdvc.io import DataError, read_projections
from pdvc.io._chunked import chunk_views, preprocess_chunked
from pdvc.io._preprocess import Normalizer, normalize
from pdvc.io._projections import ProjectionSource, open_projections

NV, NR, NC = 30, 24, 32
# float32 rounding of line integrals up to ~5 (after a Gaussian and a block mean): a few 1e-6
ATOL = 2e-5
SMALL_CHUNK = 4 * NR * NC * 3  # 3 views a chunk: 10 chunks, the last one full


@pytest.fixture(scope="module")
def sim():
    """Counts of a small cone scan with moving sample (analytic projector), flats drifting 4 % over the scan."""
    from pdvc.simulate import cast_iron_phantom, simulate_scan, tilted_axis_poses

    angles = np.linspace(0, 2 * np.pi, NV, endpoint=False)
    geom = pdvc.circular_cone(angles, sod=120.0, odd=60.0, det_shape=(NR, NC), pixel=1.0)
    rv, t = tilted_axis_poses(angles, tilt=np.deg2rad(0.5), offset=(0.6, 0.0, 0.0))
    scan = simulate_scan(cast_iron_phantom(7.0, 12.0, n_nodules=8, seed=1), geom, rotvecs=rv, translations=t,
                         i0=4e3, seed=2, supersampling=1)
    drift = np.linspace(1.0, 1.04, NV)[:, None, None]
    counts = np.rint((scan.counts - 100.0) * drift + 100.0).astype(np.uint16)  # beam drifting during the scan
    return counts, scan.flats.astype(np.uint16), scan.darks.astype(np.uint16), scan.projections


def _toml(tmp_path, data_lines, preprocess="bin = 2", calibration=""):
    path = tmp_path / "c.toml"
    path.write_text(
        f"[data]\n{data_lines}\n[geometry]\ntype = \"cone\"\nsod = 120.0\nodd = 60.0\npixel = 1.0\n"
        f"angles = {{ start = 0, stop = 360, count = {NV} }}\n[volume]\nshape = [16, 16, 16]\nvoxel_size = 1.0\n"
        f"[preprocess]\n{preprocess}\n" + (f"[calibration]\n{calibration}\n" if calibration else "")
    )
    return path


def _write_tiff_folder(tmp_path, counts, flats, darks):
    for name, frames in (("proj", counts), ("flats", flats), ("darks", darks)):
        (tmp_path / name).mkdir()
        for k, img in enumerate(frames):
            tifffile.imwrite(tmp_path / name / f"{name}_{k}.tif", img)
    return 'path = "proj"\nflats = "flats"\ndarks = "darks"'


def _write_nxtomo(tmp_path, counts, flats, darks):
    """darks, flats before, half the views, an invalid frame, the rest, flats after (scaled 4 %: a drift)."""
    h = NV // 2
    after = np.rint(flats.astype(np.float64) * 1.04).astype(np.uint16)
    frames = np.concatenate([darks, flats[:5], counts[:h], counts[:1], counts[h:], after[5:]])
    keys = np.concatenate([np.full(len(darks), 2), np.full(5, 1), np.zeros(h), [3], np.zeros(NV - h),
                           np.full(len(flats) - 5, 1)]).astype(np.int64)
    with h5py.File(tmp_path / "scan.nxs", "w") as f:
        e = f.create_group("entry")
        e.attrs["NX_class"] = "NXentry"
        e["definition"] = "NXtomo"
        det = e.create_group("instrument").create_group("detector")
        det["data"] = frames
        det["image_key"] = keys
    return 'path = "scan.nxs"'


def _write_npy(tmp_path, counts, flats, darks):
    np.save(tmp_path / "counts.npy", counts.astype(np.float32))
    np.save(tmp_path / "flats.npy", flats.astype(np.float32))
    np.save(tmp_path / "darks.npy", darks.astype(np.float32))
    return 'path = "counts.npy"\nflats = "flats.npy"\ndarks = "darks.npy"\nis_raw = true'


def _write_npy_line_integrals(tmp_path, counts, flats, darks):
    p = -np.log((counts.astype(np.float64) - darks.mean(0)) / (flats.mean(0) - darks.mean(0)))
    np.save(tmp_path / "p.npy", p.astype(np.float32))
    return 'path = "p.npy"'


def _write_multipage(tmp_path, counts, flats, darks):
    tifffile.imwrite(tmp_path / "stack.tif", counts)
    tifffile.imwrite(tmp_path / "flats.tif", flats)
    return 'path = "stack.tif"\nflats = "flats.tif"'


WRITERS = {
    "tiff-folder": _write_tiff_folder,
    "nxtomo": _write_nxtomo,
    "npy": _write_npy,
    "npy-line-integrals": _write_npy_line_integrals,
    "tiff-stack": _write_multipage,
}


def _both(cfg, **kw):
    mem = load_scan(cfg, chunked=False, **kw)
    chk = load_scan(cfg, chunked=True, chunk_bytes=SMALL_CHUNK, **kw)
    return mem, chk


def _assert_same(mem, chk):
    assert chk.projections.shape == mem.projections.shape
    np.testing.assert_allclose(chk.projections, mem.projections, rtol=0, atol=ATOL)
    np.testing.assert_array_equal(chk.geometry.vectors, mem.geometry.vectors)
    assert chk.geometry.det_shape == mem.geometry.det_shape
    if mem.geometry_unbinned is None:
        assert chk.geometry_unbinned is None
    else:
        np.testing.assert_array_equal(chk.geometry_unbinned.vectors, mem.geometry_unbinned.vectors)
        assert chk.geometry_unbinned.det_shape == mem.geometry_unbinned.det_shape
    assert chk.vol_geom == mem.vol_geom
    assert chk.problems == mem.problems
    assert [n for n in chk.notes if not n.startswith("read in chunks")] == list(mem.notes)
    assert any(n.startswith("read in chunks") for n in chk.notes)
    assert chk.air.found == mem.air.found
    if mem.air.found:
        assert chk.air.level == pytest.approx(mem.air.level, abs=1e-6)
        np.testing.assert_allclose(chk.air.per_view, mem.air.per_view, atol=1e-6)
    assert isinstance(chk.raw, ProjectionSource) and chk.raw.kind == mem.raw.kind
    for key in ("noise_variance",):
        if key in mem.calibration_options:
            assert chk.calibration_options[key] == pytest.approx(mem.calibration_options[key], rel=1e-5)


@pytest.mark.parametrize("fmt", sorted(WRITERS))
def test_chunked_equals_in_memory_binned(tmp_path, sim, fmt):
    counts, flats, darks, _ = sim
    cfg = _toml(tmp_path, WRITERS[fmt](tmp_path, counts, flats, darks), preprocess="bin = 2")
    mem, chk = _both(cfg)
    _assert_same(mem, chk)
    assert mem.projections.shape == (NV, NR // 2, NC // 2)
    assert np.ptp(mem.projections) > 0.5  # a sample is there: the comparison is not of zeros


@pytest.mark.parametrize(
    "preprocess, calibration",
    [
        ('bin = 4\nair = "auto"\nroi_rows = [2, 22]\nroi_cols = [1, 31]', 'noise = "counts"'),
        ('bin = 2\nair = "auto"\nbeam_hardening = [1.0, 0.05]\nflat_interpolation = "mean"', ""),  # two passes
        ("bin = 3\nbeam_hardening = [1.0, 0.02, 0.01]\nclip_min = 0.5\ndead_columns = [3, 17]", ""),
        ("bin = 1", ""),
    ],
)
def test_chunked_equals_in_memory_with_options(tmp_path, sim, preprocess, calibration):
    counts, flats, darks, _ = sim
    cfg = _toml(tmp_path, _write_nxtomo(tmp_path, counts, flats, darks), preprocess=preprocess, calibration=calibration)
    mem, chk = _both(cfg)
    _assert_same(mem, chk)
    if "clip_min = 0.5" in preprocess:
        assert any("clipped" in n for n in mem.notes)  # clipping counted chunk by chunk, same count
    if "noise" in calibration:
        assert "noise_variance" in chk.calibration_options


def test_open_beam_columns_chunked(tmp_path, sim):
    counts, _, _, _ = sim
    np.save(tmp_path / "c.npy", counts)
    cfg = _toml(tmp_path, 'path = "c.npy"\nopen_beam_columns = [0, 3]', preprocess="bin = 2")
    mem, chk = _both(cfg)
    _assert_same(mem, chk)
    assert "flats from open-beam columns 0..2" in chk.notes


def test_binned_geometry_maps_to_the_full_detector(tmp_path, sim):
    """Coarse pixel (I, J) of the binned geometry sits at the centre of fine pixels sI..sI+s-1, sJ..sJ+s-1."""
    counts, flats, darks, _ = sim
    s = 4
    cfg = _toml(tmp_path, _write_npy(tmp_path, counts, flats, darks), preprocess=f"bin = {s}\nroi_cols = [1, 31]")
    scan = load_scan(cfg, chunk_bytes=SMALL_CHUNK)
    fine, coarse = scan.geometry_unbinned, scan.geometry
    assert fine.det_shape == (NR, 30) and coarse.det_shape == (NR // s, 30 // s)

    def centre(g, k, i, j):
        nr, nc = g.det_shape
        return g.det_center[k] + (j - (nc - 1) / 2) * g.u[k] + (i - (nr - 1) / 2) * g.v[k]

    for k in (0, 7, NV - 1):
        for I, J in ((0, 0), (2, 5), (5, 6)):
            block = np.mean([centre(fine, k, s * I + a, s * J + b) for a in range(s) for b in range(s)], axis=0)
            np.testing.assert_allclose(centre(coarse, k, I, J), block, atol=1e-9)
    # and the full-resolution ROI geometry is the nominal one cropped to the ROI columns
    nominal = pdvc.circular_cone(np.linspace(0, 2 * np.pi, NV, endpoint=False), sod=120.0, odd=60.0,
                                 det_shape=(NR, NC), pixel=1.0)
    np.testing.assert_allclose(fine.vectors, nominal.cropped((0, NR), (1, 31)).vectors, atol=1e-12)


def test_source_reads_what_read_projections_reads(tmp_path, sim):
    counts, flats, darks, _ = sim
    for fmt in ("tiff-folder", "nxtomo", "npy", "tiff-stack"):
        d = tmp_path / fmt
        d.mkdir()
        lines = WRITERS[fmt](d, counts, flats, darks)
        path = d / lines.split('"')[1]
        kw = {}
        if "flats" in lines:
            kw["flats"] = d / lines.split("flats = ")[1].split('"')[1]
        raw = read_projections(path, **kw)
        src = open_projections(path, **kw)
        assert type(src.views).__name__ != "_ArrayViews" or fmt == "npy"  # read lazily
        assert src.kind == raw.kind and src.det_shape == raw.det_shape and src.n_views == raw.n_views
        np.testing.assert_array_equal(src.read(0, NV), raw.data)
        np.testing.assert_array_equal(src.read_views([1, 2, 5, 29]), raw.data[[1, 2, 5, 29]])
        np.testing.assert_array_equal(src.flats, raw.flats)
        whole = src.to_raw()
        np.testing.assert_array_equal(whole.data, raw.data)
        assert whole.kind == raw.kind and whole.metadata == raw.metadata
        if raw.flat_positions is not None:
            np.testing.assert_array_equal(src.flat_positions, raw.flat_positions)


def test_normalizer_in_chunks_interpolates_flats_per_view(tmp_path, sim):
    counts, flats, darks, _ = sim
    _write_nxtomo(tmp_path, counts, flats, darks)
    raw = read_projections(tmp_path / "scan.nxs")
    assert raw.flat_positions is not None and np.unique(raw.flat_positions).size == 2
    whole, rep = normalize(raw, clip_min=0.3)
    norm = Normalizer(raw, clip_min=0.3)
    parts = np.concatenate([norm(raw.data[a : a + 7], a) for a in range(0, NV, 7)])
    np.testing.assert_array_equal(parts, whole)
    assert norm.report() == rep and rep.flat_method == "linear"
    wrong = np.concatenate([Normalizer(raw, clip_min=0.3)(raw.data[a : a + 7], 0) for a in range(0, NV, 7)])
    assert np.abs(wrong - whole).max() > 1e-3  # the view index matters: the test can fail


def test_nonfinite_error_is_the_same_in_chunks(tmp_path, sim):
    counts, flats, darks, _ = sim
    bad = counts.astype(np.float32)
    bad[4, 3, 5] = np.nan
    bad[:, :, 9] = np.inf  # a dead column
    bad[17, 0, 0] = np.nan
    np.save(tmp_path / "counts.npy", bad)
    np.save(tmp_path / "flats.npy", flats.astype(np.float32))
    cfg = _toml(tmp_path, 'path = "counts.npy"\nflats = "flats.npy"', preprocess="bin = 2")
    with pytest.raises(DataError) as mem:
        load_scan(cfg, chunked=False)
    with pytest.raises(DataError) as chk:
        load_scan(cfg, chunked=True, chunk_bytes=SMALL_CHUNK)
    assert str(chk.value) == str(mem.value)
    assert "dead columns" in str(chk.value) and "9 (" in str(chk.value)


def test_beam_hardening_check_in_chunks(tmp_path, sim):
    counts, flats, darks, _ = sim
    cfg = _toml(tmp_path, _write_npy(tmp_path, counts, flats, darks), preprocess="bin = 2\nbeam_hardening = [1.0, -2.0]")
    with pytest.raises(DataError, match="do not give an increasing correction over the range of p"):
        load_scan(cfg, chunked=False)
    with pytest.raises(DataError, match="do not give an increasing correction over the range of p"):
        load_scan(cfg, chunked=True, chunk_bytes=SMALL_CHUNK)


def test_memory_budget_decides_and_is_checked(tmp_path, sim):
    counts, flats, darks, _ = sim
    cfg = _toml(tmp_path, _write_npy(tmp_path, counts, flats, darks), preprocess="bin = 1")
    assert not isinstance(load_scan(cfg).raw, ProjectionSource)  # small: in memory
    s = load_scan(cfg, memory_budget=1000)  # over the budget: chunks, also without binning
    assert isinstance(s.raw, ProjectionSource)
    assert isinstance(load_scan(_toml(tmp_path, 'path = "counts.npy"\nflats = "flats.npy"', "bin = 2")).raw,
                      ProjectionSource)  # binning: chunks
    with pytest.raises(PdvcError, match="memory_budget must be a positive number"):
        load_scan(cfg, memory_budget=-1)
    with pytest.raises(PdvcError, match="chunked must be"):
        load_scan(cfg, chunked="yes")
    with pytest.raises(pdvc.errors.ShapeError, match="chunk_bytes must be a positive int"):
        chunk_views((NR, NC), 0)
    assert chunk_views((2048, 2048)) == 8


def test_reading_logs_progress(tmp_path, sim, caplog):
    counts, flats, darks, _ = sim
    cfg = _toml(tmp_path, _write_tiff_folder(tmp_path, counts, flats, darks))
    with caplog.at_level(logging.INFO, logger="pdvc.io"):
        load_scan(cfg, chunk_bytes=SMALL_CHUNK)
    lines = [r.getMessage() for r in caplog.records if r.name == "pdvc.io" and "MB/s" in r.getMessage()]
    assert lines and f"{NV}/{NV} views (100%)" in lines[-1]


def test_preprocess_chunked_checks_its_geometry(tmp_path, sim):
    counts, flats, darks, _ = sim
    np.save(tmp_path / "c.npy", counts)
    src = open_projections(tmp_path / "c.npy", flats=flats)
    geom = pdvc.circular_cone(np.zeros(NV - 1), sod=120.0, odd=60.0, det_shape=(NR, NC), pixel=1.0)
    with pytest.raises(pdvc.errors.ShapeError, match="geom must describe the 30 views"):
        preprocess_chunked(src, geom, scale=2)


def test_inspect_says_the_scan_was_read_in_chunks(tmp_path, sim):
    from pdvc._inputs import inspect_scan

    counts, flats, darks, _ = sim
    lines, problems = inspect_scan(_toml(tmp_path, _write_npy(tmp_path, counts, flats, darks), preprocess="bin = 2"))
    assert any(line.startswith("read in chunks of") for line in lines)
    assert any("binned 2x2" in line for line in lines)
