"""
Bad input and faults (issue 16): each refused early with a one-line message naming what to fix, exit status 2 from
the command lines, no traceback, and nothing written or lost.
"""

import json
import os
import signal
import subprocess
import sys
import time
import zipfile

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import PPO
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor

from sb3_collapse import CollapseReset, DrQv2, make_dmc_env
from sb3_collapse.commands.probe import main as probe_main
from sb3_collapse.commands.report import main as report_main
from sb3_collapse.commands.sweep import main as sweep_main
from sb3_collapse.commands.train import main as train_main
from sb3_collapse.commands.zoo import main as zoo_main
from sb3_collapse.protocol import ERROR_TXT, failed_before_training
from sb3_collapse.run.config import TrainConfig
from sb3_collapse.run.runner import train
from tests.random_env import RandomObservationEnv

TINY = ["--env", "cartpole-balance", "--frames", "400", "--seed-frames", "200", "--batch-size", "16",
        "--eval-every-frames", "400", "--eval-episodes", "1", "--collapse-metrics-every-frames", "0", "--size", "48",
        "--hidden-dim", "64", "--no-progress-bar", "--torch-threads", "1"]  # fmt: skip


def tiny_config(run_dir, **changes):
    settings = dict(
        env="cartpole-balance", frames=400, seed_frames=200, batch_size=16, eval_every_frames=400, eval_episodes=1,
        collapse_metrics_every_frames=0, size=48, hidden_dim=64, progress_bar=False, torch_threads=1,
        run_dir=str(run_dir), replay_sampling="sb3",
    )  # fmt: skip
    return TrainConfig(**{**settings, **changes})


