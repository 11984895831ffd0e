"""Parallel-beam FDK/FBP stages fill the 2x correlation grid by cubic B-splines (docs/method.md §5.50).

On the 2x grid every other slice lies on a detector row of a parallel-beam
scan whose axis has no pitch toward the beam, and the reprojection of the FBP
fits the data worse there than at a small pitch: the FBP rounds walked the
pitch of rods longer than the field. The spline-filled volume has its best fit
at the true pitch.
"""

from __future__ import annotations

import numpy as np
import pytest

import pdvc
from pdvc.calibration import Stage, _pipeline, resolve_stages, truncation_weights
from pdvc.calibration._driver import correlation_volume
from pdvc.geometry import circular_cone, parallel
from pdvc.recon import refined_grid, spline_upsample
from pdvc.simulate import cast_iron_phantom, combine_poses, simulate_scan, tilted_axis_poses


def _turn(n=90):
    return np.linspace(0.0, 2 * np.pi, n, endpoint=False)


def test_parallel_fdk_stages_are_spline_oversampled_and_nothing_else_is():
    par = parallel(_turn(), det_shape=(76, 89), pixel=1.0)
    cone = circular_cone(_turn(), sod=300.0, odd=150.0, det_shape=(76, 89), pixel=1.5)
    fdk = lambda st: [s for s in st if s.reconstruct == "fdk"]  # noqa: E731
    on_par = resolve_stages((76, 89), vol_shape=(64, 64, 64), geom=par)
    assert fdk(on_par) and all(s.oversample_by == "auto" for s in fdk(on_par))
    # cone beam, no geometry (nothing known of the beam), the user's choice, nonneg_ls stages, one-to-one grids: as
    # the stage says
    for st in (resolve_stages((76, 89), vol_shape=(64, 64, 64), geom=cone), resolve_stages((76, 89), vol_shape=(64, 64, 64)),
               resolve_stages((76, 89), vol_shape=(64, 64, 64), geom=par, oversample_by="reconstruction"),
               resolve_stages((76, 89), vol_shape=(64, 64, 64), geom=par, recipe="precession"),
               resolve_stages((76, 89), vol_shape=(64, 64, 64), geom=par, oversample=1)):
        assert all(s.oversample_by == Stage().oversample_by for s in st)
    assert all(s.reconstruct == "nonneg_ls" for s in resolve_stages((76, 89), geom=par, recipe="precession"))


@pytest.fixture(scope="module")
def rod():
    """A noise-free parallel scan of a rod 3x longer than the volume, its axis offset and tilted in the detector plane."""
    n = 32
    ang = _turn(96)
    geom = parallel(ang, det_shape=(int(1.2 * n), int(1.4 * n)), pixel=1.0)
    rv, t = tilted_axis_poses(ang, tilt=np.deg2rad(-0.35), offset=(2.3, 0.0, 0.0))
    scan = simulate_scan(cast_iron_phantom(0.36 * n, 3 * n, n_nodules=11 * n, seed=3), geom, rotvecs=rv,
                         translations=t, seed=3, supersampling=2)
    vg = pdvc.VolumeGeometry((n, n, n))
    return scan.clean, geom, ang, vg, (rv, t), truncation_weights(geom, vg)


def _misfit(rod, pitch_deg, spline):
    """Weighted mean squared residual of the FBP at the true geometry with the axis pitched toward the beam."""
    p, geom, ang, vg, (rv, t), w = rod
    pitch = tilted_axis_poses(ang, tilt=np.deg2rad(pitch_deg), tilt_azimuth=-np.pi / 2)
    g = geom.apply_poses(*combine_poses((rv, t), pitch))
    fine = refined_grid(vg, 2)
    vol = spline_upsample(pdvc.fbp(p, vg, g), 2) if spline else pdvc.fbp(p, fine, g)
    return float(np.sum(w * (p - pdvc.forward(vol, fine, g)) ** 2) / np.sum(w))


def test_the_spline_filled_fbp_fits_a_rod_best_at_the_true_pitch(rod):
    # the spline-filled volume: lowest misfit at the truth (pitch 0), higher at +-0.6 deg
    at0, plus, minus = (_misfit(rod, d, True) for d in (0.0, 0.6, -0.6))
    assert at0 < min(plus, minus)
    # FBP on the 2x grid: the truth is not the best fit of the pitch (what the FBP rounds walked along)
    at0, plus, minus = (_misfit(rod, d, False) for d in (0.0, 0.6, -0.6))
    assert at0 > min(plus, minus)


def test_auto_is_the_spline_in_parallel_beam_and_the_fine_reconstruction_in_cone_beam(rod):
    p, geom, ang, vg, _, _ = rod
    auto, spline, fine = (Stage(oversample_by=k) for k in ("auto", "spline", "reconstruction"))
    np.testing.assert_array_equal(correlation_volume(p, vg, geom, auto), correlation_volume(p, vg, geom, spline))
    cone = circular_cone(ang, sod=400.0, odd=200.0, det_shape=geom.det_shape, pixel=1.5)
    np.testing.assert_array_equal(correlation_volume(p, vg, cone, auto), correlation_volume(p, vg, cone, fine))


class _Ran(Exception):
    pass


def _stages_run(monkeypatch, radius, **kw):
    """The stage list calibrate hands to run_stages on a parallel full turn of a rod of ``radius`` (x 24 voxels) in a
    volume 34 voxels wide: wider than it is a region of interest."""
    ran = []

    def record(p, geom, vol_geom, stages, **kw):
        ran.append(stages)
        raise _Ran

    monkeypatch.setattr(_pipeline, "run_stages", record)
    n = 24
    geom = parallel(_turn(48), det_shape=(8, 34), pixel=1.0)
    scan = simulate_scan(cast_iron_phantom(radius * n, 3 * n, n_nodules=40, seed=1), geom, seed=1, supersampling=1)
    with pytest.raises(_Ran):
        pdvc.calibrate(scan.projections, geom, pdvc.VolumeGeometry((8, 34, 34)), **kw)
    return ran[0]


@pytest.mark.parametrize("radius, by, tol", [(0.9, "reconstruction", Stage().diverge_tol), (0.3, "auto", 0.0)])
def test_a_region_of_interest_scan_runs_the_recipe_without_the_spline_and_the_strict_first_scale(monkeypatch, radius,
                                                                                                   by, tol):
    # no second run follows a region-of-interest scan, and rods wider than the field fitted worse on the spline volume
    # (docs/method.md §5.50): calibrate runs the recipe's stages for a region of interest there
    st = _stages_run(monkeypatch, radius)
    fdk = [s for s in st if s.reconstruct == "fdk"]
    assert fdk and all(s.oversample_by == by for s in fdk)
    assert [s for s in st if s.name == "model"][0].diverge_tol == tol


def test_stages_of_the_users_own_keep_all_but_the_automatic_oversampling_on_a_region_of_interest(monkeypatch):
    mine = tuple(s.replace(diverge_tol=0.0, rounds=3) for s in resolve_stages((8, 34), geom=parallel(_turn(48), det_shape=(
        8, 34), pixel=1.0)))
    st = _stages_run(monkeypatch, 0.9, stages=mine)
    assert st == tuple(s.replace(oversample_by="reconstruction") if s.oversample_by == "auto" else s for s in mine)
    assert any(s.oversample_by == "auto" for s in mine)
