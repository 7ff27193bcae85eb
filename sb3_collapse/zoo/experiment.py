"""rl_zoo3's ``ExperimentManager``, made safe for DrQv2 on DeepMind Control pixels."""

from __future__ import annotations

import inspect
import os
from typing import Any, ClassVar

import gymnasium as gym
import yaml
from rl_zoo3.exp_manager import ExperimentManager
from stable_baselines3.common.vec_env import VecEnv, VecTransposeImage, is_vecenv_wrapped

from sb3_collapse.drqv2 import StddevSchedule
from sb3_collapse.envs.dmc import DMCEnv
from sb3_collapse.envs.registration import ENTRY_POINT
from sb3_collapse.errors import InputError
from sb3_collapse.zoo.registration import ALGO_NAME

CallbackSpec = dict[str, dict[str, Any]]  # rl_zoo3's `callback:` format: {"dotted.path.Class": {kwarg: value}}
PIXEL_SETTINGS = ("action_repeat", "frame_stack", "size", "camera_id", "obs_type")  # same in training and evaluation

_DMC_DEFAULTS = {
    name: parameter.default
    for name, parameter in inspect.signature(DMCEnv.__init__).parameters.items()
    if name in PIXEL_SETTINGS
}


def _is_dmc_env_id(env_id: str) -> bool:
    """:return: whether the registered Gymnasium id ``env_id`` builds a :class:`~sb3_collapse.envs.dmc.DMCEnv`"""
    return env_id in gym.registry and gym.registry[env_id].entry_point == ENTRY_POINT


def _check_same_pixels(train_kwargs: dict[str, Any] | None, eval_kwargs: dict[str, Any] | None) -> None:
    """Refuse training and evaluation ``env_kwargs`` whose :data:`PIXEL_SETTINGS` differ (missing: the defaults)."""
    train, evaluation = train_kwargs or {}, eval_kwargs or {}
    pairs = {name: (train.get(name, default), evaluation.get(name, default)) for name, default in _DMC_DEFAULTS.items()}
    details = ", ".join(f"{name}: {a!r} in training, {b!r} in evaluation" for name, (a, b) in pairs.items() if a != b)
    if details:
        raise InputError(
            f"The evaluation env must see the same pixels as the training env ({details}). "
            "Drop these keys from --eval-env-kwargs (it defaults to the training env_kwargs)."
        )


def _check_drqv2_hyperparams(hyperparams: dict[str, Any]) -> None:
    """Refuse ``frame_stack``, ``normalize`` and a malformed ``stddev_schedule`` in a config entry."""
    if "frame_stack" in hyperparams:
        raise InputError(
            f"frame_stack: {hyperparams['frame_stack']!r} makes rl_zoo3 stack observations with VecFrameStack; "
            "the DeepMind Control envs stack frames themselves: set env_kwargs: {frame_stack: ...} instead."
        )
    if hyperparams.get("normalize"):
        raise InputError(
            "normalize makes rl_zoo3 wrap the env in VecNormalize, which would turn the uint8 pixels into "
            "normalized floats; DrQv2 scales the pixels itself (layer cnn0): remove normalize."
        )
    if "stddev_schedule" in hyperparams:
        try:
            StddevSchedule(hyperparams["stddev_schedule"])
        except ValueError as error:
            raise InputError(f"stddev_schedule: {error}") from None


class ZooExperimentManager(ExperimentManager):
    """
    rl_zoo3's ``ExperimentManager`` for the launcher's ``train``: the evaluation env gets the training ``env_kwargs``,
    :attr:`extra_callbacks` join the config's, and what breaks DrQv2 on pixels is refused in one line (docs/zoo.md).
    """

    extra_callbacks: ClassVar[list[CallbackSpec]] = []  # added to every experiment of this class (with_callbacks)

    @classmethod
    def with_callbacks(cls, callbacks: list[CallbackSpec]) -> type[ZooExperimentManager]:
        """:return: a subclass that appends ``callbacks`` (rl_zoo3's ``callback`` format) to the config's"""
        return type(cls.__name__, (cls,), {"extra_callbacks": [*cls.extra_callbacks, *callbacks]})

    def read_hyperparameters(self) -> tuple[dict[str, Any], dict[str, Any]]:
        if self.config.endswith((".yml", ".yaml", ".py")) and not os.path.isfile(self.config):
            hint = " (pass -conf zoo_configs/drqv2.yml)" if self.algo == ALGO_NAME else ""
            raise InputError(f"Config file {self.config} not found{hint}.")
        try:
            hyperparams, saved_hyperparams = super().read_hyperparameters()
        except yaml.YAMLError as error:
            raise InputError(f"Cannot parse {self.config}: {error}") from None
        except ValueError as error:  # rl_zoo3: "Hyperparameters not found for <algo>-<env> in <config>"
            raise InputError(f"{error}: add an entry for {self.env_name.gym_id} to it.") from None
        if self.algo == ALGO_NAME:
            _check_drqv2_hyperparams(hyperparams)
        if self.extra_callbacks:  # after the config's (None, a dotted name, a {name: kwargs} dict or a list)
            configured = hyperparams.get("callback")
            configured = [] if configured is None else configured if isinstance(configured, list) else [configured]
            hyperparams["callback"] = saved_hyperparams["callback"] = [*configured, *self.extra_callbacks]
            print(f"Callbacks added to the config's: {[next(iter(spec)) for spec in self.extra_callbacks]}")
        return hyperparams, saved_hyperparams

    def _preprocess_hyperparams(self, hyperparams: dict[str, Any]) -> Any:
        processed = super()._preprocess_hyperparams(hyperparams)
        # rl_zoo3 bound eval_env_kwargs to the command line's env_kwargs before reading the config file.
        self.eval_env_kwargs = {**self.env_kwargs, **(self._eval_env_kwargs_args or {})}
        if _is_dmc_env_id(self.env_name.gym_id):
            _check_same_pixels(self.env_kwargs, self.eval_env_kwargs)
        return processed

    def create_envs(self, n_envs: int, eval_env: bool = False, no_log: bool = False) -> VecEnv:
        env = super().create_envs(n_envs, eval_env=eval_env, no_log=no_log)
        if _is_dmc_env_id(self.env_name.gym_id) and is_vecenv_wrapped(env, VecTransposeImage):
            shape = env.get_attr("observation_space", indices=[0])[0].shape
            env.close()
            raise InputError(
                f"rl_zoo3 took the channel-first {shape} pixel observations for channel-last images (SB3 takes the "
                "smallest axis for the channels) and would transpose them: use size >= 3 * frame_stack in env_kwargs."
            )
        return env
