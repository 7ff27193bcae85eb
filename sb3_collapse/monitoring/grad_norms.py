"""
Gradient norms of the named layers at each update, without an extra backward pass, for every algorithm: one
:class:`~sb3_collapse.common.grad_norms.GradNormRecorder` per model.

- ``DrQv2`` builds its recorder with its networks (``model.grad_norm_recorder``, read as
  ``model.last_grad_norms``): ``cnn1``..``cnn4`` are recorded when the encoder's optimizer steps (critic loss),
  ``mlp0``..``action`` when the actor's optimizer steps (actor loss).
- SB3's ``TD3``, ``DDPG`` and ``SAC`` get theirs from :func:`track_grad_norms` (the callbacks call it when they
  start): every named layer of :func:`~sb3_collapse.monitoring.activations.layer_parameters` (the actor's
  features extractor and hidden layers) is recorded when the actor's optimizer steps (actor loss; every
  ``policy_delay`` updates for TD3 and DDPG).
"""

from __future__ import annotations

import weakref

import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_collapse.common.grad_norms import GradNormRecorder
from sb3_collapse.monitoring.activations import LayerMappingError, layer_parameters

_RECORDERS: weakref.WeakKeyDictionary[BaseAlgorithm, GradNormRecorder] = weakref.WeakKeyDictionary()


def _sb3_optimizers(model: BaseAlgorithm) -> list[th.optim.Optimizer | None]:
    policy = model.policy
    return [getattr(getattr(policy, part, None), "optimizer", None) for part in ("actor", "critic")]


def grad_norm_recorder(model: BaseAlgorithm) -> GradNormRecorder | None:
    """
    The recorder of a model: its own (``model.grad_norm_recorder``, DrQv2), or the one :func:`track_grad_norms`
    attached to its current optimizers.

    :param model: an SB3 algorithm
    :return: the recorder, ``None`` when there is none for the model's current optimizers
    """
    own = getattr(model, "grad_norm_recorder", None)
    if isinstance(own, GradNormRecorder):
        return own
    recorder = _RECORDERS.get(model)
    if recorder is None or not recorder.watches(_sb3_optimizers(model)):
        return None
    return recorder


def track_grad_norms(model: BaseAlgorithm) -> GradNormRecorder | None:
    """
    Make sure that the gradient norms of the model's named layers are recorded at each update.

    A DrQv2 records them itself. For SB3's TD3, DDPG and SAC, a :class:`GradNormRecorder` is hooked on the
    actor's and the critic's optimizers, once: calling again returns the same recorder, or a new one when the
    optimizers were replaced (e.g. by a reset from scratch), the old hooks removed.

    :param model: a DrQv2, TD3, DDPG or SAC model
    :return: the recorder, ``None`` for a model whose layers cannot be named (e.g. PPO)
    """
    recorder = grad_norm_recorder(model)
    if recorder is not None:
        return recorder
    try:
        layers = layer_parameters(model)
    except LayerMappingError:
        return None
    stale = _RECORDERS.pop(model, None)
    if stale is not None:
        stale.remove()
    recorder = GradNormRecorder(layers, _sb3_optimizers(model))
    _RECORDERS[model] = recorder
    return recorder


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
