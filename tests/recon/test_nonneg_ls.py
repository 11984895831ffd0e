"""Non-negative least squares on a B-spline grid (the outer loop's consistent reconstruction)."""

import numpy as np
import pytest

import pdvc
from pdvc.errors import PdvcError
from pdvc.recon import fdk, nonneg_ls, nonneg_ls_lipschitz
from pdvc.recon._iterative import _along, _banded, spline_upsampling_matrix

from ..conftest import gaussian_blob_volume


@pytest.mark.parametrize("n, factor", [(6, 2), (7, 3), (5, 1)])
def test_spline_upsampling_reproduces_constants_and_lines_inside_the_grid(n, factor):
    # cubic B-splines form a partition of unity and reproduce linear functions exactly
    M = spline_upsampling_matrix(n, factor).astype(np.float64)
    assert M.shape == (factor * n, n)
    j = np.arange(factor * n)
    xc = (j - (factor * n - 1) / 2) / factor + (n - 1) / 2  # fine voxel centres in coarse index units
    inside = (xc >= 1) & (xc <= n - 2)  # away from the zero coefficients beyond the grid
    np.testing.assert_allclose(M.sum(axis=1)[inside], 1.0, atol=1e-6)
    np.testing.assert_allclose((M @ np.arange(n))[inside], xc[inside], atol=1e-5)
    if factor == 1:
        np.testing.assert_array_equal(M, np.eye(n))


def test_spline_upsampling_is_applied_with_its_exact_transpose():
    rng = np.random.default_rng(1)
    mats = [spline_upsampling_matrix(n, 2) for n in (4, 5, 6)]
    c = rng.standard_normal((4, 5, 6)).astype(np.float32)
    y = rng.standard_normal((8, 10, 12)).astype(np.float32)
    uc, uty = c, y
    for ax, M in enumerate(mats):
        uc = _along(_banded(M), uc, ax)
        uty = _along(_banded(M.T), uty, ax)
    assert uc.shape == y.shape and uty.shape == c.shape
    lhs, rhs = float(np.vdot(uc, y)), float(np.vdot(c, uty))
    assert abs(lhs - rhs) <= 1e-5 * abs(lhs)


@pytest.mark.parametrize("factor", [1, 2, 3])
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_banded_application_equals_the_dense_matrix_product(axis, factor):
    # the banded kernels against numpy's dense product, M and its transpose, every axis
    rng = np.random.default_rng(axis + 10 * factor)
    shape = [5, 6, 7]
    M = spline_upsampling_matrix(shape[axis], factor)
    for mat in (M, M.T):
        x = rng.standard_normal(shape[:axis] + [mat.shape[1]] + shape[axis + 1:]).astype(np.float32)
        want = np.moveaxis(np.tensordot(mat.astype(np.float64), x.astype(np.float64), axes=(1, axis)), 0, axis)
        got = _along(_banded(mat), x, axis)
        assert got.dtype == np.float32 and got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


def _spline_operator(vg, geom, f):
    """(coarse shape, coarse grid, U, Π U, Uᵀ Πᵀ) of nonneg_ls over all of ``geom``'s views: the reference its step
    bound is checked against."""
    from pdvc.recon._iterative import _spline_maps, _spline_pair

    shape, vg_c, up, up_t = _spline_maps(vg, f)
    return (shape, vg_c, up, *_spline_pair(vg, geom, up, up_t, "auto"))


@pytest.fixture(scope="module")
def blob_scan():
    vg = pdvc.VolumeGeometry((16, 16, 16))
    vol = gaussian_blob_volume(vg, np.array([1.5, -2.0, 0.5]), 3.0, 1.0).astype(np.float32)
    angles = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    geom = pdvc.circular_cone(angles, sod=80.0, odd=40.0, det_shape=(24, 24), pixel=1.5)
    return vg, vol, geom, pdvc.forward(vol, vg, geom)


