"""Tests of the DeepMind Control environments (sb3_collapse.envs), with the real dm_control."""

from __future__ import annotations

import contextlib
import importlib.util
import os
import pickle
import subprocess
import sys
import warnings
from collections.abc import Callable, Iterator
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

from sb3_collapse.envs import DMC_TASKS, DMCEnv, ensure_rendering_backend, make_dmc_env, parse_task
from sb3_collapse.envs.dmc import REWARD_INPUTS, ignore_dm_control_shape_deprecation, reward_inputs_of, scale_action

ensure_rendering_backend(required=False)  # the OpenGL backend, before dm_control is imported (it reads MUJOCO_GL once)
from dm_control import suite  # isort: skip
from dm_control.suite import cheetah, dog, finger, hopper, humanoid, humanoid_CMU  # isort: skip
from dm_control.suite import manipulator, pendulum, quadruped, stacker, walker  # isort: skip
from dm_control.suite.utils import randomizers  # isort: skip
from dm_control.suite.wrappers import action_scale  # isort: skip
from dm_control.utils import rewards as dm_rewards  # isort: skip

WALKER_STATE_SHAPES = {"orientations": 14, "height": 1, "velocity": 9}


@contextlib.contextmanager
def warnings_as_errors() -> Iterator[None]:
    """Turn every warning into an error but dm_control's own deprecation under NumPy >= 2.5, which the environments
    ignore (pyproject.toml's filterwarnings too)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ignore_dm_control_shape_deprecation()
        yield


@pytest.fixture
def make_env() -> Iterator[Callable[..., DMCEnv]]:
    """:return: ``make_dmc_env``, closing the environments it made after the test."""
    envs: list[DMCEnv] = []

    def _make(task: str = "walker-walk", **kwargs) -> DMCEnv:
        envs.append(make_dmc_env(task, **kwargs))
        return envs[-1]

    yield _make
    for env in envs:
        env.close()


def raw_dmc_env(domain: str, task: str, seed: int):
    """:return: The plain dm_control environment DMCEnv wraps, for comparisons."""
    return suite.load(domain, task, task_kwargs={"random": seed}, visualize_reward=False)


def flat_state(observation) -> np.ndarray:
    """:return: A dm_control observation flattened as DMCEnv's state observation."""
    return np.concatenate([np.asarray(v, dtype=np.float32).reshape(-1) for v in observation.values()])


# ---------------------------------------------------------------- task names and registration


@pytest.mark.parametrize(
    "name, expected",
    [
        ("walker-walk", ("walker", "walk")),
        ("ball_in_cup-catch", ("ball_in_cup", "catch")),
        ("finger-turn_easy", ("finger", "turn_easy")),
        ("humanoid_CMU-run", ("humanoid_CMU", "run")),
        ("walker_walk", ("walker", "walk")),
        ("finger_turn_easy", ("finger", "turn_easy")),
        ("point_mass_easy", ("point_mass", "easy")),
        ("ball_in_cup_catch", ("ball_in_cup", "catch")),
        ("cup_catch", ("ball_in_cup", "catch")),
        ("cup-catch", ("ball_in_cup", "catch")),
    ],
)
def test_parse_task(name: str, expected: tuple[str, str]) -> None:
    assert parse_task(name) == expected


@pytest.mark.parametrize("name", ["walker-wlak", "walker_wlak", "walkerwalk", "walker", "", "walker-walk-v0"])
def test_parse_task_unknown(name: str) -> None:
    with pytest.raises(ValueError) as error:
        parse_task(name)
    message = str(error.value)
    assert repr(name) in message
    assert "DMC_TASKS" in message


def test_parse_task_suggests_close_names() -> None:
    with pytest.raises(ValueError, match="Did you mean 'walker-walk'"):
        parse_task("walker_wlak")


def test_every_task_parses_in_both_forms() -> None:
    for domain, task in DMC_TASKS:
        assert parse_task(f"{domain}-{task}") == (domain, task)
        assert parse_task(f"{domain}_{task}") == (domain, task)


def test_task_list_matches_dm_control() -> None:
    assert DMC_TASKS == tuple(suite.ALL_TASKS)


def test_all_tasks_are_registered() -> None:
    for domain, task in DMC_TASKS:
        spec = gym.spec(f"sb3_collapse/{domain}-{task}-v0")
        assert spec.entry_point == "sb3_collapse.envs.dmc:DMCEnv"
        assert spec.kwargs == {"task": f"{domain}-{task}"}
        assert spec.max_episode_steps is None
    assert gym.spec("sb3_collapse/cup-catch-v0").kwargs == {"task": "ball_in_cup-catch"}


def test_registration_is_idempotent() -> None:
    from sb3_collapse.envs import register_dmc_envs

    assert register_dmc_envs() == []


@pytest.mark.parametrize(
    "env_id, task_id",
    [
        ("sb3_collapse/walker-walk-v0", "walker-walk"),
        ("sb3_collapse/ball_in_cup-catch-v0", "ball_in_cup-catch"),
        ("sb3_collapse/cup-catch-v0", "ball_in_cup-catch"),
        ("sb3_collapse/finger-turn_easy-v0", "finger-turn_easy"),
    ],
)
def test_gymnasium_make(env_id: str, task_id: str) -> None:
    env = gym.make(env_id, obs_type="state", action_repeat=4)
    try:
        assert isinstance(env.unwrapped, DMCEnv)
        assert env.unwrapped.task_id == task_id
        assert env.unwrapped.action_repeat == 4
        assert not any(isinstance(wrapper, gym.wrappers.TimeLimit) for wrapper in _wrappers(env))
        obs, info = env.reset(seed=0)
        assert obs in env.observation_space
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert info["frames"] == 4
    finally:
        env.close()


