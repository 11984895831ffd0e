"""Vendor geometry files: Nikon .xtekct (+ _ctdata.txt / .ang) and SkyScan .log.

The sample files use the vendors' key layout with invented numbers (small
detectors, few views, so the tests are fast).
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from pdvc.errors import GeometryError
from pdvc.io._config import build_geometry, load_config
from pdvc.io._vendor import VendorGeometry, read_nikon, read_skyscan, read_vendor_geometry

NIKON = """\
[XTekCT]
Name=gear_scan
InputSeparator=_
InputFolderName=
OutputFolderName=
VoxelsX=40
VoxelsY=40
VoxelsZ=32
VoxelSizeX=0.0125
VoxelSizeY=0.0125
VoxelSizeZ=0.0125
OffsetX=0
OffsetY=0
OffsetZ=0
SrcToObject=50.0
SrcToDetector=800.0
MaskRadius=0.25
DetectorPixelsX=40
DetectorPixelsY=32
DetectorPixelSizeX=0.2
DetectorPixelSizeY=0.25
DetectorOffsetX=0
DetectorOffsetY=0
{cor}
WhiteLevel=60000
Scattering=0
CoefX4=0
CoefX3=0
CoefX2=0
CoefX1=1
CoefX0=0
Scale=1
RegionStartX=0
RegionPixelsX=40
RegionStartY=0
RegionPixelsY=32
Projections=12
InitialAngle=5
AngularStep=30
FilterType=0
CutOffFrequency=2
Exponent=1
Normalisation=1
InterpolationType=1
Scaling=1000
XraykV=160
XrayuA=62
Filter_ThicknessMM=0.5
Filter_Material=Copper
Shuttling=False
{extra}
"""

CENTRED = "CentreOfRotationTop=0\nCentreOfRotationBottom=0"


def _nikon(tmp_path, cor=CENTRED, extra="ObjectOffsetX=0\nObjectRoll=0\nObjectTilt=0", name="gear_scan.xtekct"):
    p = tmp_path / name
    p.write_text(NIKON.format(cor=cor, extra=extra), encoding="utf-8")
    return p


def _ctdata(tmp_path, angles, name="_ctdata.txt"):
    lines = ["Projs\tFrames\tExposure(ms)", f"{len(angles)}\t1\t500", "Projection\tAngle(deg)\tTime(s)"]
    lines += [f"{k + 1}\t{a:.4f}\t{0.5 * k:.3f}" for k, a in enumerate(angles)]
    (tmp_path / name).write_text("\n".join(lines) + "\n")


def _rz(t):
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


# -- Nikon -------------------------------------------------------------------
def test_nikon_values_and_nominal_angles(tmp_path):
    vg = read_nikon(_nikon(tmp_path))
    assert vg.vendor == "nikon" and vg.kind == "cone"
    assert (vg.sod, vg.odd, vg.sdd) == (50.0, 750.0, 800.0)
    assert vg.magnification == pytest.approx(16.0)
    assert vg.pixel == (0.25, 0.2) and vg.det_shape == (32, 40)
    assert vg.det_offset == (0.0, 0.0) and vg.axis_offset == 0.0 and vg.axis_roll == 0.0
    assert vg.angles_source == "nominal" and vg.n_views == 12
    # theta = alpha + 180 deg (CIL's convention), alpha = InitialAngle + k * AngularStep
    np.testing.assert_allclose(vg.angles, np.deg2rad(5 + 30 * np.arange(12)) + np.pi)
    assert vg.voxel_size == (0.0125, 0.0125, 0.0125) and vg.volume_shape == (32, 40, 40)
    assert vg.raw["XTekCT/Filter_Material"] == "Copper"
    assert vg.volume_geometry().shape == (32, 40, 40)


def test_nikon_vectors_first_view_and_detector_orientation(tmp_path):
    vg = read_nikon(_nikon(tmp_path))
    g = vg.to_vector_geometry()
    assert g.det_shape == (32, 40) and g.n_views == 12 and g.kind == "cone"
    th = math.radians(5) + math.pi
    e = np.array([math.cos(th), math.sin(th), 0.0])
    # DESIGN §1 nominal formulas at theta
    np.testing.assert_allclose(g.src[0], [50 * math.sin(th), -50 * math.cos(th), 0], atol=1e-12)
    np.testing.assert_allclose(g.det_center[0], [-750 * math.sin(th), 750 * math.cos(th), 0], atol=1e-12)
    # Nikon columns run against e (right-to-left seen from the source), rows downwards
    np.testing.assert_allclose(g.u[0], -0.2 * e, atol=1e-15)
    np.testing.assert_allclose(g.v[0], [0, 0, -0.25], atol=1e-15)
    # magnification SDD/SOD: a point on the axis at height z lands (16 z / 0.25) rows above the centre
    rc = g.project_points(np.array([[0.0, 0.0, 0.1]]))[0, 0]
    np.testing.assert_allclose(rc, [(32 - 1) / 2 - 16 * 0.1 / 0.25, (40 - 1) / 2], atol=1e-9)


def test_nikon_object_offset_moves_the_axis_on_the_detector(tmp_path):
    vg = read_nikon(_nikon(tmp_path, extra="ObjectOffsetX=0.05\nObjectRoll=0\nObjectTilt=0"))
    assert vg.axis_offset == pytest.approx(-0.05)
    g = vg.to_vector_geometry()
    # CIL puts the axis at x = -ObjectOffsetX (left seen from the source); Nikon columns grow
    # leftwards, so the axis lands M * 0.05 / px columns right of the centre, in every view.
    cols = g.project_points(np.zeros((1, 3)))[:, 0, 1]
    np.testing.assert_allclose(cols, (40 - 1) / 2 + 16 * 0.05 / 0.2, atol=1e-9)


def test_nikon_centre_of_rotation_gives_offset_and_roll(tmp_path):
    top, bottom = 0.3, 0.1  # mm on the detector
    p = _nikon(tmp_path, cor=f"CentreOfRotationTop={top}\nCentreOfRotationBottom={bottom}", extra="ObjectTilt=0")
    vg = read_nikon(p)
    assert vg.axis_offset == pytest.approx(-(top + bottom) / 2 * 50 / 800)
    assert vg.axis_roll == pytest.approx(-math.atan2(top - bottom, 32 * 0.25))
    g = vg.to_vector_geometry()
    # The axis' projection is a straight line; at the top edge of the detector (row -0.5) it
    # is CentreOfRotationTop / px columns off centre, at the bottom edge (row 31.5) Bottom / px.
    pts = np.array([[0.0, 0.0, -0.2], [0.0, 0.0, 0.2]])
    for k in (0, 5):
        (r0, c0), (r1, c1) = g.project_points(pts)[k]
        col_at = lambda r: c0 + (c1 - c0) * (r - r0) / (r1 - r0)  # noqa: E731
        assert col_at(-0.5) == pytest.approx(19.5 + top / 0.2, abs=1e-9)
        assert col_at(31.5) == pytest.approx(19.5 + bottom / 0.2, abs=1e-9)
    # without offsets the file describes the ideal centred scan
    g0 = read_nikon(p, offsets=False).to_vector_geometry()
    np.testing.assert_allclose(g0.project_points(pts)[:, :, 1], 19.5, atol=1e-9)


def test_nikon_ctdata_angles(tmp_path):
    meas = 30 * np.arange(12) + np.array([0.01, -0.02, 0.0, 0.03, 0, 0, 0.01, 0, 0, -0.01, 0, 0.02])
    _ctdata(tmp_path, meas)
    vg = read_nikon(_nikon(tmp_path))
    assert vg.angles_source == "ctdata"
    np.testing.assert_allclose(vg.angles, np.deg2rad(np.round(meas, 4)) + np.pi, atol=1e-12)
    nominal = read_nikon(_nikon(tmp_path), angles="nominal")
    assert nominal.angles_source == "nominal"
    np.testing.assert_allclose(nominal.angles, np.deg2rad(5 + 30 * np.arange(12)) + np.pi)


def test_nikon_ctdata_with_wrong_count_falls_back_to_nominal(tmp_path, caplog):
    _ctdata(tmp_path, 30 * np.arange(10))
    with caplog.at_level(logging.WARNING):
        vg = read_nikon(_nikon(tmp_path))
    assert vg.angles_source == "nominal" and vg.n_views == 12
    assert "lists 10 angles" in caplog.text


def test_nikon_ang_file_is_read_in_reverse_order(tmp_path):
    rows = ["Proj\tAngle(deg)"] + [f"{p}\t{100 + p:.3f}" for p in range(12, 0, -1)]
    (tmp_path / "gear_scan.ang").write_text("\n".join(rows) + "\n")
    vg = read_nikon(_nikon(tmp_path))
    assert vg.angles_source == "ang"
    # projection label p (1..N) belongs to image N - p
    expected = np.empty(12)
    for p in range(1, 13):
        expected[12 - p] = 100 + p
    np.testing.assert_allclose(vg.angles, np.deg2rad(expected) + np.pi)


def test_nikon_missing_key_and_degenerate_distances(tmp_path):
    p = tmp_path / "bad.xtekct"
    p.write_text(NIKON.format(cor=CENTRED, extra="").replace("SrcToDetector=800.0\n", ""))
    with pytest.raises(GeometryError, match="SrcToDetector is missing"):
        read_nikon(p)
    p.write_text(NIKON.format(cor=CENTRED, extra="").replace("SrcToDetector=800.0", "SrcToDetector=40"))
    with pytest.raises(GeometryError, match="must exceed SrcToObject"):
        read_nikon(p)
    p.write_text(NIKON.format(cor=CENTRED, extra="").replace("DetectorPixelSizeX=0.2", "DetectorPixelSizeX=0"))
    with pytest.raises(GeometryError, match="DetectorPixelSizeX must be positive"):
        read_nikon(p)
    with pytest.raises(GeometryError, match="does not exist"):
        read_nikon(tmp_path / "none.xtekct")


# -- SkyScan -----------------------------------------------------------------
SKYSCAN = """\
[System]
Scanner=SkyScan1272
Instrument S/N=17H09999
Software Version=1.1.19
Home Directory=C:\\SkyScan1272
Source Type=Hamamatsu L11871_20
Camera Type=XIMEA xiRAY16
Camera Pixel Size (um)=    9.00
Camera X/Y Ratio=1.0000
[User]
User Name=operator
[Acquisition]
Data Directory=D:\\Results\\rock_core
Filename Prefix=rock_core_
Number Of Files=   13
Number Of Rows=   30
Number Of Columns=   36
Partial Width=OFF
Image crop origin X=0
Image crop origin Y=0
Camera binning=4x4
Image Rotation=0.01200
Optical Axis (line)=  12
Camera to Source (mm)=280.00000
Object to Source (mm)=70.00000
Source Voltage (kV)=  80
Source Current (uA)= 125
Image Pixel Size (um)=9.000000
Scaled Image Pixel Size (um)=9.000000
Image Format=TIFF
Depth (bits)=16
Exposure (ms)=1350
Rotation Step (deg)=15.000
Use 360 Rotation=NO
Frame Averaging=ON (2)
Random Movement=ON (30)
Flat Field Correction=ON
Filter=Al 1mm
Rotation Direction={direction}
Type of Detector Motion=STEP AND SHOOT
Scanning Trajectory=ROUND
Number of connected scans=1
Study Date and Time=23 Sep 2020  14h:52m:29s
[Reconstruction]
Reconstruction Program=NRecon
Program Version=Version: 1.7.3.1
Postalignment={post}
Result Image Width (pixels)=36
Result Image Height (pixels)=36
Sections Count=30
Pixel Size (um)=9.00000
Reconstruction Angular Range (deg)=180.00
Angular Step (deg)=15.0000
CS Static Rotation (deg)=0.00
"""


def _skyscan(tmp_path, direction="CC", post="-1.50", name="rock_core_.log", drop=()):
    text = SKYSCAN.format(direction=direction, post=post)
    for key in drop:
        text = "\n".join(line for line in text.splitlines() if not line.startswith(key)) + "\n"
    p = tmp_path / name
    p.write_text(text, encoding="latin-1")
    return p


def test_skyscan_values(tmp_path):
    vg = read_skyscan(_skyscan(tmp_path))
    assert vg.vendor == "skyscan" and vg.kind == "cone"
    assert (vg.sod, vg.odd) == (70.0, 210.0)
    # detector pitch = image (object-plane) pixel x magnification 280/70
    assert vg.pixel == pytest.approx((0.036, 0.036), rel=1e-12)
    assert vg.det_shape == (30, 36)
    # Optical Axis 12 (from the top): centre row 14.5 -> offset 2.5 rows; Postalignment -1.5 px
    assert vg.det_offset == pytest.approx((14.5 - 12, -1.5))
    np.testing.assert_allclose(vg.angles, np.deg2rad(15 * np.arange(13)))
    assert vg.voxel_size == pytest.approx((0.009,) * 3) and vg.volume_shape == (30, 36, 36)
    assert vg.raw["System/Camera Type"] == "XIMEA xiRAY16"


def test_skyscan_vectors_known_answers(tmp_path):
    g = read_skyscan(_skyscan(tmp_path)).to_vector_geometry()
    assert g.det_shape == (30, 36) and g.n_views == 13
    np.testing.assert_allclose(g.src[0], [0, -70, 0], atol=1e-12)  # theta = 0: DESIGN §1
    np.testing.assert_allclose(g.u[0], [0.036, 0, 0], atol=1e-15)  # columns along e, rows down
    np.testing.assert_allclose(g.v[0], [0, 0, -0.036], atol=1e-15)
    th = math.radians(15)
    np.testing.assert_allclose(g.src[1], [70 * math.sin(th), -70 * math.cos(th), 0], atol=1e-12)
    # the central ray hits row "Optical Axis"; the axis lands Postalignment columns off centre
    for k in range(13):
        rc = g.project_points(np.zeros((1, 3)))[k, 0]
        np.testing.assert_allclose(rc, [12.0, 17.5 + 1.5], atol=1e-9)
    foot = g.src[0] + (g.det_center[0] - g.src[0]) @ g.det_normal[0] * g.det_normal[0]
    np.testing.assert_allclose(g.project_points(foot[None] * 0.5 + g.src[0] * 0.5)[0, 0, 0], 12.0, atol=1e-9)


def test_skyscan_clockwise_and_no_offsets(tmp_path):
    vg = read_skyscan(_skyscan(tmp_path, direction="CW"), offsets=False)
    np.testing.assert_allclose(vg.angles, -np.deg2rad(15 * np.arange(13)))
    assert vg.det_offset == (0.0, 0.0)
    with pytest.raises(GeometryError, match="Rotation Direction must be CC or CW"):
        read_skyscan(_skyscan(tmp_path, direction="UP"))


def test_skyscan_without_camera_distance(tmp_path):
    # derived from Camera Pixel Size x binning / Image Pixel Size: 9 um x 4 / 9 um -> SDD = 4 SOD
    vg = read_skyscan(_skyscan(tmp_path, drop=("Camera to Source",)))
    assert vg.sdd == pytest.approx(280.0)
    # an optical scanner: huge source distance and no camera distance -> parallel beam
    p = _skyscan(tmp_path, drop=("Camera to Source", "Camera Pixel Size"))
    p.write_text(p.read_text().replace("Object to Source (mm)=70.00000", "Object to Source (mm)=100000"))
    par = read_skyscan(p)
    assert par.kind == "parallel" and par.pixel == pytest.approx((0.009, 0.009))
    g = par.to_vector_geometry()
    assert g.kind == "parallel"
    np.testing.assert_allclose(g.ray[0], [0, -1, 0], atol=1e-15)
    q = _skyscan(tmp_path, drop=("Camera to Source", "Camera Pixel Size"), name="b.log")
    with pytest.raises(GeometryError, match="Camera to Source"):
        read_skyscan(q)


def test_skyscan_missing_rows_key(tmp_path):
    with pytest.raises(GeometryError, match="Number Of Rows is missing"):
        read_skyscan(_skyscan(tmp_path, drop=("Number Of Rows",)))


# -- dispatch and configuration ---------------------------------------------
def test_read_vendor_geometry_dispatches_on_extension(tmp_path):
    assert read_vendor_geometry(_nikon(tmp_path)).vendor == "nikon"
    assert read_vendor_geometry(_skyscan(tmp_path)).vendor == "skyscan"
    other = tmp_path / "scan.txt"
    other.write_text("x=1\n")
    with pytest.raises(GeometryError, match="from its extension"):
        read_vendor_geometry(other)
    renamed = tmp_path / "rock_core.cfg"
    renamed.write_text(_skyscan(tmp_path).read_text(encoding="latin-1"), encoding="latin-1")
    assert isinstance(read_vendor_geometry(renamed, vendor="skyscan"), VendorGeometry)
    with pytest.raises(GeometryError, match="vendor must be"):
        read_vendor_geometry(renamed, vendor="bruker")


def test_vendor_geometry_through_the_config(tmp_path):
    _nikon(tmp_path)
    cfg = load_config({"data": {"path": "p"}, "geometry": {"type": "nikon", "file": "gear_scan.xtekct"}},
                      base_dir=tmp_path)
    g = build_geometry(cfg, n_views=12, det_shape=(32, 40))
    assert g == read_nikon(tmp_path / "gear_scan.xtekct").to_vector_geometry()
    with pytest.raises(GeometryError, match="binned|bin or crop"):
        build_geometry(cfg, det_shape=(16, 20))
    with pytest.raises(GeometryError, match="gives 12 angles .* 13 projections"):
        build_geometry(cfg, n_views=13)
    _skyscan(tmp_path)
    cfg = load_config({"data": {"path": "p"}, "geometry": {"type": "skyscan", "file": "rock_core_.log",
                                                           "vendor_offsets": False}}, base_dir=tmp_path)
    assert build_geometry(cfg) == read_skyscan(tmp_path / "rock_core_.log", offsets=False).to_vector_geometry()
