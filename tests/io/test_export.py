"""Geometry exports for ASTRA, TIGRE, LEAP and CIL: known answers and round trips."""

from __future__ import annotations

import json
import logging
import math

import numpy as np
import pytest

from pdvc.errors import GeometryError
from pdvc.geometry import VectorGeometry, VolumeGeometry, circular_cone, parallel, rotvec_to_matrix
from pdvc.io._export import (
    astra_volume_geometry,
    export_astra,
    export_cil,
    export_leap,
    export_tigre,
    tigre_to_geometry,
    write_exports,
)

SOD, ODD = 120.0, 380.0
DET = (12, 16)
PIX = (0.3, 0.2)  # (row, col)
OFF = (1.5, -2.0)  # (row, col) pixels
VOL = VolumeGeometry((10, 11, 12), (0.05, 0.04, 0.03), offset=(0.2, -0.1, 0.3))


def _nominal(n=10):
    th = np.linspace(0, 2 * np.pi, n, endpoint=False) + 0.3
    return th, circular_cone(th, sod=SOD, odd=ODD, det_shape=DET, pixel=PIX, det_offset=OFF)


def _perturbed(seed=1):
    """Not circular: per-view rigid poses, a global move, and per-view detector rotations about d."""
    rng = np.random.default_rng(seed)
    _, g = _nominal()
    n = g.n_views
    g = g.apply_poses(rng.normal(scale=0.05, size=(n, 3)), rng.normal(scale=2.0, size=(n, 3)))
    g = g.transformed([0.05, -0.1, 0.2], [1.0, -2.0, 3.0])
    R = rotvec_to_matrix(rng.normal(scale=0.1, size=(n, 3)))
    vec = np.array(g.vectors)
    vec[:, 6:9] = np.einsum("nij,nj->ni", R, vec[:, 6:9])
    vec[:, 9:12] = np.einsum("nij,nj->ni", R, vec[:, 9:12])
    return VectorGeometry(vec, g.det_shape, "cone")


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


# -- a literal transcription of TIGRE's computeDeltas_Siddon (CUDA), as reference --------------
def _roll_pitch_yaw(roll, pitch, yaw, p):
    x, y, z = p
    return [
        math.cos(roll) * math.cos(pitch) * x
        + (math.cos(roll) * math.sin(pitch) * math.sin(yaw) - math.sin(roll) * math.cos(yaw)) * y
        + (math.cos(roll) * math.sin(pitch) * math.cos(yaw) + math.sin(roll) * math.sin(yaw)) * z,
        math.sin(roll) * math.cos(pitch) * x
        + (math.sin(roll) * math.sin(pitch) * math.sin(yaw) + math.cos(roll) * math.cos(yaw)) * y
        + (math.sin(roll) * math.sin(pitch) * math.cos(yaw) - math.cos(roll) * math.sin(yaw)) * z,
        -math.sin(pitch) * x + math.cos(pitch) * math.sin(yaw) * y + math.cos(pitch) * math.cos(yaw) * z,
    ]


def _euler_zyz(a, t, s, p):
    x, y, z = p
    ca, sa, ct, st, cs, ss = math.cos(a), math.sin(a), math.cos(t), math.sin(t), math.cos(s), math.sin(s)
    return [
        (ca * ct * cs - sa * ss) * x + (-ca * ct * ss - sa * cs) * y + ca * st * z,
        (sa * ct * cs + ca * ss) * x + (-sa * ct * ss + ca * cs) * y + sa * st * z,
        -st * cs * x + st * ss * y + ct * z,
    ]


