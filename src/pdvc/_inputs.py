"""From a TOML configuration to calibration-ready inputs (the CLI's front end).

``load_scan(config)`` reads the projections (and flats/darks; bad pixels
interpolated), says what the values are (counts, transmission, line
integrals) and why, normalises them to line integrals, measures the air
level (and subtracts it with ``[preprocess] air = "auto"``), applies the
beam-hardening polynomial, builds the
nominal geometry (circular cone/parallel, vector rows or a vendor file),
crops the detector ROI, bins (a large or binned scan is read, normalised and
binned a chunk of views at a time: :mod:`pdvc.io._chunked`), and builds the reconstruction grid; it
returns them with the engine options of ``[calibration]`` and the fully
resolved configuration (what ``config.toml`` in the outputs holds).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Optional

import numpy as np

from .correlation import coarse_grain
from .errors import PdvcError
from .geometry import VectorGeometry, VolumeGeometry

log = logging.getLogger("pdvc")

__all__ = ["Scan", "load_scan", "inspect_scan", "calibration_options"]


@dataclass(frozen=True)
class Scan:
    projections: np.ndarray
    geometry: VectorGeometry
    vol_geom: VolumeGeometry
    weights: Optional[np.ndarray]
    calibration_options: dict
    config: object  # the resolved Config
    notes: tuple
    raw: object
    problems: tuple = ()  # what the inputs look wrong in (air level off 0, values unlike is_raw says)
    air: object = None  # the pdvc.io.AirEstimate of the line integrals (before any subtraction)
    geometry_unbinned: Optional[VectorGeometry] = None  # the detector before [preprocess] bin (None when bin = 1)


def calibration_options(cal, det_shape, vol_shape=None, geom=None, notes=None) -> dict:
    """``[calibration]`` as :func:`pdvc.calibrate` options, with the stage list resolved for ``det_shape`` and ``vol_shape``.

    With ``geom``, a short scan without a ``reconstruct`` set
    reconstructs by ``nonneg_ls``, as :func:`pdvc.calibrate` decides
    (:func:`pdvc.calibration.short_scan_reconstruction`); why goes to
    ``notes`` (a list), or to the log.
    """
    from .calibration import Stage, resolve_stages, short_scan_reconstruction
    from .calibration._pipeline import SECOND_RUN_USER_FIELDS

    if cal.stage is not None:
        stages = tuple(Stage.from_dict(d) for d in cal.stage)
    else:
        params = cal.recipe_parameters()
        if geom is not None:
            params, note = short_scan_reconstruction(geom, **params)
            if note:
                notes.append(note) if notes is not None else log.info(note)
        stages = resolve_stages(det_shape, vol_shape=vol_shape, recipe=cal.recipe, geom=geom, notes=notes, **params)
    params = cal.recipe_parameters()
    opts = dict(
        recipe=cal.recipe, stages=stages, fix_scale=bool(cal.fix_scale), backend=cal.backend, init=cal.init,
        truncation=cal.truncation, zingers=cal.zingers, rings=cal.rings, roi=cal.roi, air=cal.air,
        # a stage list written out in the config, or a model or volume of the user's own, runs as written: no
        # second recipe (as pdvc.calibrate decides from its keywords)
        second_run=cal.second_run if cal.stage is None and not any(
            params.get(k) is not None for k in SECOND_RUN_USER_FIELDS) else "off",
    )
    if cal.center is not None:
        opts["center"] = tuple(cal.center)
    return opts


def counts_noise_variance(raw, p) -> float:
    """γ² from the Poisson statistics of raw counts with flats (photon-counting, gain 1).

    ``i0`` is the mean of flat − dark; the per-pixel variance of each line
    integral is :func:`pdvc.correlation.poisson_variance` (projection and
    averaged-flat terms), and γ² is its mean over the data.
    """
    from .correlation import poisson_variance

    i0, n_flats = _counts_i0(raw)
    return float(np.mean(poisson_variance(p, i0=i0, n_flats=n_flats)))


def _counts_i0(raw) -> tuple[float, int]:
    """``(i0, n_flats)`` of :func:`counts_noise_variance` (a RawScan or a ProjectionSource)."""
    if not raw.is_raw or raw.flats is None:
        raise PdvcError("calibration.noise = 'counts' needs raw counts with flats ([data] flats or a file that holds them)")
    dark = 0.0 if raw.darks is None else raw.darks.mean(axis=0)
    i0 = float(np.mean(raw.flats.mean(axis=0) - dark))
    if not i0 > 0:
        raise PdvcError(f"calibration.noise = 'counts': the mean flat minus dark must be positive, got {i0:g}")
    return i0, int(raw.flats.shape[0])


def _vendor(cfg):
    if cfg.geometry.type in ("nikon", "skyscan"):
        from .io import _vendor as vendor

        return vendor.read_vendor_geometry(cfg.geometry.file, cfg.geometry.type)
    return None


def load_scan(config, *, out_dir=None, memory_budget: float | None = None, chunked: bool | None = None,
              chunk_bytes: int | None = None) -> Scan:
    """Read and prepare everything a ``[data]``/``[geometry]``/``[volume]`` config describes.

    The notes say what was read and done: the data kind assumed and why, bad
    pixels interpolated, clipping, the air level (subtracted or not). Input
    problems (air level off 0, values that do not look like ``is_raw``
    says) are in ``Scan.problems`` and also as ``warning:`` notes.

    Large scans
    -----------
    With ``[preprocess] bin > 1``, or when the float32 projections of the
    full detector would exceed ``memory_budget`` bytes (default
    :data:`pdvc.io._chunked.DEFAULT_MEMORY_BUDGET`, 2 GiB), the projections
    are read, normalised, cropped and binned a chunk of views at a time
    (:func:`pdvc.io._chunked.preprocess_chunked`): the full-size float32
    stack never sits in memory, and the results equal the in-memory path's
    to float rounding. ``chunked`` forces one path (True: chunks, False: in
    memory); ``chunk_bytes`` sets the float32 bytes per chunk (default
    128 MiB). ``Scan.raw`` is then the
    :class:`pdvc.io._projections.ProjectionSource` (no ``data``).
    """
    from .io import (
        beam_hardening,
        classify_values,
        detector_roi,
        estimate_air,
        flats_from_columns,
        normalize,
        read_projections,
        subtract_air,
    )
    from .io._chunked import DEFAULT_CHUNK_BYTES, DEFAULT_MEMORY_BUDGET, preprocess_chunked
    from .io._config import build_geometry, build_volume_geometry, check_coverage, load_config
    from .io._projections import open_projections, sample_view_indices

    cfg = load_config(config)
    d = cfg.data
    pp = cfg.preprocess
    notes, problems = [], []

    def warn(text):
        problems.append(text)
        notes.append(f"warning: {text}")
        log.warning("%s", text)

    budget = DEFAULT_MEMORY_BUDGET if memory_budget is None else memory_budget
    if not (isinstance(budget, (int, float, np.integer, np.floating)) and budget > 0):
        raise PdvcError(f"memory_budget must be a positive number of bytes, got {memory_budget!r}")
    if chunked is not None and not isinstance(chunked, (bool, np.bool_)):
        raise PdvcError(f"chunked must be None (decide), True or False, got {chunked!r}")
    read_args = dict(
        fmt=d.format,
        flats=d.flats,
        darks=d.darks,
        dataset=d.dataset,
        sinogram=d.sinogram,
        is_raw=None if d.is_raw == "auto" else (d.is_raw if isinstance(d.is_raw, str) else bool(d.is_raw)),
        bad_pixels=pp.mask,
        dead_columns=pp.dead_columns,
    )
    if chunked is False:
        use_chunks = False
    else:
        src = open_projections(d.path, **read_args)
        full_bytes = 4 * src.n_views * src.det_shape[0] * src.det_shape[1]
        use_chunks = bool(chunked) or pp.bin > 1 or full_bytes > budget
    if use_chunks:
        raw = src
    elif chunked is None:  # opened already: read it whole
        raw = src.to_raw()
    else:
        raw = read_projections(d.path, **read_args)
    n_views, det_shape = raw.n_views, raw.det_shape
    words = {"counts": "raw counts", "transmission": "transmission (I/I0)", "line_integrals": "line integrals"}
    notes.append(f"read {raw.format} {d.path}: {n_views} views of {det_shape[0]}x{det_shape[1]} px, {words[raw.kind]}")
    n_bad = int(raw.metadata.get("bad_pixels", 0))
    if pp.mask is not None or pp.dead_columns is not None:
        notes.append(f"{n_bad} bad detector pixels ({raw.metadata.get('bad_pixels_source')}) interpolated along their rows")
    reason = raw.metadata.get("is_raw_reason", "")
    if d.is_raw == "auto":
        what = f"data taken as {words[raw.kind]}" + (" (-log taken)" if raw.kind == "transmission" else "")
        kind_note = f"{what}: {reason}; set [data] is_raw to override"
    else:
        kind_note = f"data taken as {words[raw.kind]}: [data] is_raw = {str(d.is_raw).lower() if isinstance(d.is_raw, bool) else repr(d.is_raw)}"
    notes.append(kind_note)
    log.info("%s", kind_note)
    float_data = not np.issubdtype(np.dtype(raw.metadata.get("raw_dtype", "float32")), np.integer)
    if float_data and (d.is_raw != "auto" or raw.flats is not None):  # "auto" without flats: classified already
        # classify_values looks at 64 evenly spaced views: the same ones in both paths
        looks, why = classify_values(src.read_views(sample_view_indices(n_views)) if use_chunks else raw.data)
        if looks != raw.kind:
            said = "[data] is_raw says" if d.is_raw != "auto" else "with flats, taken as"
            warn(f"{said} {words[raw.kind]} but the values look like {words[looks]} ({why})")
    open_beam = None
    if d.open_beam_columns is not None:
        a, b = d.open_beam_columns
        if use_chunks:
            open_beam = (a, b)
        else:
            raw = flats_from_columns(raw, columns=slice(a, b))
        notes.append(f"flats from open-beam columns {a}..{b - 1}")
    counts_noise = cfg.calibration.noise == "counts"
    if counts_noise and raw.kind != "counts":
        raise PdvcError(f"calibration.noise = 'counts' needs raw counts with flats; these data are {words[raw.kind]}")
    geom_unbinned = None
    if use_chunks:
        geom = _checked_geometry(build_geometry(cfg.geometry, n_views=n_views, det_shape=det_shape, data_angles=raw.angles),
                                 (n_views,) + tuple(det_shape))
        noise_i0 = None
        if counts_noise:
            if open_beam is not None:  # the flats are the open-beam columns: known after the first pass
                raise PdvcError("calibration.noise = 'counts' with [data] open_beam_columns is not supported for a scan "
                                "read in chunks ([preprocess] bin > 1 or a large scan); give flats, or set bin = 1")
            noise_i0 = _counts_i0(raw)
        ch = preprocess_chunked(
            src, geom, scale=int(pp.bin), roi_rows=pp.roi_rows, roi_cols=pp.roi_cols,
            flat_interpolation=pp.flat_interpolation, clip_min=pp.clip_min, subtract_air=pp.air == "auto",
            beam_hardening=pp.beam_hardening, noise_i0=noise_i0, open_beam=open_beam,
            chunk_bytes=DEFAULT_CHUNK_BYTES if chunk_bytes is None else chunk_bytes,
        )
        p, rep, air = ch.projections, ch.report, ch.air
        gamma2_counts = ch.noise_variance
    else:
        p, rep = normalize(raw, flat_interpolation=pp.flat_interpolation, clip_min=pp.clip_min)
        gamma2_counts = counts_noise_variance(raw, p) if counts_noise else None  # full resolution, before binning
        air = estimate_air(p)
    n_clipped = int(getattr(rep, "n_clipped", 0))
    if n_clipped:
        notes.append(f"normalisation clipped {n_clipped} non-positive or tiny transmissions (clip_min {pp.clip_min:g})")
    if gamma2_counts is not None and pp.bin > 1:
        from .correlation import coarse_noise_factor

        gamma2_counts *= coarse_noise_factor(int(pp.bin))
    if pp.air == "auto":
        if not use_chunks:
            p, air = subtract_air(p, air)
        if air.found:
            lo, hi = air.fitted_range
            notes.append(
                f"air background subtracted ([preprocess] air = \"auto\"): per-view offset (median "
                f"{air.level:.4g}, transmission {air.transmission:.3f}) plus a degree-{air.degree} column profile "
                f"{lo:.4g} .. {hi:.4g}; the rays that miss the sample now read 0"
            )
        else:
            warn("[preprocess] air = \"auto\" but no air was found (the sample covers the detector): nothing subtracted")
    else:
        notes.append(air.summary())
        if air.problem() is not None:
            warn(air.problem())
    if pp.beam_hardening is not None:
        if not use_chunks:
            p = beam_hardening(p, pp.beam_hardening)
        notes.append(f"beam-hardening polynomial {list(pp.beam_hardening)}")
    vend = _vendor(cfg)
    if use_chunks:
        geom_roi = ch.geometry_roi
        if pp.roi_rows is not None or pp.roi_cols is not None:
            notes.append(f"detector ROI rows {pp.roi_rows}, cols {pp.roi_cols}: {geom_roi.det_shape[0]}x{geom_roi.det_shape[1]} px")
        geom = ch.geometry
        if pp.bin > 1:
            geom_unbinned = geom_roi
            notes.append(f"binned {pp.bin}x{pp.bin} (Gaussian then block mean); the geometry is also written for the full-resolution detector")
        notes.append(
            f"read in chunks of {ch.chunk_views} views ({ch.n_passes} pass{'es' if ch.n_passes > 1 else ''}, "
            f"{ch.seconds:.1f} s, {ch.mb_per_s:.0f} MB/s): NaN/Inf, clipping and the noise from the counts counted "
            f"over all views; the air level estimated on {ch.air.per_view.size} views x the detector rows "
            f"estimate_air examines, as in memory; the data kind checked on "
            f"{len(sample_view_indices(n_views))} evenly spaced views"
            + ("; the air background subtracted after binning (binning is linear)" if ch.air_subtracted and ch.n_passes == 1 else "")
        )
    else:
        geom = _checked_geometry(build_geometry(cfg.geometry, n_views=p.shape[0], det_shape=p.shape[1:], data_angles=raw.angles),
                                 p.shape)
        if pp.roi_rows is not None or pp.roi_cols is not None:
            p, geom = detector_roi(p, geom, rows=pp.roi_rows, cols=pp.roi_cols)
            notes.append(f"detector ROI rows {pp.roi_rows}, cols {pp.roi_cols}: {p.shape[1]}x{p.shape[2]} px")
        if pp.bin > 1:
            geom_unbinned = geom
            p, geom = coarse_grain(p, geom, int(pp.bin))
            notes.append(f"binned {pp.bin}x{pp.bin} (Gaussian then block mean); the geometry is also written for the full-resolution detector")
    if p.shape[1] == 1:
        # the interpolating projectors need two rows: a one-row sinogram becomes two
        # identical rows half a pixel above and below it (a slab two voxels thick)
        p = np.repeat(p, 2, axis=1)
        geom = VectorGeometry(geom.vectors, (2, geom.det_shape[1]), geom.kind)
        notes.append("one detector row: duplicated into two identical rows (a 2-voxel slab)")
    vol_geom = build_volume_geometry(cfg.volume, geom, defaults=None if vend is None else vend.volume_geometry())
    frac = check_coverage(geom, vol_geom)
    if frac < 0.6:  # a square grid as wide as the detector gives ~0.71: its corners leave the field, as in any scan
        notes.append(f"warning: only {100 * frac:.0f}% of the volume box projects onto the detector at the worst view")
    cal_opts = calibration_options(cfg.calibration, geom.det_shape, vol_geom.shape, geom, notes)
    if gamma2_counts is not None:
        cal_opts["noise_variance"] = gamma2_counts
        notes.append(f"noise variance from the counts (Poisson, gain 1): {gamma2_counts:.3g}")
    resolved = cfg.resolved(
        n_views=p.shape[0], det_shape=raw.det_shape if pp.roi_rows is None and pp.roi_cols is None and pp.bin == 1 else None,
        vol_geom=vol_geom, stages=cal_opts["stages"],
    )
    if out_dir is not None:
        resolved = dataclasses.replace(resolved, output=dataclasses.replace(resolved.output, dir=str(out_dir)))
    return Scan(
        projections=np.ascontiguousarray(p, dtype=np.float32),
        geometry=geom,
        vol_geom=vol_geom,
        weights=None,
        calibration_options=cal_opts,
        config=resolved,
        notes=tuple(notes),
        raw=raw,
        problems=tuple(problems),
        air=air,
        geometry_unbinned=geom_unbinned,
    )


def _checked_geometry(geom: VectorGeometry, shape) -> VectorGeometry:
    """The geometry built from the config must describe the projections read."""
    if geom.n_views != shape[0] or tuple(geom.det_shape) != tuple(shape[1:]):
        raise PdvcError(
            f"the geometry describes {geom.n_views} views of {tuple(geom.det_shape)} px but the projections are "
            f"{shape[0]} views of {tuple(shape[1:])} px; expected them to agree"
        )
    return geom


def _zinger_line(p, vol_geom, geom, volume) -> str:
    """What ``zingers = "auto"`` would find at the nominal geometry, looking first as the calibration does (on
    every 8th view of a scan of 64 views or more)."""
    from .calibration._pipeline import zinger_probe
    from .io import remove_zingers
    from .projectors import forward

    rep = zinger_probe(p, volume, vol_geom, geom)
    if rep is None:
        rep = remove_zingers(p, forward(volume, vol_geom, geom))[1]
    if not rep.count:
        return f"zingers at the nominal geometry: {rep.describe()}"
    where = f" on every {rep.every}th view" if rep.every > 1 else ""
    return (f"zingers at the nominal geometry{where}: {rep.describe(replaced=False)}; calibrate replaces them by "
            'the median of their neighbours (zingers = "auto")')


def _axis_line(p, g) -> str:
    """The coarse axis without a reconstruction: the opposite views' offset, on a short scan their lean (the offsets of
    the detector's halves of rows), and in parallel beam the row sums' tilt."""
    from .calibration import InitError, estimate_axis_lean, estimate_axis_offset, estimate_axis_tilt
    from .calibration._init import SHORT_SCAN_OPPOSITE_FRACTION, opposite_fraction, pairs_phrase

    try:
        est = estimate_axis_offset(p, g)
        offset, text = est.offset_px, f"offset {est.offset_px:+.2f} px from {pairs_phrase(g, est.n_pairs)}"
    except InitError as exc:
        offset, text = 0.0, f"offset not measured ({exc})"
    if opposite_fraction(g) < SHORT_SCAN_OPPOSITE_FRACTION:  # a short scan: its rounds do not settle the lean
        try:
            lean = estimate_axis_lean(p, g)
            text += (f"; lean in the detector plane {lean.roll_deg:+.3f} ± {np.degrees(lean.roll_sd):.3f}° from the "
                     f"offsets of the detector's top and bottom halves of rows")
        except InitError as exc:
            text += f"; lean not measured ({exc})"
    if g.kind == "parallel":
        try:
            text += f"; tilt from the row sums: {estimate_axis_tilt(p, g, offset_px=offset).describe()}"
        except InitError as exc:
            text += f"; tilt not measured ({exc})"
    return f"axis (coarse, no reconstruction): {text}"


def inspect_scan(config) -> tuple[list, list]:
    """Summary lines and a list of problems (empty when consistent)."""
    lines, problems = [], []
    try:
        scan = load_scan(config)
    except PdvcError as exc:
        return [f"config {config}"], [str(exc)]
    g = scan.geometry
    p = scan.projections
    lines.append(f"config {config}")
    lines.extend(scan.notes)
    problems.extend(scan.problems)
    lines.append(f"geometry: {g.kind} beam, {g.n_views} views, detector {g.det_shape[0]}x{g.det_shape[1]}")
    from .correlation import view_angles

    ang = np.rad2deg(view_angles(g))
    span = float(ang.max() - ang.min()) if g.n_views > 1 else 0.0
    lines.append(f"angles: {ang[0]:.2f} .. {ang[-1]:.2f} deg (span {span:.1f} deg, mean step {span / max(g.n_views - 1, 1):.3f} deg)")
    if g.kind == "cone":
        sod = np.linalg.norm(g.src, axis=1)
        sdd = np.linalg.norm(g.src - g.det_center, axis=1)
        lines.append(f"SOD {np.median(sod):.4g}, SDD {np.median(sdd):.4g}, magnification {np.median(sdd / sod):.4g}")
    vg = scan.vol_geom
    lines.append(f"volume: {'x'.join(map(str, vg.shape))} voxels of {vg.voxel_size} (z, y, x), offset {vg.offset}")
    lines.append(f"projections: min {float(p.min()):.4g}, max {float(p.max()):.4g}, mean {float(p.mean()):.4g}")
    if float(p.max()) <= 0:
        problems.append("projections are all <= 0: expected positive line integrals (is [data] is_raw right?)")
    step = span / max(g.n_views - 1, 1)
    if span + step < 179.0:  # each view stands for one step: N views over [0, 180) without the end point cover 180
        problems.append(f"the angles span only {span:.1f} deg (plus one step, {span + step:.1f}): a tomographic scan "
                        "needs at least 180 deg")
    n_cols = g.det_shape[1]
    nyquist = np.pi / 2 * n_cols
    if g.n_views < 0.25 * nyquist:
        lines.append(f"note: {g.n_views} views is well below the angular Nyquist rate (~{nyquist:.0f} for {n_cols} columns)")
    from .io._config import check_coverage

    frac = check_coverage(g, vg)
    if frac < 0.5:
        problems.append(f"the volume box projects onto the detector for only {100 * frac:.0f}% of its extent at the worst view")
    from .calibration import detect_scan_truncation, field_cover
    from .calibration._pipeline import ROI_FIELD_COVER

    from .recon import analytic

    lines.append(_axis_line(p, g))
    volume = analytic(p, vg, g)
    trunc, _ = detect_scan_truncation(p, vg, g, volume)  # read off the nominal reconstruction, an air level removed
    lines.append(f"sample and volume: {trunc.describe()}")
    lines.append(_zinger_line(p, vg, g, volume))
    if trunc.lateral:
        cover = field_cover(g, vg)
        lines.append(
            f"region of interest: the volume's inscribed radius is {100 * cover:.0f}% of the field of view's; "
            + ("roi = 'auto' compensates the scan" if cover >= ROI_FIELD_COVER else
               f"roi = 'auto' needs {100 * ROI_FIELD_COVER:.0f}% (a volume as wide as the field) and leaves it alone")
        )
        lines.append(_pattern_line(p, g))
    return lines, problems


def _pattern_line(p, g) -> str:
    """What a region-of-interest scan's opposite views say of a pattern fixed on the detector (no air to measure it)."""
    from .calibration import InitError, estimate_detector_pattern

    try:
        est = estimate_detector_pattern(p, g)
    except InitError as exc:
        return f"pattern fixed on the detector: not looked for ({exc})"
    figures = est.describe()
    if est.undecided:
        return (f"pattern fixed on the detector: cannot be told from the axis offset ({figures}); without a full turn "
                f"calibrate does not confirm the axis (status undetermined)")
    if est.found:
        return (f"pattern fixed on the detector (a flat field that varies across the columns?): {figures}; calibrate "
                f"subtracts it (air = 'auto')")
    return f"pattern fixed on the detector: none found ({figures})"
