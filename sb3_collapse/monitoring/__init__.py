"""Collapse monitoring: named activations of an actor, collapse metrics, and the callbacks built on them."""

from sb3_collapse.monitoring.activations import (
    LayerMappingError,
    LayerTap,
    collect_activations,
    layer_parameters,
    layer_taps,
)
from sb3_collapse.monitoring.callbacks import (
    ActivationLogger,
    CollapseMetrics,
    FrameScheduleCallback,
    ProbeBatchSampler,
    action_repeat_of,
    frames_of,
    grad_norms_of,
)
from sb3_collapse.monitoring.metrics import (
    action_spread,
    dead_fraction,
    dormant_ratio,
    effective_rank,
    gradient_norm,
    layer_metrics,
    mean_pairwise_correlation,
    numerical_rank,
    saturated_fraction,
    singular_values,
    zero_fraction,
)
from sb3_collapse.monitoring.reset import CollapseReset

__all__ = [
    "ActivationLogger",
    "CollapseMetrics",
    "CollapseReset",
    "FrameScheduleCallback",
    "LayerMappingError",
    "LayerTap",
    "ProbeBatchSampler",
    "action_repeat_of",
    "action_spread",
    "collect_activations",
    "dead_fraction",
    "dormant_ratio",
    "effective_rank",
    "frames_of",
    "grad_norms_of",
    "gradient_norm",
    "layer_metrics",
    "layer_parameters",
    "layer_taps",
    "mean_pairwise_correlation",
    "numerical_rank",
    "saturated_fraction",
    "singular_values",
    "zero_fraction",
]