def _tigre_reference(t, k, rows, cols):
    """Source and pixel centres (Python projections [angle, v, u]) in TIGRE's voxel-index space.

    Voxel ``(ix, iy, iz)`` of TIGRE's image occupies ``[ix, ix+1)`` etc. after the transforms.
    """
    nV, nU = (int(x) for x in t["nDetector"])
    dV, dU = (float(x) for x in t["dDetector"])
    dso, dsd = float(t["DSO"][k]), float(t["DSD"][k])
    alpha, theta, psi = (float(x) for x in t["angles"][k])
    offV, offU = (float(x) for x in t["offDetector"][k])
    rot = t["rotDetector"][k]
    yaw, pitch, roll = float(rot[0]), float(rot[1]), float(rot[2])  # Python rotDetector[0,1,2] -> dYaw, dPitch, dRoll
    offZ, offY, offX = (float(x) for x in t["offOrigin"][k])
    sZ, sY, sX = (float(x) for x in t["sVoxel"])
    dZ, dY, dX = (float(x) for x in t["dVoxel"])
    cor = float(t["COR"][k])

    def finish(p, detector):
        if detector:
            p = [0.0, p[1], p[2]]
            p = _roll_pitch_yaw(roll, pitch, yaw, p)
            p = [p[0] - (dsd - dso), p[1] + offU, p[2] + offV]
        p = _euler_zyz(alpha, theta, psi, p)
        p = [p[0] - offX, p[1] - offY, p[2] - offZ]
        p = [p[0] + sX / 2, p[1] + sY / 2, p[2] + sZ / 2]
        p = [p[0] / dX, p[1] / dY, p[2] / dZ]
        return np.array([p[0] - cor * math.sin(alpha) / dX, p[1] + cor * math.cos(alpha) / dY, p[2]])

    S = finish([dso, 0.0, 0.0], False)
    P = finish([-(dsd - dso), dU * (0 - nU / 2 + 0.5), dV * (nV / 2 - 0.5 - 0)], True)
    Pu0 = finish([-(dsd - dso), dU * (1 - nU / 2 + 0.5), dV * (nV / 2 - 0.5 - 0)], True)
    Pv0 = finish([-(dsd - dso), dU * (0 - nU / 2 + 0.5), dV * (nV / 2 - 0.5 - 1)], True)
    pix = []
    for v, u in zip(rows, cols):
        pixel_v = nV - v - 1  # the kernel's row flip
        pix.append(P + u * (Pu0 - P) + pixel_v * (Pv0 - P))
    return S, np.array(pix)


def _pdvc_in_tigre_index_space(vol, points):
    """pdvc world points -> TIGRE voxel-index coordinates (x, y, z), voxel centres at i + 0.5."""
    idx = vol.world_to_index(points)  # (iz, iy, ix), centres at integers
    return idx[..., ::-1] + 0.5


# -- ASTRA -------------------------------------------------------------------
def test_astra_export_is_the_vectors():
    _, g = _nominal()
    a = export_astra(g)
    assert a["type"] == "cone_vec" and a["DetectorRowCount"] == 12 and a["DetectorColCount"] == 16
    np.testing.assert_array_equal(a["Vectors"], g.vectors)
    assert VectorGeometry.from_astra(a) == g
    p = export_astra(parallel([0.0, 1.0], det_shape=(3, 4), pixel=1.0))
    assert p["type"] == "parallel3d_vec"


def test_astra_volume_windows():
    v = astra_volume_geometry(VOL)
    assert (v["GridSliceCount"], v["GridRowCount"], v["GridColCount"]) == (10, 11, 12)
    o = v["option"]
    assert o["WindowMinX"] == pytest.approx(0.2 - 12 * 0.03 / 2) and o["WindowMaxX"] == pytest.approx(0.2 + 0.18)
    assert o["WindowMinY"] == pytest.approx(-0.1 - 11 * 0.04 / 2)
    assert o["WindowMaxZ"] == pytest.approx(0.3 + 10 * 0.05 / 2)


