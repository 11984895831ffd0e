"""Reading and writing: atomic outputs (more formats come with the pipeline)."""

from ._atomic import (
    OutputExistsError,
    atomic_path,
    atomic_write_bytes,
    atomic_write_npy,
    atomic_write_text,
    prepare_output_dir,
)

__all__ = [
    "OutputExistsError",
    "atomic_path",
    "atomic_write_bytes",
    "atomic_write_npy",
    "atomic_write_text",
    "prepare_output_dir",
]
