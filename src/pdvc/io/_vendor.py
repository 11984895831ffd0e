"""Geometry from vendor files: Nikon (``.xtekct``) and Bruker SkyScan (``.log``).

Both readers return a :class:`VendorGeometry`: the scan as the vendor
describes it (distances in mm, detector pitch, offsets, angles), plus
:meth:`VendorGeometry.to_vector_geometry`, which writes it as pdvc vectors
(``DESIGN.md`` §1). Nothing here reads projections; the vectors describe
the images **as stored in the vendor's files**: pixel ``(i, j)`` is row
``i`` counted from the top of the TIFF and column ``j`` from its left, so the
projection reader must not flip them.

How a vendor scan becomes vectors
---------------------------------
At view ``k`` with angle ``θ_k`` (pdvc convention, radians) and
``ê(θ) = (cos θ, sin θ, 0)`` (the direction to the right as seen from the
source, for an upright viewer with z up)::

    src = Rz(θ) (0, -SOD, 0) - a ê            (cone; parallel: ray = Rz(θ)(0, -1, 0))
    d   = Rz(θ) (0,  ODD, 0) - a ê + o_c u + o_r v
    u   = s_c · p_col · ê                      (s_c = column_sign)
    v   = s_r · p_row · (0, 0, 1)              (s_r = row_sign)

``a`` is :attr:`VendorGeometry.axis_offset`, the horizontal position of the
rotation axis relative to the central ray (mm at the axis, positive to the
right as seen from the source); ``(o_r, o_c)`` the detector offset in
pixels. A tilted axis (Nikon ``ObjectRoll``/``ObjectTilt`` or the
centre-of-rotation difference top/bottom) is applied by rotating the
scanner about the origin so that the axis becomes z before ``Rz(θ)``.

Both vendors store images with row 0 at the top, so ``row_sign = -1``
(rows run down, ``-z``).

Nikon conventions (and where they come from)
--------------------------------------------
Key names and file layouts follow the public readers of CIL
(``cil.io.NikonDataReader``), TIGRE (``NikonDataLoader``) and the CCPi
``XtekReader``. The orientation follows CIL, whose Nikon reader is the most
carefully validated: CIL models the scan with the source at the origin,
the beam along +y, the rotation axis at ``x = -ObjectOffsetX``, panel origin
``"top-right"`` and CIL angle ``180° - α`` for the Nikon angle ``α``.
Converted through CIL's own ASTRA conversion this is, in pdvc terms:

* ``θ = α + 180°`` (the rotation sense is the same as pdvc's; TIGRE's
  reader, ``-α`` with its images stored upside down, agrees up to a
  rotation of the whole frame by 180° about y, which confirms the sense);
* ``column_sign = -1`` (Nikon columns run right-to-left as seen from the
  source), ``row_sign = -1``;
* ``axis_offset = -ObjectOffsetX``; when ``ObjectOffsetX`` is absent,
  ``-(CentreOfRotationTop + CentreOfRotationBottom)/2 · SOD/SDD`` (the
  centre-of-rotation values are mm on the detector, as in CIL);
* axis roll ``-atan2(CoRTop - CoRBottom, DetectorPixelsY · DetectorPixelSizeY)``
  unless ``ObjectRoll`` (degrees) is given, tilt ``-ObjectTilt`` (degrees),
  as in CIL.

Uncertain, stated here and in the report: (1) ``DetectorOffsetX/Y`` (mm)
are ignored by CIL and used with an unknown sign by TIGRE; pdvc reads them
as a shift of the detector centre by ``+X`` along ``ê`` (right as seen from
the source) and ``+Y`` up, and logs a warning when they are not zero.
(2) Angle files: ``_ctdata.txt`` (3 header lines -- ``Projs Frames
Exposure(ms)``, its values, a column header -- then rows ``projection angle
time``) and ``<Name>.ang`` (header ``Proj Angle(deg)``, rows ``p angle`` or
``Proj p: angle``). The readers disagree on whether ``InitialAngle`` must be
added to these angles (the old CIL reader adds it, TIGRE does not) and the
current CIL reader ignores both files "as not correct". pdvc reads the file
angles as absolute stage angles (no ``InitialAngle`` added; a constant
offset only turns the reconstruction). Following both the CCPi and the old
CIL readers, ``.ang`` files list the projections in reverse order
(projection label ``p`` of ``N`` belongs to image ``N - p``).
``angles="nominal"`` uses ``InitialAngle + k · AngularStep`` instead.

SkyScan conventions
-------------------
Keys from Bruker SkyScan ``.log`` files (``[System]``, ``[Acquisition]``,
``[Reconstruction]``, matched case-insensitively). The detector pitch is
taken from the calibrated object-plane pixel, ``Image Pixel Size (um) ·
SDD/SOD`` (SDD = ``Camera to Source (mm)``), so a reconstruction has the
voxel size NRecon reports; rows use ``/ Camera X/Y Ratio``. ``Optical Axis
(line)`` is the row (from the top) hit at right angles by the central ray:
``det_offset_row = (n_rows - 1)/2 - OpticalAxis``. ``[Reconstruction]
Postalignment`` (pixels) shifts the detector along ``u``
(``det_offset_col = +Postalignment``), as ASTRA's SkyScan parser does.
Angles ``θ_k = s · (start + k · Rotation Step)`` with ``s = +1`` for
``Rotation Direction=CC`` (default) and ``-1`` for ``CW``, ``start`` the
``Scanning Start Angle`` (0 if absent); ``column_sign = +1``,
``row_sign = -1``. This pairing of rotation sense and column direction is
the one of ASTRA's SkyScan parser and of TIGRE's Bruker loader (which agree
up to a mirror); it is the opposite of Nikon's, consistent with Nikon's
clockwise and SkyScan's counter-clockwise ("CC") stages. Uncertain: the
handedness (a wrong guess mirrors the reconstruction, it does not blur it),
whether ``Optical Axis`` counts from the top, the ``Postalignment`` sign,
partial-width or connected (oversize) scans, which are not handled. When
``Camera to Source (mm)`` is absent, SDD comes from ``Camera Pixel Size (um)``
and ``Camera binning``; an ``Object to Source`` of 10 m or more with no
camera distance is read as parallel beam (optical scanners).
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Mapping, Optional

import numpy as np

from ..errors import GeometryError
from ..geometry import VectorGeometry, VolumeGeometry

__all__ = ["VendorGeometry", "read_nikon", "read_skyscan", "read_vendor_geometry"]

log = logging.getLogger(__name__)

#: An "Object to Source" distance at least this large (mm) with no camera
#: distance is an optical (parallel-beam) SkyScan scanner.
_PARALLEL_SOD_MM = 1.0e4


# -- the result ---------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class VendorGeometry:
    """A scan as described by a vendor file (lengths in mm, angles in radians).

    Attributes
    ----------
    vendor : {"nikon", "skyscan"}
    kind : {"cone", "parallel"}
    sod, odd : float
        Source to rotation axis and rotation axis to detector, mm
        (``inf`` and ``0`` for parallel beam).
    pixel : (row_pitch, col_pitch)
        Detector pitch, mm.
    det_shape : (n_rows, n_cols)
    det_offset : (row, col)
        Shift of the detector centre along ``v`` and ``u``, pixels.
    angles : (n_views,) float64
        View angles θ in pdvc's convention (``DESIGN.md`` §1), radians.
    axis_offset : float
        Rotation axis relative to the central ray, mm at the axis, positive
        to the right as seen from the source.
    axis_roll, axis_tilt : float
        Rotation-axis inclination about the beam (roll) and about the
        horizontal detector direction (tilt), radians (Nikon, as in CIL).
    column_sign, row_sign : {+1, -1}
        Direction of increasing column / row index: ``+1`` along ``ê`` /
        up, ``-1`` against.
    voxel_size : (sz, sy, sx) or None
        The vendor's reconstruction voxel size, mm.
    volume_shape : (nz, ny, nx) or None
        The vendor's reconstruction grid, when the file gives it.
    angles_source : str
        Where the angles came from: ``"ctdata"``, ``"ang"``, ``"nominal"``.
    path : str
        The file read.
    raw : mapping
        Every key of the file, ``"Section/Key" -> value`` (strings, read only).
    """

    vendor: str
    kind: str
    sod: float
    odd: float
    pixel: tuple[float, float]
    det_shape: tuple[int, int]
    det_offset: tuple[float, float]
    angles: np.ndarray
    axis_offset: float = 0.0
    axis_roll: float = 0.0
    axis_tilt: float = 0.0
    column_sign: int = 1
    row_sign: int = -1
    voxel_size: Optional[tuple[float, float, float]] = None
    volume_shape: Optional[tuple[int, int, int]] = None
    angles_source: str = "nominal"
    path: str = ""
    raw: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        a = np.array(self.angles, dtype=np.float64).reshape(-1)
        a.setflags(write=False)
        object.__setattr__(self, "angles", a)
        object.__setattr__(self, "raw", MappingProxyType(dict(self.raw)))

    @property
    def n_views(self) -> int:
        return int(self.angles.size)

    @property
    def sdd(self) -> float:
        """Source to detector distance, mm."""
        return self.sod + self.odd

    @property
    def magnification(self) -> float:
        """SDD / SOD (1 for parallel beam)."""
        return 1.0 if self.kind == "parallel" else self.sdd / self.sod

    def __repr__(self) -> str:
        return (
            f"VendorGeometry(vendor={self.vendor!r}, kind={self.kind!r}, sod={self.sod:g}, odd={self.odd:g}, "
            f"pixel={self.pixel}, det_shape={self.det_shape}, n_views={self.n_views}, "
            f"angles_source={self.angles_source!r})"
        )

    def volume_geometry(self) -> Optional[VolumeGeometry]:
        """The vendor's reconstruction grid (centred at the origin), or None if the file gives none."""
        if self.volume_shape is None or self.voxel_size is None:
            return None
        return VolumeGeometry(self.volume_shape, self.voxel_size)

    def to_vector_geometry(self) -> VectorGeometry:
        """Per-view vectors of this scan (module docstring gives the formulas).

        Returns
        -------
        VectorGeometry
            ``n_views`` rows, ``det_shape`` of the file, for the images as
            stored (row 0 at the top).
        """
        py, px = self.pixel
        ro, co = self.det_offset
        e = np.array([1.0, 0.0, 0.0])
        up = np.array([0.0, 0.0, 1.0])
        u0 = self.column_sign * px * e
        v0 = self.row_sign * py * up
        if self.kind == "cone":
            s0 = np.array([0.0, -self.sod, 0.0]) - self.axis_offset * e
            d0 = np.array([0.0, self.odd, 0.0])
        else:
            s0 = np.array([0.0, -1.0, 0.0])
            d0 = np.zeros(3)
        d0 = d0 - self.axis_offset * e + co * u0 + ro * v0
        R = _axis_alignment(self.axis_roll, self.axis_tilt)
        s0, d0, u0, v0 = R @ s0, R @ d0, R @ u0, R @ v0
        c, s = np.cos(self.angles), np.sin(self.angles)
        Rz = np.zeros((self.n_views, 3, 3))
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
        parts = np.stack([s0, d0, u0, v0])  # (4, 3)
        vec = np.einsum("nij,kj->nki", Rz, parts).reshape(self.n_views, 12)
        return VectorGeometry(vec, self.det_shape, self.kind)


