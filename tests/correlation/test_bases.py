"""Temporal bases: shapes, spans (exact reproduction), conditioning, errors."""

import numpy as np
import pytest

import pdvc
from pdvc.correlation._bases import (
    BasisError,
    TemporalBasis,
    bspline_basis,
    custom_basis,
    dirac_basis,
    fourier_basis,
    make_basis,
    polynomial_basis,
)

N = 90
ANGLES = np.linspace(0, 2 * np.pi, N, endpoint=False)


def _fit_residual(basis, values):
    coef, *_ = np.linalg.lstsq(basis.matrix, values, rcond=None)
    return np.max(np.abs(basis.matrix @ coef - values))


def test_dirac_is_identity_and_read_only():
    b = dirac_basis(7)
    assert (b.n_views, b.n_funcs, b.kind) == (7, 7, "dirac")
    np.testing.assert_array_equal(b.matrix, np.eye(7))
    assert b.names[0] == "view0" and b.condition() == 1.0
    with pytest.raises(ValueError):
        b.matrix[0, 0] = 2.0


@pytest.mark.parametrize("degree", [0, 1, 2, 4])
def test_polynomial_reproduces_polynomials_exactly(degree, rng):
    # irregular, unsorted times in seconds: the basis lives on time, not on view index
    times = np.sort(rng.uniform(0, 3600, N))[rng.permutation(N)]
    b = polynomial_basis(times, degree)
    assert b.matrix.shape == (N, degree + 1)
    assert b.names == tuple(f"P{k}" for k in range(degree + 1))
    tt = times / 3600
    target = sum(rng.normal() * tt**k for k in range(degree + 1))
    # exact up to rounding: float64 lstsq on a condition number < 10
    assert _fit_residual(b, target) < 1e-10 * max(1, np.abs(target).max())
    if degree < 4:  # one degree more is not in the span
        assert _fit_residual(b, tt ** (degree + 1)) > 1e-3
    # Legendre on [-1, 1]: well conditioned (raw powers of degree 4 on [0, 3600] would be ~1e15)
    assert b.condition() < 10


def test_polynomial_rescaling_maps_span_to_unit_interval():
    b = polynomial_basis([10.0, 12.0, 20.0], 1)
    np.testing.assert_allclose(b.matrix[:, 1], [-1.0, -0.6, 1.0])
    np.testing.assert_allclose(b.matrix[:, 0], 1.0)


def test_fourier_paper_basis_and_reproduction(rng):
    b = fourier_basis(ANGLES, None, 1)
    assert b.names == ("const", "drift", "cos1", "sin1") and b.n_funcs == 4
    # a once-per-turn wobble of any phase plus a drift is in the span, exactly
    target = 0.3 + 0.1 * np.linspace(-1, 1, N) + 0.7 * np.sin(ANGLES + 0.4)
    assert _fit_residual(b, target) < 1e-12
    # the second harmonic is not
    assert _fit_residual(b, np.cos(2 * ANGLES)) > 0.5
    b2 = fourier_basis(ANGLES, None, 2, drift=False)
    assert b2.names == ("const", "cos1", "sin1", "cos2", "sin2")
    assert _fit_residual(b2, np.cos(2 * ANGLES - 1.0)) < 1e-12
    assert _fit_residual(b2, np.linspace(0, 1, N)) > 0.1  # no drift column
    # columns of norms √N, √(N/3), √(N/2) and drift correlated with sin1 over one turn: ~3.4
    assert np.isfinite(b.condition()) and b.condition() < 5


def test_fourier_multi_turn_uses_angle_not_time():
    # two turns, the second slower: period one turn of the table, whatever the timing
    angles = np.concatenate([np.linspace(0, 2 * np.pi, 40, endpoint=False), np.linspace(2 * np.pi, 4 * np.pi, 80)])
    times = np.concatenate([np.linspace(0, 1, 40, endpoint=False), np.linspace(1, 3, 80)])
    b = fourier_basis(angles, times, 1)
    wrapped = fourier_basis(np.mod(angles, 2 * np.pi), times, 1)
    np.testing.assert_allclose(b.matrix, wrapped.matrix, atol=1e-12)
    assert _fit_residual(b, np.cos(angles) + 0.5 * times) < 1e-12
    np.testing.assert_allclose(b.matrix[:, 1], 2 * times / 3 - 1, atol=1e-12)  # drift is in time


@pytest.mark.parametrize("n_knots", [0, 1, 5])
def test_spline_partition_of_unity_and_polynomial_reproduction(n_knots, rng):
    times = np.sort(rng.uniform(0, 50, N))
    b = bspline_basis(times, n_knots)
    assert b.matrix.shape == (N, n_knots + 4)
    np.testing.assert_allclose(b.matrix.sum(axis=1), 1.0, atol=1e-12)
    assert np.all(b.matrix >= -1e-15)
    # clamped: first and last functions are 1 at the ends of the span
    assert b.matrix[np.argmin(times), 0] == pytest.approx(1.0)
    assert b.matrix[np.argmax(times), -1] == pytest.approx(1.0)
    assert _fit_residual(b, (times / 50) ** 3 - times / 50) < 1e-10  # cubics are in the span
    assert np.isfinite(b.condition())


def test_spline_is_local():
    b = bspline_basis(np.linspace(0, 1, 101), 9)  # 10 intervals of 0.1
    # cubic: each function is non-zero over at most 4 intervals (~40 of the 101 views)
    assert np.all(np.count_nonzero(b.matrix > 1e-14, axis=0) <= 41)
    # the middle function B6 lives on [0.3, 0.7]
    support = np.nonzero(b.matrix[:, 6] > 1e-14)[0]
    assert support.min() >= 30 and support.max() <= 70


