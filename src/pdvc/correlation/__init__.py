"""The P-DVC engine: per-view rigid motion of the sample from its projections.

:func:`correlate` measures it, regularised in space (6 rigid modes) and time
(temporal bases, or PGD modes one at a time).
"""

from ._bases import BASIS_NAMES, TemporalBasis, drift_basis, is_basis_name, bspline_basis, custom_basis, dirac_basis, fourier_basis, make_basis, polynomial_basis
from ._assess import Assessment, assess
from ._engine import CorrelationError, CorrelationResult, Mode, Observability, correlate, residual_scale
from ._frames import lab_frames, lab_to_sample_map, view_angles
from ._metrics import shannon_entropy, snr_db
from ._noise import estimate_noise_variance, poisson_variance
from ._roi import cone_artifact_rows, detector_weights
from ._scales import coarse_grain, coarse_noise_factor, coarse_volume, coarse_weights, scale_schedule

__all__ = [
    "correlate",
    "residual_scale",
    "assess",
    "Assessment",
    "CorrelationResult",
    "CorrelationError",
    "Mode",
    "Observability",
    "TemporalBasis",
    "BASIS_NAMES",
    "is_basis_name",
    "drift_basis",
    "make_basis",
    "dirac_basis",
    "polynomial_basis",
    "fourier_basis",
    "bspline_basis",
    "custom_basis",
    "lab_frames",
    "lab_to_sample_map",
    "view_angles",
    "estimate_noise_variance",
    "poisson_variance",
    "snr_db",
    "shannon_entropy",
    "cone_artifact_rows",
    "detector_weights",
    "coarse_grain",
    "coarse_noise_factor",
    "coarse_volume",
    "coarse_weights",
    "scale_schedule",
]
