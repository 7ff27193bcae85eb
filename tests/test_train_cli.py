import csv
import json
import shutil

import numpy as np
import pytest
import torch as th
from stable_baselines3 import SAC
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from sb3_collapse import DrQv2
from sb3_collapse.commands.train import main
from sb3_collapse.paper import PAPER, evaluation_schedule
from sb3_collapse.run.config import TrainConfig
from sb3_collapse.run.runner import train
from tests.shared_runs import TINY_WALKER_RUN


def test_train_end_to_end(tiny_walker_run, tmp_path_factory, tmp_path):
    # The session's tiny run (tests/conftest.py: walker-walk, 800 frames at action repeat 20, evaluated every 400).
    config = TrainConfig(**TINY_WALKER_RUN, logdir=str(tmp_path_factory.getbasetemp() / "tiny_walker_run"))
    result = tiny_walker_run
    assert result.run_dir == tmp_path_factory.getbasetemp() / "tiny_walker_run" / "walker-walk_s0"
    with open(result.run_dir / "eval.csv") as file:
        rows = list(csv.DictReader(file))
    # The scheduled evaluations (the reference's: frame 0, then every 400 frames, none at the budget's end).
    assert [int(row["frame"]) for row in rows] == evaluation_schedule(800, 400, 20) == [0, 400]
    assert [int(row["step"]) for row in rows] == [0, 20]
    assert all(np.isfinite(float(row["mean_reward"])) for row in rows)
    saved_config = json.loads((result.run_dir / "config.json").read_text())
    assert saved_config["frames"] == 800 and saved_config["variant"] == "drqv2" and saved_config["transplant"] is None
    summary = json.loads((result.run_dir / "result.json").read_text())
    assert summary == result.summary
    assert summary["status"] == "finished" and summary["task"] == "walker-walk" and summary["variant"] == "drqv2"
    assert summary["seed"] == 0 and summary["frames"] == 800 and summary["agent_steps"] == 40
    assert summary["final_eval"] == {
        "frame": 400, "mean_reward": float(rows[-1]["mean_reward"]), "std_reward": float(rows[-1]["std_reward"])
    }
    # The saved model's evaluation, at the budget's end, is labelled apart: not a row of eval.csv.
    final_model = summary["saved_model_eval"]
    assert final_model["frame"] == 800 and final_model["episodes"] == 1 and np.isfinite(final_model["mean_reward"])
    assert result.saved_model_evaluation["frame"] == 800 and len(result.evaluations) == 2
    assert summary["resets"] == 0 and summary["reset_frames"] == [] and summary["escaped"] is None
    assert summary["escape_frame"] is None and summary["wall_time_s"] > 0
    assert not (result.run_dir / "collapse_events.csv").exists()  # no reset rule
    assert not list(result.run_dir.glob("*.tmp"))

    model = DrQv2.load(result.model_path)
    assert model.num_timesteps == 40 and model.num_frames == 800
    assert model.env_config["task_id"] == "walker-walk" and model.env_config["action_repeat"] == 20
    assert model.learning_starts == 20 and model._n_updates == 10

    events = list(result.run_dir.glob("events.out.tfevents.*"))
    accumulator = EventAccumulator(str(events[0]))
    accumulator.Reload()
    assert [e.step for e in accumulator.Scalars("eval/mean_reward")] == [0, 20]
    assert [e.step for e in accumulator.Scalars("eval_saved_model/mean_reward")] == [40]

    # A second run with the same name gets its own folder (beside a copy of the first: the session's stays as it is).
    shutil.copytree(result.run_dir, tmp_path / "walker-walk_s0")
    changes = {"frames": 80, "eval_every_frames": 0, "snapshots": False, "logdir": str(tmp_path), "torch_threads": None}
    second = train(TrainConfig(**{**config.__dict__, **changes}))
    assert second.run_dir == tmp_path / "walker-walk_s0_2"
    assert second.evaluations == []