def test_custom_basis_validation():
    m = np.column_stack([np.ones(5), np.arange(5.0)])
    b = custom_basis(m, names=("one", "ramp"))
    assert b.kind == "custom" and b.names == ("one", "ramp")
    b.matrix  # noqa: B018
    m[0, 0] = 99.0
    assert b.matrix[0, 0] == 1.0  # copy, input not shared
    with pytest.raises(BasisError, match="rank deficient"):
        custom_basis(np.column_stack([np.ones(5), 2 * np.ones(5)]))
    with pytest.raises(BasisError, match="finite"):
        custom_basis(np.array([[1.0], [np.nan]]))
    with pytest.raises(pdvc.ShapeError, match="3 rows"):
        custom_basis(np.ones((5, 1)), n_views=3)
    with pytest.raises(BasisError, match="only 2 views"):
        custom_basis(np.ones((2, 3)))
    with pytest.raises(BasisError, match="names"):
        custom_basis(np.ones((4, 1)), names=("a", "b"))


def test_make_basis_specs():
    assert make_basis("dirac", angles=ANGLES).kind == "dirac"
    c = make_basis("constant", angles=ANGLES)
    assert c.n_funcs == 1 and np.all(c.matrix == 1)
    p = make_basis("poly:2", angles=ANGLES)
    np.testing.assert_allclose(p.matrix[:, 1], np.linspace(-1, 1, N), atol=1e-12)  # default times k/(n-1)
    assert make_basis("fourier:1", angles=ANGLES).n_funcs == 4
    assert make_basis("fourier:3:nodrift", angles=ANGLES).n_funcs == 7
    assert make_basis("spline:6", angles=ANGLES).n_funcs == 10
    b = fourier_basis(ANGLES, None, 1)
    assert make_basis(b, angles=ANGLES) is b
    arr = make_basis(np.ones((N, 1)), angles=ANGLES)
    assert arr.kind == "custom"
    # times are used when given
    t = np.linspace(0, 1, N) ** 2
    np.testing.assert_allclose(make_basis("poly:1", angles=ANGLES, times=t).matrix[:, 1], 2 * t - 1)


@pytest.mark.parametrize("spec", ["fourier", "poly:-1", "spline", "cubic", "fourier:1:drift", ""])
def test_make_basis_bad_spec(spec):
    with pytest.raises(BasisError, match="spec must be one of"):
        make_basis(spec, angles=ANGLES)


def test_make_basis_errors():
    with pytest.raises(pdvc.InputTypeError, match="spec must be a string"):
        make_basis(3, angles=ANGLES)
    with pytest.raises(pdvc.ShapeError, match="90 values"):
        make_basis("poly:1", angles=ANGLES, times=np.arange(10.0))
    with pytest.raises(pdvc.ShapeError, match="TemporalBasis of 7 views"):
        make_basis(dirac_basis(7), angles=ANGLES)
    # more functions than views / too few distinct angles
    with pytest.raises(BasisError, match="cannot be determined"):
        make_basis("poly:5", angles=ANGLES[:4])
    with pytest.raises(BasisError, match="rank deficient"):
        make_basis("fourier:2:nodrift", angles=np.tile([0.0, np.pi / 2], 10))
    with pytest.raises(BasisError, match="non-zero interval"):
        polynomial_basis(np.zeros(5), 1)
    with pytest.raises(BasisError, match="non-zero interval"):
        bspline_basis(np.ones(5), 2)
    with pytest.raises(BasisError, match="degree"):
        polynomial_basis(np.arange(5.0), -1)
    with pytest.raises(BasisError, match="finite"):
        polynomial_basis([0.0, np.inf], 1)


def test_dataclass_validation():
    with pytest.raises(BasisError, match="kind"):
        TemporalBasis(np.eye(2), ("a", "b"), "wavelet")
    with pytest.raises(BasisError, match="identity"):
        TemporalBasis(np.ones((2, 2)), ("a", "b"), "dirac")
    with pytest.raises(BasisError, match="distinct"):
        TemporalBasis(np.eye(2), ("a", "a"), "custom")
    with pytest.raises(pdvc.ShapeError):
        TemporalBasis(np.ones(3), ("a",), "custom")
    b = make_basis("poly:1", angles=ANGLES)
    np.testing.assert_allclose(b.gram(), b.matrix.T @ b.matrix)
    assert b.gram().shape == (2, 2)
    # condition: s_max / s_min, and the Gram's is its square
    assert np.linalg.cond(b.gram()) == pytest.approx(b.condition() ** 2, rel=1e-9)


def test_drift_m_spans_one_to_m_cycles_per_turn_with_a_quadratic_drift():
    a = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    b = make_basis("drift:2", angles=a)
    assert b.names == ("t^0", "t^1", "t^2", "cos1", "sin1", "cos2", "sin2")
    t = np.linspace(0, 1, 60)
    target = np.column_stack([1 + 0 * t, t, t**2, np.cos(a), np.sin(a), np.cos(2 * a), np.sin(2 * a)])
    coef = np.linalg.lstsq(b.matrix, target, rcond=None)[0]
    np.testing.assert_allclose(b.matrix @ coef, target, atol=1e-10)
    assert make_basis("drift:1", angles=a).names == make_basis("drift", angles=a).names
    np.testing.assert_array_equal(make_basis("drift:1", angles=a).matrix, make_basis("drift", angles=a).matrix)
