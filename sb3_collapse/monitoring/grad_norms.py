"""
Gradient norms of the named layers at each update, without an extra backward pass, for DrQv2 and SB3's TD3, DDPG
and SAC: one :class:`~sb3_collapse.common.grad_norms.GradNormRecorder` per model, recorded when the optimizer that
trains a layer steps. Which optimizer records which layer:
docs/interventions.md#the-health-value-gradient-norms-recorded-at-each-update.
"""

from __future__ import annotations

from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_collapse.baselines import collapse_model
from sb3_collapse.common.grad_norms import GradNormRecorder
from sb3_collapse.common.model import CollapseModel


def grad_norm_recorder(model: BaseAlgorithm) -> GradNormRecorder | None:
    """
    :param model: an SB3 algorithm
    :return: its recorder (``model.grad_norm_recorder``), ``None`` for a model without one
    """
    return model.grad_norm_recorder if isinstance(model, CollapseModel) else None


def track_grad_norms(model: BaseAlgorithm) -> GradNormRecorder | None:
    """
    Make sure that the gradient norms of the model's named layers are recorded at each update.

    A DrQv2 and the wrappers of :mod:`sb3_collapse.baselines` record them themselves; a model of SB3's own TD3,
    DDPG or SAC class becomes a wrapper (:func:`~sb3_collapse.baselines.collapse_model`), its recorder hooked on
    the actor's and the critic's optimizers, built again when a reset from scratch replaces them.

    :param model: a DrQv2, TD3, DDPG or SAC model
    :return: the recorder, ``None`` for a model whose layers cannot be named (e.g. PPO)
    """
    return grad_norm_recorder(collapse_model(model))


def grad_norms_of(model: BaseAlgorithm) -> dict[str, float]:
    """
    L2 gradient norm of each named layer at the model's last update, without any backward pass (see the module
    docstring: recorded by the model's :class:`GradNormRecorder`).

    :param model: a DrQv2, TD3, DDPG or SAC model
    :return: layer name -> norm; empty before the first update (or the first update after a reset), and for an
        SB3 model whose norms are not tracked (:func:`track_grad_norms`: ``CollapseMetrics`` and
        ``CollapseReset`` call it when they start)
    """
    recorder = grad_norm_recorder(model)
    return {} if recorder is None else recorder.last()