def test_nonneg_ls_fits_consistent_data_better_than_fdk_and_stays_non_negative(blob_scan):
    vg, vol, geom, p = blob_scan
    p_in = p.copy()
    norms = []
    x = nonneg_ls(p, vg, geom, n_iter=30, support=False, callback=lambda it, rn: norms.append(rn))
    np.testing.assert_array_equal(p, p_in)  # input untouched
    assert x.dtype == np.float32 and x.shape == vg.shape
    assert x.min() >= 0.0
    assert len(norms) == 30
    r_ls = np.linalg.norm(pdvc.forward(x, vg, geom) - p)
    r_fdk = np.linalg.norm(pdvc.forward(fdk(p, vg, geom), vg, geom) - p)
    assert r_ls < 0.02 * r_fdk  # measured 0.006
    assert np.linalg.norm(x - vol) < 0.01 * np.linalg.norm(vol)  # it reconstructs, not just fits (0.0013)
    # more iterations, smaller residual
    x5 = nonneg_ls(p, vg, geom, n_iter=5, support=False)
    assert r_ls < 0.1 * np.linalg.norm(pdvc.forward(x5, vg, geom) - p)


def test_the_automatic_support_zeroes_what_lies_far_from_the_sample(blob_scan):
    vg, vol, geom, p = blob_scan
    x = nonneg_ls(p, vg, geom, n_iter=10)
    far = vol < 1e-4 * vol.max()
    assert np.all(x[far & (np.abs(x) > 0)] < 0.05 * vol.max())
    assert np.count_nonzero(x[far] == 0) > 0.5 * np.count_nonzero(far)
    assert np.linalg.norm(x - vol) < 0.1 * np.linalg.norm(vol)  # a smooth blob loses its faint tails


def test_nonneg_ls_on_a_spline_grid_and_with_a_given_support(blob_scan):
    vg, vol, geom, p = blob_scan
    x = nonneg_ls(p, vg, geom, coarsen=2, n_iter=30)
    assert x.shape == vg.shape and x.min() >= 0.0
    assert np.linalg.norm(x - vol) < 0.3 * np.linalg.norm(vol)
    # a support of one coarse octant: nothing outside its splines' reach
    support = np.zeros((8, 8, 8), bool)
    support[4:, :4, 4:] = True
    xs = nonneg_ls(p, vg, geom, coarsen=2, n_iter=5, support=support)
    assert np.all(xs[:5] == 0) and np.all(xs[:, 11:] == 0) and np.all(xs[:, :, :5] == 0)
    assert xs.max() > 0


def test_nonneg_ls_clips_what_least_squares_would_make_negative(blob_scan):
    vg, vol, geom, p = blob_scan
    neg = p - 2.0 * p.mean()  # inconsistent with any non-negative volume
    x = nonneg_ls(neg, vg, geom, n_iter=5, support=False)
    assert x.min() >= 0.0


@pytest.mark.parametrize(
    "kw, err, match",
    [
        (dict(coarsen=3), pdvc.ShapeError, "coarsen"),
        (dict(coarsen=0), PdvcError, "coarsen"),
        (dict(n_iter=-1), PdvcError, "n_iter"),
        (dict(n_iter=2.5), PdvcError, "n_iter"),
        (dict(coarsen=2, support=np.ones((4, 4, 4), bool)), pdvc.ShapeError, "support"),
        (dict(lipschitz=-1.0), PdvcError, "lipschitz"),
        (dict(lipschitz=float("nan")), PdvcError, "lipschitz"),
        (dict(lipschitz="1"), PdvcError, "lipschitz"),
        (dict(subsets=0), PdvcError, "subsets"),
        (dict(subsets=41), PdvcError, "subsets"),
        (dict(subsets=2.0), PdvcError, "subsets"),
        (dict(subsets=True), PdvcError, "subsets"),
    ],
)
def test_nonneg_ls_rejects_bad_options(blob_scan, kw, err, match):
    vg, vol, geom, p = blob_scan
    with pytest.raises(err, match=match):
        nonneg_ls(p, vg, geom, **kw)


def test_nonneg_ls_rejects_projections_of_the_wrong_shape(blob_scan):
    vg, vol, geom, p = blob_scan
    with pytest.raises(pdvc.ShapeError, match="projections"):
        nonneg_ls(p[:-1], vg, geom)


