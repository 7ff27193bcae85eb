"""DeepMind Control Suite tasks as Gymnasium environments, preprocessed as in DrQ-v2's ``dmc.py``. A *frame* is one
dm_control control step; an *agent step* one :meth:`DMCEnv.step`, ``action_repeat`` frames. See docs/environments.md.
"""

from __future__ import annotations

import contextlib
import difflib
import io
import sys
import warnings
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.utils import EzPickle

from sb3_collapse.envs.registration import DMC_TASKS, DOMAIN_ALIASES, DOMAIN_NAMES
from sb3_collapse.envs.rendering import ensure_rendering_backend
from sb3_collapse.errors import NonFiniteDataError, ParameterError

OBS_TYPES = ("pixels", "state")
DEFAULT_CAMERA_IDS: dict[str, int] = {"quadruped": 2}  # DrQ-v2 zooms in on the quadruped; 0 otherwise

_UNDERSCORE_NAMES: dict[str, tuple[str, str]] = {  # DrQ-v2's names ("walker_walk", "cup_catch") -> (domain, task)
    f"{name}_{task}": (domain, task) for name, domain in DOMAIN_NAMES.items() for d, task in DMC_TASKS if d == domain
}


def ignore_dm_control_shape_deprecation() -> None:
    """Ignore NumPy's (>= 2.5) DeprecationWarning about setting an array's shape where dm_control's named indexing
    (``dm_control/mujoco/index.py``) raises it, at each step of tasks such as cartpole and walker. Importing
    ``dm_control.composer`` (as shimmy does) shows every DeprecationWarning ("always"), so this filter goes in front
    of the list after it."""
    warnings.filterwarnings("ignore", "Setting the shape on a NumPy array", DeprecationWarning, r"dm_control\.")


@dataclass(frozen=True)
class RewardInput:
    """A quantity ``name`` that a task's reward function reads: the value of the ``Physics`` method ``method`` called
    with ``args``, or its element ``index``; ``state``: a state component (a probing target), not the control."""

    name: str
    method: str
    index: int | None = None
    args: tuple[str, ...] = ()
    state: bool = True
    doc: str = ""

    def value(self, physics: Any) -> np.ndarray:
        """:return: ``(size,)`` float64, what the reward function reads of ``physics`` (a copy)"""
        value = np.array(getattr(physics, self.method)(*self.args), dtype=np.float64).reshape(-1)
        return value[[self.index]] if self.index is not None else value


CONTROL = RewardInput("control", "control", state=False, doc="the control, i.e. the last action (small-control term)")


def _read(name: str, doc: str, method: str | None = None, index: int | None = None) -> RewardInput:
    """:return: the state quantity ``name``, read by the ``Physics`` method of that name unless ``method`` is given"""
    return RewardInput(name, method or name, index, doc=doc)


def _site_distance(site1: str, site2: str) -> RewardInput:
    """:return: ``Physics.site_distance(site1, site2)``"""
    return RewardInput(f"{site1}_to_{site2}", "site_distance", args=(site1, site2), doc=f"{site1} to {site2} distance")


_WALKER_STAND = (
    _read("torso_height", "height of the torso's frame (standing term)"),
    _read("torso_upright", "zz entry of the torso's rotation matrix (upright term)"),
)
_WALKER_MOVE = (*_WALKER_STAND, _read("horizontal_velocity", "horizontal velocity of the centre of mass (move)"))
_HOPPER_HEIGHT = _read("height", "torso height above the foot (standing term)")
_CARTPOLE_SPARSE = (
    _read("cart_position", "the cart's position on the rail (centred term)"),
    _read("pole_angle_cosine", "cosine of each pole's angle (upright term)"),
)
_ANGULAR_VEL = _read("angular_vel", "each pole's angular velocity (small-velocity term)")
_CARTPOLE_SMOOTH = (*_CARTPOLE_SPARSE, CONTROL, _ANGULAR_VEL)
_HUMANOID = (
    _read("head_height", "height of the head (standing term)"),
    _read("torso_upright", "zz entry of the torso's rotation matrix (upright term)"),
    CONTROL,
    _read("com_velocity_x", "centre-of-mass velocity along x (move term)", "center_of_mass_velocity", 0),
    _read("com_velocity_y", "centre-of-mass velocity along y (move term)", "center_of_mass_velocity", 1),
)
_HUMANOID_CMU = (
    _HUMANOID[0],
    _read("thorax_upright", "zz entry of the thorax's rotation matrix (upright term)"),
    *_HUMANOID[2:],
)
_DOG_STAND = (
    _read("torso_pelvis_height", "heights of the torso and the pelvis"),
    _read("upright", "zz entries of the skull's, torso's and pelvis's rotation matrices"),
    _read("touch_sensors", "touch forces of the palms and soles (summed)"),
)
_BALL_TO_TARGET = _read("ball_to_target_distance", "ball to target distance (fetch)")
_MANIPULATOR_PEG = tuple(
    _site_distance(*sites)
    for sites in (("peg_grasp", "grasp"), ("peg_pinch", "pinch"), ("peg", "target_peg"), ("target_peg_tip", "peg_tip"))
)
_QUADRUPED_UPRIGHT = _read("torso_upright", "zz entry of the torso's rotation matrix")
_FISH_UPRIGHT = _read("upright", "zz entry of the torso's rotation matrix")