def _axis_alignment(roll: float, tilt: float) -> np.ndarray:
    """Rotation taking the (rolled, tilted) axis direction to +z, about the origin.

    The axis direction in the scanner frame is ``T(tilt) R_y(roll) ẑ`` (CIL's
    construction: roll about the beam direction y, tilt about x); the
    returned matrix is the smallest rotation mapping it onto ``ẑ``.
    """
    if roll == 0.0 and tilt == 0.0:
        return np.eye(3)
    cr, sr, ct, st = math.cos(roll), math.sin(roll), math.cos(tilt), math.sin(tilt)
    roll_m = np.array([[cr, 0.0, sr], [0.0, 1.0, 0.0], [-sr, 0.0, cr]])
    tilt_m = np.array([[1.0, 0.0, 0.0], [0.0, ct, -st], [0.0, st, ct]])
    a = tilt_m @ roll_m @ np.array([0.0, 0.0, 1.0])
    z = np.array([0.0, 0.0, 1.0])
    k = np.cross(a, z)
    sin_t, cos_t = np.linalg.norm(k), float(a @ z)
    if sin_t < 1e-15:
        return np.eye(3)
    k = k / sin_t
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + sin_t * K + (1.0 - cos_t) * (K @ K)


# -- INI-like files ----------------------------------------------------------
def _read_text(path: Path) -> str:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise GeometryError(f"vendor geometry file {str(path)!r} does not exist") from None
    except OSError as exc:
        raise GeometryError(f"cannot read vendor geometry file {str(path)!r}: {exc}") from None
    # Vendor software is Windows software: files are UTF-8 or a code page.
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return data.decode("latin-1")


