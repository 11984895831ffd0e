"""cross_validated_misfit: comparing finished calibrations on views their reconstruction was not made from."""

import numpy as np
import pytest

from pdvc.calibration import cross_validated_misfit
from pdvc.correlation._background import background_basis, without_background
from pdvc.errors import InputTypeError, ShapeError
from pdvc.geometry import fix_gauge
from pdvc.simulate import tilted_axis_poses
from tests.correlation.cases import make_case


@pytest.fixture(scope="module")
def case():
    return make_case("offset", n=32, n_views=60)


def test_the_true_geometry_predicts_the_views_left_out_best(case):
    # Known answer: analytic projections (no inverse crime) of a sample turning about an axis 2 voxels off
    # centre. The true geometry must predict the views left out better than the same axis 0.5 voxel off,
    # and that one better than the nominal geometry (2 voxels off); a 1 deg tilt too is seen. Measured:
    # 0.000766 (truth), 0.00696 (0.5 voxel off), 0.0724 (nominal), 0.000787 (tilted).
    g = case.scan.geometry
    truth = g.apply_poses(*fix_gauge(case.scan.rotvecs, case.scan.translations, g, center=case.vol_geom.offset))
    angles = np.linspace(0, 2 * np.pi, g.n_views, endpoint=False)
    half_off = truth.apply_poses(*tilted_axis_poses(angles, tilt=0.0, offset=(0.5, 0.0, 0.0)))
    tilted = truth.apply_poses(*tilted_axis_poses(angles, tilt=np.deg2rad(1.0)))
    p = case.scan.projections
    before = p.copy()
    m = cross_validated_misfit(p, case.vol_geom, [truth, half_off, g, tilted])
    assert np.array_equal(p, before)  # the data are not modified
    assert m.shape == (4,) and np.all(np.isfinite(m)) and np.all(m > 0)
    assert m[0] < m[1] < m[2] and m[0] < m[3]
    # at scale 2, with three sets of views and weights (a column given no weight), the truth still wins
    w = np.ones(g.det_shape, np.float32)
    w[:, 0] = 0.0
    m2 = cross_validated_misfit(p, case.vol_geom, [truth, g], scale=2, folds=3, weights=w)
    assert m2[0] < m2[1]  # measured 0.000129, 0.0629


def test_each_set_of_views_measures_its_step_bound_once_for_all_the_geometries(case, monkeypatch):
    # The step bound of a set's volumes depends on the grid and the set's geometry only: it is measured once per set,
    # at the first geometry. The first geometry's misfit is then the same bit for bit as when it is compared alone;
    # the others' within what the bound's change between geometries a fraction of a pixel apart makes
    import pdvc.calibration._select as sel

    g = case.scan.geometry
    truth = g.apply_poses(*fix_gauge(case.scan.rotvecs, case.scan.translations, g, center=case.vol_geom.offset))
    angles = np.linspace(0, 2 * np.pi, g.n_views, endpoint=False)
    off = truth.apply_poses(*tilted_axis_poses(angles, tilt=np.deg2rad(0.3), offset=(0.3, 0.0, 0.0)))
    p = case.scan.projections
    calls = []
    measured = sel.nonneg_ls_lipschitz
    monkeypatch.setattr(sel, "nonneg_ls_lipschitz", lambda *a, **k: calls.append(1) or measured(*a, **k))
    both = cross_validated_misfit(p, case.vol_geom, [truth, off])
    assert len(calls) == 2  # two sets of views, two geometries
    assert cross_validated_misfit(p, case.vol_geom, [truth])[0] == both[0]
    assert cross_validated_misfit(p, case.vol_geom, [off])[0] == pytest.approx(both[1], rel=1e-4)
    assert both[0] < both[1]


def test_the_background_taken_out_of_each_view_is_its_weighted_least_squares_plane():
    # Known answer: a plane per view added to a residual is taken out exactly (what is left is the residual's own
    # part orthogonal to the planes, under the weights), and pixels of weight 0 do not count
    rng = np.random.default_rng(0)
    shape = (5, 7, 9)
    phi = background_basis(shape[1:], 1).reshape(3, -1)
    noise = rng.normal(size=shape)
    planes = (rng.normal(size=(5, 3)) @ phi).reshape(shape)
    w = np.ones(shape[1:])
    w[:, :2] = 0.0
    out = without_background(noise + planes, 1, w)
    assert np.allclose(out, without_background(noise, 1, w), atol=1e-12)
    assert np.allclose((out.reshape(5, -1) * w.reshape(-1)) @ phi.T, 0.0, atol=1e-12)  # orthogonal to the planes
    # a pixel of weight 0 changes nothing
    bumped = noise.copy()
    bumped[:, :, 0] += 100.0
    assert np.allclose(without_background(bumped, 1, w)[:, :, 2:], out[:, :, 2:], atol=1e-9)
    # no weights: every pixel counts, and a plane alone is taken out entirely
    assert np.allclose(without_background(planes, 1), 0.0, atol=1e-12)


def test_an_air_level_that_drifts_is_not_counted_against_a_geometry(case):
    # An air level drifting from view to view, with a ramp across the detector that flips sign halfway (an
    # imperfect flat field), adds an unexplained residual to every geometry's predictions and hides how much better
    # the true geometry predicts than one 0.5 voxel off. With the plane of each predicted view taken out
    # (background=1), part of the truth's lead comes back (the volumes, made from views that hold the air, keep the
    # rest). Measured, misfit of the truth and ratio of the other's to it: clean 0.000766, 9.08x; with the air
    # 0.00968, 1.57x; with the air and background=1 0.00297, 2.69x.
    g = case.scan.geometry
    truth = g.apply_poses(*fix_gauge(case.scan.rotvecs, case.scan.translations, g, center=case.vol_geom.offset))
    angles = np.linspace(0, 2 * np.pi, g.n_views, endpoint=False)
    half_off = truth.apply_poses(*tilted_axis_poses(angles, tilt=0.0, offset=(0.5, 0.0, 0.0)))
    p = case.scan.projections
    nv, _, nc = p.shape
    k = np.arange(nv)[:, None, None]
    u = np.linspace(-1.0, 1.0, nc)[None, None, :]
    air = (0.15 * k / nv + 0.05 * u * np.where(k < nv // 2, 1.0, -1.0)).astype(np.float32)
    clean = cross_validated_misfit(p, case.vol_geom, [truth, half_off])
    plain = cross_validated_misfit(p + air, case.vol_geom, [truth, half_off])
    fitted = cross_validated_misfit(p + air, case.vol_geom, [truth, half_off], background=1)
    assert fitted[0] < fitted[1] and clean[0] < clean[1]
    assert fitted[0] < 0.4 * plain[0]
    assert fitted[1] / fitted[0] > 1.4 * (plain[1] / plain[0])
    with pytest.raises(InputTypeError, match="background"):
        cross_validated_misfit(p, case.vol_geom, [truth], background=3)


def test_bad_input_is_refused_with_the_parameter_named(case):
    g, p, vg = case.scan.geometry, case.scan.projections, case.vol_geom
    with pytest.raises(ShapeError, match=r"geometries\[0\]"):
        cross_validated_misfit(p[:, :-1], vg, [g])
    with pytest.raises(InputTypeError, match="geometries"):
        cross_validated_misfit(p, vg, [])
    with pytest.raises(InputTypeError, match="folds"):
        cross_validated_misfit(p, vg, [g], folds=1)
    with pytest.raises(InputTypeError, match="vol_geom"):
        cross_validated_misfit(p, "grid", [g])
