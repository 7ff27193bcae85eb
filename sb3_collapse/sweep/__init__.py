"""Multi-seed sweeps on Ray: every (task, variant, seed) trains as an independent trial into its own folder."""

from sb3_collapse.sweep.cluster import CONNECT_TIMEOUT_S, import_ray, ray_session
from sb3_collapse.sweep.donors import DONOR_KEYS, Donor, donor_candidates, pick_donors
from sb3_collapse.sweep.runner import (
    SweepSummary,
    check_sweep_arguments,
    prepare_sweep_folder,
    run_sweep,
    run_trial,
    settings_changes,
    sweep_settings,
)
from sb3_collapse.sweep.trials import (
    GRID_VARIANTS,
    PLAIN_VARIANTS,
    TRANSPLANT_SOURCES,
    Trial,
    canonical_task,
    donor_key,
    expand_trials,
    parse_checkpoint_specs,
    transplant_of,
    trial_config,
    trial_dir,
    variant_settings,
)

__all__ = [
    "CONNECT_TIMEOUT_S",
    "DONOR_KEYS",
    "GRID_VARIANTS",
    "PLAIN_VARIANTS",
    "TRANSPLANT_SOURCES",
    "Donor",
    "SweepSummary",
    "Trial",
    "canonical_task",
    "check_sweep_arguments",
    "donor_candidates",
    "donor_key",
    "expand_trials",
    "import_ray",
    "parse_checkpoint_specs",
    "pick_donors",
    "prepare_sweep_folder",
    "ray_session",
    "run_sweep",
    "run_trial",
    "settings_changes",
    "sweep_settings",
    "transplant_of",
    "trial_config",
    "trial_dir",
    "variant_settings",
]