# -- TIGRE -------------------------------------------------------------------
def test_tigre_nominal_known_answers():
    th, g = _nominal()
    t = export_tigre(g, VOL)
    np.testing.assert_allclose(t["DSO"], SOD, rtol=1e-13)
    np.testing.assert_allclose(t["DSD"], SOD + ODD, rtol=1e-13)
    # TIGRE's source starts on +x, pdvc's on -y: alpha = theta - 90 deg, theta_tigre = psi = 0
    np.testing.assert_allclose(_wrap(t["angles"][:, 0] - (th - np.pi / 2)), 0, atol=1e-12)
    np.testing.assert_allclose(t["angles"][:, 1:], 0, atol=1e-12)
    assert np.all(np.diff(t["angles"][:, 0]) > 0)  # unwrapped, same sense as the scan
    np.testing.assert_allclose(t["rotDetector"], 0, atol=1e-12)
    np.testing.assert_allclose(t["offDetector"], np.tile([OFF[0] * PIX[0], OFF[1] * PIX[1]], (10, 1)), atol=1e-12)
    np.testing.assert_array_equal(t["nDetector"], [12, 16])
    np.testing.assert_allclose(t["dDetector"], [0.3, 0.2])
    np.testing.assert_array_equal(t["nVoxel"], [10, 11, 12])
    np.testing.assert_allclose(t["dVoxel"], [0.05, 0.04, 0.03])
    np.testing.assert_allclose(t["sVoxel"], [0.5, 0.44, 0.36])
    np.testing.assert_allclose(t["offOrigin"], np.tile([0.3, -0.1, 0.2], (10, 1)))
    np.testing.assert_array_equal(t["COR"], 0)


@pytest.mark.parametrize("which", ["nominal", "perturbed"])
def test_tigre_export_matches_a_transcription_of_tigres_kernel(which):
    g = _nominal()[1] if which == "nominal" else _perturbed()
    t = export_tigre(g, VOL)
    rows, cols = [0, 0, 11, 5, 11], [0, 15, 0, 7, 15]
    for k in range(g.n_views):
        S, pix = _tigre_reference(t, k, rows, cols)
        np.testing.assert_allclose(S, _pdvc_in_tigre_index_space(VOL, g.src[k]), rtol=1e-11, atol=1e-8)
        ours = np.array([g.pixel_centers(k, rows=[r], cols=[c])[0, 0] for r, c in zip(rows, cols)])
        np.testing.assert_allclose(pix, _pdvc_in_tigre_index_space(VOL, ours), rtol=1e-11, atol=1e-8)


def test_tigre_round_trip_of_a_non_circular_geometry_with_rotated_detectors():
    g = _perturbed()
    t = export_tigre(g, VOL)
    assert np.max(np.abs(t["rotDetector"])) > 0.05  # detector rotations are really exercised
    assert np.max(np.abs(t["angles"][:, 1])) > 1e-3  # and the out-of-plane Euler angle
    g2, vol2 = tigre_to_geometry(t)
    assert g2.det_shape == g.det_shape
    np.testing.assert_allclose(g2.vectors, g.vectors, rtol=0, atol=1e-9)
    assert vol2.shape == VOL.shape
    np.testing.assert_allclose(vol2.voxel_size, VOL.voxel_size, rtol=1e-15)
    np.testing.assert_allclose(vol2.offset, VOL.offset, rtol=1e-15)
    # lists (as read back from JSON) work too
    g3, _ = tigre_to_geometry({k: np.asarray(v).tolist() if not isinstance(v, str) else v for k, v in t.items()})
    np.testing.assert_allclose(g3.vectors, g.vectors, rtol=0, atol=1e-9)