def _default_sigint() -> None:
    """In a child before it runs Python: SIGINT at its default, so that Python installs its own handler."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def one_line_error(capsys, prog="python -m sb3_collapse.train"):
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.startswith((f"{prog}: error:", "error:"))]
    assert len(lines) == 1, err
    return lines[0]


@pytest.fixture(scope="module")
def bad_checkpoints(tmp_path_factory):
    folder = tmp_path_factory.mktemp("checkpoints")
    (folder / "text.zip").write_text("not a zip")
    other = DrQv2("CnnPolicy", make_dmc_env("walker-walk", size=48), buffer_size=10, policy_kwargs=dict(hidden_dim=64))
    other.save(folder / "walker.zip")  # 6 actions where cartpole has 1
    (folder / "truncated.zip").write_bytes((folder / "walker.zip").read_bytes()[:5000])
    PPO("MlpPolicy", RandomObservationEnv(gym.spaces.Box(-1, 1, (3,), np.float32)), n_steps=8, batch_size=8).save(
        folder / "ppo.zip"
    )
    return folder


@pytest.mark.filterwarnings("ignore:The replay buffer of 1,000,000,000 transitions will not fit")
@pytest.mark.parametrize(
    "argv, message",
    [
        (["--init-cnn", "{ckpt}/text.zip"], "--init-cnn = '{ckpt}/text.zip' is not a zip file"),
        (["--init-mlp", "{ckpt}/truncated.zip"], "truncated.zip' is not a zip file (corrupt or truncated?)"),
        (["--init-mlp", "{ckpt}/ppo.zip"], "ppo.zip"),
        (["--init-mlp", "{ckpt}/walker.zip"], "action"),
        (["--device", "tpu"], "--device must be 'auto', 'cpu', 'cuda'"),
        (["--lr", "-1"], "--lr must be a finite number > 0, got -1.0."),
        (["--lr", "nan"], "--lr must be a finite number > 0, got nan."),
        (["--stddev-clip", "-1"], "--stddev-clip must be a finite number >= 0, got -1.0."),
        (["--size", "5"], "--size must be >= 15 pixels"),
        (["--buffer-size", "1000000000"], "Pass a smaller --buffer-size"),
        (["--seed", "-1"], "--seed must be an integer >= 0, got -1."),
        (["--logdir", "{tmp}/afile"], "--logdir {tmp}/afile: {tmp}/afile is a file, not a folder."),
        (["--batch-size", "0"], "--batch-size must be an integer >= 1, got 0."),
        (["--reset-window-frames", "0"], "--reset-window-frames: window_frames must be >= 1 frame, got 0."),
    ],
)
def test_train_refuses_bad_input_before_writing(argv, message, bad_checkpoints, tmp_path, capsys):
    (tmp_path / "afile").write_text("")
    fill = {"ckpt": str(bad_checkpoints), "tmp": str(tmp_path)}
    argv = [arg.format(**fill) for arg in argv]
    with pytest.raises(SystemExit) as exit_info:
        train_main([*TINY, "--run-dir", str(tmp_path / "run"), *argv])
    assert exit_info.value.code == 2
    assert message.format(**fill) in one_line_error(capsys)
    assert not (tmp_path / "run").exists() and not (tmp_path / "runs").exists()


def test_failure_after_the_folder_exists_marks_it_and_a_rerun_is_not_blocked(tmp_path, monkeypatch):
    run_dir = tmp_path / "run"

    def broken_learn(self, *args, **kwargs):
        raise OSError("No space left on device")

    with monkeypatch.context() as patch:
        patch.setattr(DrQv2, "learn", broken_learn)
        with pytest.raises(OSError, match="No space left"):
            train(tiny_config(run_dir, eval_every_frames=0))
    error = (run_dir / ERROR_TXT).read_text()
    assert error.startswith("failed at agent step 0 (frame 0)\n") and "No space left on device" in error
    assert failed_before_training(run_dir) and not (run_dir / "result.json").exists()
    result = train(tiny_config(run_dir, frames=64, eval_every_frames=0))  # the same folder is taken again
    assert result.run_dir == run_dir and not (run_dir / ERROR_TXT).exists()
    assert json.loads((run_dir / "result.json").read_text())["status"] == "finished"
    # A folder that trained (here: finished) is never taken over.
    with pytest.raises(ValueError, match="run_dir .* holds a finished run"):
        train(tiny_config(run_dir, frames=64))


def test_final_model_is_the_evaluated_one_when_a_window_ends_with_the_budget(tmp_path):
    # The window (400 frames) ends at the budget's last frame: the rule must not reset the model it then saves.
    # Action repeat 20: episodes (and evaluations) of 50 agent steps.
    config = tiny_config(tmp_path / "run", reset_rule=True, reset_window_frames=400, action_repeat=20)
    result = train(config)
    summary = result.summary
    assert (
        summary["resets"] == 0 and summary["saved_model_eval"]["frame"] == 400 and summary["final_eval"]["frame"] == 0
    )
    model = DrQv2.load(result.model_path)
    assert model.reset_step == 0 and model._n_updates > 0
    # Re-evaluate the saved model as the run did: a fresh eval env seeded as the reference's (the run's seed), the
    # frame-0 evaluation's episode first.
    eval_env = Monitor(make_dmc_env("cartpole-balance", seed=config.seed, size=48, action_repeat=20))
    evaluate_policy(model, eval_env, n_eval_episodes=1, deterministic=True)
    rewards, _ = evaluate_policy(model, eval_env, n_eval_episodes=1, deterministic=True, return_episode_rewards=True)
    assert float(np.mean(rewards)) == pytest.approx(summary["saved_model_eval"]["mean_reward"], rel=1e-6)


def test_library_values_are_checked_where_they_are_owned():
    env = RandomObservationEnv(gym.spaces.Box(-1, 1, (3,), np.float32))
    for kwargs, message in [
        (dict(batch_size=0), "batch_size must be an integer >= 1, got 0."),
        (dict(learning_starts=-1), "learning_starts must be an integer >= 0, got -1."),
        (dict(learning_rate=float("nan")), "learning_rate must be a finite number > 0, got nan."),
        (dict(gamma=1.5), "gamma must be a finite number >= 0 and <= 1, got 1.5."),
        (dict(device="cuda:0") if not __import__("torch").cuda.is_available() else dict(seed=-1), "GPU|seed"),
    ]:
        with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
            DrQv2("MlpPolicy", env, buffer_size=10, **kwargs)
    for kwargs, message in [
        (dict(threshold=-1), "threshold must be >= 0"),
        (dict(threshold=float("nan")), "threshold must be a finite number, got nan."),
        (dict(layer="nope"), "layer must be one of cnn0, cnn1"),
    ]:
        with pytest.raises(ValueError, match=message):
            CollapseReset(**kwargs)
    with pytest.raises(FileNotFoundError, match=r"no model file 'missing.zip'; give the path of a zip"):
        DrQv2.load("missing.zip")


def test_sweep_refuses_bad_input_before_writing(tmp_path, capsys):
    (tmp_path / "afile").write_text("")
    base = ["--tasks", "walker-walk", "--variants", "drqv2"]
    cases = [
        ([*base, "--seeds", "1", "--out", str(tmp_path / "afile")], "--out {tmp}/afile: {tmp}/afile is a file"),
        ([*base, "--seed-list", "1", "1", "--out", str(tmp_path / "s")], "seeds lists 1 more than once"),
        (
            [*base, "--seeds", "1", "--cpus-per-trial", "0", "--out", str(tmp_path / "s")],
            "--cpus-per-trial must be > 0",
        ),
        (
            [*base, "--seeds", "1", "--eval-every-frames", "0", "--out", str(tmp_path / "s")],
            "--eval-every-frames=0 turns",
        ),
    ]
    for argv, message in cases:
        with pytest.raises(SystemExit) as exit_info:
            sweep_main(argv)
        assert exit_info.value.code == 2
        assert message.format(tmp=tmp_path) in one_line_error(capsys, "python -m sb3_collapse.sweep")
        assert not (tmp_path / "s").exists()


def test_probe_and_report_refuse_bad_input_before_writing(tmp_path, capsys):
    checkpoint = tmp_path / "agent.zip"
    DrQv2("CnnPolicy", make_dmc_env("walker-walk", size=48), buffer_size=10, policy_kwargs=dict(hidden_dim=32)).save(
        checkpoint
    )
    (tmp_path / "folder").mkdir()
    cases = [
        (
            ["record", str(checkpoint), "--out", str(tmp_path / "folder"), "--overwrite"],
            "--out {tmp}/folder is a folder",
        ),
        ([str(checkpoint), "--out", str(tmp_path / "probe"), "--episodes", "1"], "--episodes must be >= 3"),
    ]
    if not __import__("torch").cuda.is_available():
        cases.append(([str(checkpoint), "--out", str(tmp_path / "probe"), "--device", "cuda"], "asks for a CUDA GPU"))
    for argv, message in cases:
        assert probe_main(argv) == 2
        assert message.format(tmp=tmp_path) in one_line_error(capsys)
    assert not (tmp_path / "probe").exists() and list((tmp_path / "folder").iterdir()) == []

    report_out = tmp_path / "report"
    report_out.mkdir()
    (report_out / "summary.md").write_text("a previous report")
    assert report_main([str(tmp_path / "sweep"), "--out", str(report_out), "--no-progress"]) == 2
    assert "already holds outputs (summary.md): pass --overwrite or another --out" in one_line_error(capsys)
    assert (report_out / "summary.md").read_text() == "a previous report"


def test_zoo_refuses_unknown_env_ids_and_non_yaml_configs(tmp_path, capsys):
    (tmp_path / "bad.yml").write_text("a: [")
    config = str(tmp_path.parent.parent / "x.yml")  # does not exist
    cases = [
        (
            ["--env", "sb3_collapse/walker-wlak-v0", "-conf", "zoo_configs/drqv2.yml"],
            "Did you mean sb3_collapse/walker-walk-v0",
        ),
        (["--env", "sb3_collapse/walker-walk-v0", "-conf", str(tmp_path / "bad.yml")], "is not a YAML file"),
        (["--env", "sb3_collapse/walker-walk-v0", "-conf", config], "is not a file"),
    ]
    for argv, message in cases:
        assert zoo_main(["train", "--algo", "drqv2", *argv]) == 2
        assert message in one_line_error(capsys, "python -m sb3_collapse.zoo")


def test_zip_of_a_checkpoint_stays_readable(bad_checkpoints):
    assert zipfile.is_zipfile(bad_checkpoints / "walker.zip")


def test_probe_takes_snapshots_and_sb3_baselines_and_refuses_mixed_image_sizes(tmp_path, capsys):
    from sb3_collapse.baselines import build_baseline
    from sb3_collapse.run.snapshots import save_snapshot

    tiny = ["--episodes", "3", "--max-steps", "4", "--layers", "cnn3", "mlp1", "--no-progress"]
    env = make_dmc_env("cartpole-balance", size=48, action_repeat=20)
    agent = DrQv2("CnnPolicy", env, buffer_size=10, policy_kwargs=dict(hidden_dim=16, feature_dim=8))
    snapshot = save_snapshot(agent, tmp_path / "snapshot_0000000000_frames.zip")
    # A snapshot: the encoder and the actor suffice.
    assert probe_main([str(snapshot), "--out", str(tmp_path / "a"), *tiny]) == 0
    assert (tmp_path / "a" / "probe.csv").is_file()

    td3 = tmp_path / "td3.zip"
    build_baseline("td3", env, learning_rate=1e-4, buffer_size=10, learning_starts=0, batch_size=4, feature_dim=8,
                   hidden_dim=16).save(td3)  # fmt: skip
    assert probe_main([str(td3), "--out", str(tmp_path / "b"), *tiny]) == 2  # SB3's zip does not name the task
    assert "The checkpoint does not say which environment it was trained on: pass --env" in one_line_error(capsys)
    assert not (tmp_path / "b").exists()
    argv = [
        str(td3),
        "--env",
        "cartpole-balance",
        "--size",
        "48",
        "--action-repeat",
        "20",
        "--out",
        str(tmp_path / "b"),
    ]
    assert probe_main([*argv, *tiny]) == 0

    small = tmp_path / "small.zip"  # another image size: the rollouts of the first cannot feed it
    DrQv2(
        "CnnPolicy", make_dmc_env("cartpole-balance", size=36), buffer_size=10, policy_kwargs=dict(hidden_dim=16)
    ).save(small)
    assert probe_main([str(snapshot), str(small), "--out", str(tmp_path / "c"), *tiny]) == 2
    assert one_line_error(capsys).endswith(
        f"{snapshot} takes observations of shape (9, 48, 48) and {small} of shape (9, 36, 36): the probe feeds "
        "every checkpoint the same rollouts, so probe checkpoints of another image size or frame stack in a run of "
        "their own."
    )
    assert not (tmp_path / "c").exists()  # refused before recording


def test_a_stop_caught_inside_a_string_exec_still_exits_75(tmp_path):
    """CPython marks a KeyboardInterrupt leaving a string ``exec`` unhandled, caught or not; under ``python -m`` the
    process then died by SIGINT (-2) after printing its line: the flake of the probe's signal test below, made
    certain (a SIGINT handled while a dataclass's method was being built)."""
    (tmp_path / "stop_in_exec.py").write_text(
        "import argparse\n"
        "from sb3_collapse.commands.cli import run_command\n"
        "def work():\n"
        "    exec('raise KeyboardInterrupt', {})\n"
        "raise SystemExit(run_command(argparse.ArgumentParser(), work, lambda stop: 'Stopped.'))\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(tmp_path), os.environ.get("PYTHONPATH")]))}
    done = subprocess.run(
        [sys.executable, "-m", "stop_in_exec"], capture_output=True, text=True, env=env, timeout=120, check=False
    )
    assert (done.returncode, done.stderr) == (75, "Stopped.\n")


@pytest.mark.parametrize("signum", [signal.SIGINT])
def test_a_signal_during_a_probe_leaves_nothing_and_exits_75(tmp_path, signum):
    checkpoint = tmp_path / "agent.zip"
    env = make_dmc_env("cartpole-balance", size=36, action_repeat=8)
    DrQv2("CnnPolicy", env, buffer_size=10, policy_kwargs=dict(hidden_dim=16, feature_dim=8)).save(checkpoint)
    out = tmp_path / "probe"
    argv = [sys.executable, "-m", "sb3_collapse.probe", str(checkpoint), "--out", str(out), "--episodes", "50",
            "--no-progress"]  # fmt: skip
    probe = subprocess.Popen(  # SIGINT's default handler even under a shell that started the tests with it ignored
        argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint  # noqa: PLW1509 (one call, no fork-unsafe work)
    )
    try:
        deadline = time.monotonic() + 120
        while not list(out.glob(".partial-*")):  # recording into the staging folder
            assert probe.poll() is None and time.monotonic() < deadline, probe.communicate()
            time.sleep(0.05)
        probe.send_signal(signum)
        stdout, stderr = probe.communicate(timeout=60)
    finally:
        probe.kill()
    assert probe.returncode == 75, stderr
    assert "Traceback" not in stdout + stderr
    assert stderr.strip().splitlines()[-1] == (
        f"Stopped by {signal.Signals(signum).name}: nothing was written under {out} (the outputs are staged and moved "
        "there only when complete); run the same command again (exit status 75)."
    )
    assert not out.exists()  # the staging folder removed, and the folder the probe created


@pytest.mark.parametrize(
    "argv, message",
    [
        # 7 frames are no agent step of 8 frames: blamed on --frames, not on the replay buffer's --n-steps.
        (["--env", "cartpole-swingup", "--frames", "7", "--action-repeat", "8"], "--frames must be >= 24: a budget"),
        (["--env", "walker-walk", "--frames", "7", "--action-repeat", "8"], "--frames must be >= 8: a budget"),
        (["--collapse-metrics-batch", "0"], "--collapse-metrics-batch must be >= 2, got 0."),
    ],
)
def test_train_names_the_flag_the_user_gave(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        train_main(argv)
    assert exit_info.value.code == 2
    line = one_line_error(capsys)
    assert message in line and "--batch-size" not in line and "--n-steps must" not in line


@pytest.mark.parametrize(
    "main, prog, argv",
    [
        (train_main, "python -m sb3_collapse.train", ["--frames", "0"]),
        (train_main, "python -m sb3_collapse.train", ["--no-such-flag"]),
        (train_main, "python -m sb3_collapse.train", ["--algorithm", "ppo"]),
        (sweep_main, "python -m sb3_collapse.sweep", ["--tasks", "walker-walk", "--seeds", "1", "--no-such-flag"]),
        (probe_main, "python -m sb3_collapse.probe run", ["x.zip", "--layers", "mlp9"]),
        (report_main, "python -m sb3_collapse.report", ["sweep", "--no-such-flag"]),
    ],
)
def test_command_line_errors_are_one_line_with_a_pointer_to_help_and_no_usage(main, prog, argv, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    pointer, line = capsys.readouterr().err.splitlines()  # the error last, where the eye lands
    assert pointer == f"{prog} --help lists the flags." and line.startswith(f"{prog}: error: ")