def _wrappers(env: gym.Env) -> list[gym.Env]:
    chain = [env]
    while isinstance(chain[-1], gym.Wrapper):
        chain.append(chain[-1].env)
    return chain


BACKEND_CHECK = """
import os, sys
import gymnasium as gym
import numpy as np
finders = list(sys.meta_path)
import sb3_collapse, sb3_collapse.envs
from sb3_collapse.envs import make_dmc_env, rendering
from stable_baselines3.common.vec_env import SubprocVecEnv
hooks = [f for f in sys.meta_path if f not in finders and f.__module__.startswith("sb3_collapse")]
assert not hooks, hooks  # importing the package installs no import hook (absl, editable installs add theirs)
loaded = [m for m in sys.modules if m.split(".")[0] in ("dm_control", "mujoco", "shimmy")]
assert not loaded, loaded
assert "MUJOCO_GL" not in os.environ, "importing the package must not choose the backend"
make_dmc_env("cartpole-balance", obs_type="state").close()  # building an env chooses it
backend = os.environ.get("MUJOCO_GL")
assert backend in (*rendering.HEADLESS_BACKENDS, None), backend  # None: no headless backend on this machine
if backend is not None:
    env = make_dmc_env("cartpole-balance", size=8)
    assert env.reset(seed=0)[0].shape == (9, 8, 8)
    env.close()
    from dm_control import _render
    assert _render.BACKEND == backend, _render.BACKEND

    class Inherited(gym.Env):
        observation_space = action_space = gym.spaces.Box(-1, 1, (1,), np.float32)
        def __init__(self):
            self.mujoco_gl = os.environ.get("MUJOCO_GL")  # before anything in the worker could choose one

    workers = SubprocVecEnv([Inherited])  # a forkserver worker, as the train runner starts them
    assert workers.get_attr("mujoco_gl") == [backend], workers.get_attr("mujoco_gl")
    workers.close()

# A user's MUJOCO_GL is respected: building an env checks nothing and keeps it.
def no_check(*args, **kwargs):
    raise AssertionError("a backend was checked although MUJOCO_GL is set")
os.environ["MUJOCO_GL"], rendering._chosen_backend, rendering._backend_works = "users-choice", None, no_check
make_dmc_env("cartpole-balance", obs_type="state").close()
assert os.environ["MUJOCO_GL"] == "users-choice"
print("backend:", backend)
"""


