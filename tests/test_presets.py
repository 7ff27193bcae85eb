"""Per-task presets: the table, the train CLI and the sweep use them, explicit settings override and are recorded."""

import json
from pathlib import Path

import pytest

from sb3_collapse.commands.cli import training_settings
from sb3_collapse.commands.sweep import build_parser as sweep_parser
from sb3_collapse.commands.train import build_parser, main
from sb3_collapse.drqv2 import StddevSchedule
from sb3_collapse.paper import PAPER
from sb3_collapse.presets import PRESETS, SETTING_NAMES, preset, reset_window_frames
from sb3_collapse.run.config import TrainConfig, drqv2_kwargs
from sb3_collapse.run.runner import train
from sb3_collapse.sweep.plan import sweep_plan
from sb3_collapse.sweep.runner import settings_changes, sweep_settings
from sb3_collapse.sweep.trials import expand_trials, trial_config
from sb3_collapse.zoo.config import render_zoo_config

REPO_ROOT = Path(__file__).resolve().parents[1]


def test_table_holds_drqv2_published_configs():
    # facebookresearch/drqv2 cfgs/task/*.yaml, pinned here as literals.
    walker, hopper, cheetah, humanoid = (
        preset(t) for t in ("walker_walk", "hopper-stand", "cheetah-run", "humanoid-walk")
    )
    assert (walker.tier, walker.frames, walker.batch_size, walker.n_steps) == ("easy", 1_100_000, 512, 1)
    assert (hopper.batch_size, hopper.n_steps, hopper.stddev_schedule) == (256, 3, "linear(1.0,0.1,100000)")
    assert (cheetah.tier, cheetah.frames, cheetah.stddev_schedule) == ("medium", 3_100_000, "linear(1.0,0.1,500000)")
    assert (humanoid.frames, humanoid.learning_rate, humanoid.feature_dim) == (30_100_000, 8e-5, 100)
    assert preset("quadruped-run").buffer_size == 100_000 and preset("walker-run").batch_size == 512
    assert preset("cup-catch") is PRESETS["ball_in_cup-catch"]
    assert len(PRESETS) == 23 and all(p.from_drqv2 and p.replay_sampling == "drqv2" for p in PRESETS.values())
    assert {p.seed_frames for p in PRESETS.values()} == {4000} and {p.eval_every_frames for p in PRESETS.values()} == {
        10_000
    }
    fallback = preset("dog-run")  # a suite task DrQ-v2 did not run: the easy tier, marked
    assert fallback.from_drqv2 is False and fallback.tier == "easy" and fallback.frames == 1_100_000
    with pytest.raises(ValueError, match="walker-walk"):
        preset("walker-wlak")


def test_zoo_config_is_generated_from_the_table():
    assert (REPO_ROOT / "zoo_configs" / "drqv2.yml").read_text() == render_zoo_config(), (
        "zoo_configs/drqv2.yml is out of date: run python -m sb3_collapse.zoo.config zoo_configs/drqv2.yml"
    )


def _sweep_trial_configs(tmp_path, *flags, variants=("drqv2",)):
    tasks = ["walker-walk", "hopper-stand", "cheetah-run", "humanoid-walk"]
    args = sweep_parser().parse_args(["--tasks", *tasks, "--seeds", "1", "--out", str(tmp_path), *flags])
    training = training_settings(args)
    trials = expand_trials(args.tasks, list(variants), range(args.seeds))
    return training, trials, {trial.task: trial_config(trial, tmp_path, training) for trial in trials}


def test_sweep_gives_each_task_its_preset(tmp_path):
    training, trials, configs = _sweep_trial_configs(tmp_path)
    walker, hopper, cheetah, humanoid = (
        configs[t] for t in ("walker-walk", "hopper-stand", "cheetah-run", "humanoid-walk")
    )
    assert (walker.batch_size, walker.n_steps, walker.replay_sampling) == (512, 1, "drqv2")
    assert (hopper.batch_size, hopper.n_steps, hopper.replay_sampling) == (256, 3, "drqv2")
    assert (cheetah.frames, cheetah.stddev_schedule) == (3_100_000, "linear(1.0,0.1,500000)")
    assert (humanoid.learning_rate, humanoid.feature_dim) == (8e-5, 100)
    assert walker.buffer_size == 550_000  # the preset's 1M, capped at the run's agent steps
    assert all(source == "preset" for config in configs.values() for source in config.sources.values())
    assert set(walker.sources) == set(SETTING_NAMES)
    settings = sweep_settings(trials, training, {}, {})
    assert settings["training"]["batch_size"] is None  # left to the presets...
    assert settings["task_settings"]["walker-walk"]["batch_size"] == 512  # ...which are recorded per task


def test_sweep_flag_overrides_every_task_and_is_recorded(tmp_path):
    training, trials, configs = _sweep_trial_configs(tmp_path, "--batch-size", "64", "--n-steps", "2")
    assert {(c.batch_size, c.n_steps) for c in configs.values()} == {(64, 2)}
    assert configs["humanoid-walk"].learning_rate == 8e-5  # the other settings keep each task's preset
    record = configs["walker-walk"].record()
    assert record["sources"]["batch_size"] == "user" and record["sources"]["n_steps"] == "user"
    assert record["sources"]["learning_rate"] == "preset" and record["preset"] == {
        "task": "walker-walk", "tier": "easy", "from_drqv2": True
    }
    # Resuming the sweep folder with other settings is refused, naming the setting.
    previous = sweep_settings(trials, training, {}, {})
    current = sweep_settings(trials, {**training, "batch_size": None}, {}, {})
    assert any(change.startswith("`batch_size`: 64") for change in settings_changes(previous, current))


