"""The P-DVC engine (rigid motion per view from projections). Metrics for now."""

from ._metrics import shannon_entropy, snr_db

__all__ = ["snr_db", "shannon_entropy"]