def test_train_with_collapse_metrics_and_reset_rule(tmp_path):
    config = TrainConfig(
        env="walker-walk", frames=800, action_repeat=8, seed_frames=160, batch_size=8, hidden_dim=32,
        eval_every_frames=0, logdir=str(tmp_path), progress_bar=False, collapse_metrics_every_frames=400,
        collapse_metrics_batch=16, reset_rule=True, stddev_schedule="linear(1.0,0.1,50)", replay_sampling="sb3",
    )
    result = train(config)
    # The rule's window by default: the frame at which the std schedule ends, 50 agent steps x 8 frames.
    assert json.loads((result.run_dir / "config.json").read_text())["reset_window_frames"] == 400
    accumulator = EventAccumulator(str(next(result.run_dir.glob("events.out.tfevents.*"))))
    accumulator.Reload()
    tags = set(accumulator.Tags()["scalars"])
    assert {"collapse/mlp1/numerical_rank", "collapse/mlp1/grad_norm", "collapse/action_std"} <= tags
    # One check per window of 400 frames: 5 healthy checks in a row cannot happen before the window ends.
    assert [e.value for e in accumulator.Scalars("collapse/resets")][-1] >= 1

    # The same facts in the run folder's CSV files and result.json.
    with open(result.run_dir / "collapse_metrics.csv") as file:
        metric_rows = list(csv.DictReader(file))
    assert list(metric_rows[0]) == ["frame", "step", "tag", "value"]
    assert {int(row["frame"]) for row in metric_rows} == {400, 800} and {row["step"] for row in metric_rows} == {
        "50",
        "100",
    }
    logged = accumulator.Scalars("collapse/mlp1/grad_norm")  # TensorBoard stores float32
    in_csv = [row for row in metric_rows if row["tag"] == "collapse/mlp1/grad_norm"]
    assert [int(row["step"]) for row in in_csv] == [e.step for e in logged]
    assert [float(row["value"]) for row in in_csv] == pytest.approx([e.value for e in logged], rel=1e-6)
    with open(result.run_dir / "collapse_events.csv") as file:
        events = list(csv.DictReader(file))
    summary = json.loads((result.run_dir / "result.json").read_text())
    resets = [int(row["frame"]) for row in events if row["event"] == "reset"]
    assert resets == summary["reset_frames"] and len(resets) == summary["resets"] >= 1
    assert summary["escaped"] is False and summary["escape_frame"] is None and summary["variant"] == "drqv2+reset"
    assert summary["final_eval"] is None and summary["saved_model_eval"] is None  # no evaluation


def test_train_into_an_exact_run_dir(tmp_path):
    run_dir = tmp_path / "sweep" / "walker-walk" / "cnn-good_mlp-bad" / "seed_3"
    config = TrainConfig(
        env="walker_walk", frames=48, action_repeat=8, size=32, seed=3, seed_frames=400, eval_every_frames=0,
        collapse_metrics_every_frames=0, run_dir=str(run_dir), progress_bar=False, torch_threads=1,
        variant="cnn-good_mlp-bad", transplant={"cnn": "good", "mlp": "bad"},
    )
    result = train(config)
    assert result.run_dir == run_dir and not (tmp_path / "runs").exists()
    assert json.loads((run_dir / "config.json").read_text())["transplant"] == {"cnn": "good", "mlp": "bad"}
    summary = json.loads((run_dir / "result.json").read_text())
    assert summary["variant"] == "cnn-good_mlp-bad" and summary["task"] == "walker-walk" and summary["seed"] == 3
    assert summary["frames"] == 48 and summary["agent_steps"] == 6
    # A finished run's folder is refused, with what to do; so is a folder that holds something else.
    with pytest.raises(ValueError, match="holds a finished run .result.json.: choose another folder"):
        train(config)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("not a run")
    with pytest.raises(ValueError, match="not an empty folder .nor the folder of a run.: remove it or choose another"):
        train(TrainConfig(**{**config.__dict__, "run_dir": str(tmp_path / "other")}))

    # Layer transplants: the encoder and the actor of that model, the critic blank.
    transplanted = train(
        TrainConfig(**{**config.__dict__, "run_dir": str(tmp_path / "transplanted"), "init_cnn": str(result.model_path),
                       "init_mlp": str(run_dir / "final_model"), "variant": None, "transplant": None})
    )  # fmt: skip
    assert DrQv2.load(transplanted.model_path).init_from == {
        "cnn": str(result.model_path),
        "mlp": str(result.model_path),
    }
    assert json.loads((transplanted.run_dir / "config.json").read_text())["init_mlp"] == str(run_dir / "final_model")


