"""Simulated scans with known per-view motion and realistic counting noise.

The sample is projected analytically with the *true* geometry
``geom.apply_poses(rotvecs, translations)`` (moving the sample is moving the
scanner the other way, exactly), so nothing of the voxel projector that the
calibration inverts enters the data (``DESIGN.md`` §4).

Detector model, per pixel and frame (counts, detector gain 1):

* projection: ``Poisson(i0 · exp(-p)) + dark_level + Normal(0, dark_noise)``;
* flat field: ``Poisson(i0) + dark_level + Normal(0, dark_noise)``, ``n_flats`` frames;
* dark field: ``dark_level + Normal(0, dark_noise)``, ``n_darks`` frames.

The user's projections are then ``-log((I - D) / (F - D))`` with ``D`` and
``F`` the means of the darks and flats. A normalised intensity below
``0.5 / i0`` (half a photon; zero or negative where the counts were
swamped by noise) is clipped to it, so a line integral never exceeds
``log(2 i0)``; :attr:`SimulatedScan.n_clipped` counts those pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._arrays import frozen
from ..errors import InputTypeError, ShapeError
from ..geometry import Poses, VectorGeometry
from ._checks import SimulationError, as_int, as_positive
from .analytic import project_analytic
from .phantoms import EllipsoidPhantom

__all__ = ["SimulatedScan", "simulate_scan", "add_poisson_noise"]


_frozen = frozen


@dataclass(frozen=True, eq=False)
class SimulatedScan:
    """A simulated scan and its ground truth (all arrays read-only).

    Attributes
    ----------
    projections : (n_views, n_rows, n_cols) float32
        Noisy line integrals as a user computes them from the counts,
        ``-log((counts - dark) / (flat - dark))`` (clipped, see module doc).
    clean : (n_views, n_rows, n_cols) float32
        Exact line integrals with the true geometry (no noise).
    counts : (n_views, n_rows, n_cols) float32
        Raw detector frames (photon counts plus dark signal).
    flats : (n_flats, n_rows, n_cols) float32
        Raw flat-field frames (no sample).
    darks : (n_darks, n_rows, n_cols) float32
        Raw dark frames (no beam).
    geometry : VectorGeometry
        The nominal geometry (what the user believes).
    true_geometry : VectorGeometry
        ``geometry.apply_poses(rotvecs, translations)``: what produced the data.
    rotvecs, translations : (n_views, 3) float64
        The true per-view poses (radians; length units).
    angles : (n_views,) float64 or None
        Nominal scan angles if given to :func:`simulate_scan`.
    phantom : EllipsoidPhantom
    i0 : float
        Mean photon counts per pixel and frame without sample.
    dark_level, dark_noise : float
        Mean and standard deviation of the dark signal, counts.
    supersampling : int
        Sub-rays per pixel and axis used for the clean projections.
    n_clipped : int
        Pixels of ``projections`` whose normalised intensity was clipped.
    seed : int, numpy.random.Generator or None
    """

    projections: np.ndarray
    clean: np.ndarray
    counts: np.ndarray
    flats: np.ndarray
    darks: np.ndarray
    geometry: VectorGeometry
    true_geometry: VectorGeometry
    rotvecs: np.ndarray
    translations: np.ndarray
    angles: np.ndarray | None
    phantom: EllipsoidPhantom
    i0: float
    dark_level: float
    dark_noise: float
    supersampling: int
    n_clipped: int
    seed: object = None

    @property
    def n_views(self) -> int:
        return self.projections.shape[0]

    @property
    def poses(self) -> Poses:
        """The true poses (``rotvecs``, ``translations``) as one :class:`pdvc.geometry.Poses`."""
        return Poses(self.rotvecs, self.translations)

    @property
    def flat(self) -> np.ndarray:
        """Mean flat field, ``(n_rows, n_cols)`` float32, counts."""
        return self.flats.mean(axis=0, dtype=np.float64).astype(np.float32)

    @property
    def dark(self) -> np.ndarray:
        """Mean dark field, ``(n_rows, n_cols)`` float32, counts."""
        return self.darks.mean(axis=0, dtype=np.float64).astype(np.float32)

    def noise_variance(self) -> np.ndarray:
        """Expected variance of each projection pixel (delta method), float32.

        ``Var p ≈ (N + σ²)/N² + (i0 + σ²)/(n_flats i0²)`` with ``N = i0 e^{-p}``
        the expected counts and σ = ``dark_noise`` (the dark mean's own noise
        is neglected; it is ``σ²/n_darks`` counts²). The second term (flat
        noise) is shared by all views of a pixel.
        """
        n = self.i0 * np.exp(-self.clean.astype(np.float64))
        s2 = self.dark_noise**2
        var = (n + s2) / n**2 + (self.i0 + s2) / (self.flats.shape[0] * self.i0**2)
        return var.astype(np.float32)


def simulate_scan(
    phantom: EllipsoidPhantom,
    geom: VectorGeometry,
    *,
    rotvecs=None,
    translations=None,
    angles=None,
    i0: float = 2e4,
    dark_level: float = 100.0,
    dark_noise: float = 2.0,
    n_flats: int = 10,
    n_darks: int = 10,
    seed=0,
    supersampling: int = 2,
) -> SimulatedScan:
    """Simulate a scan of a moving phantom with counting noise.

    Parameters
    ----------
    phantom : EllipsoidPhantom
        Attenuation in 1/length (length unit of ``geom``).
    geom : VectorGeometry
        Nominal geometry (cone or parallel).
    rotvecs, translations : (n_views, 3) or (3,) arrays, optional
        True per-view poses of the sample (radians, length units;
        ``DESIGN.md`` §1 convention, e.g. from :mod:`pdvc.simulate.motion`).
        Zero when omitted.
    angles : (n_views,) array, radians, optional
        Nominal scan angles, only stored in the result.
    i0 : float, counts
        Mean photons per pixel and frame in the open beam (> 0).
    dark_level : float, counts
        Mean dark signal (>= 0), added to every frame.
    dark_noise : float, counts
        Standard deviation of the dark (read) noise per frame (>= 0).
    n_flats, n_darks : int, >= 1
        Numbers of flat and dark frames averaged for the normalisation.
    seed : int or numpy.random.Generator
        Random source; the same seed gives the same data. Draw order: darks,
        flats, projections.
    supersampling : int, >= 1
        Sub-rays per pixel and axis of the analytic projection.

    Returns
    -------
    SimulatedScan

    Examples
    --------
    >>> import numpy as np
    >>> from pdvc.geometry import circular_cone
    >>> from pdvc.simulate import cast_iron_phantom, simulate_scan, drift_poses
    >>> angles = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    >>> geom = circular_cone(angles, sod=10, odd=10, det_shape=(64, 64), pixel=0.08)
    >>> rv, t = drift_poses(np.arange(90.0), angles, velocity=(1e-3, 0, 0))
    >>> scan = simulate_scan(cast_iron_phantom(1.0, 2.0), geom, rotvecs=rv, translations=t)
    >>> scan.projections.shape
    (90, 64, 64)
    """
    if not isinstance(phantom, EllipsoidPhantom):
        raise InputTypeError(f"phantom must be an EllipsoidPhantom, got {type(phantom).__name__}")
    if not isinstance(geom, VectorGeometry):
        raise InputTypeError(f"geom must be a VectorGeometry, got {type(geom).__name__}")
    n = geom.n_views
    rv = np.zeros((n, 3)) if rotvecs is None else rotvecs
    tr = np.zeros((n, 3)) if translations is None else translations
    true_geom = geom.apply_poses(rv, tr)  # validates shapes and finiteness
    rv = np.broadcast_to(np.asarray(rv, np.float64), (n, 3)).copy()
    tr = np.broadcast_to(np.asarray(tr, np.float64), (n, 3)).copy()
    if angles is not None:
        angles = np.array(angles, dtype=np.float64)
        if angles.shape != (n,):
            raise ShapeError(f"angles must have shape ({n},) like the geometry's views, got {angles.shape}")
    i0 = as_positive(i0, "i0")
    dark_level = as_positive(dark_level, "dark_level", allow_zero=True)
    dark_noise = as_positive(dark_noise, "dark_noise", allow_zero=True)
    n_flats = as_int(n_flats, "n_flats", minimum=1)
    n_darks = as_int(n_darks, "n_darks", minimum=1)
    ss = as_int(supersampling, "supersampling", minimum=1)

    clean = project_analytic(phantom, true_geom, supersampling=ss)
    rng = np.random.default_rng(seed)
    shape = geom.det_shape
    darks = dark_level + dark_noise * rng.standard_normal((n_darks, *shape))
    flats = rng.poisson(i0, (n_flats, *shape)) + dark_level + dark_noise * rng.standard_normal((n_flats, *shape))
    expected = i0 * np.exp(-clean.astype(np.float64))
    counts = rng.poisson(expected) + dark_level + dark_noise * rng.standard_normal(clean.shape)
    darks, flats, counts = darks.astype(np.float32), flats.astype(np.float32), counts.astype(np.float32)

    dark = darks.mean(axis=0, dtype=np.float64)
    flat = flats.mean(axis=0, dtype=np.float64)
    floor = 0.5 / i0
    ratio = (counts - dark) / np.maximum(flat - dark, 0.5)
    clipped = ratio < floor
    proj = -np.log(np.maximum(ratio, floor))
    return SimulatedScan(
        projections=_frozen(proj.astype(np.float32)),
        clean=_frozen(clean),
        counts=_frozen(counts),
        flats=_frozen(flats),
        darks=_frozen(darks),
        geometry=geom,
        true_geometry=true_geom,
        rotvecs=_frozen(rv),
        translations=_frozen(tr),
        angles=None if angles is None else _frozen(angles),
        phantom=phantom,
        i0=i0,
        dark_level=dark_level,
        dark_noise=dark_noise,
        supersampling=ss,
        n_clipped=int(np.count_nonzero(clipped)),
        seed=seed,
    )


def add_poisson_noise(line_integrals, i0: float, *, seed=0) -> np.ndarray:
    """Line integrals with the Poisson noise of ``i0`` photons per pixel.

    Counts ``N ~ Poisson(i0 · exp(-p))`` and returns ``-log(N / i0)``; zero
    counts are clipped to half a photon (``p <= log(2 i0)``). No flat, dark
    or read noise: use :func:`simulate_scan` for the full detector model.

    Parameters
    ----------
    line_integrals : array, dimensionless
        Any shape; not modified.
    i0 : float, counts
        Mean open-beam photons per pixel (> 0).
    seed : int or numpy.random.Generator

    Returns
    -------
    float32 array, the shape of ``line_integrals``
    """
    p = np.asarray(line_integrals, dtype=np.float64)
    if not np.all(np.isfinite(p)):
        raise SimulationError("line_integrals must be finite numbers")
    i0 = as_positive(i0, "i0")
    rng = np.random.default_rng(seed)
    counts = rng.poisson(i0 * np.exp(-p)).astype(np.float64)
    return (-np.log(np.maximum(counts, 0.5) / i0)).astype(np.float32)
