"""The residual diagnosis names what was injected, in the right proportions."""

import numpy as np
import pytest

from pdvc.calibration import diagnose_residual, sample_outline


def test_pure_noise_is_noise():
    r = np.random.default_rng(0).normal(0, 0.5, (30, 20, 40))
    d = diagnose_residual(r, 0.25)
    assert d.chi == pytest.approx(1.0, abs=0.02)
    assert d.noise > 0.97 and d.structure < 0.03


def test_injected_parts_are_found_in_proportion():
    rng = np.random.default_rng(1)
    n = (40, 16, 50)
    noise = rng.normal(0, 1.0, n)
    offset = np.repeat(rng.normal(0, 2.0, n[0]), n[1] * n[2]).reshape(n)  # per view
    cols = np.broadcast_to(np.sin(np.arange(n[2]) / 3.0) * 1.5, n)  # a fixed column pattern
    spikes = np.zeros(n)
    m = rng.random(n) < 0.002
    spikes[m] = 40.0
    r = noise + offset + cols + spikes
    d = diagnose_residual(r, 1.0)
    total = np.sum(r**2)
    assert d.view_offset == pytest.approx(np.sum(offset**2) / total, rel=0.1)
    assert d.column_pattern == pytest.approx(np.sum(cols**2) / total, rel=0.1)
    assert d.outliers == pytest.approx(np.sum(spikes**2) / total, rel=0.15)
    assert d.noise == pytest.approx(np.prod(n) / total, rel=0.1)
    text = d.describe()
    assert "constant per view" in text and "outlier" in text and "columns" in text
    assert sum((d.view_offset, d.column_pattern, d.row_pattern, d.outliers, d.noise, d.structure)) == pytest.approx(1.0)


def test_zero_weight_pixels_are_left_out():
    r = np.random.default_rng(2).normal(0, 1.0, (10, 8, 12))
    w = np.ones((8, 12))
    w[:, 5] = 0
    r[:, :, 5] = 1e3  # a dead column, masked
    assert diagnose_residual(r, 1.0, w).chi == pytest.approx(1.0, abs=0.05)


def test_the_edges_of_a_misplaced_sample_are_structure_not_outliers():
    rng = np.random.default_rng(3)
    cols = np.arange(60)
    disc = lambda c0: (np.abs(cols - c0) < 15).astype(float) * 5.0  # noqa: E731
    # the sample's edges move across the detector from view to view (a rotating, misplaced sample)
    r = np.stack([np.broadcast_to(disc(20.0 + k) - disc(19.0 + k), (12, 60)) for k in range(20)])
    r = r + rng.normal(0, 0.1, r.shape)
    d = diagnose_residual(r, 0.01)
    assert d.outliers < 0.01


def test_bright_groups_of_a_few_pixels_are_outliers():
    """A zinger whose light spread over 2 x 2 px (line integral lowered) counts as outliers; the same groups reading
    dark do not (no light source makes them; in a reconstruction's residual they are a zinger's streak)."""
    rng = np.random.default_rng(4)
    n = (30, 20, 40)
    noise = rng.normal(0, 1.0, n)
    blobs = np.zeros(n)
    for v, r0, c0 in zip(rng.integers(0, n[0], 40), rng.integers(0, n[1] - 1, 40), rng.integers(0, n[2] - 1, 40)):
        blobs[v, r0:r0 + 2, c0:c0 + 2] = -30.0
    d = diagnose_residual(noise + blobs, 1.0)
    assert d.outliers == pytest.approx(np.sum(blobs**2) / np.sum((noise + blobs) ** 2), rel=0.15)
    assert diagnose_residual(noise - blobs, 1.0).outliers < 0.01


def _rod_shadow(n_views=12, n_rows=8, n_cols=60, centre=30.0, radius=15.0):
    u = np.arange(n_cols) - centre
    prof = 2 * np.sqrt(np.clip(radius**2 - u**2, 0, None)) * 0.1
    return np.broadcast_to(prof, (n_views, n_rows, n_cols)).astype(np.float32)


def test_the_outline_is_where_the_shadow_meets_the_air():
    out = sample_outline(_rod_shadow())
    edge = np.flatnonzero(out)
    # the shadow covers columns 16-44 above a tenth of its height: the change is between 15 and 16 and between 44
    # and 45, and the outline those columns with 3 more each side
    assert edge.tolist() == list(range(12, 20)) + list(range(41, 49)), edge
    # no shadow (flat data): no outline
    assert not sample_outline(np.ones((3, 4, 20))).any()
    with pytest.raises(ValueError, match="n_views, n_rows, n_cols"):
        sample_outline(np.ones((4, 20)))


def test_a_column_pattern_at_the_sample_outline_is_not_counted_as_the_detectors():
    """A clean rod centred on the axis leaves the reconstruction's model error of its edge at the same columns in
    every view: a pattern of the columns, but none of the detector's (docs/method.md §5.40)."""
    rng = np.random.default_rng(5)
    data = _rod_shadow()
    noise = rng.normal(0, 1.0, data.shape)
    edge = np.zeros(data.shape[2])
    edge[[15, 16, 44, 45]] = [3.0, -4.0, -4.0, 3.0]
    d = diagnose_residual(noise + edge, 1.0, data=data)
    assert d.column_pattern > 0.3
    assert d.column_pattern_off_outline < 0.02
    # a detector's pattern spreads over every column: the share off the outline is about the share everywhere
    white = rng.normal(0, 0.8, data.shape[2])
    d = diagnose_residual(noise + white, 1.0, data=data)
    assert d.column_pattern_off_outline == pytest.approx(d.column_pattern, rel=0.3)
    assert d.column_pattern > 0.2
    # without the data it is not measured
    assert diagnose_residual(noise + white, 1.0).column_pattern_off_outline is None
    with pytest.raises(ValueError, match="residual's shape"):
        diagnose_residual(noise, 1.0, data=data[:, :, :-1])
