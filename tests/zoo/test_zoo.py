import argparse
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml

pytest.importorskip("rl_zoo3")

import rl_zoo3.train
from rl_zoo3.exp_manager import ExperimentManager
from stable_baselines3.common.callbacks import EvalCallback
from stable_baselines3.common.vec_env import VecTransposeImage, is_vecenv_wrapped

from sb3_collapse import CollapseMetrics, CollapseReset, DrQv2
from sb3_collapse.commands.zoo import collapse_callbacks, main
from sb3_collapse.drqv2 import FrameStackReplayBuffer
from sb3_collapse.errors import InputError
from sb3_collapse.zoo import register_with_zoo
from sb3_collapse.zoo.experiment import ZooExperimentManager

CONFIG = Path(__file__).resolve().parents[2] / "zoo_configs" / "drqv2.yml"
WALKER = "sb3_collapse/walker-walk-v0"
# The pages rendered by the env dominate the tiny runs: action repeat 25 makes episodes of 40 agent steps.
TINY_ENV = {"action_repeat": 25, "frame_stack": 3, "size": 32}
TINY = {
    "n_timesteps": 32,
    "learning_starts": 16,
    "buffer_size": 200,
    "batch_size": 8,
    "policy_kwargs": "dict(feature_dim=16, hidden_dim=32)",
    "env_kwargs": TINY_ENV,
    # The tiny runs end before their first episode: DrQ-v2's sampling (finished episodes only) would not update.
    "replay_buffer_kwargs": "dict(sampling='sb3')",
}

# DrQ-v2's published settings (facebookresearch/drqv2 cfgs/task/*.yaml), in frames, per task.
EASY = [
    "walker_walk",
    "walker_stand",
    "hopper_stand",
    "finger_spin",
    "cartpole_balance",
    "cartpole_balance_sparse",
    "cartpole_swingup",
    "cup_catch",
    "pendulum_swingup",
]
MEDIUM = [
    "walker_run",
    "hopper_hop",
    "cheetah_run",
    "quadruped_walk",
    "quadruped_run",
    "acrobot_swingup",
    "cartpole_swingup_sparse",
    "finger_turn_easy",
    "finger_turn_hard",
    "reacher_easy",
    "reacher_hard",
]
HARD = ["humanoid_stand", "humanoid_walk", "humanoid_run"]  # fmt: skip


def load_config(path=CONFIG) -> dict:
    with open(path) as file:
        return yaml.safe_load(file)


def env_entries() -> list[str]:
    return [key for key in load_config() if key != "templates"]


def tiny_config(tmp_path: Path, **changes) -> Path:
    """The walker-walk entry of the shipped file, with a tiny budget, network and image."""
    entry = {**load_config()[WALKER], **TINY, **changes}
    path = tmp_path / "tiny.yml"
    path.write_text(yaml.safe_dump({WALKER: entry}))
    return path


def experiment(tmp_path, config, env_id=WALKER, manager=ZooExperimentManager, **kwargs) -> ZooExperimentManager:
    register_with_zoo()
    settings = {"log_folder": str(tmp_path / "logs"), "eval_freq": -1, "n_eval_episodes": 1, "seed": 0, "verbose": 0}
    settings.update(kwargs)
    return manager(argparse.Namespace(), "drqv2", env_id, config=str(config), **settings)


def zoo_id(task: str) -> str:
    domain, _, name = task.partition("_")
    for long_domain in ("ball_in_cup",):
        if task.startswith(long_domain):
            domain, name = long_domain, task[len(long_domain) + 1 :]
    return f"sb3_collapse/{domain}-{name}-v0"


