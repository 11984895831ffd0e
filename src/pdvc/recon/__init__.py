"""Analytic reconstruction over per-view vector geometry.

* :func:`fdk`: Feldkamp-Davis-Kress for (near-)circular cone beam, full or
  short scan (Parker), irregular angles;
* :func:`fbp`: filtered back-projection for parallel beam;
* :func:`ramp_filter_response`: the windowed ramp filters they use
  (:data:`FILTERS` lists the names);
* :func:`spline_upsample`: a volume on a finer grid of the same box
  (:func:`refined_grid`), by cubic B-spline interpolation.

Both accept a corrected geometry (each view's source and detector moved
and tilted) directly: the back-projection uses every view's exact
projection matrix.
"""

from ._fbp import analytic, fbp, fdk
from ._filters import FILTERS, ramp_filter_response
from ._iterative import cgls, nonneg_ls, nonneg_ls_lipschitz
from ._upsample import refined_grid, spline_upsample

__all__ = ["fdk", "fbp", "analytic", "cgls", "nonneg_ls", "nonneg_ls_lipschitz", "refined_grid", "spline_upsample", "ramp_filter_response", "FILTERS"]
