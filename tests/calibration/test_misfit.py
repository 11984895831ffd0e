"""cross_validated_misfit: comparing finished calibrations on views their reconstruction was not made from."""

import numpy as np
import pytest

from pdvc.calibration import cross_validated_misfit
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