def test_import_chooses_nothing_and_building_an_env_chooses_the_backend() -> None:
    """In a fresh interpreter: ``import sb3_collapse`` adds no finder to ``sys.meta_path``, imports no dm_control and
    sets no ``MUJOCO_GL``; building an env chooses a headless backend before dm_control is imported, and
    ``SubprocVecEnv`` workers started afterwards inherit it; a ``MUJOCO_GL`` the user set is kept."""
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    result = subprocess.run(
        [sys.executable, "-W", "error::RuntimeWarning", "-c", BACKEND_CHECK],
        env=env,
        check=False,
        timeout=300,
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[-1].startswith("backend: ")


def test_steps_write_no_dm_control_deprecation_and_stdout_only_ours() -> None:
    """In a fresh interpreter, where importing shimmy makes every DeprecationWarning show: steps write nothing to stderr
    (under NumPy >= 2.5, dm_control's named indexing warned at each step; a training process whose stderr is a pipe
    that nobody reads until it ends, as in tests/test_checkpoints.py, then blocked once the pipe was full); shimmy's
    line about its locomotion envs (printed where labmaze is missing, as on Python 3.13) goes to stderr, not stdout."""
    code = (
        "from sb3_collapse.envs import make_dmc_env\n"
        "env = make_dmc_env('cartpole-balance', obs_type='state')\n"
        "env.reset(seed=0)\n"
        "for _ in range(3):\n"
        "    env.step(env.action_space.sample())\n"
        "import sys, warnings\n"
        "print(any(f[0] == 'always' and f[2] is DeprecationWarning and f[3] is None for f in warnings.filters))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], check=False, timeout=300, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == ["True"]  # dm_control.composer's "always", which shows the others
    assert "DeprecationWarning" not in result.stderr, result.stderr
    if importlib.util.find_spec("labmaze") is None:
        assert "registration of `dm_control` locomotion envs has failed" in result.stderr, result.stderr


# ---------------------------------------------------------------- pixel observations


def test_pixel_spaces(make_env) -> None:
    env = make_env("walker-walk", seed=0)
    assert env.observation_space == spaces.Box(0, 255, (9, 84, 84), np.uint8)
    assert env.action_space == spaces.Box(-1.0, 1.0, (6,), np.float32)
    assert (env.domain, env.task_name, env.task_id) == ("walker", "walk", "walker-walk")
    assert (env.action_repeat, env.frame_stack, env.obs_type, env.camera_id) == (2, 3, "pixels", 0)
    obs, info = env.reset()
    assert obs.shape == (9, 84, 84) and obs.dtype == np.uint8
    assert obs in env.observation_space
    assert info == {"frames": 0}
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert obs.shape == (9, 84, 84) and obs.dtype == np.uint8
    assert isinstance(reward, float)
    assert (terminated, truncated, info) == (False, False, {"frames": 2})


def test_non_default_sizes(make_env) -> None:
    env = make_env("cartpole-swingup", frame_stack=2, size=32, action_repeat=8)
    assert env.observation_space.shape == (6, 32, 32)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (6, 32, 32)
    assert env.step(env.action_space.sample())[-1] == {"frames": 8}


def test_reset_fills_the_stack_with_the_first_frame(make_env) -> None:
    env = make_env("walker-walk", seed=0)
    obs, _ = env.reset()
    assert obs[:3].any()
    np.testing.assert_array_equal(obs[:3], obs[3:6])
    np.testing.assert_array_equal(obs[:3], obs[6:9])
    np.testing.assert_array_equal(obs[6:9], env.render().transpose(2, 0, 1))

    action = np.ones(env.action_space.shape, dtype=np.float32)
    next_obs = env.step(action)[0]
    next_next_obs = env.step(action)[0]
    # Oldest frame first: each step shifts the stack by one frame.
    np.testing.assert_array_equal(next_obs[:6], obs[3:])
    np.testing.assert_array_equal(next_next_obs[:6], next_obs[3:])
    np.testing.assert_array_equal(next_next_obs[6:], env.render().transpose(2, 0, 1))
    assert not np.array_equal(next_next_obs[6:], obs[6:])


def test_renders_once_per_agent_step(make_env) -> None:
    env = make_env("walker-walk", seed=0, action_repeat=4)
    render = env._dmc.render
    calls = []
    env._dmc.render = lambda: calls.append(1) or render()
    env.reset()
    assert len(calls) == 1
    for _ in range(5):
        env.step(env.action_space.sample())
    assert len(calls) == 6
    env.render()
    assert len(calls) == 6  # render() returns the last render


def test_quadruped_uses_camera_2(make_env) -> None:
    env = make_env("quadruped-walk", seed=0)
    assert env.camera_id == 2
    obs, _ = env.reset()
    physics = env._dmc._env.physics
    camera_2 = physics.render(height=84, width=84, camera_id=2).transpose(2, 0, 1)
    camera_0 = physics.render(height=84, width=84, camera_id=0).transpose(2, 0, 1)
    np.testing.assert_array_equal(obs[6:], camera_2)
    assert not np.array_equal(obs[6:], camera_0)
    assert make_env("quadruped-walk", camera_id=0, obs_type="state").camera_id == 0


def test_render(make_env) -> None:
    env = make_env("walker-walk", seed=0)
    obs, _ = env.reset()
    frame = env.render()
    assert frame.shape == (84, 84, 3) and frame.dtype == np.uint8
    frame[:] = 0  # a copy: the observation is not affected
    assert env.render().any()
    assert env.metadata["render_modes"] == ["rgb_array"]
    assert env.metadata["render_fps"] == pytest.approx(20.0)  # 0.025 s per frame, 2 frames per agent step


# ---------------------------------------------------------------- dynamics: rewards, actions, time limit


def test_rewards_are_summed_over_the_action_repeat(make_env) -> None:
    env = make_env("walker-walk", seed=3, action_repeat=3, obs_type="state")
    raw = raw_dmc_env("walker", "walk", seed=3)
    obs, _ = env.reset()
    np.testing.assert_array_equal(obs, flat_state(raw.reset().observation))
    rng = np.random.default_rng(0)
    for step in range(1, 11):
        action = rng.uniform(-1, 1, size=env.action_space.shape).astype(np.float32)
        obs, reward, terminated, truncated, info = env.step(action)
        raw_reward = 0.0
        for _ in range(3):
            timestep = raw.step(action.astype(np.float64))
            raw_reward += timestep.reward
        assert reward == pytest.approx(raw_reward, rel=1e-12)
        np.testing.assert_array_equal(obs, flat_state(timestep.observation))
        assert info["frames"] == 3 * step
    assert reward > 0


def test_scale_action() -> None:
    low, high = np.array([-1.0, 0.0, -0.8, -1e3]), np.array([1.0, 2.0, 0.8, 3e3])
    np.testing.assert_array_equal(scale_action(np.full(4, -1.0), low, high), low)
    np.testing.assert_array_equal(scale_action(np.full(4, 1.0), low, high), high)
    np.testing.assert_allclose(scale_action(np.zeros(4), low, high), (low + high) / 2)
    # Clipped to [-1, 1] first.
    np.testing.assert_array_equal(scale_action(np.array([5.0, -5.0, 2.0, -2.0]), low, high), [1.0, 0.0, 0.8, -1e3])
    scaled = scale_action(np.array([0.1, 0.1, 0.1, 0.1], dtype=np.float32), low, high)
    assert scaled.dtype == np.float64
    # Unit bounds leave actions exactly unchanged.
    action = np.random.default_rng(0).uniform(-1, 1, size=100)
    np.testing.assert_array_equal(scale_action(action, -np.ones(100), np.ones(100)), action)


def test_actions_are_rescaled_to_the_task_bounds(make_env) -> None:
    # The quadruped is the suite task with bounds other than [-1, 1] (besides lqr's +-1e10).
    env = make_env("quadruped-walk", seed=0, obs_type="state", action_repeat=1)
    raw = raw_dmc_env("quadruped", "walk", seed=0)
    spec = raw.action_spec()
    assert not (np.all(spec.minimum == -1) and np.all(spec.maximum == 1))
    scaled_raw = action_scale.Wrapper(raw, minimum=-1.0, maximum=1.0)
    obs, _ = env.reset()
    np.testing.assert_array_equal(obs, flat_state(scaled_raw.reset().observation))
    rng = np.random.default_rng(0)
    for _ in range(5):
        action = rng.uniform(-1.5, 1.5, size=env.action_space.shape).astype(np.float32)
        obs, reward, *_ = env.step(action)
        timestep = scaled_raw.step(np.clip(action, -1.0, 1.0).astype(np.float64))
        np.testing.assert_allclose(obs, flat_state(timestep.observation), rtol=1e-5, atol=1e-5)
        assert reward == pytest.approx(timestep.reward, abs=1e-6)
    # The simulator receives the bounds for actions at (or beyond) -1 and 1.
    ctrl = env._dmc._env.physics.data.ctrl
    env.step(np.full(env.action_space.shape, 2.0, dtype=np.float32))
    np.testing.assert_array_equal(ctrl, spec.maximum)
    env.step(np.full(env.action_space.shape, -1.0, dtype=np.float32))
    np.testing.assert_array_equal(ctrl, spec.minimum)


def test_discounts_and_termination(make_env) -> None:
    """Rewards are weighted by the product of earlier discounts; an episode end stops the repeat early."""
    env = make_env("walker-walk", seed=0, obs_type="state", action_repeat=4)
    env.reset()
    observation = env._dmc_observation
    outcomes = iter([(False, 0.5), (False, 0.5), (True, 0.0)])

    def fake_step(action):
        terminated, discount = next(outcomes)
        return observation, 1.0, terminated, False, {"timestep.discount": discount}

    env._dmc.step = fake_step
    _, reward, terminated, truncated, info = env.step(np.zeros(6, dtype=np.float32))
    assert reward == 1.0 + 0.5 + 0.25
    assert (terminated, truncated, info) == (True, False, {"frames": 3})


@pytest.mark.parametrize("action_repeat, n_steps", [(2, 500), (3, 334)])
def test_truncation_at_the_time_limit(make_env, action_repeat: int, n_steps: int) -> None:
    env = make_env("walker-walk", seed=0, obs_type="state", action_repeat=action_repeat)
    env.reset()
    action = np.zeros(env.action_space.shape, dtype=np.float32)
    for step in range(1, n_steps + 1):
        obs, reward, terminated, truncated, info = env.step(action)
        assert not terminated
        assert truncated == (step == n_steps), step
    # walker's time limit is 1000 frames; with action_repeat=3 the last agent step stops after 1 frame.
    assert info["frames"] == 1000
    obs, info = env.reset()
    assert info == {"frames": 0}


def test_pixel_episode_through_gymnasium_make() -> None:
    # Action repeat 25: the whole episode of 1000 frames in 40 rendered agent steps.
    env = gym.make("sb3_collapse/walker-walk-v0", action_repeat=25, size=48)
    try:
        env.reset(seed=0)
        for step in range(1, 41):
            obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
            assert obs.shape == (9, 48, 48)
            assert not terminated
            assert truncated == (step == 40)
        assert info["frames"] == 1000
    finally:
        env.close()


# ---------------------------------------------------------------- true state and state observations


def test_get_state_walker(make_env) -> None:
    env = make_env("walker-walk", seed=0)
    assert env.state_shapes == WALKER_STATE_SHAPES
    assert list(env.state_shapes) == ["orientations", "height", "velocity"]
    with pytest.raises(RuntimeError, match="reset"):
        env.get_state()
    env.reset()
    state = env.get_state()
    assert list(state) == list(WALKER_STATE_SHAPES)
    for name, dim in WALKER_STATE_SHAPES.items():
        assert state[name].shape == (dim,) and state[name].dtype == np.float32
    # Copies: changing them changes nothing.
    state["height"][:] = 123.0
    assert env.get_state()["height"][0] != 123.0
    physics = env._dmc._env.physics
    assert env.get_state()["height"][0] == pytest.approx(physics.torso_height(), rel=1e-6)
    env.step(env.action_space.sample())
    assert env.get_state()["height"][0] == pytest.approx(physics.torso_height(), rel=1e-6)


def test_state_corresponds_to_pixel_observation(make_env) -> None:
    """get_state() of a pixel env equals the state observation of a state env with the same seed and actions."""
    pixel_env = make_env("walker-walk", seed=7)
    state_env = make_env("walker-walk", seed=7, obs_type="state")
    pixel_env.reset()
    state_obs, _ = state_env.reset()
    np.testing.assert_array_equal(np.concatenate(list(pixel_env.get_state().values())), state_obs)
    rng = np.random.default_rng(1)
    for _ in range(5):
        action = rng.uniform(-1, 1, size=6).astype(np.float32)
        pixel_env.step(action)
        state_obs = state_env.step(action)[0]
        np.testing.assert_array_equal(np.concatenate(list(pixel_env.get_state().values())), state_obs)
        np.testing.assert_array_equal(np.concatenate(list(state_env.get_state().values())), state_obs)


def test_state_observations(make_env) -> None:
    env = make_env("walker-walk", seed=0, obs_type="state", frame_stack=5)
    assert env.observation_space == spaces.Box(-np.inf, np.inf, (24,), np.float32)
    assert env.frame_stack == 5  # ignored
    env._dmc.render = lambda: pytest.fail("state observations must not render")
    obs, _ = env.reset()
    assert obs.shape == (24,) and obs.dtype == np.float32
    obs = env.step(env.action_space.sample())[0]
    assert obs.shape == (24,) and obs.dtype == np.float32


def test_state_mode_render_is_fresh(make_env) -> None:
    env = make_env("walker-walk", seed=0, obs_type="state", size=32)
    env.reset()
    frame = env.render()
    assert frame.shape == (32, 32, 3) and frame.dtype == np.uint8


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"obs_type": "rgb"}, "obs_type"),
        ({"action_repeat": 0}, "action_repeat"),
        ({"frame_stack": 0}, "frame_stack"),
        ({"size": 0}, "size"),
        ({"action_repeat": 1.5}, "action_repeat"),
        ({"camera_id": 10}, "camera_id"),
        ({"task": "walker-wlak"}, "walker-wlak"),
    ],
)
def test_invalid_arguments(kwargs: dict, match: str) -> None:
    kwargs = {"task": "walker-walk", "obs_type": "state", **kwargs}
    with pytest.raises(ValueError, match=match):
        make_dmc_env(**kwargs)


