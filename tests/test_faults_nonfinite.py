"""
Non-finite data and weights: a NaN reward or observation from an environment, a NaN in a replay chunk whose CRC-32
matches, a model zip holding NaN weights. Each is named as what it is and where it came from, in one line, and never
blamed on the learning rate or written into a checkpoint.
"""

from __future__ import annotations

import io
import json
import math
import zipfile
import zlib
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from sb3_collapse import DrQv2, make_dmc_env
from sb3_collapse.commands.probe import main as probe_main
from sb3_collapse.commands.train import main
from sb3_collapse.drqv2.replay_buffer import FrameStackReplayBuffer
from sb3_collapse.errors import NonFiniteDataError
from sb3_collapse.protocol import CHECKPOINTS_DIR, RESULT_JSON
from sb3_collapse.run import runner
from sb3_collapse.run.checkpoints import checkpoint_folders
from tests.random_env import RandomObservationEnv
from tests.test_faults import _flags, _unfinished_run


@pytest.fixture(autouse=True)
def _keep_torch_threads():
    threads = th.get_num_threads()
    yield
    th.set_num_threads(threads)


class NaNAt(gym.Wrapper):
    """Returns a NaN reward (or, ``observation=True``, a NaN in the observation) at its ``step``-th step."""

    def __init__(self, env: gym.Env, step: int, observation: bool = False) -> None:
        super().__init__(env)
        self.at, self.observation, self.steps = step, observation, 0

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.steps += 1
        if self.steps == self.at:
            if self.observation:
                obs = np.array(obs, dtype=np.float32)
                obs.flat[3] = math.nan
            else:
                reward = math.nan
        return obs, reward, terminated, truncated, info


def test_a_nan_reward_of_an_environment_is_refused_before_it_is_stored():
    env = NaNAt(RandomObservationEnv(gym.spaces.Box(0, 255, (3, 16, 16), np.uint8), episode_length=50), step=30)
    model = DrQv2(
        "CnnPolicy", env, buffer_size=100, learning_starts=10, batch_size=4, seed=0,
        policy_kwargs=dict(hidden_dim=16, feature_dim=8), replay_buffer_class=FrameStackReplayBuffer,
        replay_buffer_kwargs=dict(frame_stack=1),
    )  # fmt: skip
    with pytest.raises(NonFiniteDataError) as error:
        model.learn(60)
    assert str(error.value) == (
        "env 0 returned a reward that is not finite (nan), refused before it was stored: bad data from the "
        "environment, not a divergence of the training."
    )
    assert model.num_timesteps == 30 and model.replay_buffer.transitions_added == 29
    assert np.isfinite(model.replay_buffer.rewards).all()


def test_a_nan_observation_is_refused_before_anything_of_its_transition_is_stored():
    space = gym.spaces.Box(-1.0, 1.0, (2, 4, 4), np.float32)  # float frames, 2 stacked
    buffer = FrameStackReplayBuffer(10, space, gym.spaces.Box(-1, 1, (1,), np.float32), frame_stack=2, n_envs=2)
    obs = np.zeros((2, 2, 4, 4), np.float32)
    next_obs = np.concatenate([obs[:, 1:], np.ones((2, 1, 4, 4), np.float32)], axis=1)
    next_obs[1, -1, 2, 2] = math.nan
    with pytest.raises(NonFiniteDataError, match=r"^env 1 returned an observation that is not finite \(nan\), refused"):
        buffer.add(obs, next_obs, np.zeros((2, 1)), np.zeros(2), np.zeros(2), [{}, {}])
    assert buffer.transitions_added == 0 and buffer.pos == 0 and not buffer.frame_heads.any()


def _nan_env(monkeypatch, step: int) -> None:
    """The run's training env returns a NaN reward at its ``step``-th step."""
    original = runner._monitored_dmc_env

    def monitored(task_id, seed, pixels, worker=False):
        env = original(task_id, seed, pixels, worker)
        env.env = NaNAt(env.env, step)  # inside EpisodeReplay: its records see what the env returned
        return env

    monkeypatch.setattr(runner, "_monitored_dmc_env", monitored)