def test_config_has_drqv2_published_settings():
    config = load_config()
    assert all(key in gym.registry for key in env_entries())
    tiers = [(EASY, 550_000, 100_000), (MEDIUM, 1_550_000, 500_000), (HARD, 15_050_000, 2_000_000)]
    for tasks, agent_steps, std_steps in tiers:
        for task in tasks:
            entry = config[zoo_id(task)] if task != "cup_catch" else config["sb3_collapse/cup-catch-v0"]
            walker, humanoid = task.startswith("walker"), task.startswith("humanoid")
            assert entry["n_timesteps"] == agent_steps, task  # frames / action repeat 2
            assert entry["buffer_size"] == (100_000 if task == "quadruped_run" else min(1_000_000, agent_steps))
            assert entry["stddev_schedule"] == f"linear(1.0,0.1,{std_steps})"
            assert (entry["batch_size"], entry["n_steps"]) == ((512, 1) if walker else (256, 3))
            assert entry["learning_rate"] == (8e-5 if humanoid else 1e-4)
            assert eval(entry["policy_kwargs"]) == {"feature_dim": 100 if humanoid else 50, "hidden_dim": 1024}
            assert entry["env_kwargs"] == {"action_repeat": 2, "frame_stack": 3, "size": 84}
            assert (entry["learning_starts"], entry["train_freq"], entry["gradient_steps"]) == (2000, 2, 1)
            assert (entry["tau"], entry["gamma"], entry["stddev_clip"]) == (0.01, 0.99, 0.3)
    assert config["sb3_collapse/ball_in_cup-catch-v0"] == config["sb3_collapse/cup-catch-v0"]
    assert len(env_entries()) == len(EASY + MEDIUM + HARD) + 1


@pytest.mark.parametrize("env_id", env_entries())
def test_every_entry_builds_a_model(tmp_path, env_id, monkeypatch):
    # Real entries through rl_zoo3's ExperimentManager path: env (84x84 DMC), preprocessing and DrQv2 with the
    # entry's networks. Speed-ups: the orthogonal weight init (QR of the 1024x1024 layers, ~2 s per model) is
    # skipped, and the replay buffer is capped at 100,000 transitions so that a 1M buffer (21.5 GB, reserved
    # lazily) needs no such memory on small machines; the full walker-walk entry is built in the next test.
    monkeypatch.setattr(th.nn.init, "orthogonal_", lambda tensor, gain=1.0: tensor)
    entry = load_config()[env_id]
    buffer_size = min(entry["buffer_size"], 100_000)
    manager = experiment(tmp_path, CONFIG, env_id, hyperparams={"buffer_size": buffer_size})
    model, saved = manager.setup_experiment()
    assert isinstance(model, DrQv2)
    assert manager.n_timesteps == entry["n_timesteps"]
    assert model.batch_size == entry["batch_size"] and model.n_steps == entry["n_steps"]
    assert model.learning_starts == 2000 and model.train_freq.frequency == 2 and model.gradient_steps == 1
    assert model.lr_schedule(1.0) == pytest.approx(entry["learning_rate"])
    duration = int(entry["stddev_schedule"].rstrip(")").split(",")[-1])
    assert model.stddev_schedule(0) == 1.0 and model.stddev_schedule(duration) == pytest.approx(0.1)
    assert model.policy_kwargs == eval(entry["policy_kwargs"])
    assert model.actor.trunk[0].out_features == model.policy_kwargs["feature_dim"]
    assert model.observation_space.shape == (9, 84, 84)
    assert not is_vecenv_wrapped(model.env, VecTransposeImage)
    assert model.env_config["action_repeat"] == 2 and model.env_config["frame_stack"] == 3
    assert isinstance(model.replay_buffer, FrameStackReplayBuffer) and model.replay_buffer.buffer_size == buffer_size
    assert saved["stddev_schedule"] == entry["stddev_schedule"]
    model.env.close()


def test_full_entry_builds_with_its_buffer(tmp_path):
    model, _ = experiment(tmp_path, CONFIG).setup_experiment()
    assert model.buffer_size == 550_000 and model.replay_buffer.buffer_size == 550_000
    assert model.critic.q1[0].in_features == 50 + 6 and model.actor.mlp2[0].out_features == 1024
    model.env.close()