def _stacker(n_boxes: int) -> tuple[RewardInput, ...]:
    """:return: stacker's reward inputs with ``n_boxes`` boxes: each box to the target, then the hand to the target."""
    return (*(_site_distance(f"box{b}", "target") for b in range(n_boxes)), _site_distance("grasp", "target"))


REWARD_INPUTS: dict[str, tuple[RewardInput, ...]] = {
    task: inputs
    for tasks, inputs in (
        ("acrobot-swingup acrobot-swingup_sparse", (_read("to_target", "distance from the tip to the target"),)),
        ("ball_in_cup-catch", (_read("ball_to_target", "x and z from the ball to the cup's target (in_target)"),)),
        ("cartpole-balance cartpole-swingup cartpole-two_poles cartpole-three_poles", _CARTPOLE_SMOOTH),
        ("cartpole-balance_sparse cartpole-swingup_sparse", _CARTPOLE_SPARSE),
        ("cheetah-run", (_read("speed", "horizontal velocity of the centre of mass"),)),
        ("dog-stand", _DOG_STAND),
        ("dog-walk dog-trot dog-run", (*_DOG_STAND, _read("com_forward_velocity", "forward velocity"))),
        ("dog-fetch", (
            *_DOG_STAND, _read("ball_to_mouth_distance", "ball to mouth distance (reach term)"), _BALL_TO_TARGET
        )),
        ("finger-spin", (_read("hinge_velocity", "angular velocity of the spinner"),)),
        ("finger-turn_easy finger-turn_hard", (
            _read("dist_to_target", "distance from the spinner's tip to the target"),
        )),
        ("fish-upright", (_FISH_UPRIGHT,)),
        ("fish-swim", (_read("mouth_to_target", "mouth to target, in the mouth's frame (its norm)"), _FISH_UPRIGHT)),
        ("hopper-stand", (_HOPPER_HEIGHT, CONTROL)),
        ("hopper-hop", (_HOPPER_HEIGHT, _read("speed", "horizontal velocity of the torso (hop term)"))),
        ("humanoid-stand humanoid-walk humanoid-run humanoid-run_pure_state", _HUMANOID),
        ("humanoid_CMU-stand humanoid_CMU-walk humanoid_CMU-run", _HUMANOID_CMU),
        ("lqr-lqr_2_1 lqr-lqr_6_2", (_read("position", "the joints' positions (state cost)"), CONTROL)),
        ("manipulator-bring_ball manipulator-insert_ball", (_site_distance("ball", "target_ball"),)),
        ("manipulator-bring_peg manipulator-insert_peg", _MANIPULATOR_PEG),
        ("pendulum-swingup", (_read("pole_vertical", "zz entry of the pole's rotation matrix"),)),
        ("point_mass-easy point_mass-hard", (_read("mass_to_target_dist", "mass to target distance"), CONTROL)),
        ("quadruped-walk quadruped-run", (
            _QUADRUPED_UPRIGHT,
            _read("torso_velocity_x", "forward velocity of the torso (move term)", "torso_velocity", 0),
        )),
        ("quadruped-escape", (
            _QUADRUPED_UPRIGHT, _read("origin_distance", "distance of the torso from the origin (escape)")
        )),
        ("quadruped-fetch", (
            _QUADRUPED_UPRIGHT, _read("self_to_ball_distance", "workspace to ball distance (reach)"), _BALL_TO_TARGET
        )),
        ("reacher-easy reacher-hard", (_read("finger_to_target_dist", "finger to target distance"),)),
        ("stacker-stack_2", _stacker(2)),
        ("stacker-stack_4", _stacker(4)),
        ("swimmer-swimmer6 swimmer-swimmer15", (_read("nose_to_target_dist", "nose to target distance"),)),
        ("walker-stand", _WALKER_STAND),
        ("walker-walk walker-run", _WALKER_MOVE),
    )
    for task in tasks.split()
}  # fmt: skip
"""``<domain>-<task>`` (every suite task) -> what its ``get_reward`` reads, in order: Figure 2's components are
"the input to the reward function". See docs/probe.md."""


