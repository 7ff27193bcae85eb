"""An environment with random observations and no simulator, for fast tests and benchmarks.

Imported as ``tests.random_env`` from the repository root.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np


class RandomObservationEnv(gym.Env):
    """
    Random observations of a given space, random rewards in [0, 1), a time limit.

    No physics and no rendering: use it to exercise an algorithm's plumbing and speed without dm_control.

    :param observation_space: e.g. ``Box(0, 255, (9, 84, 84), uint8)`` for pixels, or a 1-d float ``Box``
    :param action_space: any space (DrQv2 needs a ``Box``)
    :param episode_length: agent steps before ``truncated=True``
    :param action_repeat: reported frames per agent step, as ``make_dmc_env`` does
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        observation_space: gym.Space | None = None,
        action_space: gym.Space | None = None,
        episode_length: int = 50,
        action_repeat: int = 1,
    ) -> None:
        super().__init__()
        self.observation_space = observation_space or gym.spaces.Box(0, 255, (9, 84, 84), np.uint8)
        self.action_space = action_space or gym.spaces.Box(-1.0, 1.0, (6,), np.float32)
        self.episode_length = episode_length
        self.action_repeat = action_repeat
        self._steps = 0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        super().reset(seed=seed)
        if seed is not None:
            self.observation_space.seed(seed)
        self._steps = 0
        return self.observation_space.sample(), {"frames": 0}

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        self._steps += 1
        truncated = self._steps >= self.episode_length
        info = {"frames": self._steps * self.action_repeat}
        return self.observation_space.sample(), float(self.np_random.random()), False, truncated, info