def test_nonneg_ls_weights_keep_rays_that_see_outside_the_volume_from_pulling_it(blob_scan):
    # Rays that also cross material outside the volume (a rod longer than the box: here the top
    # eight detector rows carry extra attenuation the box cannot hold) pull the unweighted fit;
    # with weight 0 on them it is the fit of the clean data (same iterations, same start).
    vg, vol, geom, p = blob_scan
    dirty = p.copy()
    dirty[:, :8, :] += 0.5
    w = np.ones(p.shape[1:], np.float32)
    w[:8, :] = 0.0
    kw = dict(n_iter=20, support=False)
    clean = nonneg_ls(p, vg, geom, weights=w, **kw)
    weighted = nonneg_ls(dirty, vg, geom, weights=w, **kw)
    plain = nonneg_ls(dirty, vg, geom, **kw)
    err = lambda x: float(np.linalg.norm(x - vol) / np.linalg.norm(vol))  # noqa: E731
    fdk_start = nonneg_ls(dirty, vg, geom, weights=w, n_iter=0, support=False)
    # the start (FDK of the dirty data) differs; the weighted iterations pull it back toward the clean fit
    assert err(weighted) < 0.5 * err(plain)
    assert err(weighted) < err(fdk_start)
    assert err(clean) <= err(weighted) + 0.05
    np.testing.assert_array_equal(nonneg_ls(p, vg, geom, weights=np.ones(p.shape, np.float32), **kw), nonneg_ls(p, vg, geom, **kw))
    with pytest.raises(Exception, match="weights"):
        nonneg_ls(p, vg, geom, weights=np.ones((3, 3), np.float32), n_iter=1)
    with pytest.raises(Exception, match="weights"):
        nonneg_ls(p, vg, geom, weights=2 * w, n_iter=1)


def test_nonneg_ls_lipschitz_is_the_top_eigenvalue_and_a_given_one_is_used(blob_scan):
    """``nonneg_ls_lipschitz`` is the step bound ``nonneg_ls`` estimates itself
    (the same result when passed back), it is the largest eigenvalue of
    UᵀΠᵀΠU (no unit vector is amplified more, checked on random ones), it
    barely moves when the poses move by a fraction of a voxel, and a
    different value passed in changes the iterations."""
    vg, vol, geom, p = blob_scan
    lip = nonneg_ls_lipschitz(vg, geom, coarsen=2)
    kw = dict(coarsen=2, n_iter=6)
    np.testing.assert_array_equal(nonneg_ls(p, vg, geom, lipschitz=lip, **kw), nonneg_ls(p, vg, geom, **kw))
    assert not np.array_equal(nonneg_ls(p, vg, geom, lipschitz=3 * lip, **kw), nonneg_ls(p, vg, geom, **kw))
    shape, _, _, A, AT = _spline_operator(vg, geom, 2)
    rng = np.random.default_rng(4)
    for _ in range(3):
        v = rng.standard_normal(shape).astype(np.float32)
        v /= np.linalg.norm(v)
        assert float(np.vdot(v, AT(A(v)))) <= 1.01 * lip
    rot = np.tile([0.0, 0.0, 0.002], (geom.n_views, 1))
    moved = geom.apply(pdvc.Poses(rot, np.tile([0.3, -0.2, 0.1], (geom.n_views, 1))))
    assert abs(nonneg_ls_lipschitz(vg, moved, coarsen=2) / lip - 1) < 0.02
    with pytest.raises(pdvc.ShapeError, match="coarsen"):
        nonneg_ls_lipschitz(vg, geom, coarsen=3)


def test_the_step_bound_from_ones_is_the_top_eigenvalue_from_below(blob_scan):
    """Three power iterations from the constant vector (the top eigenvector of a non-negative operator is
    non-negative) give the largest eigenvalue of UᵀΠᵀΠU within 1 %, from below."""
    from pdvc.recon._iterative import _power_iteration

    vg, vol, geom, p = blob_scan
    shape, _, _, A, AT = _spline_operator(vg, geom, 2)
    lip = nonneg_ls_lipschitz(vg, geom, coarsen=2)
    top = _power_iteration(shape, A, AT, n_iter=40)
    assert 0.99 * top < lip <= top * (1 + 1e-5)