def test_tigre_inverse_reads_cor_per_view_origin_and_psi_like_tigre():
    rng = np.random.default_rng(3)
    n = 5
    t = {
        "mode": "cone",
        "DSO": 100.0 + rng.normal(size=n),
        "DSD": 500.0 + rng.normal(size=n),
        "angles": np.stack([np.linspace(0, 3, n), rng.normal(scale=0.05, size=n), rng.normal(scale=0.05, size=n)], 1),
        "offDetector": rng.normal(size=(n, 2)),
        "rotDetector": rng.normal(scale=0.05, size=(n, 3)),
        "COR": rng.normal(scale=0.5, size=n),
        "offOrigin": rng.normal(scale=0.2, size=(n, 3)),
        "nDetector": [6, 7],
        "dDetector": [0.4, 0.3],
        "nVoxel": [8, 9, 10],
        "dVoxel": [0.1, 0.1, 0.1],
        "sVoxel": [0.8, 0.9, 1.0],
    }
    g, vol = tigre_to_geometry(t)
    assert g.det_shape == (6, 7) and vol.shape == (8, 9, 10)
    rows, cols = [0, 5, 2], [0, 6, 3]
    for k in range(n):
        S, pix = _tigre_reference(t, k, rows, cols)
        np.testing.assert_allclose(S, _pdvc_in_tigre_index_space(vol, g.src[k]), rtol=1e-11, atol=1e-9)
        ours = np.array([g.pixel_centers(k, rows=[r], cols=[c])[0, 0] for r, c in zip(rows, cols)])
        np.testing.assert_allclose(pix, _pdvc_in_tigre_index_space(vol, ours), rtol=1e-11, atol=1e-9)


def test_tigre_cor_moves_the_axis_projection():
    th, g = _nominal()
    t = export_tigre(g, VOL)
    t["COR"] = np.full(g.n_views, 0.25)
    g2, _ = tigre_to_geometry(t)
    # source and detector shifted by COR along u: the axis lands M * COR / px columns lower
    m = (SOD + ODD) / SOD
    cols = g2.project_points(np.zeros((1, 3)))[:, 0, 1]
    cols0 = g.project_points(np.zeros((1, 3)))[:, 0, 1]
    np.testing.assert_allclose(cols - cols0, -m * 0.25 / PIX[1], atol=1e-9)


def test_tigre_refuses_what_it_cannot_represent():
    with pytest.raises(GeometryError, match="cone beam only"):
        export_tigre(parallel([0.0, 1.0], det_shape=(3, 4), pixel=1.0), VOL)
    _, g = _nominal()
    vec = np.array(g.vectors)
    vec[3, 6:9] *= 1.01
    with pytest.raises(GeometryError, match="one detector pitch"):
        export_tigre(VectorGeometry(vec, g.det_shape), VOL)
    vec = np.array(g.vectors)
    v = vec[2, 9:12] + 0.01 * np.linalg.norm(vec[2, 9:12]) * vec[2, 6:9] / np.linalg.norm(vec[2, 6:9])
    vec[2, 9:12] = v * np.linalg.norm(vec[2, 9:12]) / np.linalg.norm(v)  # same pitch, sheared
    with pytest.raises(GeometryError, match="perpendicular"):
        export_tigre(VectorGeometry(vec, g.det_shape), VOL)
    with pytest.raises(GeometryError, match="vol_geom"):
        export_tigre(g, None)


# -- LEAP --------------------------------------------------------------------
def test_leap_vectors_reproduce_pixel_centres():
    g = _perturbed(seed=4)
    lp = export_leap(g, VOL)
    assert lp["geometry"] == "MODULAR" and lp["numAngles"] == 10
    assert (lp["numRows"], lp["numCols"]) == (12, 16)
    assert lp["pixelHeight"] == pytest.approx(0.3) and lp["pixelWidth"] == pytest.approx(0.2)
    nr, nc = 12, 16
    i = np.arange(nr)[:, None, None]
    j = np.arange(nc)[None, :, None]
    for k in (0, 4, 9):
        leap = (
            lp["moduleCenters"][k]
            + (i - (nr - 1) / 2) * lp["pixelHeight"] * lp["rowVectors"][k]
            + (j - (nc - 1) / 2) * lp["pixelWidth"] * lp["colVectors"][k]
        )
        np.testing.assert_allclose(leap, g.pixel_centers(k), rtol=0, atol=1e-10)
        np.testing.assert_allclose(lp["sourcePositions"][k], g.src[k])
    np.testing.assert_allclose(np.linalg.norm(lp["rowVectors"], axis=1), 1.0)
    assert lp["volume"] == {"numX": 12, "numY": 11, "numZ": 10, "voxelWidth": 0.03, "voxelHeight": 0.05,
                            "offsetX": 0.2, "offsetY": -0.1, "offsetZ": 0.3,
                            "note": lp["volume"]["note"]}  # sx != sy here: flagged
    assert export_leap(g)["volume"] is None
    with pytest.raises(GeometryError, match="cone beam only"):
        export_leap(parallel([0.0], det_shape=(2, 2), pixel=1.0))


