"""Argument checking, the read-only contract and the ``out=`` path."""

from __future__ import annotations

import numpy as np
import pytest

from pdvc.errors import GeometryError, InputTypeError, PdvcError, ShapeError
from pdvc.geometry import VolumeGeometry, circular_cone, parallel
from pdvc.recon import fbp, fdk

from .conftest import DET, ODD, PIXEL, SOD


@pytest.fixture(scope="module")
def small():
    vg = VolumeGeometry((16, 16, 16), 1.0)
    g = circular_cone(np.linspace(0, 2 * np.pi, 24, endpoint=False), sod=SOD, odd=ODD, det_shape=DET, pixel=PIXEL)
    p = np.random.default_rng(0).random((24,) + DET).astype(np.float32)
    return vg, g, p


def test_projections_not_modified_and_read_only_ok(small):
    vg, g, p = small
    keep = p.copy()
    ro = p.copy()
    ro.setflags(write=False)
    a = fdk(ro, vg, g)
    np.testing.assert_array_equal(ro, keep)
    b = fdk(p, vg, g)
    np.testing.assert_array_equal(p, keep)
    np.testing.assert_array_equal(a, b)


def test_other_dtypes_and_layouts(small):
    vg, g, p = small
    ref = fdk(p, vg, g)
    p64 = p.astype(np.float64)
    np.testing.assert_allclose(fdk(p64, vg, g), ref, rtol=1e-6, atol=1e-6)
    pf = np.asfortranarray(p)
    np.testing.assert_allclose(fdk(pf, vg, g), ref, rtol=1e-6, atol=1e-6)
    pi = (p * 100).astype(np.int16)
    np.testing.assert_allclose(fdk(pi, vg, g), fdk(pi.astype(np.float32), vg, g))
    assert fdk(list(p64), vg, g).shape == vg.shape  # array-likes


def test_out_is_overwritten_and_returned(small):
    vg, g, p = small
    out = np.full(vg.shape, 7.0, np.float32)
    res = fdk(p, vg, g, out=out)
    assert res is out
    np.testing.assert_array_equal(out, fdk(p, vg, g))


@pytest.mark.parametrize(
    "bad, match",
    [
        (np.zeros((16, 16, 16)), "C-contiguous float32"),
        (np.zeros((16, 16, 15), np.float32), r"shape \(16, 16, 16\)"),
        (np.zeros((16, 16, 32), np.float32)[:, :, ::2], "C-contiguous"),
    ],
)
def test_bad_out(small, bad, match):
    vg, g, p = small
    with pytest.raises(ShapeError, match=match):
        fdk(p, vg, g, out=bad)


def test_bad_projection_shapes(small):
    vg, g, p = small
    want = r"projections must have shape \(n_views, n_rows, n_cols\) = \(24, 64, 80\).*got \(23, 64, 80\)"
    with pytest.raises(ShapeError, match=want):
        fdk(p[:-1], vg, g)
    with pytest.raises(ShapeError, match=r"got \(24, 80, 64\)"):
        fdk(p.transpose(0, 2, 1), vg, g)
    with pytest.raises(ShapeError, match=r"got \(64, 80\)"):
        fdk(p[0], vg, g)
    with pytest.raises(ShapeError, match="real numbers"):
        fdk(p.astype(np.complex64), vg, g)
    with pytest.raises(ShapeError, match="real numbers"):
        fdk(np.full((24,) + DET, "a"), vg, g)


def test_wrong_beam_type(small):
    vg, g, p = small
    pg = parallel(np.linspace(0, np.pi, 24, endpoint=False), det_shape=DET, pixel=1.0)
    with pytest.raises(GeometryError, match="fdk needs a cone-beam geometry.*use pdvc.recon.fbp"):
        fdk(p, vg, pg)
    with pytest.raises(GeometryError, match="fbp needs a parallel-beam geometry.*use pdvc.recon.fdk"):
        fbp(p, vg, g)


def test_wrong_argument_types(small):
    vg, g, p = small
    with pytest.raises(InputTypeError, match="vol_geom must be a pdvc.VolumeGeometry, got tuple"):
        fdk(p, (16, 16, 16), g)
    with pytest.raises(InputTypeError, match="geom must be a pdvc.VectorGeometry, got ndarray"):
        fdk(p, vg, g.vectors)


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"filter": "gauss"}, "filter must be one of"),
        ({"cutoff": 0.0}, r"cutoff must be a fraction of the Nyquist frequency in \(0, 1\]"),
        ({"cutoff": 1.5}, "cutoff"),
        ({"short_scan": "yes"}, "short_scan must be 'auto', True or False"),
        ({"views_per_block": 0}, "views_per_block must be a positive int"),
        ({"center": (0.0, 0.0)}, "center must be a finite"),
        ({"axis": (0.0, 0.0, 0.0)}, "axis must be a non-zero"),
        ({"center": (0.0, -SOD - 50.0, 0.0)}, "must lie in front of the source"),
    ],
)
def test_bad_options(small, kw, match):
    vg, g, p = small
    with pytest.raises(PdvcError, match=match) as info:
        fdk(p, vg, g, **kw)
    assert isinstance(info.value, ValueError)


def test_volume_through_the_source(small):
    _, g, p = small
    big = VolumeGeometry((8, 8, 8), 2 * SOD / 7)  # reaches behind the source
    with pytest.raises(GeometryError, match="the volume reaches the source plane"):
        fdk(p, big, g)


def test_too_few_views(small):
    vg, g, p = small
    with pytest.raises(GeometryError, match="at least 2 views"):
        fdk(p[:1], vg, g[:1])


def test_views_per_block_does_not_change_the_result(small):
    vg, g, p = small
    a = fdk(p, vg, g, views_per_block=1)
    b = fdk(p, vg, g, views_per_block=100)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5 * np.abs(a).max())
