"""What the callbacks and the run checkpoints need of a model: :class:`CollapseModel`, implemented by ``DrQv2`` and
by the wrappers of SB3's TD3, DDPG and SAC in :mod:`sb3_collapse.baselines`."""

from __future__ import annotations

from abc import ABC
from typing import Any, Protocol, runtime_checkable

from stable_baselines3.common.vec_env import VecEnv

from sb3_collapse.common.grad_norms import GradNormRecorder


@runtime_checkable
class CollapseModel(Protocol):
    """An SB3 model with counters in the paper's units, gradient norms, a reset from scratch and safe points."""

    num_timesteps: int
    """Agent steps (transitions summed over the environments) so far: SB3's counter."""
    reset_step: int
    """``num_timesteps`` at the last reset from scratch, 0 when none."""
    grad_norm_recorder: GradNormRecorder | None
    """Records the gradient norm of each named layer at each update (``None`` when the layers cannot be named)."""

    @property
    def action_repeat(self) -> int:
        """Environment frames per agent step."""

    @property
    def num_frames(self) -> int:
        """Environment frames so far: ``num_timesteps x action_repeat`` (the paper's unit)."""

    @property
    def n_updates(self) -> int:
        """Gradient updates so far (SB3's ``train/n_updates``)."""

    @property
    def at_safe_point(self) -> bool:
        """Whether no environment step is in flight: a checkpoint taken now is complete."""

    def request_safe_point(self) -> None:
        """The round in progress steps no environment during its updates: the next round starts at a safe point."""

    def reset_from_scratch(self) -> None:
        """New networks and optimizers, an emptied replay buffer, the warm-up again (the paper's reset rule)."""


class CollapseModelBase(ABC):
    """The parts of :class:`CollapseModel` an SB3 off-policy algorithm has as it is (mixed in before it); an ``ABC``
    as ``BaseAlgorithm``, so that ``collapse_model`` can change the class of a model built with SB3's own."""

    reset_step: int = 0
    grad_norm_recorder: GradNormRecorder | None = None
    num_timesteps: int
    _n_updates: int

    @property
    def action_repeat(self) -> int:
        """The ``action_repeat`` of the environment."""
        return env_action_repeat(self.get_env())  # type: ignore[attr-defined]  # BaseAlgorithm's

    @property
    def num_frames(self) -> int:
        return self.num_timesteps * self.action_repeat

    @property
    def n_updates(self) -> int:
        return self._n_updates

    @property
    def at_safe_point(self) -> bool:
        """Always: SB3's loop never leaves an environment step in flight between rounds."""
        return True

    def request_safe_point(self) -> None:
        """Nothing to do (see :attr:`at_safe_point`)."""


def env_action_repeat(env: VecEnv | None) -> int:
    """:return: the ``action_repeat`` of the first environment of ``env`` (``make_dmc_env``), 1 when none"""
    if env is None:
        return 1
    try:
        return int(env.get_attr("action_repeat", indices=[0])[0] or 1)
    except AttributeError:
        return 1


ENV_CONFIG_KEYS = ("task_id", "action_repeat", "frame_stack", "size", "camera_id", "obs_type")  # saved with a DrQv2


def read_env_config(env: VecEnv) -> dict[str, Any] | None:
    """:return: the :data:`ENV_CONFIG_KEYS` of ``env``'s first environment, ``None`` for one not made by make_dmc_env"""
    # has_attr first: a SubprocVecEnv's worker dies on get_attr of a missing attribute.
    config = {key: env.get_attr(key, indices=[0])[0] if env.has_attr(key) else None for key in ENV_CONFIG_KEYS}
    if config["task_id"] is None and config["action_repeat"] is None:
        return None
    return config