def test_step_checks(make_env) -> None:
    env = make_env("walker-walk", obs_type="state")
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(6, dtype=np.float32))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(5, dtype=np.float32))


# ---------------------------------------------------------------- seeding, pickling, closing


def test_reset_seed_determinism(make_env) -> None:
    env = make_env("walker-walk")
    first, _ = env.reset(seed=42)
    other, _ = env.reset(seed=43)
    again, _ = env.reset(seed=42)
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)
    # Seeding at construction is the same as seeding the first reset.
    seeded_at_construction, _ = make_env("walker-walk", seed=42).reset()
    np.testing.assert_array_equal(first, seeded_at_construction)
    # The action space is seeded too.
    env.reset(seed=5)
    sample = env.action_space.sample()
    env.reset(seed=5)
    np.testing.assert_array_equal(sample, env.action_space.sample())


def test_pickle_round_trip(make_env) -> None:
    env = make_env("finger_turn_easy", seed=1, action_repeat=4, obs_type="state")
    clone = pickle.loads(pickle.dumps(env))
    try:
        assert isinstance(clone, DMCEnv)
        assert (clone.task_id, clone.action_repeat, clone.obs_type) == ("finger-turn_easy", 4, "state")
        np.testing.assert_array_equal(clone.reset()[0], env.reset()[0])
    finally:
        clone.close()


