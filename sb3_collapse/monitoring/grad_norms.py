"""Gradient norms of the named layers, recorded at each update by the model's recorder (docs/interventions.md)."""

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
    Record the gradient norms of the model's named layers at each update (SB3's TD3, DDPG, SAC: ``collapse_model``).

    :param model: a DrQv2, TD3, DDPG or SAC model
    :return: the recorder, ``None`` for a model whose layers cannot be named (e.g. PPO)
    """
    return grad_norm_recorder(collapse_model(model))


def grad_norms_of(model: BaseAlgorithm) -> dict[str, float]:
    """
    :param model: a DrQv2, TD3, DDPG or SAC model
    :return: layer name -> L2 gradient norm at the last update; empty before one and for an untracked model
    """
    recorder = grad_norm_recorder(model)
    return {} if recorder is None else recorder.last()