# -- CIL ---------------------------------------------------------------------
def test_cil_export_rebuilds_the_vectors():
    g = _perturbed(seed=5)
    c = export_cil(g, VOL)
    panel = c["panel"]
    assert panel["num_pixels"] == [16, 12] and panel["origin"] == "bottom-left"
    du, dv = panel["pixel_size"]
    # origin bottom-left: CIL's ASTRA conversion uses +pixel_size * direction for both axes
    vec = np.concatenate(
        [c["source_position_set"], c["detector_position_set"],
         du * np.asarray(c["detector_direction_x_set"]), dv * np.asarray(c["detector_direction_y_set"])], axis=1)
    np.testing.assert_allclose(vec, g.vectors, rtol=0, atol=1e-10)
    assert c["labels"] == ["projection", "vertical", "horizontal"]
    ig = c["image_geometry"]
    assert (ig["voxel_num_x"], ig["voxel_num_y"], ig["voxel_num_z"]) == (12, 11, 10)
    assert (ig["voxel_size_x"], ig["voxel_size_z"]) == (0.03, 0.05)
    assert (ig["center_x"], ig["center_y"], ig["center_z"]) == (0.2, -0.1, 0.3)


# -- files -------------------------------------------------------------------
def test_write_exports_writes_four_json_files(tmp_path):
    g = _perturbed(seed=6)
    out = write_exports(tmp_path, g, VOL)
    assert sorted(out) == ["astra", "cil", "leap", "tigre"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "geometry_astra.json", "geometry_cil.json", "geometry_leap.json", "geometry_tigre.json"]
    docs = {k: json.loads(p.read_text()) for k, p in out.items()}
    for name, doc in docs.items():
        assert isinstance(doc["convention"], str) and len(doc["convention"]) > 100
    # exact floats: the ASTRA rows come back bit for bit
    astra = docs["astra"]
    np.testing.assert_array_equal(np.array(astra["proj_geom"]["Vectors"]), g.vectors)
    assert VectorGeometry.from_astra(astra["proj_geom"]) == g
    assert astra["vol_geom"]["GridColCount"] == 12
    g2, vol2 = tigre_to_geometry(docs["tigre"])
    np.testing.assert_allclose(g2.vectors, g.vectors, rtol=0, atol=1e-9)
    assert vol2 == VOL


def test_write_exports_parallel_writes_astra_only(tmp_path, caplog):
    g = parallel(np.linspace(0, np.pi, 4, endpoint=False), det_shape=(4, 5), pixel=0.1)
    caplog.set_level(logging.INFO, logger="pdvc.io._export")
    out = write_exports(tmp_path, g, VolumeGeometry((4, 5, 5), 0.1))
    assert list(out) == ["astra"]
    assert [p.name for p in tmp_path.iterdir()] == ["geometry_astra.json"]
    # expected for parallel beam: one INFO line, no warning
    records = [r for r in caplog.records if r.name == "pdvc.io._export"]
    assert [r.levelno for r in records] == [logging.INFO]
    assert "geometry_tigre.json" in records[0].getMessage() and "cone beam only" in records[0].getMessage()
    with pytest.raises(GeometryError, match="not an existing folder"):
        write_exports(tmp_path / "missing", g, VolumeGeometry((4, 5, 5), 0.1))