def test_a_run_whose_environment_returns_a_nan_reward_names_it_and_keeps_its_finite_checkpoint(
    tmp_path, monkeypatch, capsys
):
    run_dir = tmp_path / "run"
    _nan_env(monkeypatch, step=25)  # frame 500: after the checkpoint at frame 400
    assert main(_flags(run_dir)) == 1
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1, error
    kept = checkpoint_folders(run_dir / CHECKPOINTS_DIR)
    assert error[0] == (
        "error: cartpole-balance at agent step 25 (frame 500): env 0 returned a reward that is not finite (nan), "
        "refused before it was stored: bad data from the environment, not a divergence of the training. The run "
        f"stops; its last checkpoint, {kept[0]}, holds none of it. A rerun meets it again: fix the environment, or "
        "train another --seed in another run folder."
    )
    assert "--lr" not in error[0] and kept[0].name == "step_000000000020"
    assert not (run_dir / RESULT_JSON).exists()


def _first_reward_offset(chunk: dict, layout: dict) -> int:
    """Byte offset in a replay chunk file of its first transition's reward (replay_checkpoint's chunk layout: per
    segment, each transition array's rows in turn: frame_starts, actions, rewards, ...)."""
    arrays = layout["arrays"]
    n_envs = layout["n_envs"]
    per_row = {
        name: int(np.prod(arrays[name]["shape"][2:], dtype=np.int64)) * np.dtype(arrays[name]["dtype"]).itemsize
        for name in ("frame_starts", "actions", "rewards")
    }
    offset = 0
    for segment in chunk["segments"]:
        rows = segment["stop"] - segment["start"]
        if segment["ring"] == "transitions":
            return offset + rows * n_envs * (per_row["frame_starts"] + per_row["actions"])
        frame = arrays["frames"]
        offset += rows * int(np.prod(frame["shape"][2:])) * np.dtype(frame["dtype"]).itemsize
    raise AssertionError("no transitions segment")


def test_a_replay_chunk_holding_a_nan_with_a_matching_crc_is_named_and_the_run_restarts_clean(
    tmp_path, monkeypatch, capsys
):
    """The chunk both checkpoints share gets a NaN reward and a CRC-32 that matches it (as a version that stored an
    env's NaN would have written it): each checkpoint is set aside naming the chunk and the array, the run restarts
    from frame 0 and finishes."""
    run_dir = tmp_path / "run"
    _unfinished_run(run_dir)
    capsys.readouterr()
    checkpoints = checkpoint_folders(run_dir / CHECKPOINTS_DIR)
    infos = [json.loads((folder / "checkpoint.json").read_text()) for folder in checkpoints]
    chunk = infos[0]["replay"]["store"]["chunks"][0]
    path = run_dir / CHECKPOINTS_DIR / "replay" / chunk["file"]
    data = bytearray(path.read_bytes())
    offset = _first_reward_offset(chunk, infos[0]["replay"]["store"]["layout"])
    data[offset : offset + 4] = np.float32(math.nan).tobytes()
    path.write_bytes(bytes(data))
    for folder, info in zip(checkpoints, infos, strict=True):
        for listed in info["replay"]["store"]["chunks"]:
            if listed["file"] == chunk["file"]:
                listed["crc32"] = zlib.crc32(bytes(data))
        (folder / "checkpoint.json").write_text(json.dumps(info))

    assert main(_flags(run_dir)) == 0
    out = capsys.readouterr().out
    notes = [line for line in out.splitlines() if line.startswith("Note: Every checkpoint")]
    assert len(notes) == 1, out
    assert f"The replay checkpoint chunk {path} holds a non-finite value (nan) in its rewards, though its CRC-32 " \
        "matches: it was written so" in notes[0]  # fmt: skip
    assert "the run restarts from frame 0" in notes[0]
    result = json.loads((run_dir / RESULT_JSON).read_text())
    assert result["frames"] == 800 and result["resumes"] == 0


def _nan_weights_zip(path: Path, task: str = "walker-walk", **pixels) -> Path:
    """A DrQv2 zip of ``task`` whose actor's first MLP weight holds a NaN (as a diverged run's would)."""
    env = make_dmc_env(task, seed=0, **pixels)
    model = DrQv2("CnnPolicy", env, buffer_size=10, seed=0, policy_kwargs=dict(hidden_dim=16, feature_dim=8))
    with th.no_grad():
        model.actor.mlp1[0].weight[0, 0] = math.nan
    model.save(path)
    env.close()
    return path


