"""Temporal bases σ_n of the space-time regularisation (``DESIGN.md`` §2).

The displacement of the sample at view ``k`` is ``Σ_n Σ_j a_jn σ_n(k) ψ_j``:
each temporal function ``σ_n`` is given by its values at the views, i.e. one
column of a ``(n_views, n_funcs)`` matrix. The functions are evaluated on the
views' **acquisition time** (their order in the scan) and, for the periodic
part, on their **rotation angle**, so multi-turn, back-and-forth and
irregularly timed scans need nothing special.

Available bases (all built here, all returned as :class:`TemporalBasis`):

==================  =========================================================
``dirac``           one free value per view (identity matrix; no smoothing)
``constant``        one function, 1 (a fixed pose offset)
``poly:D``          Legendre polynomials ``P_0 … P_D`` of time rescaled to
                    ``[-1, 1]`` (well conditioned, unlike raw powers)
``fourier:M``       constant, linear drift in time, ``cos mθ``, ``sin mθ`` for
                    ``m = 1..M`` (period one turn); ``fourier:1`` is the
                    paper's 4-function basis (§2.3.1)
``fourier:M:nodrift`` the same without the drift column
``spline:N``        clamped B-splines of degree 3 on ``N`` uniformly spaced
                    *interior* knots (``N + 4`` functions); a partition of
                    unity over the scan's time span
==================  =========================================================

A custom ``(n_views, n_funcs)`` array is accepted as well
(:func:`custom_basis`). Every basis except Dirac is checked for full column
rank on the given views: a basis the views cannot determine is an error, not
an ill-conditioned solve later.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import BSpline

from .._arrays import frozen
from ..errors import InputTypeError, PdvcError, ShapeError

__all__ = [
    "BasisError",
    "BASIS_NAMES",
    "is_basis_name",
    "drift_basis",
    "TemporalBasis",
    "dirac_basis",
    "polynomial_basis",
    "fourier_basis",
    "bspline_basis",
    "custom_basis",
    "make_basis",
]

_KINDS = ("dirac", "poly", "fourier", "spline", "custom")


class BasisError(PdvcError, ValueError):
    """A temporal basis that is malformed or that the views cannot determine."""


_frozen = frozen


@dataclass(frozen=True, eq=False)
class TemporalBasis:
    """Values of ``n_funcs`` temporal functions at ``n_views`` views, immutable.

    Parameters
    ----------
    matrix : (n_views, n_funcs) array
        ``matrix[k, n] = σ_n(view k)``, dimensionless. Stored as a read-only
        float64 copy.
    names : tuple of str
        One name per function (column), e.g. ``("P0", "P1")``.
    kind : {"dirac", "poly", "fourier", "spline", "custom"}
        The family it was built from; ``"dirac"`` tells a solver that the
        full identification is block diagonal (6x6 per view).

    Notes
    -----
    Build instances with :func:`make_basis` or the ``*_basis`` functions,
    which also check the rank; the constructor only checks shapes, finiteness
    and names.
    """

    matrix: np.ndarray
    names: tuple
    kind: str

    def __post_init__(self) -> None:
        if self.kind not in _KINDS:
            raise BasisError(f"kind must be one of {_KINDS}, got {self.kind!r}")
        try:
            mat = np.array(self.matrix, dtype=np.float64, copy=True)
        except (TypeError, ValueError):
            raise InputTypeError(
                f"matrix must be a (n_views, n_funcs) array of numbers, got {type(self.matrix).__name__}"
            ) from None
        if mat.ndim != 2 or mat.shape[0] < 1 or mat.shape[1] < 1:
            raise ShapeError(f"matrix must have shape (n_views, n_funcs) with both >= 1, got {mat.shape}")
        if not np.all(np.isfinite(mat)):
            raise BasisError("matrix must be finite; it holds NaN or Inf")
        names = tuple(self.names)
        if len(names) != mat.shape[1] or not all(isinstance(n, str) for n in names):
            raise BasisError(f"names must be {mat.shape[1]} strings (one per column), got {self.names!r}")
        if len(set(names)) != len(names):
            raise BasisError(f"names must be distinct, got {names!r}")
        if self.kind == "dirac" and not (mat.shape[0] == mat.shape[1] and np.array_equal(mat, np.eye(mat.shape[0]))):
            raise BasisError(f"a 'dirac' basis must be the identity matrix, got a {mat.shape} matrix that is not")
        object.__setattr__(self, "matrix", _frozen(mat))
        object.__setattr__(self, "names", names)

    @property
    def n_views(self) -> int:
        """Number of views (rows)."""
        return self.matrix.shape[0]

    @property
    def n_funcs(self) -> int:
        """Number of temporal functions (columns)."""
        return self.matrix.shape[1]

    def __repr__(self) -> str:
        return f"TemporalBasis(kind={self.kind!r}, n_views={self.n_views}, n_funcs={self.n_funcs})"

    def gram(self) -> np.ndarray:
        """``σᵀσ``, the ``(n_funcs, n_funcs)`` Gram matrix over the views (float64)."""
        return self.matrix.T @ self.matrix

    def condition(self) -> float:
        """2-norm condition number of the matrix, ``s_max / s_min`` (``inf`` if rank deficient).

        The Gram matrix's condition number is its square. 1 for Dirac.
        """
        if self.kind == "dirac":
            return 1.0
        s = np.linalg.svd(self.matrix, compute_uv=False)
        return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


# -- checks -----------------------------------------------------------------
def _n_views(n_views) -> int:
    if not isinstance(n_views, (int, np.integer)) or isinstance(n_views, bool) or n_views < 1:
        raise BasisError(f"n_views must be a positive int, got {n_views!r}")
    return int(n_views)


def _nonneg_int(value, name: str, minimum: int = 0) -> int:
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < minimum:
        raise BasisError(f"{name} must be an int >= {minimum}, got {value!r}")
    return int(value)


def _samples(values, name: str, n: int | None = None) -> np.ndarray:
    try:
        arr = np.array(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputTypeError(f"{name} must be a 1D array of numbers, got {type(values).__name__}") from None
    if arr.ndim != 1 or arr.size < 1:
        raise ShapeError(f"{name} must be a non-empty 1D array (one value per view), got shape {arr.shape}")
    if n is not None and arr.size != n:
        raise ShapeError(f"{name} must have {n} values (one per view), got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise BasisError(f"{name} must be finite")
    return arr


def _default_times(n: int) -> np.ndarray:
    return np.arange(n, dtype=np.float64) / max(n - 1, 1)


def _rescale(times: np.ndarray, name: str = "times") -> np.ndarray:
    """Affine map of ``times`` onto ``[-1, 1]`` (min -> -1, max -> 1)."""
    lo, hi = times.min(), times.max()
    if not hi > lo:
        raise BasisError(f"{name} must span a non-zero interval for a time-dependent basis, got all equal to {lo!r}")
    return np.clip(2.0 * (times - lo) / (hi - lo) - 1.0, -1.0, 1.0)


def _check_rank(mat: np.ndarray, what: str) -> None:
    n, m = mat.shape
    if m > n:
        raise BasisError(f"{what} has {m} functions but only {n} views: it cannot be determined; use fewer functions")
    s = np.linalg.svd(mat, compute_uv=False)
    tol = max(n, m) * np.finfo(np.float64).eps * s[0]
    rank = int(np.count_nonzero(s > tol))
    if rank < m:
        raise BasisError(
            f"{what} is rank deficient on these views (rank {rank} < {m} functions): some of its functions "
            "take the same values at every view (too few distinct times or angles); use fewer functions"
        )


# -- builders ---------------------------------------------------------------
def dirac_basis(n_views: int) -> TemporalBasis:
    """One free value per view: the ``(n_views, n_views)`` identity.

    Names are ``"view0"``, ``"view1"``, ... The full identification with it
    is the per-view (block-diagonal, 6x6) registration.
    """
    n = _n_views(n_views)
    return TemporalBasis(np.eye(n), tuple(f"view{k}" for k in range(n)), "dirac")


def polynomial_basis(times, degree: int) -> TemporalBasis:
    """Legendre polynomials ``P_0 … P_degree`` of the acquisition time.

    Parameters
    ----------
    times : (n_views,) array, any time unit
        Acquisition time of each view (need not be sorted or regular). It is
        mapped affinely onto ``[-1, 1]`` (first -> -1, last -> 1) before
        evaluation, which keeps the Gram matrix well conditioned.
    degree : int, >= 0
        Highest degree; ``degree + 1`` functions named ``"P0"``, ``"P1"``, ...
        Degree 0 is the constant (needs no time span).

    Returns
    -------
    TemporalBasis of kind ``"poly"``

    Notes
    -----
    The span is that of raw powers ``1, t, …, t^D``: a least-squares fit of
    any polynomial of degree ``<= degree`` in time is exact.
    """
    t = _samples(times, "times")
    d = _nonneg_int(degree, "degree")
    if d == 0:
        mat = np.ones((t.size, 1))
    else:
        mat = np.polynomial.legendre.legvander(_rescale(t), d)
    _check_rank(mat, f"polynomial basis of degree {d}")
    return TemporalBasis(mat, tuple(f"P{k}" for k in range(d + 1)), "poly")


def fourier_basis(angles, times, order: int, *, drift: bool = True) -> TemporalBasis:
    """Low-order Fourier modes of the rotation angle, plus a linear drift in time.

    Columns, in this order: ``"const"`` (1); ``"drift"`` (time mapped
    affinely onto ``[-1, 1]``, if ``drift``); then ``"cos1"``, ``"sin1"``, …,
    ``"cos{M}"``, ``"sin{M}"`` = ``cos mθ``, ``sin mθ``. ``order=1`` with
    drift is the 4-function basis of the paper (§2.3.1): periodic motion of
    one turn (a tilted or off-centre axis seen in the sample frame) plus a
    steady drift that breaks periodicity.

    Parameters
    ----------
    angles : (n_views,) array, radians
        Rotation angle θ of each view. Since ``cos mθ`` and ``sin mθ`` are
        2π-periodic for integer m, unwrapped (multi-turn, ``0 … 4π``) and
        wrapped (``[0, 2π)``) angles give the same basis: the period is one
        turn of the table either way.
    times : (n_views,) array or None
        Acquisition times (any unit) for the drift column; ``None`` means the
        view index, which is right for a steady scan.
    order : int, >= 0
        Highest harmonic M (``0``: constant and drift only).
    drift : bool
        Include the linear drift column.

    Returns
    -------
    TemporalBasis of kind ``"fourier"``, ``1 + drift + 2·order`` functions.
    """
    th = _samples(angles, "angles")
    n = th.size
    t = _default_times(n) if times is None else _samples(times, "times", n)
    m = _nonneg_int(order, "order")
    cols, names = [np.ones(n)], ["const"]
    if drift:
        cols.append(_rescale(t))
        names.append("drift")
    for k in range(1, m + 1):
        cols += [np.cos(k * th), np.sin(k * th)]
        names += [f"cos{k}", f"sin{k}"]
    mat = np.column_stack(cols)
    _check_rank(mat, f"Fourier basis of order {m}{' with drift' if drift else ''}")
    return TemporalBasis(mat, tuple(names), "fourier")


def bspline_basis(times, n_knots: int, degree: int = 3) -> TemporalBasis:
    """Clamped B-splines of the acquisition time: smooth, local motion.

    Parameters
    ----------
    times : (n_views,) array, any time unit
        Acquisition time of each view.
    n_knots : int, >= 0
        Number of **interior** knots, placed uniformly over
        ``(min(times), max(times))``: the span is cut into ``n_knots + 1``
        equal intervals. The boundary knots ``min(times)`` and ``max(times)``
        are repeated ``degree + 1`` times (clamped), so there are
        ``n_knots + degree + 1`` functions (``"B0"``, ``"B1"``, ...), the first
        and last equal to 1 at the first and last time. ``n_knots = 0`` is
        the Bernstein basis of degree ``degree`` (a polynomial).
    degree : int, >= 0
        Polynomial degree of each piece (3: cubic, C² across knots).

    Returns
    -------
    TemporalBasis of kind ``"spline"``

    Notes
    -----
    The rows sum to 1 (partition of unity) at every view, so a constant pose
    is represented exactly (all coefficients equal), as is any polynomial of
    degree ``<= degree`` in time. Each function is non-zero over
    ``degree + 1`` intervals only. Every interval's functions must be seen
    by enough views, or the basis is rank deficient (an error).
    """
    t = _samples(times, "times")
    nk = _nonneg_int(n_knots, "n_knots")
    k = _nonneg_int(degree, "degree")
    lo, hi = float(t.min()), float(t.max())
    if not hi > lo:
        raise BasisError(f"times must span a non-zero interval for a spline basis, got all equal to {lo!r}")
    inner = np.linspace(lo, hi, nk + 2)[1:-1]
    knots = np.concatenate([np.full(k + 1, lo), inner, np.full(k + 1, hi)])
    mat = BSpline.design_matrix(np.clip(t, lo, hi), knots, k).toarray()
    _check_rank(mat, f"spline basis with {nk} interior knots and degree {k}")
    return TemporalBasis(mat, tuple(f"B{i}" for i in range(mat.shape[1])), "spline")


def custom_basis(matrix, names=None, *, n_views: int | None = None) -> TemporalBasis:
    """A user-given basis, checked.

    Parameters
    ----------
    matrix : (n_views, n_funcs) array
        Values of the functions at the views; finite, full column rank.
    names : sequence of str, optional
        Default ``"c0"``, ``"c1"``, ...
    n_views : int, optional
        If given, the number of rows the matrix must have.

    Returns
    -------
    TemporalBasis of kind ``"custom"`` (a copy; ``matrix`` is not modified)
    """
    try:
        mat = np.array(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputTypeError(
            f"matrix must be a (n_views, n_funcs) array of numbers, got {type(matrix).__name__}"
        ) from None
    if mat.ndim != 2 or mat.shape[0] < 1 or mat.shape[1] < 1:
        raise ShapeError(f"matrix must have shape (n_views, n_funcs), got {mat.shape}")
    if n_views is not None and mat.shape[0] != _n_views(n_views):
        raise ShapeError(f"matrix must have {n_views} rows (one per view), got shape {mat.shape}")
    if not np.all(np.isfinite(mat)):
        raise BasisError("matrix must be finite; it holds NaN or Inf")
    _check_rank(mat, "custom basis")
    names = tuple(f"c{i}" for i in range(mat.shape[1])) if names is None else tuple(names)
    return TemporalBasis(mat, names, "custom")


_SPEC = re.compile(r"^(dirac|constant|drift(?::(\d+))?|poly:(\d+)|fourier:(\d+)(:nodrift)?|spline:(\d+))$")

#: The names :func:`make_basis` accepts, for messages.
BASIS_NAMES = "'dirac', 'constant', 'drift', 'drift:M', 'poly:D', 'fourier:M', 'fourier:M:nodrift', 'spline:N'"


def is_basis_name(spec) -> bool:
    """Whether ``spec`` is a basis name that :func:`make_basis` accepts (case and spaces ignored)."""
    return isinstance(spec, str) and _SPEC.match(spec.strip().lower()) is not None


def drift_basis(angles, times=None, order: int = 1) -> TemporalBasis:
    """{1, t, t², cos kθ, sin kθ (k = 1..order)}: an offset, a drift with constant acceleration and a shifted axis.

    In the lab frame ``order = 1`` also spans a once-per-turn precession of
    the axis, ``order = 2`` a precession at one and two cycles per turn.
    Falls back to fewer functions when the views cannot determine them (very
    few views). ``make_basis("drift", ...)`` (``"drift:M"``) gives the same.
    """
    th = _samples(angles, "angles")
    n = th.size
    t = _default_times(n) if times is None else _samples(times, "times", n)
    if not isinstance(order, (int, np.integer)) or isinstance(order, bool) or order < 0:
        raise BasisError(f"order must be an int >= 0, got {order!r}")
    orders = sorted({int(order), min(int(order), 1), 0}, reverse=True)
    for degree, m in [(d, o) for o in orders for d in (2, 1, 0)]:
        try:
            cols = [polynomial_basis(t, degree).matrix] if degree > 0 else [np.ones((n, 1))]
            names = [f"t^{d}" for d in range(cols[0].shape[1])]
            if m:
                cols.append(fourier_basis(th, t, m, drift=False).matrix[:, 1:])
                names += [f"{f}{k}" for k in range(1, m + 1) for f in ("cos", "sin")]
            return custom_basis(np.column_stack(cols), names=names)
        except BasisError:
            continue
    raise BasisError(f"no drift basis can be determined from {n} views")  # pragma: no cover


def make_basis(spec, *, angles, times=None) -> TemporalBasis:
    """Temporal basis from a short specification.

    Parameters
    ----------
    spec : str, TemporalBasis or (n_views, n_funcs) array
        ``"dirac"``, ``"constant"``, ``"drift"`` (:func:`drift_basis`), ``"poly:D"``, ``"fourier:M"`` (with
        linear drift), ``"fourier:M:nodrift"``, ``"spline:N"`` (cubic, N
        interior knots; see :func:`bspline_basis`); a :class:`TemporalBasis`
        (checked for the number of views and returned as is); or an array
        (:func:`custom_basis`).
    angles : (n_views,) array, radians
        Rotation angle of each view; fixes ``n_views``.
    times : (n_views,) array, optional
        Acquisition time of each view (any unit). Default: the view index
        scaled to ``[0, 1]``, ``k / (n_views - 1)``.

    Returns
    -------
    TemporalBasis

    Examples
    --------
    >>> import numpy as np
    >>> b = make_basis("fourier:1", angles=np.linspace(0, 2 * np.pi, 100, endpoint=False))
    >>> b.names
    ('const', 'drift', 'cos1', 'sin1')
    """
    th = _samples(angles, "angles")
    n = th.size
    t = _default_times(n) if times is None else _samples(times, "times", n)
    if isinstance(spec, TemporalBasis):
        if spec.n_views != n:
            raise ShapeError(f"spec is a TemporalBasis of {spec.n_views} views, but angles has {n}")
        return spec
    if isinstance(spec, np.ndarray) or (isinstance(spec, (list, tuple)) and np.ndim(spec) == 2):
        return custom_basis(spec, n_views=n)
    if not isinstance(spec, str):
        raise InputTypeError(
            f"spec must be a string, a TemporalBasis or a 2D array, got {type(spec).__name__}"
        )
    m = _SPEC.match(spec.strip().lower())
    if m is None:
        raise BasisError(f"spec must be one of {BASIS_NAMES} (D, M, N non-negative ints), got {spec!r}")
    word = m.group(1)
    if word == "dirac":
        return dirac_basis(n)
    if word == "constant":
        return polynomial_basis(t, 0)
    if word.startswith("drift"):
        return drift_basis(th, t, 1 if m.group(2) is None else int(m.group(2)))
    if m.group(3) is not None:
        return polynomial_basis(t, int(m.group(3)))
    if m.group(4) is not None:
        return fourier_basis(th, t, int(m.group(4)), drift=m.group(5) is None)
    return bspline_basis(t, int(m.group(6)))
