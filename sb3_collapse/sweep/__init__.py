"""Multi-seed sweeps on Ray: every (task, variant, seed) trains as an independent trial into its own folder."""

from sb3_collapse.run.variants import GRID_VARIANTS, transplant_of, variant_settings
from sb3_collapse.sweep.cluster import ray_session
from sb3_collapse.sweep.donors import donor_candidates, pick_donors
from sb3_collapse.sweep.runner import SweepSummary, run_sweep, run_trial, settings_changes
from sb3_collapse.sweep.trials import Trial, expand_trials, parse_checkpoint_specs, trial_config, trial_dir

__all__ = [
    "GRID_VARIANTS", "SweepSummary", "Trial", "donor_candidates", "expand_trials", "parse_checkpoint_specs",
    "pick_donors", "ray_session", "run_sweep", "run_trial", "settings_changes", "transplant_of", "trial_config",
    "trial_dir", "variant_settings",
]  # fmt: skip
