"""Every figure and table of the paper, drawn from what it is given (the pipelines that read the folders and write
the files: :mod:`sb3_collapse.commands`); each module's part: docs/layout.md."""

from sb3_collapse.report.headline import escape_probability
from sb3_collapse.report.loading import Sweep, Trial, load_sweep
from sb3_collapse.report.pipeline import Report
from sb3_collapse.report.reference import load_reference_curves, reference_task_name
from sb3_collapse.report.statistics import ReportSettings, stuck_in_collapse

__all__ = [
    "Report",
    "ReportSettings",
    "Sweep",
    "Trial",
    "escape_probability",
    "load_reference_curves",
    "load_sweep",
    "reference_task_name",
    "stuck_in_collapse",
]
