"""Collapse monitoring: named activations of an actor, collapse metrics, and the callbacks built on them."""

from sb3_collapse.monitoring.activations import (
    LayerMappingError,
    LayerTap,
    collect_activations,
    layer_parameters,
    layer_taps,
)

__all__ = ["LayerMappingError", "LayerTap", "collect_activations", "layer_parameters", "layer_taps"]