def test_help_documents_units(monkeypatch, capsys):
    monkeypatch.setenv("COLUMNS", "80")  # the width of `python -m sb3_collapse.train --help` into a pipe
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    for flag in ("--frames", "--eval-every-frames", "--seed-frames", "--stddev-schedule", "--buffer-size", "--logdir"):
        assert flag in out
    assert "in frames" in out and "agent steps" in out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--env", "walker-wlak"], "walker-walk"),
        (["--frames", "0"], "--frames must be >= 1"),
        (["--stddev-schedule", "linear(1,0.1)"], "stddev schedule"),
        (["--eval-episodes", "0"], "--eval-episodes must be >= 1"),
        (["--torch-threads", "0"], "--torch-threads must be >= 1"),
        (["--init-mlp", "missing.zip"], "--init-mlp: init_from['mlp']: checkpoint 'missing.zip' does not exist"),
        (["--intervention", "redo"], "--intervention='redo' is what the reset rule does: set --reset-rule"),
        (["--algorithm", "td3", "--size", "32"], "--size must be >= 36 pixels for algorithm='td3' (SB3's NatureCNN)"),
        (["--algorithm", "sac", "--init-cnn", "x.zip"], "layer transplants are for DrQ-v2 checkpoints"),
        (["--algorithm", "ppo"], "invalid choice: 'ppo'"),
        (["--algorithm", "td3", "--activation", "leaky_relu"], "is a DrQ-v2 option; algorithm='td3' keeps SB3's ReLU"),
        (["--activation", "gelu"], "invalid choice: 'gelu'"),
        (["--redo-every-updates", "-1"], "must be >= 0 (0: no ReDo), got -1"),
    ],
)
def test_bad_arguments_exit_with_a_message(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_train_sb3_sac_with_an_intervention(tmp_path):
    # 20 agent steps of 25 frames; the rule's window of 200 frames ends at frames 200 and 400.
    config = TrainConfig(
        env="cartpole-balance", algorithm="sac", reset_rule=True, intervention="shrink_perturb", frames=500,
        action_repeat=25, size=48, hidden_dim=32, feature_dim=16, batch_size=8, seed_frames=100, eval_every_frames=500,
        eval_episodes=1, collapse_metrics_every_frames=200, collapse_metrics_batch=4, reset_window_frames=200,
        run_dir=str(tmp_path / "run"), progress_bar=False, torch_threads=1,
    )
    assert config.variant_name == "sac+shrink_perturb"
    result = train(config)
    saved = json.loads((result.run_dir / "config.json").read_text())
    assert (saved["algorithm"], saved["intervention"], saved["variant"]) == (
        "sac",
        "shrink_perturb",
        "sac+shrink_perturb",
    )
    assert result.summary["frames"] == 500 and result.summary["resets"] == 2
    assert [row["frame"] for row in result.evaluations] == [0]  # 500 is the budget: the final model's evaluation
    assert result.summary["saved_model_eval"]["frame"] == 500
    with open(result.run_dir / "collapse_events.csv") as file:
        events = list(csv.DictReader(file))
    assert [row["intervention"] for row in events] == ["shrink_perturb", "shrink_perturb"]
    assert events[0]["detail"].startswith("theta <- 0.8 theta + 0.2 theta_0 (toward a fresh init) on the actor, critic")
    with open(result.run_dir / "collapse_metrics.csv") as file:
        tags = {row["tag"] for row in csv.DictReader(file)}
    assert {"collapse/mlp1/grad_norm", "collapse/mlp1/dormant_ratio", "collapse/action_std"} <= tags
    model = SAC.load(result.model_path)
    assert model.num_timesteps == 20 and model.actor.latent_pi[0].out_features == 32
    assert TrainConfig(algorithm="td3").variant_name == "td3"
    assert TrainConfig(reset_rule=True).variant_name == "drqv2+reset"


def test_train_with_parallel_envs(tmp_path, capsys):
    """--n-envs 2: subprocess envs, frames summed over them, one update per 2 transitions, the timings in
    result.json. The command's main in this process: the environments' processes are the subprocesses."""
    threads = th.get_num_threads()
    status = main(
        ["--env", "walker-walk", "--frames", "320", "--action-repeat", "20",
         "--size", "48", "--seed-frames", "160", "--batch-size", "8", "--hidden-dim", "32", "--n-envs", "2",
         "--eval-every-frames", "320", "--eval-episodes", "1", "--collapse-metrics-every-frames", "0",
         "--replay-sampling", "sb3",
         "--run-dir", str(tmp_path / "run"), "--torch-threads", "1", "--no-progress-bar"],
    )  # fmt: skip
    th.set_num_threads(threads)
    assert status == 0
    out = capsys.readouterr().out
    assert "summed over 2 envs" in out
    summary = json.loads((tmp_path / "run" / "result.json").read_text())
    assert summary["frames"] == 320 and summary["agent_steps"] == 16
    assert json.loads((tmp_path / "run" / "config.json").read_text())["n_envs"] == 2
    timings = summary["timings"]
    assert timings["warmup"]["transitions"] == 8 and timings["learning"]["transitions"] == 8
    assert timings["learning"]["updates"] == 16 // 2 - 8 // 2
    assert timings["learning"]["env_s"] > 0 and timings["first_round_updates"] == 1
    model = DrQv2.load(tmp_path / "run" / "final_model.zip")
    assert model.n_envs == 2 and model._n_updates == 4 and model.num_frames == 320
    with open(tmp_path / "run" / "eval.csv") as file:  # the single evaluation env, at frame 0 (320: the final model)
        assert [int(row["frame"]) for row in csv.DictReader(file)] == [0]
    assert summary["saved_model_eval"]["frame"] == 320
    with pytest.raises(ValueError, match=r"n_envs=2 is a DrQv2 option"):
        TrainConfig(algorithm="sac", n_envs=2).validate()


def test_evaluation_schedule_is_the_references():
    # The paper's budget: frames 0, 10k, ..., 1.09M, its x in [0, 109]; none at 1.1M (the final model's, apart).
    schedule = evaluation_schedule(PAPER.train_frames, PAPER.check_every_frames, frames_per_step=2)
    assert schedule == list(range(0, 1_100_000, 10_000)) and len(schedule) == PAPER.evaluations == 110
    assert schedule[-1] == 1_090_000
    # An evaluation falls on the first agent step at or after its frame (action repeat 8 does not divide 300).
    assert evaluation_schedule(1000, 300, frames_per_step=8) == [0, 304, 600, 904]
    assert evaluation_schedule(800, 400, frames_per_step=8) == [0, 400]
    with pytest.raises(ValueError, match="every_frames"):
        evaluation_schedule(800, 0)


def test_train_leaky_relu_with_periodic_redo(tmp_path):
    """The Leaky-ReLU ablation and ReDo every 3 updates: recorded in the settings, the saved model and the logs."""
    config = TrainConfig(
        env="cartpole-balance", activation="leaky_relu", redo_every_updates=3, frames=500, action_repeat=25, size=48,
        hidden_dim=32, feature_dim=16, batch_size=8, seed_frames=100, eval_every_frames=0,
        collapse_metrics_every_frames=0, collapse_metrics_batch=8, replay_sampling="sb3", run_dir=str(tmp_path / "run"),
        progress_bar=False, torch_threads=1,
    )  # fmt: skip
    assert config.variant_name == "drqv2-leaky+redo_periodic"
    result = train(config)
    saved = json.loads((result.run_dir / "config.json").read_text())
    assert (saved["activation"], saved["redo_every_updates"], saved["variant"]) == (
        "leaky_relu", 3, "drqv2-leaky+redo_periodic"
    )  # fmt: skip
    model = DrQv2.load(result.model_path)
    assert model.policy_kwargs["activation"] == "leaky_relu"
    assert isinstance(model.policy.critic.q1[1], th.nn.LeakyReLU)
    with open(result.run_dir / "progress.csv") as file:
        recycles = [row["redo/recycles"] for row in csv.DictReader(file) if row.get("redo/recycles")]
    assert recycles and int(float(recycles[-1])) >= 2  # 8 updates (from step 4, one per 2 steps): at 3 and 6


def test_train_draws_no_progress_bar_into_a_captured_stream(tmp_path, capfd):
    argv = ["--env", "walker-walk", "--frames", "80", "--action-repeat", "20", "--seed-frames", "40", "--batch-size",
            "8", "--hidden-dim", "32", "--eval-every-frames", "0", "--logdir", str(tmp_path)]  # fmt: skip
    assert main(argv) == 0  # the progress bar is on by default; stdout and stderr are not terminals
    captured = capfd.readouterr()
    text = captured.out + captured.err
    assert "\r" not in text and "━" not in text and "%|" not in text
