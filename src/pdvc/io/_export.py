"""Exports of a per-view geometry for other toolkits: ASTRA, TIGRE, LEAP, CIL.

pdvc's geometry is ASTRA's vector layout (``DESIGN.md`` §1): per view
``(src, d, u, v)`` in the volume frame, pixel ``(i, j)`` at
``d + (j - (nc-1)/2) u + (i - (nr-1)/2) v``, volume ``f[z, y, x]`` with
voxel centres at ``((ix - (nx-1)/2) sx, ...) + offset``. Each export below
states how that maps onto the toolkit's own parameters; all of them use the
same world frame (x, y, z) and the same data order (projections
``[view, row, col]``, volumes ``[z, y, x]``), so no array needs to be
transposed or flipped. Lengths are in the geometry's unit (mm).

* **ASTRA** -- identical rows (``cone_vec`` / ``parallel3d_vec``); volume
  as ``astra.create_vol_geom(ny, nx, nz, minx, maxx, miny, maxy, minz, maxz)``.
* **TIGRE** (Python) -- cone beam only. Per view: the source is
  ``E (DSO, 0, 0)`` with ``E = Rz(α) Ry(θ) Rz(ψ)`` (the ZYZ Euler angles
  ``geo.angles[k] = (α, θ, ψ)``); the detector centre
  ``E (-(DSD - DSO), offDetector_U, offDetector_V)``; the column and row
  steps ``E R ŷ dDetector_U`` and ``E R ẑ dDetector_V`` with
  ``R = Rz(roll) Ry(pitch) Rx(yaw)`` and Python's
  ``rotDetector = (yaw, pitch, roll)`` (about x, y, z); the image centre at
  ``offOrigin``. This is TIGRE's ``computeDeltas_Siddon`` (CUDA) read with
  the Python wrapper's orders: ``nDetector = dDetector = (V, U)`` (rows,
  columns), ``offDetector = (V, U)``, ``nVoxel = dVoxel = sVoxel =
  offOrigin = (z, y, x)``, and Python projections ``[angle, v, u]`` whose
  row ``v`` runs along ``+ẑ`` of the detector. pdvc writes ``ψ = 0``,
  ``COR = 0`` and ``offOrigin`` = the volume offset for every view, so the
  TIGRE world frame is pdvc's volume frame. For a nominal circular scan
  this gives ``DSO = SOD``, ``DSD = SOD + ODD``, ``α = θ - 90°`` (TIGRE's
  source starts on +x, pdvc's on -y) and ``θ_tigre = ψ = 0``,
  ``rotDetector = 0``, ``offDetector = (det_offset_row · py, det_offset_col · px)``.
  :func:`tigre_to_geometry` is the exact inverse (it also reads ``COR``
  and per-view ``offOrigin``).
* **LEAP** modular beam -- ``sourcePositions = src``, ``moduleCenters = d``,
  ``rowVectors = v/|v|`` (direction of increasing row index),
  ``colVectors = u/|u|``, ``pixelHeight = |v|``, ``pixelWidth = |u|``;
  LEAP's modular beam puts pixel ``(i, j)`` at
  ``c + (i - (numRows-1)/2) pixelHeight rowVec + (j - (numCols-1)/2) pixelWidth colVec``
  (its ``convert_conebeam_to_modularbeam``). Volume as
  ``set_volume(numX, numY, numZ, voxelWidth, voxelHeight, offsetX, offsetY, offsetZ)``.
* **CIL** -- ``AcquisitionGeometry.create_Cone3D_Flex(source_position_set,
  detector_position_set, detector_direction_x_set, detector_direction_y_set)``
  with the unit vectors ``u/|u|`` and ``v/|v|``, then
  ``set_panel(num_pixels=[n_cols, n_rows], pixel_size=[|u|, |v|],
  origin="bottom-left")`` (CIL's ASTRA conversion negates a direction only
  for a "right" or "top" origin) and labels
  ``["projection", "vertical", "horizontal"]``; the volume as
  ``ImageGeometry(voxel_num_x=nx, ..., voxel_size_x=sx, ..., center_x=ox, ...)``.
  ``volume_centre_position`` is written as ``[0, 0, 0]`` so that CIL's frame
  is not re-centred; the volume offset is in the ImageGeometry's centre.
  This last point is inferred from CIL's tests, not from its documentation.

LEAP, CIL and TIGRE hold one detector pitch for all views and a
rectangular pixel grid: a geometry whose ``|u|``, ``|v|`` vary between
views or whose ``u`` and ``v`` are not perpendicular (relative tolerance
1e-6) cannot be exported to them (:class:`~pdvc.errors.GeometryError`).
Rigid poses (:meth:`VectorGeometry.apply_poses`) keep both properties.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import GeometryError
from ..geometry import VectorGeometry, VolumeGeometry
from ._atomic import atomic_write_text

__all__ = [
    "export_astra",
    "astra_volume_geometry",
    "export_tigre",
    "tigre_to_geometry",
    "export_leap",
    "export_cil",
    "write_exports",
]

log = logging.getLogger(__name__)

#: Relative tolerance on constant pitch and perpendicular u, v for TIGRE, LEAP and CIL.
PITCH_RTOL = 1e-6


def _check_geom(geom, vol_geom=None, *, need_vol=False) -> None:
    if not isinstance(geom, VectorGeometry):
        raise GeometryError(f"geom must be a VectorGeometry, got {type(geom).__name__}")
    if need_vol and vol_geom is None:
        raise GeometryError("vol_geom (a VolumeGeometry) is required for this export")
    if vol_geom is not None and not isinstance(vol_geom, VolumeGeometry):
        raise GeometryError(f"vol_geom must be a VolumeGeometry, got {type(vol_geom).__name__}")


def _detector_frame(geom: VectorGeometry, tool: str):
    """Constant pitch (du, dv) and unit column/row directions, checked for ``tool``."""
    if geom.kind != "cone":
        raise GeometryError(f"the {tool} export supports cone beam only; this geometry is {geom.kind!r} (use the ASTRA export)")
    nu = np.linalg.norm(geom.u, axis=1)
    nv = np.linalg.norm(geom.v, axis=1)
    du, dv = float(np.mean(nu)), float(np.mean(nv))
    if np.max(np.abs(nu - du)) > PITCH_RTOL * du or np.max(np.abs(nv - dv)) > PITCH_RTOL * dv:
        raise GeometryError(
            f"{tool} needs one detector pitch for all views; |u| ranges {nu.min():.9g}..{nu.max():.9g} and "
            f"|v| {nv.min():.9g}..{nv.max():.9g}"
        )
    uh, vh = geom.u / nu[:, None], geom.v / nv[:, None]
    cos = np.abs(np.einsum("ij,ij->i", uh, vh))
    if np.max(cos) > PITCH_RTOL:
        raise GeometryError(
            f"{tool} needs perpendicular detector axes; u and v make an angle off 90 deg by up to "
            f"{np.degrees(np.arcsin(min(1.0, float(np.max(cos))))):.3g} deg (view {int(np.argmax(cos))})"
        )
    return du, dv, uh, vh


# -- ASTRA -------------------------------------------------------------------
def export_astra(geom: VectorGeometry) -> dict:
    """ASTRA projection geometry: ``{"type", "DetectorRowCount", "DetectorColCount", "Vectors"}``.

    ``Vectors`` is an ``(n_views, 12)`` float64 array, pdvc's rows unchanged;
    ``type`` is ``"cone_vec"`` or ``"parallel3d_vec"``.
    """
    _check_geom(geom)
    return geom.to_astra()


def astra_volume_geometry(vol_geom: VolumeGeometry) -> dict:
    """ASTRA 3D volume geometry dict, as ``astra.create_vol_geom(ny, nx, nz, minx, maxx, miny, maxy, minz, maxz)``."""
    if not isinstance(vol_geom, VolumeGeometry):
        raise GeometryError(f"vol_geom must be a VolumeGeometry, got {type(vol_geom).__name__}")
    nz, ny, nx = vol_geom.shape
    lo = np.asarray(vol_geom.offset) - vol_geom.extent_xyz / 2
    hi = np.asarray(vol_geom.offset) + vol_geom.extent_xyz / 2
    return {
        "GridColCount": nx,
        "GridRowCount": ny,
        "GridSliceCount": nz,
        "option": {
            "WindowMinX": float(lo[0]), "WindowMaxX": float(hi[0]),
            "WindowMinY": float(lo[1]), "WindowMaxY": float(hi[1]),
            "WindowMinZ": float(lo[2]), "WindowMaxZ": float(hi[2]),
        },
    }


# -- TIGRE -------------------------------------------------------------------
def _rz(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    m = np.zeros(a.shape + (3, 3))
    m[..., 0, 0], m[..., 0, 1], m[..., 1, 0], m[..., 1, 1], m[..., 2, 2] = c, -s, s, c, 1.0
    return m


def _ry(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    m = np.zeros(a.shape + (3, 3))
    m[..., 0, 0], m[..., 0, 2], m[..., 2, 0], m[..., 2, 2], m[..., 1, 1] = c, s, -s, c, 1.0
    return m


def _rx(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    m = np.zeros(a.shape + (3, 3))
    m[..., 1, 1], m[..., 1, 2], m[..., 2, 1], m[..., 2, 2], m[..., 0, 0] = c, -s, s, c, 1.0
    return m


def export_tigre(geom: VectorGeometry, vol_geom: VolumeGeometry) -> dict:
    """TIGRE (Python) geometry with per-view parameters; exact for any cone-beam vectors.

    Parameters
    ----------
    geom : VectorGeometry, cone beam
    vol_geom : VolumeGeometry

    Returns
    -------
    dict
        ``mode`` ("cone"); per view: ``DSO``, ``DSD`` ``(n,)``, ``angles``
        ``(n, 3)`` = ZYZ Euler ``(α, θ, ψ)`` rad, ``offOrigin`` ``(n, 3)``
        ``(z, y, x)``, ``offDetector`` ``(n, 2)`` ``(V, U)``,
        ``rotDetector`` ``(n, 3)`` ``(yaw, pitch, roll)`` rad, ``COR``
        ``(n,)``; global: ``nDetector``, ``dDetector``, ``sDetector``
        ``(V, U)``, ``nVoxel``, ``dVoxel``, ``sVoxel`` ``(z, y, x)``. Arrays
        are float64 numpy arrays (module docstring gives the mapping).

    Raises
    ------
    GeometryError
        Parallel beam, pitch varying between views, non-perpendicular
        detector axes, or a source at the volume-frame origin.
    """
    _check_geom(geom, vol_geom, need_vol=True)
    du, dv, uh, vh = _detector_frame(geom, "TIGRE")
    n = geom.n_views
    S = geom.src
    dso = np.linalg.norm(S, axis=1)
    if np.any(dso <= 0):
        raise GeometryError("TIGRE needs the source away from the volume-frame origin (DSO > 0)")
    sh = S / dso[:, None]
    alpha = np.unwrap(np.arctan2(sh[:, 1], sh[:, 0]))
    alpha -= 2 * np.pi * np.round(alpha[0] / (2 * np.pi))
    theta = np.arcsin(np.clip(-sh[:, 2], -1.0, 1.0))
    psi = np.zeros(n)
    E = _rz(alpha) @ _ry(theta)  # (n, 3, 3); psi = 0
    Et = np.transpose(E, (0, 2, 1))
    L = np.einsum("nij,nj->ni", Et, geom.det_center)
    dsd = dso - L[:, 0]
    y = np.einsum("nij,nj->ni", Et, uh)
    z = np.einsum("nij,nj->ni", Et, vh)
    x = np.cross(y, z)
    R = np.stack([x, y, z], axis=2)  # columns
    roll = np.arctan2(R[:, 1, 0], R[:, 0, 0])
    pitch = np.arcsin(np.clip(-R[:, 2, 0], -1.0, 1.0))
    yaw = np.arctan2(R[:, 2, 1], R[:, 2, 2])
    nr, nc = geom.det_shape
    nz, ny, nx = vol_geom.shape
    dvox = np.array(vol_geom.voxel_size, np.float64)
    return {
        "mode": "cone",
        "DSO": dso,
        "DSD": dsd,
        "angles": np.stack([alpha, theta, psi], axis=1),
        "offOrigin": np.tile(np.asarray(vol_geom.offset, np.float64)[::-1], (n, 1)),
        "offDetector": np.stack([L[:, 2], L[:, 1]], axis=1),
        "rotDetector": np.stack([yaw, pitch, roll], axis=1),
        "COR": np.zeros(n),
        "nDetector": np.array([nr, nc]),
        "dDetector": np.array([dv, du]),
        "sDetector": np.array([nr * dv, nc * du]),
        "nVoxel": np.array([nz, ny, nx]),
        "dVoxel": dvox,
        "sVoxel": np.array([nz, ny, nx]) * dvox,
    }


def _per_view(value, n: int, width: int, name: str) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    try:
        if width == 0:
            return np.broadcast_to(a.reshape(-1) if a.ndim else a, (n,)).astype(np.float64)
        return np.broadcast_to(a, (n, width)).astype(np.float64)
    except ValueError:
        want = f"({n},)" if width == 0 else f"({width},) or ({n}, {width})"
        raise GeometryError(f"TIGRE {name} must have shape {want}, got {a.shape}") from None


def tigre_to_geometry(tigre: dict) -> tuple[VectorGeometry, VolumeGeometry]:
    """Inverse of :func:`export_tigre`: TIGRE (Python) geometry -> pdvc vectors and volume grid.

    Reads a dict with the keys of :func:`export_tigre` (lists or arrays;
    per-view or single values); ``angles`` may be ``(n,)`` (α only) or
    ``(n, 3)``; ``COR``, ``rotDetector``, ``offDetector``, ``offOrigin``
    default to zero. Per-view ``offOrigin`` is honoured: the returned
    volume sits at the first view's ``offOrigin`` and each view is shifted
    accordingly.

    Returns
    -------
    (VectorGeometry, VolumeGeometry)
    """
    try:
        ang = np.asarray(tigre["angles"], np.float64)
        nV, nU = (int(x) for x in np.asarray(tigre["nDetector"]).reshape(2))
        dV, dU = (float(x) for x in np.asarray(tigre["dDetector"], np.float64).reshape(2))
        dso_in, dsd_in = tigre["DSO"], tigre["DSD"]
        n_vox = tuple(int(x) for x in np.asarray(tigre["nVoxel"]).reshape(3))
        d_vox = tuple(float(x) for x in np.asarray(tigre["dVoxel"], np.float64).reshape(3))
    except (KeyError, TypeError, ValueError) as exc:
        raise GeometryError(
            "tigre must hold angles, nDetector, dDetector, DSO, DSD, nVoxel and dVoxel "
            f"(see export_tigre); {exc!r}"
        ) from None
    if tigre.get("mode", "cone") != "cone":
        raise GeometryError(f"only TIGRE cone-beam geometries are supported, got mode {tigre.get('mode')!r}")
    if ang.ndim == 1:
        ang = np.stack([ang, np.zeros_like(ang), np.zeros_like(ang)], axis=1)
    if ang.ndim != 2 or ang.shape[1] != 3:
        raise GeometryError(f"TIGRE angles must have shape (n,) or (n, 3), got {ang.shape}")
    n = ang.shape[0]
    dso = _per_view(dso_in, n, 0, "DSO")
    dsd = _per_view(dsd_in, n, 0, "DSD")
    off_det = _per_view(tigre.get("offDetector", (0.0, 0.0)), n, 2, "offDetector")
    rot = _per_view(tigre.get("rotDetector", (0.0, 0.0, 0.0)), n, 3, "rotDetector")
    cor = _per_view(tigre.get("COR", 0.0), n, 0, "COR")
    org = _per_view(tigre.get("offOrigin", (0.0, 0.0, 0.0)), n, 3, "offOrigin")[:, ::-1]  # -> (x, y, z)
    alpha, theta, psi = ang[:, 0], ang[:, 1], ang[:, 2]
    E = _rz(alpha) @ _ry(theta) @ _rz(psi)
    Rd = _rz(rot[:, 2]) @ _ry(rot[:, 1]) @ _rx(rot[:, 0])
    zeros = np.zeros(n)
    shift = np.stack([-cor * np.sin(alpha), cor * np.cos(alpha), zeros], axis=1) - org + org[0]
    src = np.einsum("nij,nj->ni", E, np.stack([dso, zeros, zeros], axis=1)) + shift
    det = np.einsum("nij,nj->ni", E, np.stack([-(dsd - dso), off_det[:, 1], off_det[:, 0]], axis=1)) + shift
    ER = E @ Rd
    u = dU * ER[:, :, 1]
    v = dV * ER[:, :, 2]
    geom = VectorGeometry(np.concatenate([src, det, u, v], axis=1), (nV, nU), "cone")
    return geom, VolumeGeometry(n_vox, d_vox, tuple(org[0]))


# -- LEAP --------------------------------------------------------------------
def export_leap(geom: VectorGeometry, vol_geom: Optional[VolumeGeometry] = None) -> dict:
    """LEAP modular-beam parameters (``set_modularbeam``) and, if given, the volume (``set_volume``).

    Returns
    -------
    dict
        ``geometry`` ("MODULAR"), ``numAngles``, ``numRows``, ``numCols``,
        ``pixelHeight`` (= ``|v|``), ``pixelWidth`` (= ``|u|``),
        ``sourcePositions``, ``moduleCenters``, ``rowVectors`` (``v/|v|``),
        ``colVectors`` (``u/|u|``) as ``(n_views, 3)`` float64 arrays, and
        ``volume``: a dict of ``set_volume`` arguments, or None.
    """
    _check_geom(geom, vol_geom)
    du, dv, uh, vh = _detector_frame(geom, "LEAP")
    nr, nc = geom.det_shape
    out = {
        "geometry": "MODULAR",
        "numAngles": geom.n_views,
        "numRows": nr,
        "numCols": nc,
        "pixelHeight": dv,
        "pixelWidth": du,
        "sourcePositions": np.array(geom.src),
        "moduleCenters": np.array(geom.det_center),
        "rowVectors": vh,
        "colVectors": uh,
        "volume": None,
    }
    if vol_geom is not None:
        nz, ny, nx = vol_geom.shape
        sz, sy, sx = vol_geom.voxel_size
        ox, oy, oz = vol_geom.offset
        vol = {"numX": nx, "numY": ny, "numZ": nz, "voxelWidth": sx, "voxelHeight": sz,
               "offsetX": ox, "offsetY": oy, "offsetZ": oz}
        if abs(sx - sy) > PITCH_RTOL * sx:
            vol["note"] = f"LEAP uses one voxelWidth for x and y; this grid has sx = {sx!r}, sy = {sy!r}"
        out["volume"] = vol
    return out


# -- CIL ---------------------------------------------------------------------
def export_cil(geom: VectorGeometry, vol_geom: VolumeGeometry) -> dict:
    """Arguments of CIL's ``create_Cone3D_Flex``, ``set_panel``, ``set_labels`` and ``ImageGeometry``.

    Returns
    -------
    dict
        ``source_position_set``, ``detector_position_set``,
        ``detector_direction_x_set`` (``u/|u|``), ``detector_direction_y_set``
        (``v/|v|``) as ``(n_views, 3)`` arrays, ``volume_centre_position``,
        ``panel`` (``num_pixels = [n_cols, n_rows]``, ``pixel_size = [|u|, |v|]``,
        ``origin = "bottom-left"``), ``labels`` and ``image_geometry``.
    """
    _check_geom(geom, vol_geom, need_vol=True)
    du, dv, uh, vh = _detector_frame(geom, "CIL")
    nr, nc = geom.det_shape
    nz, ny, nx = vol_geom.shape
    sz, sy, sx = vol_geom.voxel_size
    ox, oy, oz = vol_geom.offset
    return {
        "source_position_set": np.array(geom.src),
        "detector_position_set": np.array(geom.det_center),
        "detector_direction_x_set": uh,
        "detector_direction_y_set": vh,
        "volume_centre_position": [0.0, 0.0, 0.0],
        "panel": {"num_pixels": [nc, nr], "pixel_size": [du, dv], "origin": "bottom-left"},
        "labels": ["projection", "vertical", "horizontal"],
        "image_geometry": {
            "voxel_num_x": nx, "voxel_num_y": ny, "voxel_num_z": nz,
            "voxel_size_x": sx, "voxel_size_y": sy, "voxel_size_z": sz,
            "center_x": ox, "center_y": oy, "center_z": oz,
        },
    }


# -- files -------------------------------------------------------------------
_CONVENTIONS = {
    "astra": (
        "ASTRA Toolbox. proj_geom: astra.create_proj_geom(type, DetectorRowCount, DetectorColCount, "
        "np.array(Vectors)) -- rows (src or ray, d, u, v) as pdvc's, pixel (i, j) at d + (j-(nc-1)/2) u + "
        "(i-(nr-1)/2) v; data [view, row, col] (pass np.swapaxes(p, 0, 1) to ASTRA's [row, view, col]). "
        "vol_geom: astra.create_vol_geom(GridRowCount=ny, GridColCount=nx, GridSliceCount=nz, WindowMinX, "
        "WindowMaxX, WindowMinY, WindowMaxY, WindowMinZ, WindowMaxZ); volume [z, y, x]. Lengths in mm."
    ),
    "tigre": (
        "TIGRE (Python), cone beam. geo = tigre.geometry(); set geo.<key> = np.array(value) for DSO, DSD, "
        "offOrigin, offDetector, rotDetector, COR, nDetector, dDetector, sDetector, nVoxel, dVoxel, sVoxel "
        "(per-view arrays of length n_views, first axis); pass np.array(angles) (n_views, 3) = ZYZ Euler "
        "(alpha, theta, psi), rad, to tigre.Ax / algorithms. Orders: nDetector, dDetector, offDetector = (V, U) = "
        "(rows, cols); nVoxel, dVoxel, offOrigin = (z, y, x); rotDetector = (yaw, pitch, roll) = rotations about "
        "x, y, z. World frame = pdvc's volume frame: source E(DSO,0,0), detector centre "
        "E(-(DSD-DSO), offU, offV), E = Rz(alpha) Ry(theta) Rz(psi); nominal circular scan: alpha = theta_pdvc - 90 deg. "
        "Projections [angle, v, u] as pdvc's [view, row, col]; volume [z, y, x]. Lengths in mm. Exact for "
        "TIGRE's projectors Ax/Atb; FDK assumes a circular orbit."
    ),
    "leap": (
        "LEAP (LivermorE AI Projector), modular beam: leapct.set_modularbeam(numAngles, numRows, numCols, "
        "pixelHeight, pixelWidth, sourcePositions, moduleCenters, rowVectors, colVectors) with float32 C-contiguous "
        "(numAngles, 3) arrays; rowVectors = direction of increasing row index (v/|v|), colVectors = increasing "
        "column (u/|u|); pixel (i, j) at moduleCenter + (i-(numRows-1)/2) pixelHeight rowVec + "
        "(j-(numCols-1)/2) pixelWidth colVec. volume: leapct.set_volume(numX, numY, numZ, voxelWidth, "
        "voxelHeight, offsetX, offsetY, offsetZ). Projections [angle, row, col], volume [z, y, x]. Lengths in mm."
    ),
    "cil": (
        "CIL (Core Imaging Library): ag = AcquisitionGeometry.create_Cone3D_Flex(source_position_set, "
        "detector_position_set, detector_direction_x_set, detector_direction_y_set, volume_centre_position)"
        ".set_panel(**panel).set_labels(labels); ig = ImageGeometry(**image_geometry). direction_x = u/|u| "
        "(increasing column), direction_y = v/|v| (increasing row), origin 'bottom-left' so that neither is "
        "negated. Data [projection, vertical, horizontal] = pdvc's [view, row, col]; volume [z, y, x] "
        "(vertical, horizontal_y, horizontal_x). volume_centre_position [0,0,0] keeps pdvc's frame; the "
        "volume offset is in image_geometry center_x/y/z (inferred from CIL's tests). Lengths in mm."
    ),
}


def _jsonable(obj):
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def _dump(payload: dict) -> str:
    return json.dumps(_jsonable(payload), indent=1, allow_nan=False) + "\n"


def write_exports(out_dir, geom: VectorGeometry, vol_geom: VolumeGeometry) -> dict[str, Path]:
    """Write ``geometry_astra.json``, ``geometry_tigre.json``, ``geometry_leap.json``, ``geometry_cil.json``.

    Each file is one JSON object with a ``"convention"`` text (how to use it)
    and the toolkit's parameters (:func:`export_astra` and
    :func:`astra_volume_geometry`, :func:`export_tigre`, :func:`export_leap`,
    :func:`export_cil`), written atomically. Floats are written exactly
    (shortest round-trip form). A toolkit that cannot represent the
    geometry is skipped: parallel beam for TIGRE, LEAP modular and CIL Flex
    with one INFO log line, a varying pitch with a logged warning.

    Parameters
    ----------
    out_dir : str or Path
        Existing folder.
    geom : VectorGeometry
    vol_geom : VolumeGeometry

    Returns
    -------
    dict
        ``{"astra" | "tigre" | "leap" | "cil": Path}`` of the files written.
    """
    _check_geom(geom, vol_geom, need_vol=True)
    out = Path(out_dir)
    if not out.is_dir():
        raise GeometryError(f"out_dir {str(out)!r} is not an existing folder")
    builders = {
        "astra": lambda: {"proj_geom": export_astra(geom), "vol_geom": astra_volume_geometry(vol_geom)},
        "tigre": lambda: export_tigre(geom, vol_geom),
        "leap": lambda: export_leap(geom, vol_geom),
        "cil": lambda: export_cil(geom, vol_geom),
    }
    if geom.kind != "cone":
        # expected for every parallel-beam run: one INFO line, not a warning per toolkit
        cone_only = ("tigre", "leap", "cil")
        log.info(
            "%s beam: %s not written (those exports support cone beam only); geometry_astra.json holds the geometry",
            geom.kind,
            ", ".join(f"geometry_{name}.json" for name in cone_only),
        )
        builders = {name: build for name, build in builders.items() if name not in cone_only}
    written: dict[str, Path] = {}
    for name, build in builders.items():
        try:
            payload = build()
        except GeometryError as exc:
            log.warning("geometry_%s.json not written: %s", name, exc)
            continue
        path = out / f"geometry_{name}.json"
        atomic_write_text(path, _dump({"convention": _CONVENTIONS[name], **payload}))
        written[name] = path
    return written
