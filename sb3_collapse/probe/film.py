"""Films of Figures 6-7 (drawn by :mod:`sb3_collapse.report.film`): an episode's first frames, rendered larger."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from sb3_collapse.envs import make_dmc_env

FILM_FRAMES = 300
"""Frames filmed by default: the paper's "video frames from 0 to 300 frames"."""
FILM_SIZE = 256
"""Height and width of the film's renders, in pixels (the agent still sees its own observation size)."""


@dataclass
class Film:
    """A film named ``label`` (checkpoint and episode seed): ``(T, size, size, 3)`` uint8 ``images`` rendered at
    environment ``frames`` ``(T,)``, the ``(T, action_dim)`` ``actions`` taken from each and their ``(T,)``
    ``rewards`` (nan after the last picture)."""

    label: str
    frames: np.ndarray
    images: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    task: str


def film_episode(
    model: Any,
    env_config: dict[str, Any],
    label: str,
    frames: int = FILM_FRAMES,
    size: int = FILM_SIZE,
    seed: int = 0,
    deterministic: bool = True,
) -> Film:
    """
    Run the agent from a reset for ``frames`` environment frames and render each agent step at ``size`` pixels.

    :param model: the agent, acting on its own observations
    :param env_config: its ``make_dmc_env`` settings
    :param label: the film's name
    :param frames: environment frames to film (rounded up to whole agent steps; fewer if the episode ends)
    :param size: the film's render size, in pixels
    :param seed: seed of the episode's initial state
    :param deterministic: the policy's deterministic action
    :return: the film
    """
    env = make_dmc_env(env_config["task_id"], seed=seed, **{k: v for k, v in env_config.items() if k != "task_id"})
    try:
        render = functools.partial(env.physics.render, height=size, width=size, camera_id=env.camera_id)
        observation, _ = env.reset(seed=seed)
        pictures, frame_numbers, actions, rewards, elapsed = [render()], [0], [], [], 0
        while elapsed < frames:
            action, _ = model.predict(observation, deterministic=deterministic)
            observation, reward, terminated, truncated, info = env.step(action)
            actions.append(np.asarray(action, dtype=np.float32).reshape(-1))
            rewards.append(float(reward))
            elapsed = int(info["frames"])
            pictures.append(render())
            frame_numbers.append(elapsed)
            if terminated or truncated:
                break
    finally:
        env.close()
    padded = np.full((len(pictures), actions[0].shape[0]), np.nan, dtype=np.float32)
    padded[: len(actions)] = actions
    rewards = np.append(np.asarray(rewards, dtype=np.float32), np.nan)
    frame_numbers = np.asarray(frame_numbers, dtype=np.int64)
    return Film(label, frame_numbers, np.stack(pictures).astype(np.uint8), padded, rewards, str(env_config["task_id"]))
