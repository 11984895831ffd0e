"""Reading and writing: projections (TIFF, HDF5 Data Exchange, NeXus NXtomo,
.npy), flat/dark normalisation, vendor geometry files, the configuration,
geometry exports, and atomic outputs."""

from ._atomic import (
    OutputExistsError,
    atomic_path,
    atomic_write_bytes,
    atomic_write_npy,
    atomic_write_text,
    prepare_output_dir,
)
from ._config import (
    AngleRange,
    CalibrationConfig,
    Config,
    ConfigError,
    DataConfig,
    GeometryConfig,
    OutputConfig,
    ComputeConfig,
    PreprocessConfig,
    VolumeConfig,
    build_geometry,
    build_volume_geometry,
    check_coverage,
    load_config,
    resolve_angles,
    write_config,
)
from ._export import astra_volume_geometry, export_astra, export_cil, export_leap, export_tigre, tigre_to_geometry, write_exports
from ._fingerprint import run_fingerprint
from ._preprocess import (
    AirEstimate,
    PreprocessReport,
    bad_pixel_mask,
    beam_hardening,
    detector_roi,
    estimate_air,
    fill_bad_pixels,
    flats_from_columns,
    normalize,
    subtract_air,
)
from ._projections import DataError, FormatError, InputFileError, RawScan, classify_values, read_projections
from ._vendor import VendorGeometry, read_nikon, read_skyscan, read_vendor_geometry
from ._rings import RING_WIDTH, RingReport, remove_rings, ring_pattern
from ._zingers import ZingerReport, remove_zingers

__all__ = [
    "Config", "ConfigError", "DataConfig", "GeometryConfig", "AngleRange", "VolumeConfig",
    "PreprocessConfig", "CalibrationConfig", "OutputConfig", "ComputeConfig", "load_config", "write_config",
    "build_geometry", "build_volume_geometry", "resolve_angles", "check_coverage",
    "VendorGeometry", "read_nikon", "read_skyscan", "read_vendor_geometry",
    "export_astra", "astra_volume_geometry", "export_tigre", "tigre_to_geometry", "export_leap", "export_cil", "write_exports",
    "RawScan",
    "read_projections",
    "classify_values",
    "DataError",
    "InputFileError",
    "FormatError",
    "PreprocessReport",
    "normalize",
    "flats_from_columns",
    "beam_hardening",
    "detector_roi",
    "bad_pixel_mask",
    "fill_bad_pixels",
    "AirEstimate",
    "estimate_air",
    "subtract_air",
    "OutputExistsError",
    "atomic_path",
    "atomic_write_bytes",
    "atomic_write_npy",
    "atomic_write_text",
    "prepare_output_dir",
    "run_fingerprint", "ZingerReport", "remove_zingers", "RingReport", "remove_rings", "ring_pattern", "RING_WIDTH",
]