def _parse_ini(text: str) -> dict[tuple[str, str], tuple[str, str, str]]:
    """``{(section, key) lowercased: (Section, Key, value)}``; first occurrence wins."""
    out: dict[tuple[str, str], tuple[str, str, str]] = {}
    section = ""
    for line in text.splitlines():
        s = line.strip()
        if not s or s[0] in ";#":
            continue
        if s.startswith("[") and s.endswith("]"):
            section = s[1:-1].strip()
            continue
        if "=" not in s:
            continue
        key, value = s.split("=", 1)
        ident = (section.lower(), key.strip().lower())
        if ident not in out:
            out[ident] = (section, key.strip(), value.strip())
    return out


class _Keys:
    """Typed, case-insensitive access to a parsed vendor file, with clear errors."""

    def __init__(self, entries, path: Path, vendor: str):
        self._entries = entries
        self._path = path
        self._vendor = vendor

    def raw(self) -> dict[str, str]:
        return {f"{sec}/{key}" if sec else key: val for sec, key, val in self._entries.values()}

    def get(self, key: str, section: Optional[str] = None) -> Optional[str]:
        k = key.lower()
        if section is not None:
            hit = self._entries.get((section.lower(), k))
            return None if hit is None or hit[2] == "" else hit[2]
        for (_, kk), (_, _, val) in self._entries.items():
            if kk == k and val != "":
                return val
        return None

    def _fail(self, key: str, what: str) -> GeometryError:
        return GeometryError(f"{self._vendor} file {str(self._path)!r}: {key} {what}")

    def number(self, key: str, section: Optional[str] = None, default: Optional[float] = None) -> float:
        val = self.get(key, section)
        if val is None:
            if default is None:
                raise self._fail(key, "is missing (needed for the geometry)")
            return float(default)
        m = re.match(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)", val)
        if m is None:
            raise self._fail(key, f"must be a number, got {val!r}")
        x = float(m.group(1))
        if not math.isfinite(x):
            raise self._fail(key, f"must be finite, got {val!r}")
        return x

    def optional_number(self, key: str, section: Optional[str] = None) -> Optional[float]:
        return None if self.get(key, section) is None else self.number(key, section)

    def count(self, key: str, section: Optional[str] = None) -> int:
        x = self.number(key, section)
        if x != int(x) or x < 1:
            raise self._fail(key, f"must be a positive whole number, got {self.get(key, section)!r}")
        return int(x)

    def positive(self, key: str, section: Optional[str] = None, default: Optional[float] = None) -> float:
        x = self.number(key, section, default)
        if x <= 0:
            raise self._fail(key, f"must be positive, got {x!r}")
        return x