def test_close_twice(make_env) -> None:
    env = make_dmc_env("walker-walk", obs_type="state")
    env.reset()
    env.close()
    env.close()


# ---------------------------------------------------------------- API checkers and vectorized envs


def test_gymnasium_check_env() -> None:
    env = gym.make("sb3_collapse/walker-walk-v0")
    try:
        with warnings_as_errors():
            gym_check_env(env.unwrapped)
    finally:
        env.close()


def test_gymnasium_check_env_state() -> None:
    env = gym.make("sb3_collapse/cartpole-swingup-v0", obs_type="state")
    try:
        with warnings_as_errors():
            # Unbounded state observations are intended.
            warnings.filterwarnings("ignore", message=".*observation space (minimum|maximum) value is")
            gym_check_env(env.unwrapped)
    finally:
        env.close()


@pytest.mark.parametrize("obs_type", ["pixels", "state"])
def test_sb3_check_env(make_env, obs_type: str) -> None:
    with warnings_as_errors():
        sb3_check_env(make_env("walker-walk", seed=0, obs_type=obs_type))


def test_dummy_vec_env() -> None:
    vec_env = make_vec_env("sb3_collapse/walker-walk-v0", n_envs=2, seed=0, vec_env_cls=DummyVecEnv)
    try:
        obs = vec_env.reset()
        assert obs.shape == (2, 9, 84, 84) and obs.dtype == np.uint8
        assert not np.array_equal(obs[0], obs[1])  # seeds 0 and 1
        for _ in range(3):
            obs, _, _, infos = vec_env.step(np.stack([vec_env.action_space.sample() for _ in range(2)]))
        assert obs.shape == (2, 9, 84, 84)
        assert [info["frames"] for info in infos] == [6, 6]
        states = vec_env.env_method("get_state")
        assert [{k: v.shape for k, v in s.items()} for s in states] == [
            {"orientations": (14,), "height": (1,), "velocity": (9,)}
        ] * 2
    finally:
        vec_env.close()


def test_subproc_vec_env_default_start_method() -> None:
    """The plain registered id works in forkserver workers (the forkserver preloads sb3_collapse.envs)."""
    vec_env = make_vec_env("sb3_collapse/walker-walk-v0", n_envs=2, seed=0, vec_env_cls=SubprocVecEnv)
    try:
        obs = vec_env.reset()
        assert obs.shape == (2, 9, 84, 84) and obs.dtype == np.uint8
        for _ in range(3):
            obs, _, _, infos = vec_env.step(np.stack([vec_env.action_space.sample() for _ in range(2)]))
        assert [info["frames"] for info in infos] == [6, 6]
        states = vec_env.env_method("get_state")
        assert [list(s) for s in states] == [list(WALKER_STATE_SHAPES)] * 2
        assert vec_env.get_attr("task_id") == ["walker-walk"] * 2
    finally:
        vec_env.close()


def test_subproc_vec_env_spawn_with_module_prefix() -> None:
    """With "spawn", workers import nothing by themselves: "module:id" makes gymnasium import the registering module."""
    vec_env = make_vec_env(
        "sb3_collapse.envs:sb3_collapse/cheetah-run-v0",
        n_envs=2,
        seed=0,
        vec_env_cls=SubprocVecEnv,
        vec_env_kwargs={"start_method": "spawn"},
        env_kwargs={"obs_type": "state"},
    )
    try:
        obs = vec_env.reset()
        assert obs.shape == (2, 17)
        obs, *_ = vec_env.step(np.stack([vec_env.action_space.sample() for _ in range(2)]))
        assert obs.shape == (2, 17)
    finally:
        vec_env.close()


def test_subproc_vec_env_with_callables() -> None:
    vec_env = SubprocVecEnv([lambda rank=rank: make_dmc_env("walker-walk", seed=rank, size=32) for rank in range(2)])
    try:
        assert vec_env.reset().shape == (2, 9, 32, 32)
    finally:
        vec_env.close()


# ---------------------------------------------------------------- reward inputs (the paper's Figure 2 columns)

INF = float("inf")
tol = dm_rewards.tolerance


def _small_control(control: np.ndarray) -> float:
    """The small-control term of hopper-stand, humanoid and point_mass (before its ``(4 + x) / 5``)."""
    return float(tol(control, margin=1, value_at_margin=0, sigmoid="quadratic").mean())


