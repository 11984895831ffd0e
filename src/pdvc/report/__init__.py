"""Calibration report: figures, the HTML page, ``motion.csv`` and ``result.h5``.

Everything here takes plain NumPy arrays (no engine objects), so a report can
be rebuilt from saved results.  Parameter order is ``(tx, ty, tz, rx, ry, rz)``;
translations in volume units, rotations in radians on input, degrees in
figures and tables.  Figures use matplotlib's object API on an Agg canvas (no
pyplot state, no display); every file is written atomically.

* :mod:`~pdvc.report._figures`: one function per figure of the paper (SNR per
  view, temporal and spatial modes, poses, residual maps, axis trajectory,
  slices) and :func:`snr_modes_table` (Table 1);
* :mod:`~pdvc.report._html`: :func:`write_report`, PNG files and ``report.html``;
* :mod:`~pdvc.report._tables`: ``motion.csv`` and ``result.h5`` writers/readers.

Examples
--------
>>> import numpy as np, tempfile
>>> from pdvc.report import snr_per_view_figure, write_report
>>> ang = np.linspace(0, 360, 90, endpoint=False)
>>> fig = snr_per_view_figure(ang, 20 + np.sin(np.radians(ang)), 26 + 0 * ang)
>>> html = write_report(tempfile.mkdtemp(), title="demo", summary={"chi": 1.02},
...                     figures={"snr_per_view": fig})
>>> html.name
'report.html'
"""

from ._figures import (
    PARAM_NAMES,
    axis_trajectory_figure,
    pose_figure,
    residual_maps_figure,
    slices_figure,
    snr_modes_table,
    snr_per_view_figure,
    spatial_modes_figure,
    temporal_modes_figure,
)
from ._html import REPORT_DPI, ReportError, write_report
from ._tables import MOTION_COLUMNS, read_motion_csv, read_result_h5, write_motion_csv, write_result_h5

__all__ = [
    "PARAM_NAMES",
    "MOTION_COLUMNS",
    "REPORT_DPI",
    "ReportError",
    "snr_per_view_figure",
    "temporal_modes_figure",
    "spatial_modes_figure",
    "pose_figure",
    "residual_maps_figure",
    "axis_trajectory_figure",
    "slices_figure",
    "snr_modes_table",
    "write_report",
    "write_motion_csv",
    "read_motion_csv",
    "write_result_h5",
    "read_result_h5",
]