@pytest.mark.parametrize("command", [[], ["record"], ["film"]])
def test_probe_refuses_a_model_with_non_finite_weights_in_one_line(tmp_path, capsys, command):
    model = _nan_weights_zip(tmp_path / "diverged.zip", action_repeat=8, size=32)
    out = tmp_path / ("out.npz" if command == ["record"] else "out")
    status = probe_main([*command, str(model), "--out", str(out), "--no-progress"])
    error = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(error) == 1, error
    assert error[0] == (
        f"error: {model} holds weights that are not finite: 'actor.mlp1.0.weight' has 1 NaN or infinite value(s) of "
        "{:,} (a diverged model); give a checkpoint saved before it diverged.".format(
            th.load(io.BytesIO(zipfile.ZipFile(model).read("policy.pth")), weights_only=True)[
                "actor.mlp1.0.weight"
            ].numel()
        )
    )
    assert not out.exists()


def test_a_physics_error_from_a_non_finite_action_is_one_line(tmp_path, monkeypatch, capsys):
    """The weights check off, the NaN action reaches MuJoCo while rollouts are recorded: one line, exit status 1,
    no file."""
    from sb3_collapse.probe import checkpoints

    model = _nan_weights_zip(tmp_path / "diverged.zip", action_repeat=8, size=32)
    from sb3_collapse.drqv2 import sb3_compat

    for module in (checkpoints, sb3_compat):  # the probe's check, and DrQv2.load's
        monkeypatch.setattr(module, "check_finite_weights", lambda *args: None)
    out = tmp_path / "rollouts.npz"
    assert probe_main(["record", str(model), "--episodes", "3", "--out", str(out), "--no-progress"]) == 1
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and error[0].startswith(
        "error: MuJoCo could not step frame 1 of the episode with the action"
    )
    assert "the action is not finite (a diverged policy?) (PhysicsError: Physics state is invalid." in error[0]
    assert not out.exists()


def test_train_refuses_to_transplant_non_finite_weights_before_writing_anything(tmp_path, capsys):
    source = _nan_weights_zip(tmp_path / "diverged.zip", "cartpole-balance", action_repeat=20, size=36)
    run_dir = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_info:
        main([*_flags(run_dir), "--init-mlp", str(source)])
    error = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2
    assert error[-1].startswith(f"python -m sb3_collapse.train: error: --init-mlp = '{source}' holds weights that are ")
    assert "'actor.mlp1.0.weight' has 1 NaN or infinite value(s)" in error[-1]
    assert not run_dir.exists()


class NaNReset(gym.Wrapper):
    """Returns an observation holding a NaN at its ``reset``-th reset (an episode's first observation, which the actor
    reads before anything of it is stored)."""

    def __init__(self, env: gym.Env, reset: int) -> None:
        super().__init__(env)
        self.at, self.resets = reset, 0

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.resets += 1
        if self.resets == self.at:
            obs = np.array(obs, dtype=np.float32)
            obs.flat[1] = math.nan
        return obs, info


def test_a_nan_first_observation_after_the_warmup_is_the_environment_s_not_a_divergence():
    env = NaNReset(RandomObservationEnv(gym.spaces.Box(-1.0, 1.0, (5,), np.float32), episode_length=20), reset=2)
    model = DrQv2("MlpPolicy", env, buffer_size=100, learning_starts=10, batch_size=4, seed=0,
                  policy_kwargs=dict(hidden_dim=16))  # fmt: skip
    with pytest.raises(NonFiniteDataError, match=r"^env 0 returned an observation that is not finite \(nan\)"):
        model.learn(40)
    assert model.num_timesteps == 20  # the step that would have acted on it was not taken


def test_drqv2_load_refuses_a_zip_with_non_finite_weights(tmp_path):
    from sb3_collapse.errors import InputError

    env = RandomObservationEnv(gym.spaces.Box(-1.0, 1.0, (5,), np.float32), episode_length=20)
    model = DrQv2("MlpPolicy", env, buffer_size=100, learning_starts=10, batch_size=4, seed=0,
                  policy_kwargs=dict(hidden_dim=16))  # fmt: skip
    with th.no_grad():
        next(model.actor.parameters()).view(-1)[0] = math.nan
    model.save(tmp_path / "diverged.zip")
    with pytest.raises(InputError, match=r"diverged\.zip holds weights that are not finite: 'actor\."):
        DrQv2.load(tmp_path / "diverged.zip")
