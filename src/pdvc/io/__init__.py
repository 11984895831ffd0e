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
from ._preprocess import PreprocessReport, beam_hardening, detector_roi, flats_from_columns, normalize
from ._projections import DataError, FormatError, InputFileError, RawScan, read_projections

__all__ = [
    "RawScan",
    "read_projections",
    "DataError",
    "InputFileError",
    "FormatError",
    "PreprocessReport",
    "normalize",
    "flats_from_columns",
    "beam_hardening",
    "detector_roi",
    "OutputExistsError",
    "atomic_path",
    "atomic_write_bytes",
    "atomic_write_npy",
    "atomic_write_text",
    "prepare_output_dir",
]