# -- Nikon -------------------------------------------------------------------
def _numeric_rows(lines: list[str]) -> list[list[list[float]]]:
    """Contiguous blocks of lines made only of numbers (tab, space or comma separated)."""
    blocks: list[list[list[float]]] = []
    cur: list[list[float]] = []
    for line in lines:
        toks = [t for t in re.split(r"[\s,]+", line.strip()) if t]
        try:
            row = [float(t) for t in toks] if toks else None
        except ValueError:
            row = None
        if row:
            cur.append(row)
        else:
            if cur:
                blocks.append(cur)
            cur = []
    if cur:
        blocks.append(cur)
    return blocks


def _read_ctdata(path: Path) -> np.ndarray:
    """Angles (degrees) of ``_ctdata.txt``, in projection order."""
    blocks = [b for b in _numeric_rows(_read_text(path).splitlines()) if all(len(r) >= 2 for r in b)]
    if not blocks:
        raise GeometryError(f"Nikon angle file {str(path)!r} holds no table of 'projection angle' rows")
    table = max(blocks, key=len)
    idx = np.array([r[0] for r in table])
    ang = np.array([r[1] for r in table])
    return ang[np.argsort(idx, kind="stable")]


_ANG_ROW = re.compile(r"^\s*(?:[A-Za-z]+\s*)?(\d+)\s*[:\t ,]\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*$")