def _quadruped_upright(upright: np.ndarray, deviation_angle: float = 0.0) -> float:
    deviation = np.cos(np.deg2rad(deviation_angle))
    return float(tol(upright, bounds=(deviation, INF), sigmoid="linear", margin=1 + deviation, value_at_margin=0)[0])


def _humanoid(r, model, task, upright: str, stand_height: float) -> float:
    stand = (
        tol(r["head_height"], bounds=(stand_height, INF), margin=stand_height / 4)[0]
        * tol(r[upright], bounds=(0.9, INF), sigmoid="linear", margin=1.9, value_at_margin=0)[0]
    )
    small_control = (4 + _small_control(r["control"])) / 5
    horizontal = np.concatenate([r["com_velocity_x"], r["com_velocity_y"]])
    if task._move_speed == 0:
        return small_control * stand * float(tol(horizontal, margin=2).mean())
    speed = task._move_speed
    move = tol(np.linalg.norm(horizontal), bounds=(speed, INF), margin=speed, value_at_margin=0, sigmoid="linear")
    return small_control * stand * (5 * float(move) + 1) / 6


def _dog(r, model, task) -> float:
    factors = [
        tol(r["torso_pelvis_height"][0], bounds=(task._stand_height[0], INF), margin=task._stand_height[0]),
        tol(r["torso_pelvis_height"][1], bounds=(task._stand_height[1], INF), margin=task._stand_height[1]),
        *tol(r["upright"], bounds=(dog._MIN_UPRIGHT_COSINE, INF), sigmoid="linear",
             margin=dog._MIN_UPRIGHT_COSINE + 1, value_at_margin=0),
        tol(r["touch_sensors"].sum(), bounds=(task._body_weight, INF), margin=task._body_weight, sigmoid="linear",
            value_at_margin=0.9),
    ]  # fmt: skip
    if "com_forward_velocity" in r:
        speed = task._move_speed
        forward = tol(r["com_forward_velocity"][0], bounds=(speed, 2 * speed), margin=max(1.0, speed),
                      value_at_margin=0, sigmoid="linear")  # fmt: skip
        factors.append((4 * forward + 1) / 5)
    if "ball_to_mouth_distance" in r:
        reach = (6 * tol(r["ball_to_mouth_distance"][0], bounds=(0, model.site_size["upper_bite", 0]),
                         sigmoid="reciprocal", margin=2) + 1) / 7  # fmt: skip
        target_radius = model.geom_size["target", 0]
        near = tol(r["ball_to_target_distance"][0], bounds=(0, target_radius), sigmoid="reciprocal",
                   margin=model.geom_size["floor", 0])  # fmt: skip
        factors += [1 if r["ball_to_target_distance"][0] < 2 * target_radius else reach, (near + 1) / 2]
    return float(np.prod(factors))


def _manipulator(r, model, task) -> float:
    def close(distance):
        return float(tol(distance[0], (0, manipulator._CLOSE), manipulator._CLOSE * 2))

    if not task._use_peg:
        return close(r["ball_to_target_ball"])
    grasping = (close(r["peg_grasp_to_grasp"]) + close(r["peg_pinch_to_pinch"])) / 2
    bringing = (close(r["peg_to_target_peg"]) + close(r["target_peg_tip_to_peg_tip"])) / 2
    return max(bringing, grasping / 3)


def _stacker(r, model, task) -> float:
    box_size = model.geom_size["target", 0]
    box_distance = min(r[f"{name}_to_target"][0] for name in task._box_names)
    hand_is_far = tol(r["grasp_to_target"][0], bounds=(0.1, INF), margin=stacker._CLOSE)
    return float(tol(box_distance, margin=2 * box_size) * hand_is_far)


def _fish_swim(r, model, task) -> float:
    radii = model.geom_size[["mouth", "target"], 0].sum()
    in_target = tol(np.linalg.norm(r["mouth_to_target"]), bounds=(0, radii), margin=2 * radii)
    return (7 * in_target + 0.5 * (r["upright"][0] + 1)) / 8


def _walker(r, model, task) -> float:
    stand = (3 * tol(r["torso_height"][0], bounds=(walker._STAND_HEIGHT, INF), margin=walker._STAND_HEIGHT / 2)
             + (1 + r["torso_upright"][0]) / 2) / 4  # fmt: skip
    if task._move_speed == 0:
        return stand
    speed = task._move_speed
    move = tol(r["horizontal_velocity"][0], bounds=(speed, INF), margin=speed / 2, value_at_margin=0.5,
               sigmoid="linear")  # fmt: skip
    return stand * (5 * move + 1) / 6


def _hopper(r, model, task) -> float:
    standing = tol(r["height"][0], (hopper._STAND_HEIGHT, 2))
    if task._hopping:
        speed = hopper._HOP_SPEED
        return standing * tol(r["speed"][0], bounds=(speed, INF), margin=speed / 2, value_at_margin=0.5,
                              sigmoid="linear")  # fmt: skip
    return standing * (_small_control(r["control"]) + 4) / 5


def _cartpole(r, model, task) -> float:
    if task._sparse:
        return (
            tol(r["cart_position"][0], task._CART_RANGE) * tol(r["pole_angle_cosine"], task._ANGLE_COSINE_RANGE).prod()
        )
    upright = (r["pole_angle_cosine"] + 1) / 2
    centered = (1 + tol(r["cart_position"][0], margin=2)) / 2
    small_control = (4 + tol(r["control"], margin=1, value_at_margin=0, sigmoid="quadratic")[0]) / 5
    small_velocity = (1 + tol(r["angular_vel"], margin=5).min()) / 2
    return upright.mean() * small_control * small_velocity * centered