def test_eval_env_gets_the_training_pixels(tmp_path):
    manager = experiment(tmp_path, tiny_config(tmp_path), eval_freq=10, eval_env_kwargs={"render_mode": None})
    model, _ = manager.setup_experiment()
    (evaluation,) = [callback for callback in manager.callbacks if isinstance(callback, EvalCallback)]
    assert evaluation.eval_env.observation_space == model.env.observation_space
    assert model.observation_space.shape == (9, 32, 32)
    assert evaluation.eval_env.get_attr("size") == [32] and evaluation.eval_env.get_attr("action_repeat") == [25]
    assert evaluation.eval_env.get_attr("render_mode") == [None]  # --eval-env-kwargs still apply, key by key
    assert model.env.get_attr("render_mode") == ["rgb_array"]
    for env in (model.env, evaluation.eval_env):
        assert not is_vecenv_wrapped(env, VecTransposeImage)
        env.close()

    different = experiment(tmp_path, tiny_config(tmp_path), eval_freq=10, eval_env_kwargs={"size": 64})
    with pytest.raises(InputError, match="size: 32 in training, 64 in evaluation"):
        different.setup_experiment()


def test_transposed_pixels_are_refused(tmp_path):
    # 3 * frame_stack > size: SB3 takes the smallest axis (the 8 pixels) for the channels.
    manager = experiment(tmp_path, tiny_config(tmp_path, env_kwargs={**TINY_ENV, "size": 8}))
    with pytest.warns(UserWarning, match="channels-last"), pytest.raises(InputError, match=r"size >= 3 \* frame"):
        manager.setup_experiment()


def test_reset_rule_adds_the_collapse_callbacks(tmp_path):
    manager_class = ZooExperimentManager.with_callbacks(collapse_callbacks(collapse_metrics=True, reset_rule=True))
    config = tiny_config(tmp_path, callback=[{"sb3_collapse.monitoring.CollapseReset": {"window_frames": 400}}])
    manager = experiment(tmp_path, config, manager=manager_class)
    model, saved = manager.setup_experiment()
    configured, metrics, reset = manager.callbacks
    assert isinstance(configured, CollapseReset) and configured.window_frames == 400
    assert isinstance(metrics, CollapseMetrics) and metrics.check_every_frames == 10_000
    assert isinstance(reset, CollapseReset) and reset.window_frames == 200_000 and reset.threshold == 1e-3
    assert [next(iter(spec)) for spec in saved["callback"]] == [
        "sb3_collapse.monitoring.CollapseReset", "sb3_collapse.monitoring.CollapseMetrics",
        "sb3_collapse.monitoring.CollapseReset",
    ]  # fmt: skip
    model.env.close()