@pytest.mark.parametrize("kind", ["parallel_half_turn", "cone_full_turn", "cone_uneven"])
def test_the_step_bound_from_a_sample_of_the_views_is_the_one_of_all_views(kind):
    """Above 2 x LIPSCHITZ_VIEWS views the step bound is measured on every k-th view and scaled by the views' number
    over the sample's: within 0.5 % of the power iteration over all views (91 parallel views over 180°, whose sample
    of 31 is not a third of them; a cone full turn of 150 views; 120 views crowded into the first half of the turn),
    and nonneg_ls steps by it."""
    from pdvc.recon._iterative import LIPSCHITZ_VIEWS, _lipschitz_views, _power_iteration

    vg = pdvc.VolumeGeometry((12, 20, 20))
    if kind == "parallel_half_turn":
        geom = pdvc.parallel(np.linspace(0, np.pi, 91, endpoint=False), det_shape=(12, 24), pixel=1.0)
    elif kind == "cone_full_turn":
        geom = pdvc.circular_cone(np.linspace(0, 2 * np.pi, 150, endpoint=False), sod=80.0, odd=40.0,
                                  det_shape=(16, 28), pixel=1.5)
    else:
        u = np.linspace(0, 1, 120, endpoint=False)
        geom = pdvc.circular_cone(2 * np.pi * u**2, sod=80.0, odd=40.0, det_shape=(16, 28), pixel=1.5)
    views = _lipschitz_views(geom.n_views)
    assert LIPSCHITZ_VIEWS <= views.size < geom.n_views
    for coarsen in (1, 2):
        shape, _, _, A, AT = _spline_operator(vg, geom, coarsen)
        full = _power_iteration(shape, A, AT)
        assert abs(nonneg_ls_lipschitz(vg, geom, coarsen=coarsen) / full - 1) < 0.005
    p = pdvc.forward(gaussian_blob_volume(vg, np.zeros(3), 3.0, 1.0).astype(np.float32), vg, geom)
    lip = nonneg_ls_lipschitz(vg, geom)
    np.testing.assert_array_equal(nonneg_ls(p, vg, geom, n_iter=3, lipschitz=lip), nonneg_ls(p, vg, geom, n_iter=3))
    assert _lipschitz_views(2 * LIPSCHITZ_VIEWS - 1).size == 2 * LIPSCHITZ_VIEWS - 1  # fewer: all of them


def test_the_ramp_preconditioner_is_symmetric_positive_and_a_ramp_in_the_planes_normal_to_z():
    from pdvc.recon._iterative import RAMP_FLOOR, _ramp_preconditioner

    rng = np.random.default_rng(3)
    shape = (5, 12, 10)
    M = _ramp_preconditioner(shape, (1.0, 1.0, 1.0))
    u, v = (rng.standard_normal(shape).astype(np.float32) for _ in range(2))
    lhs, rhs = float(np.vdot(u, M(v))), float(np.vdot(M(u), v))
    assert abs(lhs - rhs) <= 1e-5 * abs(lhs)  # symmetric
    assert float(np.vdot(u, M(u))) > 0  # positive
    # no coupling between planes: a slice stays in its plane
    only = np.zeros(shape, np.float32)
    only[2] = u[2]
    out = M(only)
    assert np.all(out[[0, 1, 3, 4]] == 0)
    # a constant is scaled by the floor (k = 0); a plane wave of k cycles per voxel by about |k| + floor in the
    # middle of the plane (the zero padding lets the edges differ)
    c = M(np.ones(shape, np.float32))
    assert abs(float(c[2, 6, 5]) - RAMP_FLOOR) < 0.2 * RAMP_FLOOR + 0.05 * 0.5
    wave = np.cos(2 * np.pi * 0.25 * np.arange(10))[None, None, :] * np.ones(shape, np.float32)
    ratio = M(wave.astype(np.float32))[2, 6, 4] / wave[2, 6, 4]
    assert 0.2 < ratio < 0.35  # |k| = 0.25