def _read_ang(path: Path) -> np.ndarray:
    """Angles (degrees) of a Nikon ``.ang`` file, in image order (the file lists them reversed)."""
    rows = []
    for line in _read_text(path).splitlines():
        m = _ANG_ROW.match(line)
        if m:
            rows.append((int(m.group(1)), float(m.group(2))))
    if not rows:
        raise GeometryError(f"Nikon angle file {str(path)!r} holds no 'Proj Angle(deg)' rows")
    n = len(rows)
    labels = np.array([p for p, _ in rows])
    angles = np.array([a for _, a in rows])
    first = 0 if labels.min() == 0 else 1
    if sorted(labels.tolist()) != list(range(first, first + n)):
        raise GeometryError(f"Nikon angle file {str(path)!r}: projection labels are not 0..N-1 or 1..N")
    out = np.empty(n)
    out[(n - 1 + first) - labels] = angles  # label p of 1..N -> image N - p (0..N-1: N-1-p)
    return out


def _nikon_angle_file(folder: Path, name: Optional[str], stem: str) -> tuple[Optional[Path], str]:
    ct = folder / "_ctdata.txt"
    if ct.is_file():
        return ct, "ctdata"
    cts = sorted(folder.glob("*_ctdata.txt"))
    if cts:
        return cts[0], "ctdata"
    for cand in ([name] if name else []) + [stem]:
        p = folder / f"{cand}.ang"
        if p.is_file():
            return p, "ang"
    angs = sorted(folder.glob("*.ang"))
    if len(angs) == 1:
        return angs[0], "ang"
    return None, "nominal"