def reward_inputs_of(domain: str, task: str) -> tuple[RewardInput, ...]:
    """:return: every quantity the reward of ``domain``-``task`` reads (:data:`REWARD_INPUTS`), control included"""
    return REWARD_INPUTS.get(f"{domain}-{task}", ())


def parse_task(name: str) -> tuple[str, str]:
    """
    :param name: a task name: ``"<domain>-<task>"`` (``"walker-walk"``), DrQ-v2's ``"walker_walk"``, or with the alias
        ``cup`` for ``ball_in_cup`` (``"cup-catch"``)
    :return: ``(domain, task)`` as in ``dm_control.suite.ALL_TASKS``, e.g. ``("ball_in_cup", "catch")``
    :raises ValueError: if the name is not a task of the suite (the message suggests close names)
    """
    if "-" in name:
        domain, task = name.split("-", 1)
        domain = DOMAIN_ALIASES.get(domain, domain)
        if (domain, task) in DMC_TASKS:
            return domain, task
    elif name in _UNDERSCORE_NAMES:
        return _UNDERSCORE_NAMES[name]
    canonical = {f"{domain}-{task}": f"{domain}-{task}" for domain, task in DMC_TASKS}
    canonical.update({underscored: f"{domain}-{task}" for underscored, (domain, task) in _UNDERSCORE_NAMES.items()})
    matches = difflib.get_close_matches(name, list(canonical), n=6, cutoff=0.6)
    suggestions = list(dict.fromkeys(canonical[match] for match in matches))[:3]
    hint = f" Did you mean {', '.join(repr(s) for s in suggestions)}?" if suggestions else ""
    raise ValueError(
        f"Unknown DeepMind Control task {name!r}.{hint} Tasks are named '<domain>-<task>', e.g. 'walker-walk' "
        "(DrQ-v2's 'walker_walk' also works); list them with `sb3_collapse.envs.DMC_TASKS`."
    )