def test_the_preconditioned_fit_converges_faster_to_the_same_volume(blob_scan):
    # a parallel scan (rays normal to z: the ramp is Π^T Π's inverse there) of an analytic-free smooth blob
    vg, vol, _, _ = blob_scan
    geom = pdvc.parallel(np.linspace(0, np.pi, 60, endpoint=False), det_shape=(20, 24), pixel=1.0)
    p = pdvc.forward(vol, vg, geom)
    p_in = p.copy()

    def residual(x):
        return float(np.linalg.norm(pdvc.forward(x, vg, geom) - p))

    ref = nonneg_ls(p, vg, geom, n_iter=400, support=False)
    plain = nonneg_ls(p, vg, geom, n_iter=20, support=False)
    pre = nonneg_ls(p, vg, geom, n_iter=10, support=False, precondition=True)
    np.testing.assert_array_equal(p, p_in)
    assert pre.min() >= 0.0 and pre.dtype == np.float32
    # measured: 10 filtered iterations leave a residual of 0.031, 20 plain ones 0.052 (10 plain: 0.19); the
    # volume is within 0.20 % of the 400-iteration fit (10 plain: 0.27 %)
    assert residual(pre) < 0.8 * residual(plain)
    assert np.linalg.norm(pre - ref) < 0.004 * np.linalg.norm(ref)
    # its step bound is the top eigenvalue of the filtered normal operator, from below but close
    lip = nonneg_ls_lipschitz(vg, geom, precondition=True)
    assert lip != nonneg_ls_lipschitz(vg, geom)
    from pdvc.recon._iterative import _power_iteration, _ramp_preconditioner

    shape, vg_c, _, A, AT = _spline_operator(vg, geom, 1)
    assert abs(_power_iteration(shape, A, AT, _ramp_preconditioner(shape, vg_c.voxel_size), n_iter=30) / lip - 1) < 0.05


def test_ordered_subsets_reach_the_plain_iterations_volume_at_a_fraction_of_the_projections():
    """Interleaved subsets of the views (each subset's gradient scaled by their number) follow the
    plain iteration of an early-stopped fit: 30 iterations on 5 subsets of 18 views (the mean of the
    last five iterates returned) give the volume of 30 plain iterations within 0.5 % and the same
    residual within 0.5 % (measured 0.34 % and 0.10 %), while 30 plain iterations on one subset alone
    are 7x farther (2.5 %: a fifth of the data). With per-view weights each subset takes its own views'
    weights (0.4 % from the clean fit, 4.4 % without them); ``subsets=1`` is the plain iteration."""
    vg = pdvc.VolumeGeometry((16, 20, 20))
    vol = (gaussian_blob_volume(vg, np.array([1.5, -2.0, 0.5]), 3.0, 1.0)
           + gaussian_blob_volume(vg, np.array([-3.0, 2.5, -1.0]), 1.5, 0.7)).astype(np.float32)
    angles = np.linspace(0, np.pi, 90, endpoint=False)
    geom = pdvc.parallel(angles, det_shape=(16, 26), pixel=1.0)
    p = pdvc.forward(vol, vg, geom)
    p = p + np.random.default_rng(0).normal(0.0, 0.02 * float(p.max()), p.shape).astype(np.float32)
    kw = dict(coarsen=2, n_iter=30)
    plain = nonneg_ls(p, vg, geom, **kw)
    os5 = nonneg_ls(p, vg, geom, subsets=5, **kw)
    rel = lambda a, b: float(np.linalg.norm(a - b) / np.linalg.norm(b))  # noqa: E731
    res = lambda x: float(np.linalg.norm(pdvc.forward(x, vg, geom) - p))  # noqa: E731
    assert rel(os5, plain) < 0.005
    assert abs(res(os5) / res(plain) - 1) < 0.005
    one = nonneg_ls(p[0::5], vg, geom[np.arange(0, 90, 5)], **kw)
    assert rel(one, plain) > 5 * rel(os5, plain)
    np.testing.assert_array_equal(nonneg_ls(p, vg, geom, subsets=1, **kw), plain)
    w = np.ones(p.shape, np.float32)
    w[1::5, :4] = 0.0  # the top rows of one subset's views only
    dirty = p.copy()
    dirty[1::5, :4] += 1.0
    weighted = nonneg_ls(dirty, vg, geom, weights=w, subsets=5, **kw)
    unweighted = nonneg_ls(dirty, vg, geom, subsets=5, **kw)
    assert rel(weighted, plain) < 0.5 * rel(unweighted, plain)