def read_nikon(path, *, angles: str = "auto", offsets: bool = True) -> VendorGeometry:
    """Read a Nikon XT(H) ``.xtekct`` file (and its angle file, if any).

    Parameters
    ----------
    path : str or Path
        The ``.xtekct`` file (INI layout, section ``[XTekCT]``).
    angles : {"auto", "nominal"}
        ``"auto"``: the angles of ``_ctdata.txt`` or ``<Name>.ang`` next to
        the file when present (and listing ``Projections`` angles), else
        ``InitialAngle + k · AngularStep``; ``"nominal"``: always the latter.
    offsets : bool
        Apply the axis offset (``ObjectOffsetX`` / ``CentreOfRotation*``),
        axis roll/tilt and ``DetectorOffsetX/Y``. False gives the ideal
        centred scan.

    Returns
    -------
    VendorGeometry
        Conventions and their sources are in the module docstring.
    """
    if angles not in ("auto", "nominal"):
        raise GeometryError(f"angles must be 'auto' or 'nominal', got {angles!r}")
    p = Path(path)
    k = _Keys(_parse_ini(_read_text(p)), p, "Nikon")
    sod = k.positive("SrcToObject")
    sdd = k.positive("SrcToDetector")
    if sdd <= sod:
        raise GeometryError(
            f"Nikon file {str(p)!r}: SrcToDetector ({sdd}) must exceed SrcToObject ({sod}): "
            "the detector must lie beyond the rotation axis"
        )
    n_cols, n_rows = k.count("DetectorPixelsX"), k.count("DetectorPixelsY")
    px, py = k.positive("DetectorPixelSizeX"), k.positive("DetectorPixelSizeY")
    n_proj = k.count("Projections") if k.get("Projections") is not None else None
    init = k.number("InitialAngle", default=0.0)

    deg = None
    source = "nominal"
    if angles == "auto":
        file, kind = _nikon_angle_file(p.parent, k.get("Name"), p.stem)
        if file is not None:
            deg = _read_ctdata(file) if kind == "ctdata" else _read_ang(file)
            source = kind
            if n_proj is not None and deg.size != n_proj:
                log.warning(
                    "%s lists %d angles but %s has Projections=%d; using the nominal angles",
                    file, deg.size, p.name, n_proj,
                )
                deg, source = None, "nominal"
    if deg is None:
        if n_proj is None:
            raise GeometryError(f"Nikon file {str(p)!r}: Projections is missing and no angle file was found")
        step = k.number("AngularStep", default=360.0 / n_proj)
        deg = init + step * np.arange(n_proj)
        source = "nominal"

    axis_offset = roll = tilt = 0.0
    det_off = (0.0, 0.0)
    if offsets:
        cor_top = k.number("CentreOfRotationTop", default=0.0)
        cor_bot = k.number("CentreOfRotationBottom", default=0.0)
        obj_x = k.optional_number("ObjectOffsetX")
        if obj_x is None:
            obj_x = 0.5 * (cor_top + cor_bot) * sod / sdd
        axis_offset = -obj_x
        obj_roll = k.optional_number("ObjectRoll")
        if obj_roll is None:
            roll = -math.atan2(cor_top - cor_bot, n_rows * py)
        else:
            roll = math.radians(obj_roll)
        tilt = -math.radians(k.number("ObjectTilt", default=0.0))
        dx, dy = k.number("DetectorOffsetX", default=0.0), k.number("DetectorOffsetY", default=0.0)
        if dx or dy:
            log.warning(
                "%s: DetectorOffsetX/Y = %g, %g mm applied as a shift right/up as seen from the source; "
                "the sign of these keys is not documented (see pdvc.io._vendor)", p.name, dx, dy,
            )
        # u = -px ê (column_sign -1), v = -py ẑ (row_sign -1)
        det_off = (-dy / py, -dx / px)

    vox = [k.optional_number(f"VoxelSize{a}") for a in "ZYX"]
    nvox = [k.optional_number(f"Voxels{a}") for a in "ZYX"]
    voxel_size = tuple(float(v) for v in vox) if all(v is not None and v > 0 for v in vox) else None
    vol_shape = tuple(int(n) for n in nvox) if all(n is not None and n >= 2 for n in nvox) else None
    return VendorGeometry(
        vendor="nikon",
        kind="cone",
        sod=sod,
        odd=sdd - sod,
        pixel=(py, px),
        det_shape=(n_rows, n_cols),
        det_offset=det_off,
        angles=np.deg2rad(np.asarray(deg, np.float64)) + math.pi,
        axis_offset=axis_offset,
        axis_roll=roll,
        axis_tilt=tilt,
        column_sign=-1,
        row_sign=-1,
        voxel_size=voxel_size,  # type: ignore[arg-type]
        volume_shape=vol_shape,  # type: ignore[arg-type]
        angles_source=source,
        path=str(p),
        raw=k.raw(),
    )