def test_the_rules_window_is_the_tasks_exploration_end(tmp_path):
    # Proposition 1: m is "the frames where the exploration decreases to the smallest": the agent step at which the
    # preset's std schedule reaches its final value, times the action repeat.
    cheetah = preset("cheetah-run")
    end = StddevSchedule(cheetah.stddev_schedule).end_step * cheetah.action_repeat
    assert (cheetah.tier, end) == ("medium", 500_000 * 2)
    assert reset_window_frames("cheetah-run") == end and reset_window_frames("humanoid-walk") == 4_000_000
    assert reset_window_frames("walker-walk") == reset_window_frames("finger-spin") == PAPER.window_frames == 200_000
    assert reset_window_frames("cheetah-run", "0.2") == PAPER.window_frames  # a constant std has no end to read
    # The runner's settings (resolve), the sweep's trials and its plan take it; the flag overrides it.
    assert TrainConfig(env="cheetah-run").resolve().reset_window_frames == end
    assert TrainConfig(env="cheetah-run", action_repeat=4).resolve().reset_window_frames == 2 * end  # the run's repeat
    assert TrainConfig(env="cheetah-run", reset_window_frames=300_000).resolve().reset_window_frames == 300_000
    _, trials, configs = _sweep_trial_configs(tmp_path, variants=("drqv2+reset",))
    assert {task: c.reset_window_frames for task, c in configs.items()} == {
        "walker-walk": 200_000, "hopper-stand": 200_000, "cheetah-run": end, "humanoid-walk": 4_000_000
    }  # fmt: skip
    plan = sweep_plan({trial: configs[trial.task] for trial in trials}, {})
    assert plan["reset_window_frames"]["cheetah-run/drqv2+reset"] == end
    _, _, given = _sweep_trial_configs(tmp_path, "--reset-window-frames", "300000", variants=("drqv2+reset",))
    assert {c.reset_window_frames for c in given.values()} == {300_000}


def test_train_records_values_and_sources(tmp_path):
    config = TrainConfig(
        env="walker-walk", frames=64, action_repeat=8, size=32, hidden_dim=32, eval_every_frames=0,
        collapse_metrics_every_frames=0, run_dir=str(tmp_path / "run"), progress_bar=False, torch_threads=1,
    )
    train(config)
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["batch_size"] == 512 and saved["n_steps"] == 1 and saved["replay_sampling"] == "drqv2"
    assert saved["sources"]["batch_size"] == "preset" and saved["sources"]["frames"] == "user"
    assert saved["sources"]["hidden_dim"] == "user" and saved["preset"]["tier"] == "easy"
    assert saved["buffer_size"] == 8  # the preset's, capped at the run's 8 agent steps


def test_cli_defaults_are_the_task_preset(capsys):
    assert main(["--env", "humanoid-walk", "--show-settings"]) == 0
    out = capsys.readouterr().out
    assert "--lr" in out and "8e-05  (preset)" in out and "--feature-dim" in out and "100  (preset)" in out
    assert main(["--env", "humanoid-walk", "--lr", "0.001", "--show-settings"]) == 0
    assert "0.001  (user)" in capsys.readouterr().out
    help_text = build_parser().format_help()
    assert "preset" in help_text and "docs/presets.md" in help_text


@pytest.mark.parametrize("task", ["walker-walk", "hopper-stand", "cheetah-run", "quadruped-run", "humanoid-walk"])
def test_a_presets_drqv2_kwargs_are_the_train_commands(task):
    # What `train --env TASK --seed 3` gives DrQv2 (its parsed flags, resolved), against the library's one call.
    arguments = vars(build_parser().parse_args(["--env", task, "--seed", "3"]))
    config = TrainConfig(**{name: value for name, value in arguments.items() if name != "show_settings"}).resolve()
    command = drqv2_kwargs(config)
    library = preset(task).drqv2_kwargs(seed=3)
    run_only = {"device", "verbose", "step_envs_during_updates", "compile_update", "init_from"}
    assert {**library, "policy_kwargs": {**library["policy_kwargs"], "activation": "relu"}} == {
        name: value for name, value in command.items() if name not in run_only
    }
    assert library["buffer_size"] == min(preset(task).buffer_size, preset(task).frames // preset(task).action_repeat)
    assert preset(task).env_kwargs() == {"action_repeat": config.action_repeat, "frame_stack": config.frame_stack}


def test_a_presets_drqv2_kwargs_take_a_budget_and_overrides():
    walker = preset("walker-walk")
    kwargs = walker.drqv2_kwargs(frames=6_000, seed=1, batch_size=32)
    assert (kwargs["buffer_size"], kwargs["batch_size"], kwargs["seed"], kwargs["n_steps"]) == (3_000, 32, 1, 1)
    assert (kwargs["learning_starts"], kwargs["train_freq"]) == (2_000, (2, "transition"))
    assert kwargs["replay_buffer_kwargs"] == {"sampling": "drqv2"}