def scale_action(action: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """:return: ``action`` clipped to [-1, 1] and mapped linearly onto [``low``, ``high``], float64 (as dm_control's
    ``action_scale`` wrapper; bounds of [-1, 1] leave it unchanged, bit for bit)"""
    action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
    return (high - low) / 2.0 * action + (high + low) / 2.0


class DMCEnv(gym.Env[np.ndarray, np.ndarray], EzPickle):
    """A DeepMind Control Suite task with DrQ-v2 preprocessing (docs/environments.md): observations ``uint8``
    ``(3 * frame_stack, size, size)``, the last renders, oldest first; actions in [-1, 1]; ``info["frames"]``.
    The parameters are :func:`make_dmc_env`'s, and ``render_mode``: "rgb_array" (:meth:`render`) or None."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(
        self,
        task: str,
        seed: int | None = None,
        action_repeat: int = 2,
        frame_stack: int = 3,
        size: int = 84,
        camera_id: int | None = None,
        obs_type: str = "pixels",
        render_mode: str | None = "rgb_array",
    ) -> None:
        EzPickle.__init__(self, task, seed, action_repeat, frame_stack, size, camera_id, obs_type, render_mode)
        check_env_arguments(action_repeat, frame_stack, size, obs_type, render_mode)
        self.domain, self.task_name = parse_task(task)
        self.task_id = f"{self.domain}-{self.task_name}"
        self.action_repeat, self.frame_stack, self.size = action_repeat, frame_stack, size
        self.obs_type, self.render_mode = obs_type, render_mode
        self.camera_id = DEFAULT_CAMERA_IDS.get(self.domain, 0) if camera_id is None else camera_id

        self._dmc = self._load(seed)
        n_cameras = self._dmc._env.physics.model.ncam
        if not -1 <= self.camera_id < n_cameras:
            self.close()
            raise ValueError(
                f"camera_id={self.camera_id} does not exist in {self.task_id}, which has {n_cameras} cameras "
                "(ids 0 to ncam - 1, or -1 for the free camera)."
            )

        action_spec = self._dmc._env.action_spec()
        self._action_low = np.broadcast_to(action_spec.minimum, action_spec.shape).astype(np.float64)
        self._action_high = np.broadcast_to(action_spec.maximum, action_spec.shape).astype(np.float64)
        self.action_space = spaces.Box(-1.0, 1.0, shape=action_spec.shape, dtype=np.float32, seed=seed)

        self._state_shapes = OrderedDict(
            (name, int(np.prod(spec.shape))) for name, spec in self._dmc._env.observation_spec().items()
        )
        if obs_type == "pixels":
            self.observation_space = spaces.Box(0, 255, shape=(3 * frame_stack, size, size), dtype=np.uint8)
        else:
            dim = sum(self._state_shapes.values())
            self.observation_space = spaces.Box(-np.inf, np.inf, shape=(dim,), dtype=np.float32)

        agent_step_s = self._dmc._env.control_timestep() * action_repeat
        self.metadata = {"render_modes": ["rgb_array"], "render_fps": 1.0 / agent_step_s}

        self._frames: deque[np.ndarray] = deque(maxlen=frame_stack)  # CHW renders, oldest first
        self._last_render: np.ndarray | None = None  # HWC
        self._dmc_observation: dict[str, np.ndarray] | None = None  # of the current timestep
        self._elapsed_frames = 0

    def _load(self, seed: int | None) -> Any:
        """:return: the dm_control task wrapped by shimmy's ``DmControlCompatibilityV0``, seeded with ``seed``"""
        ensure_rendering_backend(required=self.obs_type == "pixels")
        from dm_control import suite

        # shimmy prints to stdout why it registered no locomotion envs (no labmaze, as on Python 3.13): said on stderr
        # instead, so that stdout holds only what this package prints.
        with contextlib.redirect_stdout(io.StringIO()) as shimmy_printed:
            from shimmy.dm_control_compatibility import DmControlCompatibilityV0
        sys.stderr.write(shimmy_printed.getvalue())

        ignore_dm_control_shape_deprecation()  # after shimmy's import, which imports dm_control.composer
        dm_env = suite.load(self.domain, self.task_name, task_kwargs={"random": seed}, visualize_reward=False)
        render_kwargs = {"height": self.size, "width": self.size, "camera_id": self.camera_id}
        return DmControlCompatibilityV0(dm_env, render_mode="rgb_array", render_kwargs=render_kwargs)

    @property
    def state_shapes(self) -> OrderedDict[str, int]:
        """Names of the true state components (dm_control's order) and their flattened sizes."""
        return OrderedDict(self._state_shapes)

    def get_state(self) -> dict[str, np.ndarray]:
        """:return: the true state of the current timestep, by component (:attr:`state_shapes`), flat float32 copies"""
        if self._dmc_observation is None:
            raise RuntimeError("get_state() needs a current timestep: call reset() first.")
        return {name: np.array(value, dtype=np.float32).reshape(-1) for name, value in self._dmc_observation.items()}

    @property
    def physics(self) -> Any:
        """The dm_control ``Physics`` of the task (its simulator state)."""
        return self._dmc._env.physics

    def reward_inputs(self) -> dict[str, np.ndarray]:
        """:return: the state components the task's reward reads (:data:`REWARD_INPUTS` but the control) now, name ->
        ``(size,)`` float32"""
        if self._dmc_observation is None:
            raise RuntimeError("reward_inputs() needs a current timestep: call reset() first.")
        inputs = reward_inputs_of(self.domain, self.task_name)
        return {item.name: item.value(self.physics).astype(np.float32) for item in inputs if item.state}

    def get_rng_state(self) -> dict[str, Any]:
        """:return: the state of the task's and the action space's random generators (picklable), for a checkpoint"""
        return {
            "task": self._dmc._env.task.random.get_state(),
            "action_space": self.action_space.np_random.bit_generator.state,
        }

    def set_rng_state(self, state: dict[str, Any]) -> None:
        """:param state: what :meth:`get_rng_state` returned, put back"""
        self._dmc._env.task.random.set_state(state["task"])
        self.action_space.np_random.bit_generator.state = state["action_space"]

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """:return: the first observation and info with ``frames`` = 0; a ``seed`` reseeds the task and action space"""
        super().reset(seed=seed)
        if seed is not None:
            self._dmc._env.task._random = np.random.RandomState(seed)
            self.action_space.seed(seed)
        self._dmc_observation, _ = self._dmc.reset()
        self._elapsed_frames = 0
        if self.obs_type == "pixels":
            self._frames.extend([self._render_frame()] * self.frame_stack)
        return self._observation(), {"frames": 0}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Apply ``action`` (in [-1, 1], clipped) for ``action_repeat`` frames (fewer if the episode ends); the reward
        is summed over them with dm_control's discounts, info's ``frames`` counts frames since the reset."""
        if self._dmc_observation is None:
            raise RuntimeError("Call reset() before step().")
        action = np.asarray(action)
        if action.shape != self.action_space.shape:
            raise ValueError(f"Expected an action of shape {self.action_space.shape}, got {action.shape}.")
        dmc_action = scale_action(action, self._action_low, self._action_high)

        reward, discount = 0.0, 1.0
        terminated = truncated = False
        for _ in range(self.action_repeat):
            try:
                self._dmc_observation, frame_reward, terminated, truncated, info = self._dmc.step(dmc_action)
            except RuntimeError as error:  # dm_control's PhysicsError: one line, not a traceback
                raise _physics_error(error, action, self._elapsed_frames + 1) from None
            self._elapsed_frames += 1
            reward += float(frame_reward) * discount
            discount *= float(info["timestep.discount"])
            if terminated or truncated:
                break

        if self.obs_type == "pixels":
            self._frames.append(self._render_frame())
        return self._observation(), reward, terminated, truncated, {"frames": self._elapsed_frames}

    def render(self) -> np.ndarray | None:
        """:return: ``(size, size, 3)`` uint8, the last render (a fresh one for states); None without ``render_mode``"""
        if self.render_mode is None:
            return None
        if self.obs_type == "pixels" and self._last_render is not None:
            return self._last_render.copy()
        return self._dmc.render()

    def close(self) -> None:
        """Free the simulator (calling it again does nothing)."""
        if getattr(self, "_dmc", None) is not None:
            self._dmc.close()
            self._dmc = None

    def _render_frame(self) -> np.ndarray:
        """:return: a render of the current state, ``(3, size, size)`` uint8"""
        self._last_render = self._dmc.render()
        return self._last_render.transpose(2, 0, 1)

    def _observation(self) -> np.ndarray:
        """:return: the current observation (a new array)"""
        if self.obs_type == "pixels":
            return np.concatenate(list(self._frames), axis=0)
        return np.concatenate(list(self.get_state().values()))


def check_env_arguments(
    action_repeat: int, frame_stack: int, size: int, obs_type: str = "pixels", render_mode: str | None = None
) -> None:
    """Raise a ``ParameterError`` for invalid :class:`DMCEnv` arguments, before building one."""
    for name, value in (("action_repeat", action_repeat), ("frame_stack", frame_stack), ("size", size)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ParameterError(name, f"{name} must be an integer >= 1, got {value!r}.")
    if obs_type not in OBS_TYPES:
        raise ParameterError("obs_type", f"obs_type must be one of {OBS_TYPES}, got {obs_type!r}.")
    if render_mode not in (None, "rgb_array"):
        raise ParameterError("render_mode", f"render_mode must be 'rgb_array' or None, got {render_mode!r}.")


def make_dmc_env(
    task: str,
    seed: int | None = None,
    action_repeat: int = 2,
    frame_stack: int = 3,
    size: int = 84,
    camera_id: int | None = None,
    obs_type: str = "pixels",
) -> DMCEnv:
    """A DeepMind Control Suite task with DrQ-v2 preprocessing, a :class:`DMCEnv`.

    :param task: task name, e.g. "walker-walk", "walker_walk" or "cup-catch" (see :func:`parse_task`)
    :param seed: seed of the task's random initial states and of the action space; None for a random one
    :param action_repeat: frames (simulator control steps) per agent step, each with the same action
    :param frame_stack: renders (one per agent step) stacked in a pixel observation; ignored for states
    :param size: height and width of the renders, in pixels
    :param camera_id: camera of the renders; None for DrQ-v2's choice (2 for quadruped, 0 otherwise)
    :param obs_type: "pixels" for stacked renders, "state" for the vectorized true state
    """
    return DMCEnv(task, seed, action_repeat, frame_stack, size, camera_id, obs_type)


def _physics_error(error: RuntimeError, action: np.ndarray, frame: int) -> Exception:
    """:return: ``error`` as a ``NonFiniteDataError`` naming the ``action`` and the ``frame`` of the episode when it is
    dm_control's ``PhysicsError`` (MuJoCo could not step), else ``error``"""
    from dm_control.rl.control import PhysicsError

    if not isinstance(error, PhysicsError):
        return error
    why = "the action is not finite (a diverged policy?)" if not np.isfinite(action).all() else "an unstable simulation"
    reason = (str(error).strip().splitlines() or [""])[0]
    return NonFiniteDataError(f"MuJoCo could not step frame {frame} of the episode with the action {action}: {why} "
                              f"(PhysicsError: {reason}).")  # fmt: skip
