"""Configuration of a calibration run: TOML file -> checked :class:`Config` -> geometries.

The configuration file
======================

One TOML file describes a run. Lengths are in mm, angles in degrees,
positions on the detector in pixels, pairs on the detector are
``[row, col]`` (row first, like the arrays ``p[view, row, col]``), volume
triples follow the volume's conventions (``shape`` and ``voxel_size`` in
array order ``[z, y, x]``, ``offset`` a point ``[x, y, z]``). Relative paths
are relative to the folder of the configuration file. An unknown section or
key is an error that lists the allowed ones: a misspelt key is never
silently ignored. Only ``[data] path`` and ``[geometry] type`` (with what
that type needs) are required; everything else has the default shown.

.. code-block:: toml

    [data]                      # the projections
    path = "scan/"              # file, folder or glob: TIFF folder/stack, HDF5 (NXtomo, Data Exchange), .npy  (required)
    format = "auto"             # "auto" | "tiff-folder" | "tiff" | "dxchange" | "nxtomo" | "npy"
    # dataset = "/entry/data"   # dataset inside an HDF5 file (default: found by the reader)
    # flats = "flats/"          # open-beam images: file, folder or glob
    # darks = "darks/*.tif"     # dark images: file, folder or glob
    sinogram = false            # true: stored as sinograms [row, view, col]
    is_raw = "auto"             # true: raw counts (-log of flat/dark-normalised values is taken; needs flats);
                                # "transmission": flat-field-corrected I/I0 (-log taken, no flats needed);
                                # false: line integrals already; "auto": counts with flats, integers or a file
                                # that says counts, else decided from the values (pdvc.io.classify_values:
                                # values in (0, ~1.05] with the air at the top -> transmission; air near 0
                                # with the sample larger -> line integrals; values >> 1 -> counts); the
                                # decision and why are printed by `pdvc inspect` and `pdvc calibrate`
    # open_beam_columns = [0, 40]  # columns [a, b) free of sample, to normalise views without flats

    [geometry]
    type = "cone"               # "cone" | "parallel" | "vectors" | "nikon" | "skyscan"  (required)
    # type = "cone": nominal circular scan (DESIGN.md §1), rotation axis = z
    sod = 250.0                 # source to rotation axis, mm (> 0)                       (required)
    odd = 750.0                 # rotation axis to detector, mm (> 0) -- or sdd = 1000.0   (required)
    pixel = 0.2                 # detector pitch, mm: one number or [row, col]            (required)
    det_offset = [0.0, 0.0]     # shift of the detector centre along v and u, pixels
    angles = "auto"             # see "angles" below
    # det_shape = [1024, 1024]  # [rows, cols]; default: from the projections
    # type = "parallel": pixel, det_offset, det_shape, angles
    # type = "vectors":
    #   vectors = "geom.npy"    # .npy or text, (n_views, 12) rows (src, d, u, v), mm, volume frame
    #                           # (ASTRA cone_vec; parallel3d_vec with beam = "parallel")   (required)
    #   beam = "cone"           # "cone" | "parallel"
    #   det_shape = [rows, cols]
    # type = "nikon" | "skyscan":
    #   file = "scan.xtekct"    # .xtekct (Nikon) or .log (SkyScan)                        (required)
    #   vendor_angles = "auto"  # nikon: "auto" (_ctdata.txt / .ang when present) | "nominal" (step)
    #   vendor_offsets = true   # apply the file's axis and detector offsets
    #   (vendor geometries describe the images as stored, row 0 at the top; see pdvc.io._vendor)

    # angles -- one of:
    #   "auto" (default)   the angles stored with the projections (HDF5) if any, else evenly
    #                      over [0, 360) (cone) or [0, 180) (parallel), one per projection
    #   "data"             the angles stored with the projections (an error if there are none)
    #   a list of degrees, one per projection     angles = [0.0, 0.5, 1.0]
    #   a file (.npy or text, one per line)       angles = "angles.txt"   (a file named data: "./data")
    #   a range                                   angles = {start = 0, stop = 360, count = 720, endpoint = false}
    #     count angles from start towards stop, stop excluded unless endpoint = true;
    #     count defaults to the number of projections.

    [volume]                    # the reconstruction grid
    # shape = [nz, ny, nx]      # default [n_rows, n_cols, n_cols]
    # voxel_size = 0.05         # mm, one number or [sz, sy, sx]; default below
    offset = [0.0, 0.0, 0.0]    # position of the volume centre [x, y, z], mm

    [preprocess]
    # mask = "mask.tif"         # bad detector pixels: a (rows, cols) .tif/.npy image, nonzero = bad, in
                                # the layout of the views; replaced in projections, flats and darks by
                                # linear interpolation along the row from the nearest good pixels,
                                # before anything else (NaN/Inf there are then no error)
    # dead_columns = [12, 13]   # whole bad detector columns (added to mask); a lone dead column
                                # becomes the mean of its two neighbours
    flat_interpolation = "linear"  # "linear" (flats interpolated in time between groups) | "mean"
    clip_min = 1e-6             # transmissions below this are clipped (0 < clip_min < 1)
    air = "none"                # the air level (what rays missing the sample read; 0 when the flats
                                # match) is always measured and reported (pdvc.io.estimate_air), a problem
                                # when off 0 by more than 0.02 (and 3x its uncertainty) or varying by more
                                # than 0.05 across the columns; "none": report only; "auto": subtract
                                # it -- a per-view offset plus a degree-2 polynomial profile across the
                                # columns, shared by all views, fitted to the air pixels (a flat mismatch multiplies
                                # the beam by view x column factors: additive in line integrals; the
                                # shared profile bridges columns the sample always covers)
    # beam_hardening = [1.0, 0.05, 0.01]  # p -> c1 p + c2 p^2 + c3 p^3 ... on the line integrals
    # roi_rows = [100, 900]     # keep detector rows [a, b) (crop, geometry follows)
    # roi_cols = [0, 1024]      # keep detector columns [a, b)
    bin = 1                     # bin the projections bin x bin when loading

    [calibration]
    recipe = "default"          # "default" (tilted, offset axis; drift) | "precession" (a precessing axis)
                                # | "jolts" (sudden jumps) | "axis" (a fixed axis only); see docs/method.md
    # recipe parameters: each changes the recipe's model stage (unset: the recipe's own value)
    # basis = "fourier:1"       # "dirac" | "constant" | "drift" | "poly:D" | "fourier:M" | "fourier:M:nodrift" | "spline:N"
    # method = "full"           # "full" | "pgd"
    # frame = "sample"          # "sample" | "lab"
    # fixed = ["rz"]            # parameters held at zero, among "tx","ty","tz","rx","ry","rz"
    # reconstruct = "fdk"       # correlation volume: "fdk" (FBP in parallel beam) | "nonneg_ls" | "cgls";
                                #   unset on a parallel scan over 180°: "nonneg_ls" (the offset is weakly determined)
    # guards = ["consistency"]  # "consistency" (stop if a fresh reconstruction fits worse) | "entropy"
    # max_outer = 10            # rounds per scale, warm-up included (precession, jolts: 8)
    # tol_px = 0.01             # a round moving sample points by less ends the stage (full-resolution px)
    # max_iter = 10             # Jacobian passes per correlation (per round)
    # accelerate = true         # Anderson-accelerated Gauss-Newton steps (docs/method.md 5.6)
    # extrapolate = false       # rounds that creep along one mode jump to their limit (Aitken; off: docs/method.md 5.6)
    # robust = 0                # Huber weights on the residual beyond this many robust std, in every pass (IRLS),
                                #   for outliers the preprocessing left (5 measured); 0 = least squares (docs/method.md 5.19)
    # max_modes = 5             # PGD: modes at most
    # pgd_passes = 5            # PGD: alternating passes per mode
    # min_gain = 0.01           # PGD: stop when a mode lowers chi by less than this fraction
    # noise_floor = 1.05        # PGD: stop when chi falls below this
    # rcond = 1e-6              # eigenvalue ratio below which a direction is unobservable
    # oversample = 2            # correlation grid this many times finer than the reconstruction grid
    # oversample_by = "reconstruction"  # or "spline": FDK on the stage grid, cubic B-spline to the finer one (8x cheaper);
                                # unset, parallel-beam FDK stages take "auto" (the spline, but on a region of interest)
    # background = "auto"       # a smooth background per view fitted with the motion: -1 none, 0 offset, 1 plane,
                                # 2 quadratic; "auto": a plane when the residual's per-view offset is well above the noise
    # candidates = ["fixed_axis", "precession"]  # default recipe: motion models compared with its own ("axis") on
                                # views they were not fitted to, before the model stage; [] = none (also when
                                # basis/frame/fixed are set); "fixed_axis": an offset, tilted axis (full turns only)
    scales = "auto"             # coarse-graining scales, strictly decreasing, e.g. [4, 2]; "auto": from the detector
                                # (without the finest scales a parallel full turn of few views undersamples)
    warmup = 1                  # translation-only rounds before a model with free rotations, at the first scale
    # refine = false            # true: the default recipe (its model chosen from the data, its own volume) ends with
                                #   up to 4 rounds of the precession model on nonneg_ls volumes at the coarsest scale
                                #   (docs/method.md 5.22; better on the benchmark, worse on a plain tilted axis)
    # ... or the whole stage list, one table per stage (then no recipe parameter above):
    # [[calibration.stage]]
    # name = "warmup"           # every field of pdvc.calibration.Stage: name, basis, frame, fixed, method,
    # basis = "drift"           # reconstruct, scale, oversample, oversample_by, rounds, tol_px, until ("converged" |
    # frame = "lab"             # "rounds"), stall_ratio (0: none), guards, diverge_tol, entropy_tol,
    # fixed = ["rx", "ry", "rz"]  # max_iter, accelerate, max_modes, pgd_passes, min_gain, noise_floor, rcond, background,
                                # candidates, extrapolate, robust (0: none), subsets ("auto" | int: nonneg_ls
                                # ordered subsets)
    # until = "rounds"
    # rounds = 1
    # run settings
    # center = [0.0, 0.0, 0.0]  # centre of the rotation modes [x, y, z] (default: volume centre)
    fix_scale = true            # cone beam: keep the nominal mean source distance (gauge)
    backend = "auto"            # projector backend
    init = "auto"               # "auto" | "axis" | "none": axis offset from opposite views first
    truncation = "auto"         # "auto" | "on" | "off": drop the rays that leave the volume through its top or
                                # bottom face (a sample longer than the volume); "auto": when the sample reaches them
    zingers = "auto"            # "auto" | "off": replace isolated pixels and bright spots of 2-9 px far from the
                                # reprojection of the nominal reconstruction (zingers, hot and dead pixels) by
                                # their neighbours' median
    rings = "auto"              # "auto" | "on" | "off": subtract the detector's fixed pattern (a flat field wrong at
                                # some columns: rings) from every view; "auto": when it holds 10 % of the residual at
                                # the calibrated geometry away from the sample's outline, and then calibrate again
    roi = "auto"                # "auto" | "on" | "off": a sample wider than the field of view (region-of-interest
                                # scan): subtract what the material outside the volume adds on average to every view;
                                # "auto": when the nominal reconstruction shows material at the volume's sides and
                                # the volume is about as wide as the field of view
    air = "auto"                # "auto" | "off": an air level left in the line integrals (a flat field that does not
                                # match, [preprocess] air = "none") is subtracted for the calibration and its volumes
                                # when it is measurably off 0 (pdvc.io.estimate_air); "off": the data as they are
    second_run = "auto"         # "auto" | "off": when the default recipe keeps a model without the precession on a
                                # full turn (not a region-of-interest scan), run the precession recipe as well (at
                                # the scales whose correlation grid is at most 200^3) and keep the geometry that
                                # predicts the views left out better; where it predicts them worse, it runs once more with a
                                # precession twice a turn (basis "drift:2") and that geometry is compared instead
    noise = "image"             # γ²: "image" (Immerkær's estimator on the line integrals) | "counts"
                                # (Poisson statistics of raw counts with flats, photon-counting gain 1)
    # The output folder's config.toml always holds the full stage list that ran.

    [output]
    dir = "pdvc_output"         # output folder
    overwrite = false           # allow a non-empty folder
    save_initial_volume = false # also save the reconstruction with the nominal geometry
    save_final_volume = true
    volume_format = "tiff"      # "tiff" | "npy" | "hdf5"
    exports = true              # geometry files for ASTRA, TIGRE, LEAP and CIL
    report = true               # figures and the HTML report

    [compute]                   # where the projection passes and reconstructions run (same results)
    scheduler = "threads"       # "threads" (this process) | "local:N" (a local Dask cluster of N worker
                                # processes, "local:NxT": T threads each) | "tcp://host:port" (a running
                                # Dask cluster); --scheduler overrides it; needs pip install 'pdvc[dask]'
                                # for anything but "threads" (docs/distributed.md)

Default volume
--------------
:func:`build_volume_geometry` fills what ``[volume]`` leaves out from the
detector: ``shape = [n_rows, n_cols, n_cols]`` and a voxel equal to the
detector pitch seen at the volume centre -- ``pitch · SOD/SDD`` for cone
beam (the magnification is measured per view along the detector normal,
and the median over views is taken, so it also holds for ``vectors`` and
vendor geometries), ``pitch`` for parallel beam; rows give ``sz``, columns
``sy = sx``. ``offset`` defaults to the origin (the rotation axis of a
nominal scan).

Resolved configuration
----------------------
:func:`load_config` fills every default and makes every path absolute;
:meth:`Config.resolved` also fills what only the data tell (angle count,
detector shape, volume grid); :func:`write_config` writes that as TOML, and
reading it back gives an equal :class:`Config`.

Errors
------
:class:`ConfigError` (a ``ValueError``) names ``section.key``, what was
expected and what came. A degenerate geometry (non-positive pitch or
distance, source on the detector, an angle list that does not match the
projections) raises an error that is both a :class:`ConfigError` (when it
comes from the file) and a :class:`~pdvc.errors.GeometryError`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Union

import numpy as np

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

import tomli_w

from ..compute import SchedulerError, parse_scheduler
from ..correlation import BASIS_NAMES, is_basis_name
from ..errors import GeometryError, PdvcError
from ..geometry import VectorGeometry, VolumeGeometry, circular_cone, parallel
from ..projectors import POSE_PARAMETERS
from ._atomic import atomic_write_text

__all__ = [
    "ConfigError",
    "Config",
    "DataConfig",
    "GeometryConfig",
    "AngleRange",
    "VolumeConfig",
    "PreprocessConfig",
    "CalibrationConfig",
    "OutputConfig",
    "ComputeConfig",
    "load_config",
    "write_config",
    "build_geometry",
    "build_volume_geometry",
    "resolve_angles",
    "check_coverage",
]

log = logging.getLogger(__name__)


class ConfigError(PdvcError, ValueError):
    """A configuration that is malformed: unknown key, wrong type, value out of range."""


class _ConfigGeometryError(ConfigError, GeometryError):
    """A configuration whose geometry is degenerate (both a ConfigError and a GeometryError)."""


_TOML_TYPES = {str: "string", bool: "boolean", int: "integer", float: "float", list: "array", dict: "table"}


def _got(value) -> str:
    kind = _TOML_TYPES.get(type(value), type(value).__name__)
    text = repr(value)
    if len(text) > 60:
        text = text[:57] + "..."
    return f"{text} ({kind})"


# -- section dataclasses -----------------------------------------------------
@dataclass(frozen=True)
class DataConfig:
    """``[data]``: where the projections are and how they are stored."""

    path: str
    format: str = "auto"
    dataset: Optional[str] = None
    flats: Optional[str] = None
    darks: Optional[str] = None
    sinogram: bool = False
    is_raw: Union[bool, str] = "auto"  # True, False, "auto" or "transmission"
    open_beam_columns: Optional[tuple[int, int]] = None


@dataclass(frozen=True)
class AngleRange:
    """``count`` angles from ``start`` towards ``stop`` (degrees); ``stop`` excluded unless ``endpoint``.

    ``count=None`` means "as many as there are projections".
    """

    start: float = 0.0
    stop: float = 360.0
    count: Optional[int] = None
    endpoint: bool = False

    def degrees(self, n_views: Optional[int] = None) -> np.ndarray:
        """The angles in degrees, ``(count,)``; ``n_views`` fills a missing count."""
        n = self.count if self.count is not None else n_views
        if n is None:
            raise _ConfigGeometryError(
                "geometry.angles is a range without count and the number of projections is unknown; "
                "give angles.count or pass n_views"
            )
        return np.linspace(self.start, self.stop, int(n), endpoint=self.endpoint)


AnglesSpec = Union[AngleRange, tuple, str]


@dataclass(frozen=True)
class GeometryConfig:
    """``[geometry]``: the nominal (or vendor) scan geometry.

    Lengths in mm; ``pixel`` and ``det_offset`` are ``(row, col)``; the keys
    that ``type`` does not use are None.
    """

    type: str
    sod: Optional[float] = None
    odd: Optional[float] = None
    pixel: Optional[tuple[float, float]] = None
    det_offset: Optional[tuple[float, float]] = None
    det_shape: Optional[tuple[int, int]] = None
    angles: Optional[AnglesSpec] = None
    vectors: Optional[str] = None
    beam: Optional[str] = None
    file: Optional[str] = None
    vendor_angles: Optional[str] = None
    vendor_offsets: Optional[bool] = None

    @property
    def sdd(self) -> Optional[float]:
        """Source to detector distance ``sod + odd``, mm (cone beam)."""
        return None if self.sod is None or self.odd is None else self.sod + self.odd

    @property
    def kind(self) -> str:
        """Beam kind of the resulting VectorGeometry (vendor files: as read)."""
        if self.type == "vectors":
            return self.beam or "cone"
        return "parallel" if self.type == "parallel" else "cone"


@dataclass(frozen=True)
class VolumeConfig:
    """``[volume]``: the reconstruction grid; None = derived from the detector (module docstring)."""

    shape: Optional[tuple[int, int, int]] = None
    voxel_size: Optional[tuple[float, float, float]] = None
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class PreprocessConfig:
    """``[preprocess]``: corrections applied to the projections before calibration."""

    flat_interpolation: str = "linear"
    clip_min: float = 1e-6
    beam_hardening: Optional[tuple[float, ...]] = None
    roi_rows: Optional[tuple[int, int]] = None
    roi_cols: Optional[tuple[int, int]] = None
    bin: int = 1
    air: str = "none"
    mask: Optional[str] = None
    dead_columns: Optional[tuple[int, ...]] = None


@dataclass(frozen=True)
class CalibrationConfig:
    """``[calibration]``: the recipe or the stage list, and the run's settings.

    The recipe parameters (``basis`` ... ``guards``) are None when not set:
    the recipe's own default applies. ``stage`` holds the
    ``[[calibration.stage]]`` tables (checked, every field filled) when the
    stage list is spelt out; the recipe parameters cannot be combined with it.
    """

    recipe: str = "default"
    stage: Optional[tuple] = None
    basis: Optional[str] = None
    method: Optional[str] = None
    frame: Optional[str] = None
    fixed: Optional[tuple[str, ...]] = None
    reconstruct: Optional[str] = None
    guards: Optional[tuple[str, ...]] = None
    scales: Union[str, tuple[int, ...]] = "auto"
    max_outer: Optional[int] = None
    warmup: int = 1
    refine: bool = False
    tol_px: Optional[float] = None
    max_iter: Optional[int] = None
    accelerate: Optional[bool] = None
    extrapolate: Optional[bool] = None
    robust: Optional[float] = None
    max_modes: Optional[int] = None
    pgd_passes: Optional[int] = None
    min_gain: Optional[float] = None
    noise_floor: Optional[float] = None
    rcond: Optional[float] = None
    oversample: Optional[int] = None
    oversample_by: Optional[str] = None
    background: Union[int, str, None] = None
    candidates: Optional[tuple[str, ...]] = None
    center: Optional[tuple[float, float, float]] = None
    fix_scale: bool = True
    backend: str = "auto"
    init: str = "auto"
    noise: str = "image"
    truncation: str = "auto"
    zingers: str = "auto"
    rings: str = "auto"
    roi: str = "auto"
    air: str = "auto"
    second_run: str = "auto"

    def recipe_parameters(self) -> dict:
        """The recipe parameters that are set, as :func:`pdvc.calibration.recipe_stages` keywords."""
        out = {k: getattr(self, k) for k in _RECIPE_KEYS if getattr(self, k) is not None}
        if self.scales != "auto":
            out["scales"] = tuple(self.scales)
        if self.warmup != 1:
            out["warmup"] = self.warmup
        if self.refine:
            out["refine"] = True
        return out


@dataclass(frozen=True)
class OutputConfig:
    """``[output]``: where and what to write."""

    dir: str
    overwrite: bool = False
    save_initial_volume: bool = False
    save_final_volume: bool = True
    volume_format: str = "tiff"
    exports: bool = True
    report: bool = True


@dataclass(frozen=True)
class ComputeConfig:
    """``[compute]``: where the operators run (:func:`pdvc.compute.parse_scheduler`)."""

    scheduler: str = "threads"


_SECTIONS = ("data", "geometry", "volume", "preprocess", "calibration", "output", "compute")


@dataclass(frozen=True)
class Config:
    """A checked, fully defaulted configuration (one frozen dataclass per section).

    ``source`` (the file read, if any) does not take part in equality.
    """

    data: DataConfig
    geometry: GeometryConfig
    volume: VolumeConfig = VolumeConfig()
    preprocess: PreprocessConfig = PreprocessConfig()
    calibration: CalibrationConfig = CalibrationConfig()
    output: OutputConfig = field(default_factory=lambda: OutputConfig(dir=os.path.abspath("pdvc_output")))
    source: Optional[str] = field(default=None, compare=False)
    compute: ComputeConfig = ComputeConfig()

    def to_dict(self) -> dict:
        """Plain TOML-ready dict of every set value (None values are left out)."""
        return {name: _to_plain(getattr(self, name)) for name in _SECTIONS}

    def resolved(
        self, *, n_views: Optional[int] = None, det_shape=None, vol_geom: Optional[VolumeGeometry] = None, angles=None,
        stages=None,
    ) -> "Config":
        """A copy with what only the data tell filled in.

        Parameters
        ----------
        n_views : int, optional
            Fills the count of an angle range that has none.
        det_shape : (n_rows, n_cols), optional
            Fills ``geometry.det_shape`` (types cone, parallel, vectors).
        vol_geom : VolumeGeometry, optional
            Fills ``[volume]`` with this grid (e.g. from :func:`build_volume_geometry`).
        angles : (n_views,) array, radians, optional
            Replaces ``geometry.angles`` (types cone and parallel) by this
            explicit list (written in degrees), e.g. the angles ``"auto"``
            picked.
        stages : sequence of pdvc.calibration.Stage, optional
            The stage list that runs: written out in full as
            ``[[calibration.stage]]`` tables (the recipe parameters, which
            made it, are then left out).
        """
        g = self.geometry
        if angles is not None and g.type in ("cone", "parallel"):
            deg = np.rad2deg(np.asarray(angles, dtype=np.float64).reshape(-1))
            if deg.size == 0 or not np.all(np.isfinite(deg)):
                raise ConfigError("angles must be a non-empty array of finite radians")
            g = dataclasses.replace(g, angles=tuple(float(a) for a in deg))
        if n_views is not None and isinstance(g.angles, AngleRange) and g.angles.count is None:
            g = dataclasses.replace(g, angles=dataclasses.replace(g.angles, count=_count(n_views, "n_views")))
        if det_shape is not None and g.type in ("cone", "parallel", "vectors"):
            shape = _pair(list(det_shape), "det_shape", int, minimum=1)
            if g.det_shape is not None and g.det_shape != shape:
                raise _ConfigGeometryError(
                    f"geometry.det_shape is {list(g.det_shape)} but the projections are {list(shape)} (rows, cols)"
                )
            g = dataclasses.replace(g, det_shape=shape)
        vol = self.volume
        if vol_geom is not None:
            vol = VolumeConfig(tuple(vol_geom.shape), tuple(vol_geom.voxel_size), tuple(vol_geom.offset))
        cal = self.calibration
        if stages is not None:
            keep = {k: getattr(cal, k) for k in ("recipe", "center", "fix_scale", "backend", "init", "noise", "truncation", "zingers",
                                                "rings", "roi", "air", "second_run")}
            cal = CalibrationConfig(stage=tuple(s.to_dict() for s in stages), **keep)
        return dataclasses.replace(self, geometry=g, volume=vol, calibration=cal)


def _to_plain(obj):
    if dataclasses.is_dataclass(obj):
        out = {}
        for f in dataclasses.fields(obj):
            val = getattr(obj, f.name)
            if val is None or f.name == "source":
                continue
            out[f.name] = _to_plain(val)
        return out
    if isinstance(obj, (tuple, list)):
        return [_to_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


# -- value checkers ----------------------------------------------------------
def _count(value, where: str) -> int:
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
        raise ConfigError(f"{where} must be a positive integer, got {_got(value)}")
    return int(value)


def _number(value, where: str, *, positive=False, nonneg=False, lo=None, hi=None, geometry=False) -> float:
    err = _ConfigGeometryError if geometry else ConfigError
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ConfigError(f"{where} must be a number, got {_got(value)}")
    x = float(value)
    if not math.isfinite(x):
        raise ConfigError(f"{where} must be finite, got {_got(value)}")
    if positive and x <= 0:
        raise err(f"{where} must be positive, got {x!r}")
    if nonneg and x < 0:
        raise err(f"{where} must be zero or positive, got {x!r}")
    if lo is not None and x < lo:
        raise ConfigError(f"{where} must be at least {lo}, got {x!r}")
    if hi is not None and x >= hi:
        raise ConfigError(f"{where} must be below {hi}, got {x!r}")
    return x


def _integer(value, where: str, *, minimum: Optional[int] = None) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ConfigError(f"{where} must be an integer, got {_got(value)}")
    if minimum is not None and value < minimum:
        raise ConfigError(f"{where} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _boolean(value, where: str) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{where} must be true or false, got {_got(value)}")
    return value


def _string(value, where: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{where} must be a non-empty string, got {_got(value)}")
    return value


def _choice(value, where: str, choices) -> str:
    if not isinstance(value, str) or value not in choices:
        raise ConfigError(f"{where} must be one of {', '.join(repr(c) for c in choices)}, got {_got(value)}")
    return value


def _pair(value, where: str, kind=float, *, minimum=None, positive=False, scalar_ok=False, geometry=False):
    if scalar_ok and not isinstance(value, (list, tuple)):
        value = [value, value]
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        what = "a number or a pair [row, col]" if scalar_ok else "a pair [a, b]"
        raise ConfigError(f"{where} must be {what}, got {_got(value)}")
    if kind is int:
        out = tuple(_integer(v, f"{where}[{i}]", minimum=minimum) for i, v in enumerate(value))
    else:
        out = tuple(_number(v, f"{where}[{i}]", positive=positive, geometry=geometry) for i, v in enumerate(value))
    return out


def _triple(value, where: str, *, kind=float, positive=False, minimum=None, scalar_ok=False):
    if scalar_ok and not isinstance(value, (list, tuple)):
        value = [value] * 3
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        what = "a number or three numbers" if scalar_ok else "three numbers"
        raise ConfigError(f"{where} must be {what}, got {_got(value)}")
    if kind is int:
        return tuple(_integer(v, f"{where}[{i}]", minimum=minimum) for i, v in enumerate(value))
    return tuple(_number(v, f"{where}[{i}]", positive=positive) for i, v in enumerate(value))


def _range(value, where: str) -> tuple[int, int]:
    a, b = _pair(value, where, int, minimum=0)
    if b <= a:
        raise ConfigError(f"{where} must be a range [a, b) with 0 <= a < b, got {list(value)}")
    return a, b


def _path(value, where: str, base: Path) -> str:
    text = os.path.expanduser(_string(value, where))
    return os.path.abspath(os.path.join(base, text))


class _Table:
    """One section of the raw file: hands out keys, then rejects the ones nobody asked for."""

    def __init__(self, raw: dict, name: str, base: Path):
        table = raw.get(name, {})
        if not isinstance(table, dict):
            raise ConfigError(f"[{name}] must be a table (a section), got {_got(table)}")
        self.name, self.t, self.base = name, dict(table), base

    def has(self, key: str) -> bool:
        return key in self.t

    def pop(self, key: str, default: Any = None):
        return self.t.pop(key, default)

    def require(self, key: str, why: str = ""):
        if key not in self.t:
            raise ConfigError(f"{self.name}.{key} is required{why}")
        return self.t.pop(key)

    def finish(self, allowed, context: str = "") -> None:
        if self.t:
            bad = sorted(self.t)
            raise ConfigError(
                f"unknown key{'s' if len(bad) > 1 else ''} {', '.join(repr(k) for k in bad)} in [{self.name}]{context}; "
                f"allowed keys: {', '.join(sorted(allowed))}"
            )


# -- section parsers ---------------------------------------------------------
_DATA_KEYS = ("path", "format", "dataset", "flats", "darks", "sinogram", "is_raw", "open_beam_columns")
_FORMATS = ("auto", "tiff-folder", "tiff", "dxchange", "nxtomo", "npy")


def _parse_data(t: _Table) -> DataConfig:
    w = "data."
    path = _path(t.require("path"), w + "path", t.base)
    fmt = _choice(t.pop("format", "auto"), w + "format", _FORMATS)
    dataset = t.pop("dataset")
    dataset = None if dataset is None else _string(dataset, w + "dataset")
    flats = t.pop("flats")
    flats = None if flats is None else _path(flats, w + "flats", t.base)
    darks = t.pop("darks")
    darks = None if darks is None else _path(darks, w + "darks", t.base)
    sinogram = _boolean(t.pop("sinogram", False), w + "sinogram")
    is_raw = t.pop("is_raw", "auto")
    if not (isinstance(is_raw, bool) or is_raw in ("auto", "transmission")):
        raise ConfigError(
            f"data.is_raw must be true, false or \"auto\" (or \"transmission\" for I/I0 data), got {_got(is_raw)}"
        )
    obc = t.pop("open_beam_columns")
    obc = None if obc is None else _range(obc, w + "open_beam_columns")
    t.finish(_DATA_KEYS)
    return DataConfig(path, fmt, dataset, flats, darks, sinogram, is_raw, obc)


_GEOMETRY_TYPES = ("cone", "parallel", "vectors", "nikon", "skyscan")
_GEOMETRY_KEYS = {
    "cone": ("type", "sod", "odd", "sdd", "pixel", "det_offset", "det_shape", "angles"),
    "parallel": ("type", "pixel", "det_offset", "det_shape", "angles"),
    "vectors": ("type", "vectors", "beam", "det_shape"),
    "nikon": ("type", "file", "vendor_angles", "vendor_offsets"),
    "skyscan": ("type", "file", "vendor_offsets"),
}
_ALL_GEOMETRY_KEYS = sorted({k for keys in _GEOMETRY_KEYS.values() for k in keys})


_ANGLE_WORDS = ("auto", "data")


def _parse_angles(value, where: str, base: Path, default_stop: float) -> AnglesSpec:
    if value is None:
        return "auto"
    if isinstance(value, str):
        return value if value in _ANGLE_WORDS else _path(value, where, base)
    if isinstance(value, (list, tuple)):
        if not value:
            raise _ConfigGeometryError(f"{where} must list at least one angle, got an empty array")
        return tuple(_number(v, f"{where}[{i}]") for i, v in enumerate(value))
    if isinstance(value, dict):
        allowed = ("start", "stop", "count", "endpoint")
        bad = sorted(set(value) - set(allowed))
        if bad:
            raise ConfigError(f"unknown key(s) {', '.join(repr(k) for k in bad)} in {where}; allowed keys: {', '.join(allowed)}")
        start = _number(value.get("start", 0.0), where + ".start")
        stop = _number(value.get("stop", default_stop), where + ".stop")
        count = value.get("count")
        count = None if count is None else _count(count, where + ".count")
        endpoint = _boolean(value.get("endpoint", False), where + ".endpoint")
        if stop == start and (count is None or count > 1):
            raise ConfigError(f"{where} must span a non-zero range, got start = stop = {start!r}")
        return AngleRange(start, stop, count, endpoint)
    raise ConfigError(
        f"{where} must be a list of degrees, a file name or a table {{start, stop, count}}, got {_got(value)}"
    )


def _parse_geometry(t: _Table) -> GeometryConfig:
    w = "geometry."
    typ = _choice(t.require("type", " (one of " + ", ".join(repr(x) for x in _GEOMETRY_TYPES) + ")"), w + "type", _GEOMETRY_TYPES)
    allowed = _GEOMETRY_KEYS[typ]
    misplaced = sorted(k for k in t.t if k not in allowed and k in _ALL_GEOMETRY_KEYS)
    if misplaced:
        raise ConfigError(
            f"{', '.join(w + k for k in misplaced)} {'is' if len(misplaced) == 1 else 'are'} not used with "
            f"type = {typ!r}; remove {'it' if len(misplaced) == 1 else 'them'}. Keys for type {typ!r}: {', '.join(allowed)}"
        )
    kw: dict[str, Any] = {"type": typ}
    if typ == "cone":
        kw["sod"] = _number(t.require("sod", " for type = 'cone' (source to rotation axis, mm)"), w + "sod", positive=True, geometry=True)
        if t.has("odd") and t.has("sdd"):
            raise ConfigError("give geometry.odd or geometry.sdd, not both (sdd = sod + odd)")
        if t.has("sdd"):
            sdd = _number(t.pop("sdd"), w + "sdd", positive=True, geometry=True)
            if sdd <= kw["sod"]:
                raise _ConfigGeometryError(
                    f"geometry.sdd ({sdd!r}) must exceed geometry.sod ({kw['sod']!r}): the detector must lie "
                    "beyond the rotation axis (a source on or behind the detector is degenerate)"
                )
            kw["odd"] = sdd - kw["sod"]
        else:
            odd = _number(t.require("odd", " for type = 'cone' (rotation axis to detector, mm; or give sdd)"), w + "odd", geometry=True)
            if odd <= 0:
                raise _ConfigGeometryError(
                    f"geometry.odd must be positive (the detector beyond the rotation axis), got {odd!r}"
                    + ("; the source would be on or behind the detector" if odd <= -kw["sod"] else "")
                )
            kw["odd"] = odd
    if typ in ("cone", "parallel"):
        kw["pixel"] = _pair(t.require("pixel", f" for type = {typ!r} (detector pitch, mm)"), w + "pixel",
                            positive=True, scalar_ok=True, geometry=True)
        kw["det_offset"] = _pair(t.pop("det_offset", [0.0, 0.0]), w + "det_offset")
        kw["angles"] = _parse_angles(t.pop("angles"), w + "angles", t.base, 360.0 if typ == "cone" else 180.0)
    if typ in ("cone", "parallel", "vectors"):
        ds = t.pop("det_shape")
        kw["det_shape"] = None if ds is None else _pair(ds, w + "det_shape", int, minimum=1)
    if typ == "vectors":
        kw["vectors"] = _path(t.require("vectors", " for type = 'vectors' (.npy or text file of (n_views, 12) rows)"), w + "vectors", t.base)
        kw["beam"] = _choice(t.pop("beam", "cone"), w + "beam", ("cone", "parallel"))
    if typ in ("nikon", "skyscan"):
        kw["file"] = _path(t.require("file", f" for type = {typ!r} (the vendor geometry file)"), w + "file", t.base)
        kw["vendor_offsets"] = _boolean(t.pop("vendor_offsets", True), w + "vendor_offsets")
    if typ == "nikon":
        kw["vendor_angles"] = _choice(t.pop("vendor_angles", "auto"), w + "vendor_angles", ("auto", "nominal"))
    t.finish(allowed, f" (type = {typ!r})")
    return GeometryConfig(**kw)


def _parse_volume(t: _Table) -> VolumeConfig:
    w = "volume."
    shape = t.pop("shape")
    shape = None if shape is None else _triple(shape, w + "shape", kind=int, minimum=2)
    vs = t.pop("voxel_size")
    vs = None if vs is None else _triple(vs, w + "voxel_size", positive=True, scalar_ok=True)
    offset = _triple(t.pop("offset", [0.0, 0.0, 0.0]), w + "offset")
    t.finish(("shape", "voxel_size", "offset"))
    return VolumeConfig(shape, vs, offset)


def _parse_preprocess(t: _Table) -> PreprocessConfig:
    w = "preprocess."
    interp = _choice(t.pop("flat_interpolation", "linear"), w + "flat_interpolation", ("linear", "mean"))
    clip_min = _number(t.pop("clip_min", 1e-6), w + "clip_min", positive=True, hi=1.0)
    bh = t.pop("beam_hardening")
    if bh is not None:
        if not isinstance(bh, (list, tuple)) or not bh:
            raise ConfigError(f"preprocess.beam_hardening must be a non-empty list [c1, c2, ...], got {_got(bh)}")
        bh = tuple(_number(c, f"{w}beam_hardening[{i}]") for i, c in enumerate(bh))
    rr = t.pop("roi_rows")
    rr = None if rr is None else _range(rr, w + "roi_rows")
    rc = t.pop("roi_cols")
    rc = None if rc is None else _range(rc, w + "roi_cols")
    b = _integer(t.pop("bin", 1), w + "bin", minimum=1)
    air = _choice(t.pop("air", "none"), w + "air", _AIR_MODES)
    mask = t.pop("mask")
    mask = None if mask is None else _path(mask, w + "mask", t.base)
    dc = t.pop("dead_columns")
    if dc is not None:
        if not isinstance(dc, (list, tuple)) or not dc:
            raise ConfigError(f"preprocess.dead_columns must be a non-empty list of column indices, got {_got(dc)}")
        dc = tuple(_integer(c, f"{w}dead_columns[{i}]", minimum=0) for i, c in enumerate(dc))
    t.finish(tuple(f.name for f in dataclasses.fields(PreprocessConfig)))
    return PreprocessConfig(interp, clip_min, bh, rr, rc, b, air=air, mask=mask, dead_columns=dc)


_AIR_MODES = ("none", "auto")


_CALIBRATION_KEYS = tuple(f.name for f in dataclasses.fields(CalibrationConfig))


_RECIPE_KEYS = (
    "basis", "method", "frame", "fixed", "reconstruct", "guards", "max_outer", "tol_px", "max_iter", "max_modes",
    "pgd_passes", "min_gain", "noise_floor", "rcond", "oversample", "oversample_by", "accelerate", "background",
    "candidates", "extrapolate", "robust",
)


def _names(value, where: str, allowed, *, distinct=True) -> tuple:
    if not isinstance(value, (list, tuple)):
        raise ConfigError(f"{where} must be a list of names among {list(allowed)}, got {_got(value)}")
    for i, name in enumerate(value):
        _choice(name, f"{where}[{i}]", allowed)
    if distinct and len(set(value)) != len(value):
        raise ConfigError(f"{where} names an entry twice: {list(value)}")
    return tuple(value)


def _parse_calibration(t: _Table) -> CalibrationConfig:
    from ..calibration import GUARDS, MODELS, OVERSAMPLE_BY, RECIPES, RECONSTRUCTIONS, StageError, stages_from_dicts

    w = "calibration."
    d = CalibrationConfig()
    kw: dict = {}
    basis = t.pop("basis")
    if basis is not None:
        if not is_basis_name(basis):
            raise ConfigError(f"calibration.basis must be one of {BASIS_NAMES} (D, M, N non-negative integers), got {_got(basis)}")
        kw["basis"] = basis.strip().lower()
    for key, allowed in (("method", ("full", "pgd")), ("frame", ("sample", "lab")), ("reconstruct", RECONSTRUCTIONS),
                         ("oversample_by", OVERSAMPLE_BY)):
        val = t.pop(key)
        if val is not None:
            kw[key] = _choice(val, w + key, allowed)
    fixed = t.pop("fixed")
    if fixed is not None:
        kw["fixed"] = _names(fixed, w + "fixed", POSE_PARAMETERS)
        if len(kw["fixed"]) == 6:
            raise ConfigError("calibration.fixed holds all six parameters: nothing would be calibrated")
    guards = t.pop("guards")
    if guards is not None:
        kw["guards"] = _names(guards, w + "guards", GUARDS)
    candidates = t.pop("candidates")
    if candidates is not None:
        kw["candidates"] = _names(candidates, w + "candidates", tuple(MODELS))
    for key, minimum in (("max_outer", 1), ("max_iter", 1), ("max_modes", 1), ("pgd_passes", 1), ("oversample", 1)):
        val = t.pop(key)
        if val is not None:
            kw[key] = _integer(val, w + key, minimum=minimum)
    for key, rule in (("tol_px", dict(positive=True)), ("min_gain", dict(nonneg=True, hi=1.0)), ("noise_floor", dict(lo=0.0)),
                      ("rcond", dict(positive=True, hi=1.0)), ("robust", dict(nonneg=True))):
        val = t.pop(key)
        if val is not None:
            kw[key] = _number(val, w + key, **rule)
    for key in ("accelerate", "extrapolate"):
        val = t.pop(key)
        if val is not None:
            kw[key] = _boolean(val, w + key)
    background = t.pop("background")
    if background == "auto":
        kw["background"] = "auto"
    elif background is not None:
        if isinstance(background, str):
            raise ConfigError(f"calibration.background must be \"auto\", -1 (none), 0, 1 or 2 (a polynomial degree), got {_got(background)}")
        kw["background"] = _integer(background, w + "background", minimum=-1)
        if kw["background"] > 2:
            raise ConfigError(f"calibration.background must be \"auto\", -1 (none), 0, 1 or 2 (a polynomial degree), got {_got(background)}")
    scales = t.pop("scales", d.scales)
    if scales == "auto":
        pass
    elif not isinstance(scales, (list, tuple)) or not scales:
        raise ConfigError(f"calibration.scales must be 'auto' or a non-empty list of integers, got {_got(scales)}")
    else:
        scales = tuple(_integer(s, f"{w}scales[{i}]", minimum=1) for i, s in enumerate(scales))
    if scales != "auto" and any(b >= a for a, b in zip(scales, scales[1:])):
        raise ConfigError(f"calibration.scales must be strictly decreasing (coarse to fine), got {list(scales)}")
    warmup = _integer(t.pop("warmup", d.warmup), w + "warmup", minimum=0)
    refine = _boolean(t.pop("refine", d.refine), w + "refine")
    recipe = _choice(t.pop("recipe", d.recipe), w + "recipe", RECIPES)
    stage = t.pop("stage")
    if stage is not None:
        given = sorted(kw) + [k for k, changed in (("scales", scales != "auto"), ("warmup", warmup != d.warmup),
                                                   ("refine", refine != d.refine)) if changed]
        if given:
            raise ConfigError(
                f"calibration.{given[0]} cannot be combined with [[calibration.stage]] tables: "
                "the stage list is complete; set it in each stage instead"
            )
        try:
            stage = tuple(s.to_dict() for s in stages_from_dicts(stage, "calibration.stage"))
        except StageError as exc:
            raise ConfigError(str(exc)) from None
    center = t.pop("center")
    out = CalibrationConfig(
        recipe=recipe,
        stage=stage,
        scales=scales,
        warmup=warmup,
        refine=refine,
        center=None if center is None else _triple(center, w + "center"),
        fix_scale=_boolean(t.pop("fix_scale", d.fix_scale), w + "fix_scale"),
        backend=_string(t.pop("backend", d.backend), w + "backend"),
        init=_choice(t.pop("init", d.init), w + "init", ("auto", "axis", "none")),
        noise=_choice(t.pop("noise", d.noise), w + "noise", ("image", "counts")),
        truncation=_choice(t.pop("truncation", d.truncation), w + "truncation", ("auto", "on", "off")),
        zingers=_choice(t.pop("zingers", d.zingers), w + "zingers", ("auto", "off")),
        rings=_choice(t.pop("rings", d.rings), w + "rings", ("auto", "on", "off")),
        roi=_choice(t.pop("roi", d.roi), w + "roi", ("auto", "on", "off")),
        air=_choice(t.pop("air", d.air), w + "air", ("auto", "off")),
        second_run=_choice(t.pop("second_run", d.second_run), w + "second_run", ("auto", "off")),
        **kw,
    )
    t.finish(_CALIBRATION_KEYS)
    return out


def _parse_output(t: _Table) -> OutputConfig:
    w = "output."
    out = OutputConfig(
        dir=_path(t.pop("dir", "pdvc_output"), w + "dir", t.base),
        overwrite=_boolean(t.pop("overwrite", False), w + "overwrite"),
        save_initial_volume=_boolean(t.pop("save_initial_volume", False), w + "save_initial_volume"),
        save_final_volume=_boolean(t.pop("save_final_volume", True), w + "save_final_volume"),
        volume_format=_choice(t.pop("volume_format", "tiff"), w + "volume_format", ("tiff", "npy", "hdf5")),
        exports=_boolean(t.pop("exports", True), w + "exports"),
        report=_boolean(t.pop("report", True), w + "report"),
    )
    t.finish(tuple(f.name for f in dataclasses.fields(OutputConfig)))
    return out


def _parse_compute(t: _Table) -> ComputeConfig:
    text = _string(t.pop("scheduler", "threads"), "compute.scheduler")
    try:
        parse_scheduler(text)
    except SchedulerError as exc:
        raise ConfigError(f"compute.{exc}") from None
    t.finish(tuple(f.name for f in dataclasses.fields(ComputeConfig)))
    return ComputeConfig(scheduler=text.strip())


# -- public API --------------------------------------------------------------
def load_config(source, *, base_dir=None) -> Config:
    """Read and check a configuration.

    Parameters
    ----------
    source : str, Path or dict
        A TOML file, or the same content as a dict (e.g. ``tomllib.load``'s
        result).
    base_dir : str or Path, optional
        Folder that relative paths are relative to. Default: the folder of
        the file, or the current folder for a dict.

    Returns
    -------
    Config
        Every default filled in, every path absolute.

    Raises
    ------
    ConfigError
        Unknown section or key, wrong type or value; the message names
        ``section.key``, what was expected and what came.
    """
    where = None
    if isinstance(source, dict):
        raw = source
        base = Path(base_dir) if base_dir is not None else Path.cwd()
    elif isinstance(source, (str, os.PathLike)):
        p = Path(source)
        try:
            text = p.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise ConfigError(f"configuration file {str(p)!r} does not exist") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"cannot read configuration file {str(p)!r}: {exc}") from None
        try:
            raw = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"configuration file {str(p)!r} is not valid TOML: {exc}") from None
        base = Path(base_dir) if base_dir is not None else p.resolve().parent
        where = str(p.resolve())
    else:
        raise ConfigError(f"source must be a TOML file path or a dict, got {type(source).__name__}")
    base = Path(os.path.abspath(base))
    unknown = sorted(k for k in raw if k not in _SECTIONS)
    if unknown:
        raise ConfigError(
            f"unknown section{'s' if len(unknown) > 1 else ''} {', '.join('[' + k + ']' for k in unknown)}; "
            f"allowed sections: {', '.join('[' + s + ']' for s in _SECTIONS)}"
        )
    if "data" not in raw:
        raise ConfigError("section [data] is required (at least data.path)")
    if "geometry" not in raw:
        raise ConfigError("section [geometry] is required (at least geometry.type)")
    return Config(
        data=_parse_data(_Table(raw, "data", base)),
        geometry=_parse_geometry(_Table(raw, "geometry", base)),
        volume=_parse_volume(_Table(raw, "volume", base)),
        preprocess=_parse_preprocess(_Table(raw, "preprocess", base)),
        calibration=_parse_calibration(_Table(raw, "calibration", base)),
        output=_parse_output(_Table(raw, "output", base)),
        compute=_parse_compute(_Table(raw, "compute", base)),
        source=where,
    )


def write_config(path, config: Config) -> Path:
    """Write ``config`` as TOML, atomically; :func:`load_config` of the file gives an equal Config.

    Every default is written (the file documents the run completely); paths
    are absolute.
    """
    from .. import __version__

    if not isinstance(config, Config):
        raise ConfigError(f"config must be a Config (see load_config), got {type(config).__name__}")
    header = (
        f"# pdvc {__version__} configuration, resolved: every default filled in, paths absolute.\n"
        "# Lengths in mm, angles in degrees, detector pairs [row, col].\n\n"
    )
    return atomic_write_text(path, header + tomli_w.dumps(config.to_dict()))


# -- geometries from a configuration ----------------------------------------
def _read_numbers(path: str, where: str) -> np.ndarray:
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{where} file {path!r} does not exist")
    try:
        if p.suffix.lower() == ".npy":
            return np.asarray(np.load(p, allow_pickle=False), dtype=np.float64)
        rows = []
        for line in p.read_text(encoding="utf-8", errors="replace").splitlines():
            s = line.split("#", 1)[0].strip()
            if s:
                rows.append([float(x) for x in re.split(r"[\s,;]+", s) if x])
    except (ValueError, OSError) as exc:
        raise ConfigError(f"{where}: cannot read numbers from {path!r}: {exc}") from None
    widths = {len(r) for r in rows}
    if len(widths) > 1:
        raise ConfigError(f"{where}: {path!r} has rows of different lengths {sorted(widths)}")
    return np.array(rows, dtype=np.float64)


def resolve_angles(spec: AnglesSpec, n_views: Optional[int] = None, *, kind: str = "cone", data_angles=None) -> np.ndarray:
    """View angles of a ``geometry.angles`` value, in **radians**, ``(n_views,)``.

    Parameters
    ----------
    spec : AngleRange, sequence of degrees, file path, "auto" or "data"
    n_views : int, optional
        Number of projections: checked, and fills a range without count.
    kind : {"cone", "parallel"}
        For ``"auto"`` without data angles: a full turn (cone) or half a
        turn (parallel).
    data_angles : (n_views,) array, radians, optional
        Angles stored with the projections (``RawScan.angles``).

    Raises
    ------
    GeometryError
        When the angles do not match ``n_views`` (the number of projections),
        or ``"data"`` without data angles.
    """
    if isinstance(spec, str) and spec in _ANGLE_WORDS:
        if data_angles is not None:
            rad = np.asarray(data_angles, dtype=np.float64).reshape(-1)
            if n_views is not None and rad.size != n_views:
                raise _ConfigGeometryError(
                    f"the projections carry {rad.size} angles but there are {n_views} projections"
                )
            if not np.all(np.isfinite(rad)):
                raise _ConfigGeometryError("the angles stored with the projections are not all finite")
            return rad
        if spec == "data":
            raise _ConfigGeometryError(
                'geometry.angles = "data" but the projections carry no angles; give the angles in [geometry]'
            )
        spec = AngleRange(0.0, 180.0 if kind == "parallel" else 360.0)
    if isinstance(spec, AngleRange):
        deg = spec.degrees(n_views)
    elif isinstance(spec, str):
        deg = _read_numbers(spec, "geometry.angles")
        if deg.ndim == 2 and 1 in deg.shape:
            deg = deg.reshape(-1)
        if deg.ndim != 1 or deg.size == 0:
            raise ConfigError(f"geometry.angles: {spec!r} must hold one angle per projection (one column), got shape {deg.shape}")
    elif isinstance(spec, (tuple, list, np.ndarray)):
        deg = np.asarray(spec, dtype=np.float64).reshape(-1)
    else:
        raise ConfigError(f"geometry.angles must be a list, a file or an AngleRange, got {type(spec).__name__}")
    if not np.all(np.isfinite(deg)):
        raise ConfigError("geometry.angles must be finite numbers (degrees)")
    if n_views is not None and deg.size != n_views:
        raise _ConfigGeometryError(
            f"geometry.angles gives {deg.size} angles but there are {n_views} projections; "
            "give one angle per projection"
        )
    return np.deg2rad(deg)


def _det_shape(cfg_shape, arg_shape, what: str) -> tuple[int, int]:
    shape = None
    if arg_shape is not None:
        shape = _pair(list(arg_shape), "det_shape", int, minimum=1)
    if cfg_shape is not None:
        if shape is not None and tuple(cfg_shape) != shape:
            raise GeometryError(
                f"geometry.det_shape is {list(cfg_shape)} but the projections are {list(shape)} (rows, cols)"
            )
        shape = tuple(cfg_shape)
    if shape is None:
        raise GeometryError(f"{what} needs the detector shape: give geometry.det_shape or pass det_shape=(n_rows, n_cols)")
    return shape  # type: ignore[return-value]


def build_geometry(cfg, n_views: Optional[int] = None, det_shape=None, *, data_angles=None) -> VectorGeometry:
    """The nominal (or vendor) per-view geometry a ``[geometry]`` section describes.

    Parameters
    ----------
    cfg : GeometryConfig or Config
    n_views : int, optional
        Number of projections; checked against the angles / vectors, and
        fills the count of an angle range that has none.
    det_shape : (n_rows, n_cols), optional
        Shape of the projections; checked against the configuration or the
        vendor file, required when neither gives it.
    data_angles : (n_views,) array, radians, optional
        Angles stored with the projections (``RawScan.angles``), used by
        ``angles = "auto"`` (default) and ``"data"``.

    Returns
    -------
    VectorGeometry
        Float64 vectors, lengths in mm.

    Raises
    ------
    GeometryError
        Degenerate geometry, or angles / shape that do not match the data.
    """
    if isinstance(cfg, Config):
        cfg = cfg.geometry
    if not isinstance(cfg, GeometryConfig):
        raise ConfigError(f"cfg must be a GeometryConfig or a Config, got {type(cfg).__name__}")
    if n_views is not None:
        n_views = _count(n_views, "n_views")
    typ = cfg.type
    if typ in ("cone", "parallel"):
        shape = _det_shape(cfg.det_shape, det_shape, f"type = {typ!r}")
        angles = resolve_angles(cfg.angles if cfg.angles is not None else "auto", n_views, kind=typ, data_angles=data_angles)
        if typ == "cone":
            return circular_cone(angles, sod=cfg.sod, odd=cfg.odd, det_shape=shape, pixel=cfg.pixel, det_offset=cfg.det_offset)
        return parallel(angles, det_shape=shape, pixel=cfg.pixel, det_offset=cfg.det_offset)
    if typ == "vectors":
        shape = _det_shape(cfg.det_shape, det_shape, "type = 'vectors'")
        vec = _read_numbers(cfg.vectors, "geometry.vectors")
        if vec.ndim == 1 and vec.size == 12:
            vec = vec[None, :]
        if vec.ndim != 2 or vec.shape[1] != 12:
            raise ConfigError(f"geometry.vectors: {cfg.vectors!r} must hold (n_views, 12) rows (src, d, u, v), got shape {vec.shape}")
        if n_views is not None and vec.shape[0] != n_views:
            raise GeometryError(f"geometry.vectors holds {vec.shape[0]} views but there are {n_views} projections")
        return VectorGeometry(vec, shape, cfg.beam or "cone")
    # vendor files
    from ._vendor import read_nikon, read_skyscan

    if typ == "nikon":
        vg = read_nikon(cfg.file, angles=cfg.vendor_angles or "auto", offsets=cfg.vendor_offsets is not False)
    else:
        vg = read_skyscan(cfg.file, offsets=cfg.vendor_offsets is not False)
    if det_shape is not None and tuple(det_shape) != vg.det_shape:
        raise GeometryError(
            f"the {typ} file {cfg.file!r} describes a {vg.det_shape[0]} x {vg.det_shape[1]} detector (rows x cols) "
            f"but the projections are {det_shape[0]} x {det_shape[1]}; bin or crop the geometry "
            "(VectorGeometry.binned / cropped) the same way as the projections"
        )
    if n_views is not None and vg.n_views != n_views:
        raise GeometryError(
            f"the {typ} file {cfg.file!r} gives {vg.n_views} angles ({vg.angles_source}) but there are "
            f"{n_views} projections"
        )
    return vg.to_vector_geometry()


def _pitch_at(geom: VectorGeometry, point: np.ndarray) -> tuple[float, float]:
    """Detector pitch (row, col) seen at ``point``: median over views of ``|v|/M``, ``|u|/M``."""
    nu = np.linalg.norm(geom.u, axis=1)
    nv = np.linalg.norm(geom.v, axis=1)
    if geom.kind == "parallel":
        return float(np.median(nv)), float(np.median(nu))
    n = geom.det_normal
    s = geom.src
    num = np.einsum("ij,ij->i", geom.det_center - s, n)
    den = np.einsum("ij,ij->i", point[None, :] - s, n)
    if np.any(den * num <= 0):
        bad = np.nonzero(den * num <= 0)[0]
        raise GeometryError(
            f"the volume centre {point.tolist()} is not between the source and the detector at views {bad[:10].tolist()}"
        )
    mag = num / den
    return float(np.median(nv / mag)), float(np.median(nu / mag))


def build_volume_geometry(cfg, geom: VectorGeometry, *, defaults: Optional[VolumeGeometry] = None) -> VolumeGeometry:
    """The reconstruction grid of a ``[volume]`` section, its gaps filled from the detector.

    Parameters
    ----------
    cfg : VolumeConfig or Config
    geom : VectorGeometry
        The scan (after any binning), for the default shape and voxel size.
    defaults : VolumeGeometry, optional
        Values to use, before the detector rule, for what ``cfg`` leaves
        out (e.g. a vendor's grid, :meth:`VendorGeometry.volume_geometry`).

    Returns
    -------
    VolumeGeometry
        ``shape`` given or ``(n_rows, n_cols, n_cols)``; ``voxel_size`` given
        or the detector pitch at the volume centre (``pitch · SOD/SDD``
        cone, ``pitch`` parallel; rows -> z, columns -> y and x).
    """
    if isinstance(cfg, Config):
        cfg = cfg.volume
    if not isinstance(cfg, VolumeConfig):
        raise ConfigError(f"cfg must be a VolumeConfig or a Config, got {type(cfg).__name__}")
    if not isinstance(geom, VectorGeometry):
        raise GeometryError(f"geom must be a VectorGeometry, got {type(geom).__name__}")
    nr, nc = geom.det_shape
    offset = np.asarray(cfg.offset, np.float64)
    shape = cfg.shape or (defaults.shape if defaults is not None else (max(nr, 2), max(nc, 2), max(nc, 2)))
    if cfg.voxel_size is not None:
        vs = cfg.voxel_size
    elif defaults is not None:
        vs = defaults.voxel_size
    else:
        pr, pc = _pitch_at(geom, offset)
        vs = (pr, pc, pc)
    return VolumeGeometry(tuple(shape), vs, tuple(offset))


def check_coverage(geom: VectorGeometry, vol_geom: VolumeGeometry) -> float:
    """How much of the volume box's projection falls on the detector, worst view.

    The 8 corners of the box (voxel edges) are projected with
    :meth:`VectorGeometry.project_points`; per view, the fraction of their
    bounding rectangle that lies on the detector (pixel edges
    ``[-0.5, n - 0.5]``) is computed, and the smallest is returned.

    Returns
    -------
    float in (0, 1]
        1: every view sees the whole box. Below 0.5 a warning is logged
        (most of the volume is outside the field of view: a local
        tomography, or a volume too large).

    Raises
    ------
    GeometryError
        The box reaches the source plane (corners at or behind the source),
        or its projection misses the detector completely in some view.
    """
    if not isinstance(geom, VectorGeometry) or not isinstance(vol_geom, VolumeGeometry):
        raise GeometryError("check_coverage needs a VectorGeometry and a VolumeGeometry")
    half = vol_geom.extent_xyz / 2
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
    corners = np.asarray(vol_geom.offset) + signs * half
    if geom.kind == "cone":
        n = geom.det_normal
        depth_det = np.einsum("ij,ij->i", geom.det_center - geom.src, n)
        depth = np.einsum("vpk,vk->vp", corners[None] - geom.src[:, None], n) / depth_det[:, None]
        bad = np.nonzero(np.any(depth <= 1e-9, axis=1))[0]
        if bad.size:
            raise GeometryError(
                f"the volume box reaches the source plane (corners at or behind the source) at views {bad[:10].tolist()}; "
                "make the volume smaller or check sod and the volume offset"
            )
    rc = geom.project_points(corners)
    nr, nc = geom.det_shape
    r0, r1 = rc[..., 0].min(axis=1), rc[..., 0].max(axis=1)
    c0, c1 = rc[..., 1].min(axis=1), rc[..., 1].max(axis=1)
    area = np.maximum(r1 - r0, 1e-12) * np.maximum(c1 - c0, 1e-12)
    hr = np.clip(np.minimum(r1, nr - 0.5) - np.maximum(r0, -0.5), 0.0, None)
    hc = np.clip(np.minimum(c1, nc - 0.5) - np.maximum(c0, -0.5), 0.0, None)
    frac = hr * hc / area
    miss = np.nonzero(frac <= 0)[0]
    if miss.size:
        raise GeometryError(
            f"the volume's projection misses the detector completely at views {miss[:10].tolist()}; "
            "check the volume offset and the geometry"
        )
    worst = float(frac.min())
    if worst < 0.5:
        log.warning(
            "the volume box projects mostly outside the detector (%.0f %% of it on the detector at worst, view %d)",
            100 * worst, int(np.argmin(frac)),
        )
    return worst
