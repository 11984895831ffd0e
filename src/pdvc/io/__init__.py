"""Reading and writing: atomic outputs (more formats come with the pipeline)."""

from ._atomic import atomic_write_npy, prepare_output_dir

__all__ = ["atomic_write_npy", "prepare_output_dir"]