# Each task's reward, rebuilt from its reward inputs alone (the formulas of dm_control's get_reward, its module
# constants, the task's settings and the model's sizes; never the simulator state): r (name -> float64 input),
# model (physics.named.model), task.
REWARD_FROM_INPUTS: dict[str, Callable[[Any, Any, Any], float]] = {
    "acrobot": lambda r, model, task: tol(
        r["to_target"][0], bounds=(0, model.site_size["target", 0]), margin=0 if task._sparse else 1
    ),
    "ball_in_cup": lambda r, model, task: float(
        all(abs(r["ball_to_target"]) < model.site_size["target", [0, 2]] - model.geom_size["ball", 0])
    ),
    "cartpole": _cartpole,
    "cheetah": lambda r, model, task: tol(
        r["speed"][0], bounds=(cheetah._RUN_SPEED, INF), margin=cheetah._RUN_SPEED, value_at_margin=0, sigmoid="linear"
    ),
    "dog": _dog,
    "finger-spin": lambda r, model, task: float(r["hinge_velocity"][0] <= -finger._SPIN_VELOCITY),
    "finger": lambda r, model, task: float(r["dist_to_target"][0] <= 0),
    "fish-upright": lambda r, model, task: tol(r["upright"][0], bounds=(1, 1), margin=1),
    "fish-swim": _fish_swim,
    "hopper": _hopper,
    "humanoid": lambda r, model, task: _humanoid(r, model, task, "torso_upright", humanoid._STAND_HEIGHT),
    "humanoid_CMU": lambda r, model, task: _humanoid(r, model, task, "thorax_upright", humanoid_CMU._STAND_HEIGHT),
    "lqr": lambda r, model, task: 1 - (
        0.5 * r["position"] @ r["position"] + 0.5 * r["control"] @ r["control"] * task._control_cost_coef
    ),
    "manipulator": _manipulator,
    "pendulum": lambda r, model, task: tol(r["pole_vertical"][0], (pendulum._COSINE_BOUND, 1)),
    "point_mass": lambda r, model, task: tol(
        r["mass_to_target_dist"][0], bounds=(0, size := model.geom_size["target", 0]), margin=size
    ) * (_small_control(r["control"]) + 4) / 5,
    "quadruped-escape": lambda r, model, task: _quadruped_upright(r["torso_upright"], 20) * tol(
        r["origin_distance"][0], bounds=(size := model.hfield_size[quadruped._HEIGHTFIELD_ID, 0], INF), margin=size,
        value_at_margin=0, sigmoid="linear",
    ),
    "quadruped-fetch": lambda r, model, task: _quadruped_upright(r["torso_upright"]) * tol(
        r["self_to_ball_distance"][0], bounds=(0, model.site_size["workspace", 0] + model.geom_size["ball", 0]),
        sigmoid="linear", margin=(arena := model.geom_size["floor", 0] * np.sqrt(2)), value_at_margin=0,
    ) * (0.5 + 0.5 * tol(r["ball_to_target_distance"][0], bounds=(0, model.site_size["target", 0]),
                         sigmoid="linear", margin=arena, value_at_margin=0)),
    "quadruped": lambda r, model, task: _quadruped_upright(r["torso_upright"]) * tol(
        r["torso_velocity_x"][0], bounds=(task._desired_speed, INF), margin=task._desired_speed, value_at_margin=0.5,
        sigmoid="linear",
    ),
    "reacher": lambda r, model, task: tol(
        r["finger_to_target_dist"][0], (0, model.geom_size[["target", "finger"], 0].sum())
    ),
    "stacker": _stacker,
    "swimmer": lambda r, model, task: tol(
        r["nose_to_target_dist"][0], bounds=(0, size := model.geom_size["target", 0]), margin=5 * size,
        sigmoid="long_tail",
    ),
    "walker": _walker,
}  # fmt: skip


class _Recorder(dict):
    """A dict that records the keys read from it."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.read: set[str] = set()

    def __getitem__(self, key: str) -> Any:
        self.read.add(key)
        return super().__getitem__(key)


def _to_target(physics, rng: np.random.Generator, kind: str, target: str, effector: str) -> None:
    """Move the target (a model ``geom`` or ``body`` of the world) to near the effector's (``geom`` or ``site``)
    current position."""
    physics.forward()
    position = getattr(physics.named.data, f"{'site' if kind == 'body' else kind}_xpos")[effector]
    getattr(physics.named.model, f"{kind}_pos")[target] = position + rng.normal(0, 0.01, 3)


def _ball_to(physics, rng: np.random.Generator, target: str) -> None:
    """Move the ball (slide joints ``ball_x``, ``ball_z``) to near the ``target`` site."""
    physics.forward()
    data = physics.named.data
    gap = data.site_xpos[target, ["x", "z"]] - data.site_xpos["ball", ["x", "z"]]
    data.qpos[["ball_x", "ball_z"]] += gap + rng.normal(0, 0.01, 2)


def _peg_to_target(physics, rng: np.random.Generator) -> None:
    """Move manipulator's target peg onto the peg (the two bodies have the same sites)."""
    physics.forward()
    physics.named.model.body_pos["target_peg"] = physics.named.data.xpos["peg"] + rng.normal(0, 0.005, 3)
    physics.named.model.body_quat["target_peg"] = physics.named.data.xquat["peg"]


def _joints_near_zero(physics, rng: np.random.Generator, joints: list[str], root_velocity: str | None = None) -> None:
    """Set the joints near 0 (upright, at the origin), and a random forward velocity."""
    physics.named.data.qpos[joints] = rng.normal(0, 0.05, len(joints))
    if root_velocity is not None:
        physics.named.data.qvel[root_velocity] = rng.uniform(0, 4)


def _lqr_near_zero(physics, rng: np.random.Generator) -> None:
    """Set lqr's positions and controls (bounded by +-1e10) near 0, where both costs count."""
    physics.data.qpos[:] = rng.normal(0, 0.5, physics.model.nq)
    physics.data.ctrl[:] = rng.normal(0, 0.5, physics.model.nu)