# -- SkyScan -----------------------------------------------------------------
def read_skyscan(path, *, offsets: bool = True) -> VendorGeometry:
    """Read a Bruker SkyScan acquisition ``.log`` file.

    Parameters
    ----------
    path : str or Path
        The ``.log`` file (INI layout: ``[System]``, ``[Acquisition]``,
        ``[Reconstruction]``; keys matched case-insensitively).
    offsets : bool
        Apply ``Optical Axis (line)`` and ``[Reconstruction] Postalignment``.

    Returns
    -------
    VendorGeometry
        Conventions and their doubts are in the module docstring.
    """
    p = Path(path)
    k = _Keys(_parse_ini(_read_text(p)), p, "SkyScan")
    acq = "Acquisition"
    n_files = k.count("Number Of Files", acq)
    n_rows, n_cols = k.count("Number Of Rows", acq), k.count("Number Of Columns", acq)
    img_px = k.positive("Image Pixel Size (um)", acq) / 1000.0
    sod = k.positive("Object to Source (mm)", acq)
    step = k.number("Rotation Step (deg)", acq)
    if step == 0:
        raise GeometryError(f"SkyScan file {str(p)!r}: Rotation Step (deg) must not be zero")
    ratio = k.positive("Camera X/Y Ratio", default=1.0)
    sdd = k.optional_number("Camera to Source (mm)", acq)
    kind = "cone"
    if sdd is None:
        cam = k.optional_number("Camera Pixel Size (um)")
        if sod >= _PARALLEL_SOD_MM:
            kind = "parallel"
        elif cam is not None and cam > 0:
            binning = k.get("Camera binning", acq) or "1x1"
            m = re.match(r"\s*(\d+)\s*[xX]\s*(\d+)", binning)
            bx = int(m.group(1)) if m else 1
            sdd = sod * cam / 1000.0 * bx / img_px
        else:
            raise GeometryError(
                f"SkyScan file {str(p)!r}: 'Camera to Source (mm)' is missing and cannot be derived "
                "(no 'Camera Pixel Size (um)'); add it to the file or describe the scan with [geometry] type='cone'"
            )
    if kind == "cone":
        if sdd <= sod:
            raise GeometryError(
                f"SkyScan file {str(p)!r}: Camera to Source ({sdd:g} mm) must exceed Object to Source "
                f"({sod:g} mm): the detector must lie beyond the rotation axis"
            )
        px = img_px * sdd / sod
        odd = sdd - sod
    else:
        px = img_px
        sod, odd = math.inf, 0.0
    py = px / ratio

    direction = (k.get("Rotation Direction", acq) or "CC").strip().upper()
    if direction not in ("CC", "CCW", "CW"):
        raise GeometryError(f"SkyScan file {str(p)!r}: Rotation Direction must be CC or CW, got {direction!r}")
    sign = -1.0 if direction == "CW" else 1.0
    start = k.number("Scanning Start Angle", acq, default=0.0)
    deg = sign * (start + step * np.arange(n_files))

    det_off = (0.0, 0.0)
    if offsets:
        oa = k.optional_number("Optical Axis (line)", acq)
        row_off = 0.0 if oa is None else (n_rows - 1) / 2.0 - oa
        post = k.optional_number("Postalignment", "Reconstruction")
        det_off = (row_off, 0.0 if post is None else post)

    rec_px = k.optional_number("Pixel Size (um)", "Reconstruction")
    voxel_size = (rec_px / 1000.0,) * 3 if rec_px is not None and rec_px > 0 else None
    w = k.optional_number("Result Image Width (pixels)", "Reconstruction")
    h = k.optional_number("Result Image Height (pixels)", "Reconstruction")
    nz = k.optional_number("Sections Count", "Reconstruction")
    vol_shape = (int(nz), int(h), int(w)) if None not in (w, h, nz) and min(w, h, nz) >= 2 else None  # type: ignore[type-var]
    return VendorGeometry(
        vendor="skyscan",
        kind=kind,
        sod=sod,
        odd=odd,
        pixel=(py, px),
        det_shape=(n_rows, n_cols),
        det_offset=det_off,
        angles=np.deg2rad(deg),
        column_sign=1,
        row_sign=-1,
        voxel_size=voxel_size,  # type: ignore[arg-type]
        volume_shape=vol_shape,  # type: ignore[arg-type]
        angles_source="nominal",
        path=str(p),
        raw=k.raw(),
    )


def read_vendor_geometry(path, vendor: str = "auto", **options) -> VendorGeometry:
    """Read a vendor geometry file, choosing the reader by ``vendor`` or the file extension.

    Parameters
    ----------
    path : str or Path
        ``.xtekct`` (Nikon) or ``.log`` (SkyScan).
    vendor : {"auto", "nikon", "skyscan"}
    **options
        Passed to :func:`read_nikon` or :func:`read_skyscan`.
    """
    p = Path(path)
    if vendor == "auto":
        ext = p.suffix.lower()
        vendor = {".xtekct": "nikon", ".log": "skyscan"}.get(ext, "")
        if not vendor:
            raise GeometryError(
                f"cannot tell the vendor of {str(p)!r} from its extension {ext!r}; "
                "expected .xtekct (Nikon) or .log (SkyScan), or pass vendor='nikon'/'skyscan'"
            )
    if vendor == "nikon":
        return read_nikon(p, **options)
    if vendor == "skyscan":
        return read_skyscan(p, **options)
    raise GeometryError(f"vendor must be 'auto', 'nikon' or 'skyscan', got {vendor!r}")
