"""Flat/dark normalisation, open-beam flats, beam hardening, detector ROI: known answers."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

import pdvc
from pdvc.errors import InputTypeError, ShapeError
from pdvc.io._preprocess import beam_hardening, detector_roi, flats_from_columns, normalize
from pdvc.io._projections import DataError, RawScan, read_projections

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
TOOTH = DATA / "tomopy-tooth" / "tooth.h5"
NEUTRON = DATA / "sarepy-neutron360" / "sinogram_360_neutron_image.tif"

# float32 data and a float32 result: -log(t) agrees to a few float32 ulps of the counts
TOL = dict(rtol=0, atol=2e-6)


def _transmission(rng, shape):
    return rng.uniform(0.05, 0.95, size=shape)


# --------------------------------------------------------------------------- normalize


def test_flat_dark_normalisation_known_transmission(rng):
    n, shape = 5, (3, 4)
    T = _transmission(rng, (n,) + shape)
    dark = 100.0 + rng.uniform(0, 5, size=shape)
    flat = 20000.0 + rng.uniform(0, 500, size=shape)
    # flats and darks scatter around their means; the scatter averages out exactly
    flats = np.stack([flat - 50.0, flat + 50.0, flat])
    darks = np.stack([dark - 1.0, dark + 1.0])
    data = dark + T * (flat - dark)
    raw = RawScan(data, flats=flats, darks=darks)
    p, rep = normalize(raw)
    assert p.dtype == np.float32 and p.shape == (n,) + shape
    np.testing.assert_allclose(p, -np.log(T), **TOL)
    assert rep.n_flats == 3 and rep.n_darks == 2 and rep.flat_method == "mean"
    assert rep.n_clipped == 0 and rep.clipped_views == ()


def test_normalize_does_not_modify_input(rng):
    raw = RawScan(rng.uniform(10, 100, (3, 2, 2)), flats=np.full((1, 2, 2), 200.0))
    before = raw.data.copy()
    normalize(raw)
    np.testing.assert_array_equal(raw.data, before)


def test_flats_before_and_after_are_interpolated_linearly(rng):
    n, shape = 8, (2, 3)
    A = 10000.0 + rng.uniform(0, 100, size=shape)  # beam before the scan
    B = 14000.0 + rng.uniform(0, 100, size=shape)  # ... and after: it drifted up by 40 %
    pos_k = np.arange(n)
    true_flat = A + (B - A) * ((pos_k + 0.5) / n)[:, None, None]  # flat of view k, position k on the line -0.5 .. n-0.5
    T = _transmission(rng, (n,) + shape)
    raw = RawScan(
        T * true_flat,
        flats=np.stack([A, A, B]),
        flat_positions=[-0.5, -0.5, n - 0.5],
    )
    p, rep = normalize(raw)
    np.testing.assert_allclose(p, -np.log(T), **TOL)
    assert rep.flat_method == "linear" and rep.flat_group_positions == (-0.5, n - 0.5)

    # averaging the same flats is wrong by up to log((A+B)/2 / A) ~ 0.17 at the first view
    p_mean, rep_mean = normalize(raw, flat_interpolation="mean")
    assert rep_mean.flat_method == "mean"
    assert np.max(np.abs(p_mean - (-np.log(T)))) > 0.1


def test_three_flat_groups_piecewise_linear(rng):
    n, shape = 6, (1, 2)
    F0, F1, F2 = 1000.0, 2000.0, 1500.0
    positions = np.array([-0.5, 2.0, 5.5])
    values = np.array([F0, F1, F2])
    flat_k = np.interp(np.arange(n), positions, values)
    T = _transmission(rng, (n,) + shape)
    raw = RawScan(
        T * flat_k[:, None, None],
        flats=np.stack([np.full(shape, v) for v in values]),
        flat_positions=positions,
    )
    p, _ = normalize(raw)
    np.testing.assert_allclose(p, -np.log(T), **TOL)


def test_flats_outside_scan_are_held_constant(rng):
    # two groups both inside the time line: views before/after take the nearest group
    n, shape = 5, (1, 1)
    raw = RawScan(
        np.full((n,) + shape, 50.0),
        flats=np.array([[[100.0]], [[200.0]]]),
        flat_positions=[1.0, 3.0],
    )
    p, _ = normalize(raw)
    expected_flat = np.array([100.0, 100.0, 150.0, 200.0, 200.0])
    np.testing.assert_allclose(p[:, 0, 0], -np.log(50.0 / expected_flat), **TOL)


def test_nxtomo_flats_before_and_after_end_to_end(tmp_path, rng):
    # an NXtomo file with flats before and after a drifting beam normalises exactly
    n, shape = 6, (2, 3)
    A, B = 8000.0, 12000.0
    T = _transmission(rng, (n,) + shape)
    beam = A + (B - A) * (np.arange(n) + 0.5) / n
    proj = T * beam[:, None, None]
    frames = np.concatenate([np.full((2,) + shape, A), proj, np.full((2,) + shape, B)])
    keys = np.array([1, 1] + [0] * n + [1, 1])
    with h5py.File(tmp_path / "drift.nx", "w") as f:
        e = f.create_group("entry")
        e.attrs["NX_class"] = "NXentry"
        e["definition"] = "NXtomo"
        det = e.create_group("instrument/detector")
        det["data"] = frames.astype(np.float32)
        det["image_key"] = keys
        e.create_group("sample")["rotation_angle"] = np.linspace(0, 180, keys.size)
    raw = read_projections(tmp_path / "drift.nx")
    np.testing.assert_array_equal(raw.flat_positions, [-0.5, -0.5, n - 0.5, n - 0.5])
    p, rep = normalize(raw)
    assert rep.flat_method == "linear"
    np.testing.assert_allclose(p, -np.log(T), atol=5e-6, rtol=0)  # float32 storage of the counts


def test_clipping_is_counted_exactly():
    shape = (2, 3)
    data = np.full((5,) + shape, 500.0)
    data[1, 0, 0] = 0.0  # zero transmission
    data[1, 1, 2] = 5.0  # below the dark: negative
    data[4, 0, 1] = 10.0  # exactly the dark: zero
    data[4, 1, 1] = 10.0 + 1e-7 * 990  # positive but below clip_min=1e-6
    raw = RawScan(data, flats=np.full((1,) + shape, 1000.0), darks=np.full((1,) + shape, 10.0))
    p, rep = normalize(raw, clip_min=1e-6)
    assert rep.n_clipped == 4
    assert rep.n_nonpositive == 3
    assert rep.clipped_views == (1, 4) and rep.clipped_counts == (2, 2)
    assert rep.clipped_fraction == pytest.approx(4 / data.size)
    cap = -np.log(np.float32(1e-6))
    for k, r, c in [(1, 0, 0), (1, 1, 2), (4, 0, 1), (4, 1, 1)]:
        assert p[k, r, c] == pytest.approx(cap, rel=1e-6)
    np.testing.assert_allclose(p[0], -np.log(490.0 / 990.0), **TOL)
    assert np.all(np.isfinite(p))


def test_line_integrals_pass_through_as_copy(rng):
    raw = RawScan(rng.normal(size=(3, 2, 2)).astype(np.float32), is_raw=False)
    p, rep = normalize(raw)
    np.testing.assert_array_equal(p, raw.data)
    assert p is not raw.data and not np.shares_memory(p, raw.data)
    assert rep.is_raw is False and rep.flat_method == "none"


def test_raw_without_flats_is_an_error():
    raw = RawScan(np.full((2, 2, 2), 5.0), is_raw=True)
    with pytest.raises(DataError, match="raw counts need flats; pass flats= or set is_raw=False"):
        normalize(raw)


def test_flats_not_above_darks_name_pixel_count():
    flats = np.full((2, 4, 5), 1000.0)
    darks = np.full((1, 4, 5), 100.0)
    darks[0, 1, 2] = darks[0, 3, 0] = 1000.0  # dark equals the flat
    darks[0, 2, 4] = 2000.0  # dark above the flat
    raw = RawScan(np.full((3, 4, 5), 500.0), flats=flats, darks=darks)
    with pytest.raises(DataError, match=r"darks >= flats.*3 of 20 pixels are <= 0 \(first at row 1, col 2\).*ROI.*bad pixels"):
        normalize(raw)


def test_zero_flats_without_darks():
    flats = np.full((1, 2, 2), 1000.0)
    flats[0, 1, 1] = 0.0
    with pytest.raises(DataError, match=r"flats must be > 0 at every detector pixel; 1 of 4 pixels"):
        normalize(RawScan(np.full((1, 2, 2), 5.0), flats=flats))


def test_flat_shape_mismatch_and_bad_options():
    with pytest.raises(ShapeError, match=r"flats must have shape \(n_flats, 2, 2\)"):
        RawScan(np.ones((1, 2, 2)), flats=np.ones((1, 2, 3)))
    with pytest.raises(ShapeError, match=r"darks must have shape \(n_darks, 2, 2\)"):
        RawScan(np.ones((1, 2, 2)), darks=np.ones((2, 2)))
    raw = RawScan(np.ones((1, 2, 2)), flats=np.full((1, 2, 2), 2.0))
    with pytest.raises(DataError, match="flat_interpolation must be one of"):
        normalize(raw, flat_interpolation="cubic")
    with pytest.raises(DataError, match=r"clip_min must be a number in \(0, 1\)"):
        normalize(raw, clip_min=0.0)
    with pytest.raises(InputTypeError, match="raw must be a RawScan"):
        normalize(np.ones((1, 2, 2)))


# --------------------------------------------------------------------------- open-beam columns


def test_flats_from_columns_recovers_transmission_with_fluctuating_beam(rng):
    n, rows, cols, n_open = 7, 2, 12, 3
    beam = 1000.0 * (1 + 0.2 * rng.uniform(-1, 1, size=(n, rows)))  # per view and row
    T = np.ones((n, rows, cols))
    T[:, :, n_open:] = _transmission(rng, (n, rows, cols - n_open))
    raw = RawScan(T * beam[:, :, None])
    out = flats_from_columns(raw, columns=slice(0, n_open))
    assert out.flats.shape == (n, rows, cols)
    np.testing.assert_array_equal(out.flat_positions, np.arange(n))
    np.testing.assert_allclose(out.flats[:, :, 5], beam, rtol=1e-6)
    p, rep = normalize(out)
    np.testing.assert_allclose(p, -np.log(T), **TOL)
    assert rep.flat_method == "linear" and raw.flats is None  # the input scan is unchanged


def test_flats_from_columns_errors():
    raw = RawScan(np.ones((2, 1, 10)))
    with pytest.raises(DataError, match="columns must select at least one"):
        flats_from_columns(raw, columns=slice(5, 5))
    with pytest.raises(ShapeError, match="columns must lie inside the detector's 10 columns"):
        flats_from_columns(raw, columns=[0, 10])
    with pytest.raises(DataError, match="needs raw counts"):
        flats_from_columns(RawScan(np.ones((2, 1, 10)), is_raw=False))


# --------------------------------------------------------------------------- beam hardening


def test_beam_hardening_known_polynomial(rng):
    p = rng.uniform(0.0, 3.0, size=(4, 3, 5)).astype(np.float32)
    before = p.copy()
    out = beam_hardening(p, (1.0, 0.5, 0.1))
    x = p.astype(np.float64)
    np.testing.assert_allclose(out, x + 0.5 * x**2 + 0.1 * x**3, rtol=1e-6)
    assert out.dtype == np.float32 and out.shape == p.shape
    np.testing.assert_array_equal(p, before)
    np.testing.assert_array_equal(beam_hardening(p, [1.0]), p)


def test_beam_hardening_rejects_non_monotone_correction():
    p = np.linspace(0.0, 2.0, 24).reshape(2, 3, 4)
    # p - p**2 rises until p = 0.5 then falls: derivative 1 - 2p is 0 at p = 0.5
    with pytest.raises(DataError, match=r"coeffs \(1.0, -1.0\) do not give an increasing correction.*p = 0.5"):
        beam_hardening(p, (1.0, -1.0))
    # the same coefficients are fine where the data stay below 0.5
    beam_hardening(p * 0.2, (1.0, -1.0))
    with pytest.raises(DataError, match="coeffs must be a non-empty sequence"):
        beam_hardening(p, [])
    with pytest.raises(DataError, match="derivative is <= 0"):
        beam_hardening(p, (-1.0,))


# --------------------------------------------------------------------------- detector ROI


def test_detector_roi_crops_data_and_geometry(rng):
    geom = pdvc.parallel(np.array([0.0, 0.8, 2.0]), det_shape=(6, 8), pixel=(0.5, 0.25))
    p = rng.normal(size=(3, 6, 8)).astype(np.float32)
    p_roi, g_roi = detector_roi(p, geom, rows=(1, 5), cols=slice(2, -1))
    np.testing.assert_array_equal(p_roi, p[:, 1:5, 2:7])
    assert g_roi.det_shape == (4, 5) and not np.shares_memory(p_roi, p)
    for k in range(3):  # the kept pixels sit where they were
        np.testing.assert_allclose(g_roi.pixel_centers(k), geom.pixel_centers(k)[1:5, 2:7], atol=1e-12)
    same, g_same = detector_roi(p, geom)
    np.testing.assert_array_equal(same, p)
    assert g_same.det_shape == (6, 8)


def test_detector_roi_errors(rng):
    geom = pdvc.parallel(np.array([0.0, 1.0]), det_shape=(4, 4), pixel=1.0)
    p = np.zeros((2, 4, 4), np.float32)
    with pytest.raises(ShapeError, match=r"rows selects no detector row"):
        detector_roi(p, geom, rows=(2, 2))
    with pytest.raises(ShapeError, match=r"cols must lie inside 0..4"):
        detector_roi(p, geom, cols=(0, 9))
    with pytest.raises(ShapeError, match=r"p must have shape .* = \(2, 4, 4\) to match geom"):
        detector_roi(np.zeros((2, 4, 5)), geom)
    with pytest.raises(InputTypeError, match="geom must be a VectorGeometry"):
        detector_roi(p, np.zeros((2, 12)))


# --------------------------------------------------------------------------- real files


def test_real_tooth_normalises_to_plausible_line_integrals():
    if not TOOTH.exists():
        pytest.skip(f"real data file absent: {TOOTH}")
    raw = read_projections(TOOTH)
    p, rep = normalize(raw)
    assert p.shape == (181, 2, 640) and np.all(np.isfinite(p))
    assert rep.n_clipped == 0 and rep.n_flats == 10 and rep.n_darks == 10
    # counts 3.9e3 .. 3.4e4 under a ~2.8e4 flat: -log between about -0.2 and 2.1
    assert -0.3 < p.min() and p.max() < 2.5
    assert np.mean((p > -0.1) & (p < 2.2)) > 0.99
    # the tooth absorbs: the middle of the detector is well above the open beam at the edges
    assert p[:, :, 250:350].mean() > 0.5 and abs(np.median(p[:, :, :20])) < 0.1


def test_real_neutron_sinogram_with_open_beam_columns():
    if not NEUTRON.exists():
        pytest.skip(f"real data file absent: {NEUTRON}")
    raw = read_projections(NEUTRON, sinogram=True)
    with pytest.raises(DataError, match="raw counts need flats"):
        normalize(raw)
    p, rep = normalize(flats_from_columns(raw, columns=slice(0, 30)))
    assert p.shape == (459, 1, 503) and np.all(np.isfinite(p))
    # only zero counts can fall below 1e-6 of a ~4.7e4 open beam: the clip count is the zero count
    assert rep.n_clipped == int(np.count_nonzero(raw.data <= 0))
    assert abs(p[:, :, :30].mean()) < 1e-3  # open beam normalises to ~0
    unclipped = np.ones(p.shape, bool)
    for k in rep.clipped_views:
        unclipped[k] &= raw.data[k] > 0
    assert np.percentile(p[unclipped], 99) < 5.0
