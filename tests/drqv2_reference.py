"""DrQ-v2's augmentation and update with the reference implementation's operations: a test oracle and a baseline.

``sb3_collapse.drqv2.augmentation.random_shift`` is tested equal to :func:`random_shift_grid_sample`, and
``DrQv2._update`` to :func:`reference_update` (same weights, same batch, same random draws);
``benchmarks/update_speed.py`` times both updates. Imported as ``tests.drqv2_reference`` from the repository root.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch as th
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.utils import polyak_update
from torch.nn import functional as F

from sb3_collapse.drqv2.policies import sample_action

if TYPE_CHECKING:
    from sb3_collapse.drqv2.drqv2 import DrQv2


def random_shift_grid_sample(obs: th.Tensor, pad: int = 4, shifts: th.Tensor | None = None) -> th.Tensor:
    """
    The augmentation of ``sb3_collapse.drqv2.augmentation.random_shift``, as DrQ-v2's reference computes it:
    replicate padding, then bilinear ``grid_sample`` on a grid of pixel centres moved by integer offsets.

    :param obs: float images, shape ``(batch, channels, height, width)``
    :param pad: padding in pixels
    :param shifts: optional integer offsets ``(batch, 2)`` in ``[0, 2 * pad]``, as ``(x, y)``
    :return: shifted float images, same shape
    """
    n, _, h, w = obs.shape
    padded = F.pad(obs, (pad,) * 4, "replicate")
    # Centres of the padded pixels in grid_sample's normalized coordinates (align_corners=False).
    on = {"device": obs.device, "dtype": obs.dtype}
    xs = th.linspace(-1.0 + 1.0 / (w + 2 * pad), 1.0 - 1.0 / (w + 2 * pad), w + 2 * pad, **on)[:w]
    ys = th.linspace(-1.0 + 1.0 / (h + 2 * pad), 1.0 - 1.0 / (h + 2 * pad), h + 2 * pad, **on)[:h]
    base_grid = th.stack(th.meshgrid(xs, ys, indexing="xy"), dim=-1)  # (h, w, 2) as (x, y)
    if shifts is None:
        shifts = th.randint(0, 2 * pad + 1, (n, 2), device=obs.device)
    scale = th.tensor([2.0 / (w + 2 * pad), 2.0 / (h + 2 * pad)], device=obs.device, dtype=obs.dtype)
    grid = base_grid.unsqueeze(0) + (shifts.to(obs.dtype) * scale).view(n, 1, 1, 2)
    return F.grid_sample(padded, grid, padding_mode="zeros", align_corners=False)


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
