"""
Reports of a sweep folder: the paper's Figure 5, the per-variant table and the layer-transplant grid
(Figure 3(a)). ``python -m sb3_collapse.report --help`` for the command line; the library:

- :mod:`~sb3_collapse.report.loading`: read ``<sweep>/<task>/<variant>/seed_<k>/`` folders (:func:`load_sweep`);
- :mod:`~sb3_collapse.report.statistics`: aligned curves, percentile bands, "stuck in action collapse", the table
  and the grid;
- :mod:`~sb3_collapse.report.reference`: the published DrQ-v2 curves shipped with the package;
- :mod:`~sb3_collapse.report.tables` and :mod:`~sb3_collapse.report.plots`: CSV, Markdown and PNG outputs;
- :mod:`~sb3_collapse.report.collapse_figure` and :mod:`~sb3_collapse.report.fixed_inputs`: Figures 4, 8, 9 (the
  three agents, their metrics on the fixed probing set and online);
- :mod:`~sb3_collapse.report.pipeline`: :func:`build_report` and :func:`write_report`.
"""

from sb3_collapse.errors import ReportError
from sb3_collapse.report.fixed_inputs import FixedInputSettings
from sb3_collapse.report.loading import Sweep, Trial, load_sweep
from sb3_collapse.report.pipeline import Report, build_report, write_report
from sb3_collapse.report.reference import ReferenceCurves, load_reference_curves, reference_task_name
from sb3_collapse.report.statistics import (
    BandCurve,
    GridCell,
    ReportSettings,
    VariantSummary,
    aligned_returns,
    last_evals_std_mean,
    percentile_band,
    stuck_in_collapse,
    summarize,
    transplant_grid,
)

__all__ = [
    "BandCurve",
    "FixedInputSettings",
    "GridCell",
    "ReferenceCurves",
    "Report",
    "ReportError",
    "ReportSettings",
    "Sweep",
    "Trial",
    "VariantSummary",
    "aligned_returns",
    "build_report",
    "last_evals_std_mean",
    "load_reference_curves",
    "load_sweep",
    "percentile_band",
    "reference_task_name",
    "stuck_in_collapse",
    "summarize",
    "transplant_grid",
    "write_report",
]
