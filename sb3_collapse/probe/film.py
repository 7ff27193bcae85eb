"""
Films of the paper's Figures 6 and 7 (drawn by :mod:`sb3_collapse.report.film`): what an agent does in the first
frames of an episode.

The agent acts on its own observations (its ``make_dmc_env`` settings, e.g. 84x84 stacks); after every agent
step, a larger view of the same simulator state (``size`` pixels, same camera) is rendered for the film.
"""

from __future__ import annotations

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
    """
    One filmed episode.

    :param label: its name (checkpoint and episode seed)
    :param frames: ``(T,)`` the environment frame of each picture (0, action repeat, 2 x action repeat, ...)
    :param images: ``(T, size, size, 3)`` uint8 renders
    :param actions: ``(T, action_dim)`` the action taken from each picture's state (nan after the last one)
    :param rewards: ``(T,)`` the reward of that action (nan after the last one)
    :param task: the task
    """

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

    :param model: the agent
    :param env_config: its ``make_dmc_env`` settings (``task_id``, ``action_repeat``, ``frame_stack``, ``size``,
        ``camera_id``)
    :param label: the film's name
    :param frames: environment frames to film (rounded up to whole agent steps; fewer if the episode ends)
    :param size: the film's render size, in pixels
    :param seed: seed of the episode's initial state
    :param deterministic: the policy's deterministic action
    :return: the film
    """
    env = make_dmc_env(env_config["task_id"], seed=seed, **{k: v for k, v in env_config.items() if k != "task_id"})
    try:
        physics = env._dmc._env.physics
        camera_id = env.camera_id

        def render() -> np.ndarray:
            return np.asarray(physics.render(height=size, width=size, camera_id=camera_id), dtype=np.uint8)

        observation, _ = env.reset(seed=seed)
        pictures, frame_numbers, actions, rewards = [render()], [0], [], []
        elapsed = 0
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
    action_dim = actions[0].shape[0]
    padded = np.full((len(pictures), action_dim), np.nan, dtype=np.float32)
    padded[: len(actions)] = actions
    return Film(
        label=label,
        frames=np.asarray(frame_numbers, dtype=np.int64),
        images=np.stack(pictures),
        actions=padded,
        rewards=np.append(np.asarray(rewards, dtype=np.float32), np.nan),
        task=str(env_config["task_id"]),
    )