def test_launcher_trains_and_enjoys(tmp_path, capsys):
    logs = tmp_path / "logs"
    args = ["--algo", "drqv2", "--env", WALKER, "-conf", str(tiny_config(tmp_path)), "-f", str(logs), "--seed", "0",
            "--eval-freq", "32", "--eval-episodes", "1", "--num-threads", "1"]  # fmt: skip
    assert main(["train", *args, "--collapse-metrics", "--reset-rule"]) == 0
    assert rl_zoo3.train.ExperimentManager is ExperimentManager and sys.argv[0] != "python -m sb3_collapse.zoo train"
    run = logs / "drqv2" / "sb3_collapse-walker-walk-v0_1"
    params = run / "sb3_collapse-walker-walk-v0"
    assert {"sb3_collapse-walker-walk-v0.zip", "best_model.zip", "evaluations.npz", "0.monitor.csv"} <= {
        path.name for path in run.iterdir()
    }
    with open(params / "config.yml") as file:
        config = yaml.load(file, Loader=yaml.UnsafeLoader)
    assert config["env_kwargs"] == TINY_ENV and config["stddev_schedule"] == "linear(1.0,0.1,100000)"
    assert len(config["callback"]) == 2
    with open(params / "args.yml") as file:
        assert yaml.load(file, Loader=yaml.UnsafeLoader)["algo"] == "drqv2"
    evaluations = np.load(run / "evaluations.npz")
    assert evaluations["timesteps"].tolist() == [32] and evaluations["ep_lengths"].tolist() == [[40]]

    model = DrQv2.load(run / "sb3_collapse-walker-walk-v0.zip")
    assert model.num_timesteps == 32 and model.num_frames == 800 and model._n_updates == 8
    assert model.env_config["size"] == 32 and model.policy_kwargs == {"feature_dim": 16, "hidden_dim": 32}

    # Continuing from the saved agent (-i): rl_zoo3 passes the config's stddev_schedule string to DrQv2.load.
    assert (
        main(["train", *args, "-n", "8", "--eval-freq", "-1", "-i", str(run / "sb3_collapse-walker-walk-v0.zip")]) == 0
    )
    assert (
        DrQv2.load(logs / "drqv2" / "sb3_collapse-walker-walk-v0_2" / "sb3_collapse-walker-walk-v0.zip").num_timesteps
        == 8
    )

    capsys.readouterr()
    assert (
        main(
            [
                "enjoy",
                "--exp-id",
                "1",
                "--algo",
                "drqv2",
                "--env",
                WALKER,
                "-f",
                str(logs),
                "-n",
                "45",
                "--num-threads",
                "1",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "sb3_collapse-walker-walk-v0.zip" in out and "Episode Length 40" in out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["bogus"], "unknown sub-command 'bogus'"),
        ([], "missing sub-command"),
        (["train", "--algo", "drqv2", "--env", WALKER], "-conf zoo_configs/drqv2.yml"),
        (["train", "--algo", "drqv2", "--env", WALKER, "-conf", "missing.yml"], "-conf missing.yml is not a file"),
        (["train", "--algo", "drqv2", "--env", WALKER, "-conf", str(CONFIG), "-optimize"], "no hyperparameter sampler"),
        (["enjoy", "--algo", "drqv2", "--reset-rule"], "train options"),
    ],
)
def test_bad_command_lines(argv, message, capsys):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize(
    ("env_id", "params", "message"),
    [
        ("sb3_collapse/cheetah-run-v0", [], "has no entry for sb3_collapse/cheetah-run-v0; add one"),
        (WALKER, ["-params", "frame_stack:4"], "env_kwargs: {frame_stack: ...}"),
        (WALKER, ["-params", "normalize:True"], "remove normalize"),
        (WALKER, ["-params", "stddev_schedule:'linear(1.0)'"], "stddev_schedule"),
    ],
)
def test_bad_configs(tmp_path, env_id, params, message, capsys):
    argv = ["train", "--algo", "drqv2", "--env", env_id, "-conf", str(tiny_config(tmp_path)), "-f", str(tmp_path)]
    assert main([*argv, *params]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "drqv2").exists()  # refused before any run folder is made


def test_missing_rl_zoo3(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "rl_zoo3", None)
    assert main(["train", "--algo", "drqv2"]) == 2
    assert "pip install -e '.[zoo]'" in capsys.readouterr().err


def test_help(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "{train,enjoy}" in out and "--reset-rule" in out and "agent steps" in out and "--no-render" in out
    assert main(["train", "--help"]) == 0
    assert "--conf-file" in capsys.readouterr().out  # rl_zoo3's own options follow


def test_zoo_train_sets_the_train_commands_cuda_flags(monkeypatch):
    # Building a model leaves torch's process-wide flags alone; the zoo's train command sets them as `train` does.
    from sb3_collapse.backends import configure_backends, current_backends
    from sb3_collapse.commands.zoo import run_train

    before = current_backends()
    benchmark_before = th.backends.cudnn.benchmark
    seen = {}

    def fake_train() -> None:
        seen["settings"] = current_backends()
        seen["benchmark"] = th.backends.cudnn.benchmark

    monkeypatch.setattr(rl_zoo3.train, "train", fake_train)
    configure_backends(tf32=False, deterministic=True)
    try:
        run_train(["--algo", "drqv2"], [])
    finally:
        configure_backends(tf32=before.tf32, deterministic=before.deterministic)
        th.backends.cudnn.benchmark = benchmark_before
    assert seen["settings"].tf32 and not seen["settings"].deterministic
    assert seen["benchmark"] is True


def test_the_config_command_without_pyyaml_says_what_to_install(monkeypatch, tmp_path, capsys):
    from sb3_collapse.zoo import config

    monkeypatch.setitem(sys.modules, "yaml", None)  # import yaml raises ImportError
    assert config.main([str(tmp_path / "drqv2.yml")]) == 1
    assert capsys.readouterr().err == "error: pyyaml cannot be imported: pip install -e '.[zoo]' (or pyyaml)\n"
    assert not (tmp_path / "drqv2.yml").exists()
