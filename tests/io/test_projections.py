"""Projection readers: files written here are read back exactly; every error path names its parameter."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile

from pdvc.errors import InputTypeError, PdvcError, ShapeError
from pdvc.io._projections import DataError, FormatError, InputFileError, RawScan, read_projections

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
TOOTH = DATA / "tomopy-tooth" / "tooth.h5"
NEUTRON = DATA / "sarepy-neutron360" / "sinogram_360_neutron_image.tif"


def _stack(rng, n=4, shape=(3, 5), dtype=np.uint16):
    return rng.integers(100, 60000, size=(n,) + shape).astype(dtype)


# --------------------------------------------------------------------------- TIFF


def test_tiff_folder_natural_order_and_exact_values(tmp_path, rng):
    imgs = _stack(rng, 4)
    # written in a scrambled order; names sort lexically as 1, 10, 2, 3
    for idx, k in [(10, 3), (2, 1), (1, 0), (3, 2)]:
        tifffile.imwrite(tmp_path / f"proj_{idx}.tif", imgs[k])
    (tmp_path / "notes.txt").write_text("not an image")
    raw = read_projections(tmp_path)
    assert raw.format == "tiff-folder"
    assert raw.data.dtype == np.float32 and raw.data.shape == (4, 3, 5)
    np.testing.assert_array_equal(raw.data, imgs.astype(np.float32))
    assert raw.metadata["first_file"] == "proj_1.tif" and raw.metadata["last_file"] == "proj_10.tif"
    assert raw.is_raw is True  # uint16 files are counts
    assert raw.flats is None and raw.angles is None and raw.flat_positions is None


def test_tiff_glob_selects_projections_and_flats(tmp_path, rng):
    imgs, flats = _stack(rng, 3), _stack(rng, 2)
    for k in range(3):
        tifffile.imwrite(tmp_path / f"proj_{k}.tiff", imgs[k])
    for k in range(2):
        tifffile.imwrite(tmp_path / f"flat_{k}.tiff", flats[k])
    raw = read_projections(str(tmp_path / "proj_*.tiff"), flats=str(tmp_path / "flat_*.tiff"))
    np.testing.assert_array_equal(raw.data, imgs)
    np.testing.assert_array_equal(raw.flats, flats)
    assert raw.is_raw and raw.metadata["is_raw_reason"] == "flats present"


def test_multipage_tiff_and_single_image(tmp_path, rng):
    stack = rng.normal(size=(5, 4, 6)).astype(np.float32)
    tifffile.imwrite(tmp_path / "stack.tif", stack)
    raw = read_projections(tmp_path / "stack.tif")
    assert raw.format == "tiff" and raw.data.shape == (5, 4, 6)
    np.testing.assert_array_equal(raw.data, stack)
    assert raw.is_raw is False  # float data without flats: line integrals

    tifffile.imwrite(tmp_path / "one.tif", stack[0])
    one = read_projections(tmp_path / "one.tif")
    assert one.data.shape == (1, 4, 6)
    np.testing.assert_array_equal(one.data[0], stack[0])


def test_tiff_written_page_by_page_is_stacked(tmp_path, rng):
    stack = _stack(rng, 3)
    for k in range(3):
        tifffile.imwrite(tmp_path / "pages.tif", stack[k], append=True)
    raw = read_projections(tmp_path / "pages.tif")
    np.testing.assert_array_equal(raw.data, stack)


def test_sinogram_tiff_2d_becomes_one_row(tmp_path, rng):
    sino = _stack(rng, 1, (7, 9))[0]  # (n_angles, n_cols)
    tifffile.imwrite(tmp_path / "sino.tif", sino)
    raw = read_projections(tmp_path / "sino.tif", sinogram=True)
    assert raw.data.shape == (7, 1, 9)
    np.testing.assert_array_equal(raw.data[:, 0, :], sino)


def test_tiff_folder_of_sinograms_is_transposed(tmp_path, rng):
    sinos = _stack(rng, 2, (6, 5))  # 2 rows, each (n_views=6, n_cols=5)
    for r in range(2):
        tifffile.imwrite(tmp_path / f"sino_{r}.tif", sinos[r])
    raw = read_projections(tmp_path, sinogram=True)
    assert raw.data.shape == (6, 2, 5)
    np.testing.assert_array_equal(raw.data, sinos.transpose(1, 0, 2))


def test_tiff_folder_errors(tmp_path, rng):
    with pytest.raises(InputFileError, match="no TIFF files"):
        read_projections(tmp_path)
    tifffile.imwrite(tmp_path / "a_1.tif", _stack(rng, 1)[0])
    tifffile.imwrite(tmp_path / "a_2.tif", _stack(rng, 1, (4, 5))[0])
    with pytest.raises(ShapeError, match=r"'a_2.tif' has shape \(4, 5\)"):
        read_projections(tmp_path)


def test_unreadable_tiff_is_an_input_file_error(tmp_path):
    bad = tmp_path / "broken.tif"
    bad.write_bytes(b"this is not a TIFF file at all")
    with pytest.raises(InputFileError, match="could not be read as TIFF") as exc:
        read_projections(bad)
    assert isinstance(exc.value, FileNotFoundError) and isinstance(exc.value, PdvcError)


# --------------------------------------------------------------------------- .npy


def test_npy_3d_and_sinogram(tmp_path, rng):
    arr = rng.normal(size=(4, 3, 5)).astype(np.float64)
    np.save(tmp_path / "p.npy", arr)
    raw = read_projections(tmp_path / "p.npy")
    assert raw.format == "npy" and raw.data.dtype == np.float32
    np.testing.assert_array_equal(raw.data, arr.astype(np.float32))

    sino3 = rng.normal(size=(2, 6, 5)).astype(np.float32)  # (n_rows, n_views, n_cols)
    np.save(tmp_path / "s3.npy", sino3)
    np.testing.assert_array_equal(read_projections(tmp_path / "s3.npy", sinogram=True).data, sino3.transpose(1, 0, 2))

    np.save(tmp_path / "s2.npy", sino3[0])
    assert read_projections(tmp_path / "s2.npy", sinogram=True).data.shape == (6, 1, 5)
    with pytest.raises(ShapeError, match="sinogram=True"):
        read_projections(tmp_path / "s2.npy")


def test_wrong_dimensions(tmp_path):
    np.save(tmp_path / "four.npy", np.zeros((2, 2, 2, 2)))
    with pytest.raises(ShapeError, match=r"must be 3D .* got 4D"):
        read_projections(tmp_path / "four.npy")


# --------------------------------------------------------------------------- flats, darks, angles arguments


def test_flats_darks_as_arrays_and_paths_are_copied(tmp_path, rng):
    data = _stack(rng, 4)
    flats = _stack(rng, 2)
    dark = _stack(rng, 1)[0]  # one 2D dark image
    np.save(tmp_path / "p.npy", data)
    np.save(tmp_path / "darks.npy", dark)
    flats_before = flats.copy()
    raw = read_projections(tmp_path / "p.npy", flats=flats, darks=tmp_path / "darks.npy")
    np.testing.assert_array_equal(raw.flats, flats)
    assert raw.darks.shape == (1, 3, 5)
    np.testing.assert_array_equal(raw.darks[0], dark)
    assert not np.shares_memory(raw.flats, flats)
    np.testing.assert_array_equal(flats, flats_before)


def test_flats_and_darks_shape_mismatch_names_parameter(tmp_path, rng):
    np.save(tmp_path / "p.npy", _stack(rng, 4))
    with pytest.raises(ShapeError, match=r"flats must have shape \(n_flats, 3, 5\).*got \(2, 3, 4\)"):
        read_projections(tmp_path / "p.npy", flats=np.ones((2, 3, 4)))
    with pytest.raises(ShapeError, match=r"darks must have shape .*got \(4, 5\)"):
        read_projections(tmp_path / "p.npy", darks=np.ones((4, 5)))
    with pytest.raises(InputFileError, match="flats path .* does not exist"):
        read_projections(tmp_path / "p.npy", flats=tmp_path / "nope.tif")


def test_one_row_detector_accepts_2d_flats(tmp_path, rng):
    sino = _stack(rng, 1, (6, 5))[0]
    np.save(tmp_path / "s.npy", sino)
    raw = read_projections(tmp_path / "s.npy", sinogram=True, flats=np.full((3, 5), 7.0))
    assert raw.flats.shape == (3, 1, 5) and np.all(raw.flats == 7.0)


def test_angles_degrees_to_radians_from_array_and_text_file(tmp_path, rng):
    np.save(tmp_path / "p.npy", _stack(rng, 4))
    deg = np.array([0.0, 45.0, 90.0, 180.0])
    raw = read_projections(tmp_path / "p.npy", angles=deg)
    np.testing.assert_allclose(raw.angles, [0, np.pi / 4, np.pi / 2, np.pi], rtol=0, atol=1e-15)
    assert raw.angles.dtype == np.float64
    (tmp_path / "angles.txt").write_text("# degrees\n0\n45\n90\n180\n")
    raw2 = read_projections(tmp_path / "p.npy", angles=tmp_path / "angles.txt")
    np.testing.assert_array_equal(raw2.angles, raw.angles)


def test_angles_count_mismatch_names_parameter(tmp_path, rng):
    np.save(tmp_path / "p.npy", _stack(rng, 4))
    with pytest.raises(ShapeError, match="angles must hold one value per view: expected 4 angles, got 3"):
        read_projections(tmp_path / "p.npy", angles=[0, 1, 2])
    with pytest.raises(DataError, match="angles must be finite"):
        read_projections(tmp_path / "p.npy", angles=[0, 1, np.nan, 3])


def test_nan_in_data_names_count_and_first_view(tmp_path, rng):
    arr = rng.normal(size=(6, 3, 5)).astype(np.float32)
    arr[3, 1, 1] = np.nan
    arr[5, 0, 2] = np.inf
    np.save(tmp_path / "p.npy", arr)
    with pytest.raises(DataError, match="data must be finite; it holds 2 NaN/Inf values, the first in view 3"):
        read_projections(tmp_path / "p.npy")


def test_is_raw_override_and_flat_positions_argument(tmp_path, rng):
    np.save(tmp_path / "p.npy", _stack(rng, 4))
    assert read_projections(tmp_path / "p.npy", is_raw=False).is_raw is False
    raw = read_projections(tmp_path / "p.npy", flats=np.ones((2, 3, 5)), flat_positions=[-0.5, 3.5])
    np.testing.assert_array_equal(raw.flat_positions, [-0.5, 3.5])
    with pytest.raises(ShapeError, match=r"flat_positions must hold one value per flat: expected shape \(2,\)"):
        read_projections(tmp_path / "p.npy", flats=np.ones((2, 3, 5)), flat_positions=[0.0])
    with pytest.raises(InputTypeError, match="is_raw"):
        read_projections(tmp_path / "p.npy", is_raw="yes")


# --------------------------------------------------------------------------- format detection


def test_missing_path_and_unknown_format(tmp_path):
    with pytest.raises(InputFileError, match="does not exist") as exc:
        read_projections(tmp_path / "missing.tif")
    assert isinstance(exc.value, FileNotFoundError)
    assert str(exc.value).startswith("path '") and "path path" not in str(exc.value)
    (tmp_path / "scan.raw").write_bytes(b"\0" * 64)
    with pytest.raises(FormatError, match=r"not a supported projection format.*'\.raw'"):
        read_projections(tmp_path / "scan.raw")
    with pytest.raises(FormatError, match="fmt must be"):
        read_projections(tmp_path / "scan.raw", fmt="edf")


def test_options_that_do_not_apply(tmp_path, rng):
    np.save(tmp_path / "p.npy", _stack(rng, 2))
    with pytest.raises(FormatError, match="dataset applies to HDF5"):
        read_projections(tmp_path / "p.npy", dataset="exchange/data")
    _write_dxchange(tmp_path / "dx.h5", rng)
    with pytest.raises(FormatError, match="sinogram=True applies to TIFF and .npy"):
        read_projections(tmp_path / "dx.h5", sinogram=True)


# --------------------------------------------------------------------------- Data Exchange


def _write_dxchange(path, rng, theta_units="degrees"):
    data = rng.uniform(1000, 30000, size=(5, 3, 4)).astype(np.float32)
    white = rng.uniform(30000, 31000, size=(2, 3, 4)).astype(np.float32)
    dark = rng.uniform(90, 110, size=(3, 3, 4)).astype(np.float32)
    theta = np.array([0.0, 36.0, 72.0, 108.0, 144.0])
    with h5py.File(path, "w") as f:
        ex = f.create_group("exchange")
        ex.create_dataset("data", data=data).attrs["units"] = "counts"
        ex.create_dataset("data_white", data=white)
        ex.create_dataset("data_dark", data=dark)
        th = ex.create_dataset("theta", data=np.deg2rad(theta) if theta_units == "rad" else theta)
        if theta_units is not None:
            th.attrs["units"] = theta_units
    return data, white, dark, theta


def test_dxchange_roundtrip_with_degrees(tmp_path, rng):
    data, white, dark, theta = _write_dxchange(tmp_path / "scan.h5", rng)
    raw = read_projections(tmp_path / "scan.h5")
    assert raw.format == "dxchange" and raw.is_raw
    np.testing.assert_array_equal(raw.data, data)
    np.testing.assert_array_equal(raw.flats, white)
    np.testing.assert_array_equal(raw.darks, dark)
    np.testing.assert_allclose(raw.angles, np.deg2rad(theta), rtol=0, atol=1e-15)
    assert raw.flat_positions is None


def test_dxchange_theta_radians_attribute_and_default(tmp_path, rng):
    *_, theta = _write_dxchange(tmp_path / "rad.h5", rng, theta_units="rad")
    np.testing.assert_allclose(read_projections(tmp_path / "rad.h5").angles, np.deg2rad(theta), atol=1e-15)
    *_, theta = _write_dxchange(tmp_path / "none.h5", rng, theta_units=None)
    np.testing.assert_allclose(read_projections(tmp_path / "none.h5").angles, np.deg2rad(theta), atol=1e-15)


def test_dxchange_user_angles_and_flats_override_file(tmp_path, rng):
    _write_dxchange(tmp_path / "scan.h5", rng)
    raw = read_projections(tmp_path / "scan.h5", angles=[0, 1, 2, 3, 4], flats=np.full((3, 4), 5.0))
    np.testing.assert_allclose(raw.angles, np.deg2rad([0, 1, 2, 3, 4]))
    assert raw.flats.shape == (1, 3, 4) and np.all(raw.flats == 5.0)


def test_hdf5_without_known_layout(tmp_path):
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["stuff"] = np.zeros((2, 2, 2))
    with pytest.raises(FormatError, match=r"neither Data Exchange.*\['stuff'\]"):
        read_projections(tmp_path / "other.h5")
    raw = read_projections(tmp_path / "other.h5", dataset="stuff", is_raw=False)
    assert raw.data.shape == (2, 2, 2) and raw.format == "dxchange"


# --------------------------------------------------------------------------- NXtomo

# darks, flats before, projections, an invalid frame, flats after
KEYS = np.array([2, 2, 1, 1, 1, 0, 0, 0, 0, 3, 0, 1, 1])


def _write_nxtomo(path, rng, *, entry="entry", units="degree", link_data=False, definition=True, f=None):
    n = KEYS.size
    frames = rng.integers(0, 4000, size=(n, 2, 3)).astype(np.uint16)
    angles = np.linspace(0.0, 120.0, n)
    own = f is None
    f = h5py.File(path, "w") if own else f
    try:
        e = f.create_group(entry)
        e.attrs["NX_class"] = "NXentry"
        if definition:
            e["definition"] = "NXtomo"
        det = e.create_group("instrument").create_group("detector")
        e["instrument"].attrs["NX_class"] = "NXinstrument"
        det.attrs["NX_class"] = "NXdetector"
        if link_data:
            d = e.create_group("data")
            d.attrs["NX_class"] = "NXdata"
            d["data"] = frames
            d["image_key"] = KEYS
        else:
            det["data"] = frames
            det["image_key"] = KEYS
        s = e.create_group("sample")
        s.attrs["NX_class"] = "NXsample"
        ra = s.create_dataset("rotation_angle", data=angles if units != "rad" else np.deg2rad(angles))
        if units is not None:
            ra.attrs["units"] = units
    finally:
        if own:
            f.close()
    return frames, angles


def test_nxtomo_image_key_splitting_and_flat_positions(tmp_path, rng):
    frames, angles = _write_nxtomo(tmp_path / "scan.nx", rng)
    raw = read_projections(tmp_path / "scan.nx")
    assert raw.format == "nxtomo" and raw.is_raw
    proj = KEYS == 0
    np.testing.assert_array_equal(raw.data, frames[proj])
    np.testing.assert_array_equal(raw.flats, frames[KEYS == 1])
    np.testing.assert_array_equal(raw.darks, frames[KEYS == 2])
    np.testing.assert_allclose(raw.angles, np.deg2rad(angles[proj]), atol=1e-15)
    # 5 projections: three flats before view 0, two after view 4
    np.testing.assert_array_equal(raw.flat_positions, [-0.5, -0.5, -0.5, 4.5, 4.5])
    assert raw.metadata["n_invalid_frames"] == 1


def test_nxtomo_data_group_link_and_radians(tmp_path, rng):
    frames, angles = _write_nxtomo(tmp_path / "scan.h5", rng, link_data=True, units="rad")
    raw = read_projections(tmp_path / "scan.h5")
    np.testing.assert_array_equal(raw.data, frames[KEYS == 0])
    np.testing.assert_allclose(raw.angles, np.deg2rad(angles[KEYS == 0]), atol=1e-15)


def test_nxtomo_several_entries_need_dataset(tmp_path, rng):
    with h5py.File(tmp_path / "two.nxs", "w") as f:
        _write_nxtomo(None, rng, entry="entry0000", f=f)
        frames1, _ = _write_nxtomo(None, rng, entry="entry0001", f=f)
    with pytest.raises(FormatError, match="2 NXtomo entries.*dataset="):
        read_projections(tmp_path / "two.nxs")
    raw = read_projections(tmp_path / "two.nxs", dataset="entry0001")
    np.testing.assert_array_equal(raw.data, frames1[KEYS == 0])


def test_nxtomo_bad_image_key_and_angle_units(tmp_path, rng):
    _write_nxtomo(tmp_path / "a.nx", rng, units="furlong")
    with pytest.raises(DataError, match="rotation_angle has units 'furlong'"):
        read_projections(tmp_path / "a.nx")
    _write_nxtomo(tmp_path / "b.nx", rng)
    with h5py.File(tmp_path / "b.nx", "r+") as f:
        f["entry/instrument/detector/image_key"][0] = 7
    with pytest.raises(DataError, match=r"image_key must hold 0 \(projection\).*\[7\]"):
        read_projections(tmp_path / "b.nx")


# --------------------------------------------------------------------------- RawScan


def test_rawscan_checks_on_replace(rng):
    raw = RawScan(rng.normal(size=(3, 2, 2)).astype(np.float32), is_raw=False)
    assert raw.format == "memory" and raw.n_views == 3 and raw.det_shape == (2, 2)
    with pytest.raises(ShapeError, match=r"angles must have shape \(n_views,\) = \(3,\)"):
        dataclasses.replace(raw, angles=np.zeros(2))
    with pytest.raises(ShapeError, match="flats must have shape"):
        dataclasses.replace(raw, flats=np.ones((1, 2, 3)))
    with pytest.raises(ShapeError, match=r"data must have shape \(n_views, n_rows, n_cols\)"):
        RawScan(np.zeros((2, 2)))


# --------------------------------------------------------------------------- real files


def test_real_tooth_dxchange():
    if not TOOTH.exists():
        pytest.skip(f"real data file absent: {TOOTH}")
    raw = read_projections(TOOTH)
    assert raw.format == "dxchange" and raw.is_raw
    assert raw.data.shape == (181, 2, 640)
    assert raw.flats.shape == (10, 2, 640) and raw.darks.shape == (10, 2, 640)
    assert raw.angles.shape == (181,)
    step = np.diff(raw.angles)
    np.testing.assert_allclose(step, np.pi / 181, rtol=1e-6)  # 181 views of 180/181 deg
    np.testing.assert_allclose(raw.angles[-1] - raw.angles[0] + step.mean(), np.pi, rtol=1e-6)


def test_real_neutron_sinogram_tiff():
    if not NEUTRON.exists():
        pytest.skip(f"real data file absent: {NEUTRON}")
    raw = read_projections(NEUTRON, sinogram=True)
    assert raw.data.shape == (459, 1, 503) and raw.format == "tiff"
    assert raw.is_raw and raw.metadata["raw_dtype"] == "uint16"
    assert raw.data.max() == 53711.0