# Near-goal states, for the rewards that random joint states almost never make non-zero.
GOAL_STATES: dict[str, Callable[[Any, np.random.Generator], None]] = {
    "acrobot": lambda p, rng: _to_target(p, rng, "site", "target", "tip"),
    "ball_in_cup": lambda p, rng: _ball_to(p, rng, "target"),
    "cartpole": lambda p, rng: _joints_near_zero(p, rng, ["slider", "hinge_1"]),
    "hopper": lambda p, rng: _joints_near_zero(p, rng, list(p.named.data.qpos.axes.row.names), "rootx"),
    "lqr": lambda p, rng: _lqr_near_zero(p, rng),
    "manipulator-bring_ball": lambda p, rng: _to_target(p, rng, "body", "target_ball", "ball"),
    "manipulator-insert_ball": lambda p, rng: _to_target(p, rng, "body", "target_ball", "ball"),
    "manipulator-bring_peg": _peg_to_target,
    "manipulator-insert_peg": _peg_to_target,
    "pendulum": lambda p, rng: _joints_near_zero(p, rng, ["hinge"]),
    "point_mass": lambda p, rng: _to_target(p, rng, "geom", "target", "pointmass"),
    "reacher": lambda p, rng: _to_target(p, rng, "geom", "target", "finger"),
    "stacker": lambda p, rng: _to_target(p, rng, "body", "target", "box0"),
}


def _random_states(env, task: str, rng: np.random.Generator, steps: int = 4, states: int = 24) -> Iterator[float]:
    """
    :return: the reward of ``steps`` steps of random actions, then of ``states`` random states (joints at random
        positions, velocities and controls; every other one near the task's goal, :data:`GOAL_STATES`), each as
        ``get_reward`` gives it at the physics state left behind
    """
    physics, spec = env.physics, env.action_spec()
    for _ in range(steps):
        yield float(env.step(rng.uniform(spec.minimum, spec.maximum)).reward)
    random_state = np.random.RandomState(int(rng.integers(2**31)))
    goal = GOAL_STATES.get(task, GOAL_STATES.get(task.split("-")[0]))
    for k in range(states):
        with physics.reset_context():
            randomizers.randomize_limited_and_rotational_joints(physics, random_state)
            physics.data.qvel[:] = rng.normal(0, 0.5 + k / 2, physics.model.nv)
            physics.data.ctrl[:] = rng.uniform(spec.minimum, spec.maximum) * rng.uniform(0, 1.5)
            if goal is not None and k % 2:
                physics.data.qvel[:] /= 10 + k
                goal(physics, rng)
        yield float(env.task.get_reward(physics))


@pytest.mark.parametrize("task", [f"{domain}-{task}" for domain, task in DMC_TASKS])
def test_reward_is_rebuilt_from_the_reward_inputs(task: str) -> None:
    """On states met by random actions and on random joint states, each suite task's reward equals the reward
    rebuilt from its reward inputs alone, and the rebuilt reward reads every one of them."""
    domain, name = parse_task(task)
    rebuild = REWARD_FROM_INPUTS.get(task, REWARD_FROM_INPUTS.get(domain))
    env = suite.load(domain, name, task_kwargs={"random": 0})
    env.reset()
    inputs = reward_inputs_of(domain, name)
    read: set[str] = set()
    rewards = set()
    for reward in _random_states(env, task, np.random.default_rng(0)):
        values = _Recorder({item.name: item.value(env.physics) for item in inputs})
        assert float(rebuild(values, env.physics.named.model, env.task)) == pytest.approx(reward, rel=1e-9, abs=1e-9)
        read |= values.read
        rewards.add(round(reward, 9))
    assert read == {item.name for item in inputs}
    assert len(rewards) >= 2  # the states reach more than one reward


def test_reward_inputs_are_per_task() -> None:
    """Every suite task has its own entry; tasks of one domain whose rewards read different quantities differ."""
    assert set(REWARD_INPUTS) == {f"{domain}-{task}" for domain, task in DMC_TASKS}

    def names(task):
        return [item.name for item in reward_inputs_of(*parse_task(task))]

    assert names("hopper-stand") == ["height", "control"] and names("hopper-hop") == ["height", "speed"]
    assert names("walker-stand") == ["torso_height", "torso_upright"]
    assert names("walker-walk") == names("walker-run") == ["torso_height", "torso_upright", "horizontal_velocity"]
    assert names("cartpole-balance_sparse") == ["cart_position", "pole_angle_cosine"]
    assert reward_inputs_of("walker", "no_such_task") == ()


@pytest.mark.parametrize(
    "task, expected",
    [
        ("walker-walk", ["torso_height", "torso_upright", "horizontal_velocity"]),
        ("walker-stand", ["torso_height", "torso_upright"]),
        ("hopper-stand", ["height"]),  # its reward's other input, the control, is the action
    ],
)
def test_env_reward_inputs_are_the_state_ones(make_env, task: str, expected: list[str]) -> None:
    """DMCEnv.reward_inputs gives the state reward inputs (not the control), as float32 values of their Physics
    methods at the current timestep."""
    env = make_env(task, seed=3, obs_type="state", action_repeat=1)
    with pytest.raises(RuntimeError, match="reset"):
        env.reward_inputs()
    env.reset(seed=3)
    env.step(env.action_space.sample())
    inputs = env.reward_inputs()
    assert list(inputs) == expected
    for name, value in inputs.items():
        assert value.dtype == np.float32
        np.testing.assert_array_equal(value, np.float32(getattr(env.physics, name)()).reshape(-1))
