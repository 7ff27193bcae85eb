"""DrQ-v2's update written with the reference implementation's operations, as an oracle and a baseline.

Not used for training. :meth:`DrQv2._update` computes the same update faster: it is tested equal to
:func:`reference_update` (same weights, same batch, same random draws), and ``benchmarks/update_speed.py``
times both.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch as th
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.utils import polyak_update
from torch.nn import functional as F

from sb3_collapse.drqv2.augmentation import random_shift_grid_sample
from sb3_collapse.drqv2.policies import sample_action

if TYPE_CHECKING:
    from sb3_collapse.drqv2.drqv2 import DrQv2


def reference_update(model: DrQv2, data: ReplayBufferSamples) -> None:
    """
    One DrQ-v2 update of ``model`` on ``data`` as facebookresearch/drqv2 computes it: ``grid_sample``
    augmentation on float images, a full backward of the actor loss (the critic's gradients are computed
    and discarded), the optimizers as configured. Draws random numbers in the same order as ``DrQv2._update``.

    :param model: a pixel ``DrQv2`` model
    :param data: a batch from its replay buffer
    """
    std, pad = model.current_stddev, model.augmentation_pad
    encoder, actor, critic = model.encoder, model.actor, model.critic
    obs = random_shift_grid_sample(data.observations.float(), pad)
    next_obs = random_shift_grid_sample(data.next_observations.float(), pad)
    features = encoder(obs)
    with th.no_grad():
        next_features = encoder(next_obs)
        next_action = sample_action(actor(next_features), std, clip=model.stddev_clip)
        next_v = th.min(*model.critic_target(next_features, next_action))
        target_q = data.rewards + (1.0 - data.dones) * data.discounts * next_v
    q1, q2 = critic(features, data.actions)
    critic_loss = F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q)
    encoder.optimizer.zero_grad(set_to_none=True)
    critic.optimizer.zero_grad(set_to_none=True)
    critic_loss.backward()
    critic.optimizer.step()
    encoder.optimizer.step()
    features = features.detach()
    action = sample_action(actor(features), std, clip=model.stddev_clip)
    actor_loss = -th.min(*critic(features, action)).mean()
    actor.optimizer.zero_grad(set_to_none=True)
    actor_loss.backward()
    actor.optimizer.step()
    polyak_update(critic.parameters(), model.critic_target.parameters(), model.tau)
