"""
Faults around a run's end and its folder: a full disk at the final save, a read-only folder, a diverging run.
"""

from __future__ import annotations

import errno
import json
import math
import shutil
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.save_util import load_from_zip_file

from sb3_collapse import DrQv2
from sb3_collapse.commands.cli import report_unwritable_outputs
from sb3_collapse.commands.sweep import main as sweep_main
from sb3_collapse.commands.train import main
from sb3_collapse.drqv2.divergence import DivergenceGuard, all_finite
from sb3_collapse.errors import DivergenceError, unwritable_message
from sb3_collapse.protocol import (
    CHECKPOINT_MODEL,
    CHECKPOINTS_DIR,
    CONFIG_JSON,
    FINAL_MODEL,
    RESULT_JSON,
    atomic_output,
)
from sb3_collapse.run.checkpoints import checkpoint_folders
from tests.random_env import RandomObservationEnv


def _flags(run_dir: Path, frames: int = 800) -> list[str]:
    return [
        "--env", "cartpole-balance", "--frames", str(frames), "--action-repeat", "20", "--size", "36",
        "--hidden-dim", "16",
        "--feature-dim", "8", "--batch-size", "8", "--seed-frames", "200", "--eval-every-frames", "0",
        "--checkpoint-every-frames", "200", "--collapse-metrics-every-frames", "0", "--no-progress-bar",
        "--replay-sampling", "sb3", "--torch-threads", "1", "--run-dir", str(run_dir),
    ]  # fmt: skip


@pytest.fixture(autouse=True)
def _keep_torch_threads():
    threads = th.get_num_threads()
    yield
    th.set_num_threads(threads)


def test_atomic_output_leaves_nothing_under_the_final_name_after_an_error(tmp_path):
    target = tmp_path / "final_model.zip"
    target.write_text("previous")
    with pytest.raises(OSError, match="No space"), atomic_output(target) as temporary:
        assert temporary.suffix == ".zip" and temporary.parent == tmp_path
        temporary.write_text("half")
        raise OSError(errno.ENOSPC, "No space left on device")
    assert target.read_text() == "previous" and [p.name for p in tmp_path.iterdir()] == ["final_model.zip"]
    with atomic_output(target) as temporary:
        temporary.write_text("new")
    assert target.read_text() == "new" and [p.name for p in tmp_path.iterdir()] == ["final_model.zip"]


def test_unwritable_messages():
    assert unwritable_message(ValueError("x")) is None
    assert unwritable_message(OSError(errno.ENOENT, "No such file", "a")) is None
    full = unwritable_message(OSError(errno.ENOSPC, "No space left on device", "/runs/x/final_model.zip"))
    assert (
        full == "could not write /runs/x/final_model.zip (No space left on device): free space, then run the same "
        "command again."
    )
    assert "cannot write /ro (Read-only file system): choose a folder you can write to" in unwritable_message(
        OSError(errno.EROFS, "Read-only file system", "/ro")
    )


def test_full_disk_at_the_final_save_is_one_line_and_the_rerun_finishes(tmp_path, monkeypatch, capsys):
    run_dir = tmp_path / "run"
    original = DrQv2.save

    def full_disk(self, path, *args, **kwargs):
        if "final_model" not in str(path):  # the checkpoints fit
            return original(self, path, *args, **kwargs)
        with open(path, "wb") as file:
            file.write(b"PK\x03\x04 truncated")  # what a full disk leaves behind
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(DrQv2, "save", full_disk)
    assert main(_flags(run_dir, frames=810)) == 1
    printed = capsys.readouterr()
    assert (
        "the budget of 810 frames is not a multiple of the action repeat 20: the run trains 800 frames" in printed.out
    )
    error = printed.err.strip().splitlines()
    assert len(error) == 1 and error[0].startswith("error: could not write ") and "No space left on device" in error[0]
    assert "free space, then run the same command again" in error[0] and "resumes from the checkpoint step_" in error[0]
    assert not (run_dir / FINAL_MODEL).exists() and not (run_dir / RESULT_JSON).exists()
    assert not [path for path in run_dir.iterdir() if path.name.startswith(".")]  # no partial file left
    assert checkpoint_folders(run_dir / CHECKPOINTS_DIR)

    monkeypatch.setattr(DrQv2, "save", original)
    assert main(_flags(run_dir, frames=810)) == 0  # the same command finishes from the checkpoint
    assert "Resuming" in capsys.readouterr().out
    assert (run_dir / RESULT_JSON).is_file() and load_from_zip_file(run_dir / FINAL_MODEL)[1]


def test_read_only_run_folder_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys):
    run_dir = tmp_path / "read-only" / "run"
    original = Path.mkdir

    def read_only(self, *args, **kwargs):
        if str(self).startswith(str(tmp_path / "read-only")):
            raise OSError(errno.EROFS, "Read-only file system", str(self))
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", read_only)
    with pytest.raises(SystemExit) as exit_info:
        main(_flags(run_dir))
    assert exit_info.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert "error: run folder: cannot write " in error and "(Read-only file system)" in error
    assert not (tmp_path / "read-only").exists()


def test_divergence_guard_stops_on_non_finite_values_and_warns_once_on_growth():
    guard = DivergenceGuard(growth=100.0, reference_dumps=2)
    guard.check({"critic_loss": 3.0, "actor_loss": -0.5}, True, update=10, frame=100)
    guard.check({"critic_loss": 5.0, "actor_loss": -0.2}, True, update=20, frame=200)
    assert guard.scale == {"critic_loss": 5.0, "actor_loss": 1.0}
    guard.check({"critic_loss": 400.0, "actor_loss": -90.0}, True, update=30, frame=300)  # 80x and 90x: no warning
    with pytest.warns(RuntimeWarning, match=r"the critic_loss is 600 at update 40 \(frame 400\), over 100 times its"):
        guard.check({"critic_loss": 600.0, "actor_loss": -1.0}, True, update=40, frame=400)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        guard.check({"critic_loss": 1e6, "actor_loss": -1.0}, True, update=50, frame=500)  # once per loss
    assert len(guard.warnings) == 1
    with pytest.raises(DivergenceError, match=r"the critic_loss is nan at update 60 \(frame 600\)"):
        guard.check({"critic_loss": math.nan, "actor_loss": 0.0}, True, update=60, frame=600)
    with pytest.raises(DivergenceError, match="a weight is not finite after update 70"):
        guard.check({"critic_loss": 1.0}, False, update=70, frame=700)
    assert bool(all_finite([th.ones(2), th.zeros(3)])) and not bool(all_finite([th.ones(2), th.tensor([math.inf])]))


def test_divergence_guard_warns_on_losses_the_rewards_cannot_explain_from_the_first_dump():
    """A run diverging from its first updates: its losses are compared with what its rewards allow."""
    guard = DivergenceGuard()
    # Rewards of at most 2 and gamma 0.99: values up to 200, a critic loss up to 100 x 200^2 = 4e6 without a warning.
    guard.check({"critic_loss": 3.9e6, "actor_loss": -1.9e4, "batch_reward": 2.0}, True, 1, 10, gamma=0.99)
    assert guard.warnings == [] and guard.max_reward == 2.0
    with pytest.warns(RuntimeWarning, match=r"the critic_loss is 1.6e\+09 at update 2 .* rewards allow \(4e\+04\)"):
        guard.check({"critic_loss": 1.6e9, "actor_loss": -10.0, "batch_reward": 0.5}, True, 2, 20, gamma=0.99)
    with pytest.warns(RuntimeWarning, match=r"the actor_loss is -3e\+04 .* rewards allow \(200\)"):
        guard.check({"critic_loss": 1.0, "actor_loss": -3e4, "batch_reward": 0.5}, True, 3, 30, gamma=0.99)
    assert len(guard.warnings) == 2


def test_diverging_run_stops_with_one_line_and_keeps_its_last_finite_checkpoint(tmp_path, monkeypatch, capsys):
    run_dir = tmp_path / "run"
    original = DrQv2._update
    calls = []

    def diverging(self, *args, **kwargs):
        original(self, *args, **kwargs)
        calls.append(1)
        if len(calls) == 8:  # frame 520: after the checkpoint at frame 400
            with th.no_grad():
                next(self.critic.parameters()).fill_(math.nan)

    monkeypatch.setattr(DrQv2, "_update", diverging)
    assert main(_flags(run_dir)) == 1
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and error[0].startswith("error: training diverged: ")
    assert "its last checkpoint" in error[0] and "Try a smaller --lr" in error[0]
    kept = checkpoint_folders(run_dir / CHECKPOINTS_DIR)
    assert kept and not (run_dir / RESULT_JSON).exists()
    weights = load_from_zip_file(kept[0] / CHECKPOINT_MODEL)[1]["policy"]
    assert all(th.isfinite(tensor).all() for tensor in weights.values())


def test_command_lines_end_with_one_line_on_an_unwritable_output(capsys):
    def failing(error: OSError):
        @report_unwritable_outputs
        def main(argv: list[str] | None = None) -> int:
            raise error

        return main

    assert failing(OSError(errno.EROFS, "Read-only file system", "/ro/out"))([]) == 2
    assert failing(OSError(errno.ENOSPC, "No space left on device", "/full/out"))([]) == 1
    assert capsys.readouterr().err.splitlines() == [
        (
            "error: cannot write /ro/out (Read-only file system): choose a folder you can write to, or make this one "
            "writable."
        ),
        "error: could not write /full/out (No space left on device): free space, then run the same command again.",
    ]
    with pytest.raises(FileNotFoundError):
        failing(FileNotFoundError(errno.ENOENT, "No such file or directory", "/x"))([])


def test_sweep_into_a_read_only_folder_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys):
    out = tmp_path / "read-only" / "sweep"
    original = Path.mkdir

    def read_only(self, *args, **kwargs):
        if "read-only" in str(self):
            raise OSError(errno.EROFS, "Read-only file system", str(self))
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", read_only)
    flags = ["--frames", "800", "--action-repeat", "20", "--size", "36", "--eval-every-frames", "400"]
    status = sweep_main(["--tasks", "cartpole-balance", "--seeds", "1", "--out", str(out), *flags])
    assert status == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert error == [
        (
            f"error: cannot write {out} (Read-only file system): choose a folder you can write to, or make this "
            "one writable."
        )
    ]
    assert not (tmp_path / "read-only").exists()


def test_resume_after_the_learning_rate_was_edited_in_the_settings_file_is_refused(tmp_path, monkeypatch, capsys):
    run_dir = tmp_path / "run"
    original = DrQv2._update
    calls = []

    def crashing(self, *args, **kwargs):
        original(self, *args, **kwargs)
        calls.append(1)
        if len(calls) == 8:  # frame 520: after the checkpoint at frame 400
            raise RuntimeError("a crash")

    monkeypatch.setattr(DrQv2, "_update", crashing)
    with pytest.raises(RuntimeError, match="a crash"):
        main(_flags(run_dir))
    monkeypatch.setattr(DrQv2, "_update", original)
    config = json.loads((run_dir / CONFIG_JSON).read_text())
    trained_with = config["learning_rate"]
    (run_dir / CONFIG_JSON).write_text(json.dumps({**config, "learning_rate": 0.001}))  # edited by hand
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        main([*_flags(run_dir), "--lr", "0.001"])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    (kept,) = checkpoint_folders(run_dir / CHECKPOINTS_DIR)[:1]
    assert error.endswith(
        f"error: --run-dir {run_dir} holds an unfinished run with other settings: --lr 0.001 (its checkpoint "
        f"{kept.name} trained with {trained_with:g}). Run it with the settings it trained with (and its config.json "
        "as it wrote it) to resume it, or train into another folder."
    )
    assert checkpoint_folders(run_dir / CHECKPOINTS_DIR)[0] == kept  # nothing changed
    (run_dir / CONFIG_JSON).write_text(json.dumps(config))  # the settings file as the run wrote it: it resumes
    assert main(_flags(run_dir)) == 0
    assert json.loads((run_dir / RESULT_JSON).read_text())["resumes"] == 1


def test_run_folder_turning_read_only_while_training_is_one_line_exit_1_and_the_rerun_resumes(
    tmp_path, monkeypatch, capsys
):
    from stable_baselines3.common.logger import CSVOutputFormat

    run_dir = tmp_path / "run"
    original = CSVOutputFormat.write

    def read_only_after_a_checkpoint(self, *args, **kwargs):
        if checkpoint_folders(run_dir / CHECKPOINTS_DIR):  # the file system was remounted read-only
            raise OSError(errno.EROFS, "Read-only file system", self.file.name)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(CSVOutputFormat, "write", read_only_after_a_checkpoint)
    flags = _flags(run_dir, frames=1200)  # the first episode ends at frame 1000: SB3 logs, into progress.csv
    assert main(flags) == 1
    error = capsys.readouterr().err.strip().splitlines()
    (kept,) = checkpoint_folders(run_dir / CHECKPOINTS_DIR)[:1]
    assert len(error) == 1 and error[0].startswith(f"error: could not write {run_dir / 'progress.csv'} (Read-only file")
    assert error[0].endswith(
        f": the run stops. Make the folder writable again, then run the same command again: it resumes from the "
        f"checkpoint {kept.name}, which is intact."
    )
    assert not (run_dir / RESULT_JSON).exists()
    frames = json.loads((kept / "checkpoint.json").read_text())["frames"]
    monkeypatch.setattr(CSVOutputFormat, "write", original)  # writable again
    assert main(flags) == 0
    assert f"from its checkpoint at frame {frames:,} ({kept.name})" in capsys.readouterr().out
    assert json.loads((run_dir / RESULT_JSON).read_text())["resumes"] == 1


def test_reset_on_an_episode_end_waits_for_a_sampleable_episode_instead_of_failing():
    """The reset rule resets at agent step 100, where an episode of 50 steps ends: the buffer, emptied before that
    step is stored, holds its last transition only (finished, but shorter than n_steps). With a warm-up shorter than
    an episode, DrQ-v2's sampling (finished episodes only) had nothing to draw and every rerun raised; the updates
    now wait for the next episode's end."""
    from sb3_collapse import CollapseReset
    from sb3_collapse.drqv2.replay_buffer import FrameStackReplayBuffer

    env = RandomObservationEnv(gym.spaces.Box(0, 255, (9, 16, 16), np.uint8), episode_length=50, action_repeat=2)
    model = DrQv2(
        "CnnPolicy", env, buffer_size=300, learning_starts=20, batch_size=4, seed=0, n_steps=3,
        policy_kwargs=dict(hidden_dim=16, feature_dim=8), replay_buffer_class=FrameStackReplayBuffer,
        replay_buffer_kwargs=dict(sampling="drqv2", frame_stack=1),
    )  # fmt: skip
    with th.no_grad():
        model.actor.mlp1[0].bias.fill_(-1e3)  # collapsed: the rule resets at the end of its window
    updates = {}

    class Rule(CollapseReset):
        def _on_step(self):
            updates[self.num_timesteps] = self.model._n_updates
            return super()._on_step()

    rule = Rule(window_frames=200, check_every_frames=20, patience=3, max_resets=1)
    with pytest.warns(UserWarning, match="no episode of at least n_steps transitions has finished"):
        model.learn(160, callback=rule)
    assert rule.reset_frames == [200] and model.reset_step == 100
    assert model.replay_buffer.episodes_done.sum() == 2  # the cut one (1 transition) and the next, at step 150
    assert updates[100] == updates[150] and model._n_updates > updates[150]  # no update until step 150's episode


def _unfinished_run(run_dir: Path, *flags: str) -> Path:
    """A tiny run stopped by a full disk at its final save: checkpoints at frames 400 and 600 (it trained 800)."""
    original = DrQv2.save

    def full_disk(self, path, *args, **kwargs):
        if "final_model" not in str(path):
            return original(self, path, *args, **kwargs)
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    threads = th.get_num_threads()  # a module's fixture: set up before _keep_torch_threads
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(DrQv2, "save", full_disk)
        assert main([*_flags(run_dir), *flags]) == 1
    th.set_num_threads(threads)
    return run_dir


EVALUATIONS = ("--eval-every-frames", "400", "--eval-episodes", "1")


@pytest.fixture(scope="module")
def unfinished_run(tmp_path_factory) -> Path:
    """One unfinished run (no evaluation) for the tests that damage it: each damages a copy."""
    return _unfinished_run(tmp_path_factory.mktemp("unfinished") / "run")


@pytest.fixture(scope="module")
def unfinished_evaluated_run(tmp_path_factory) -> Path:
    """One unfinished run evaluated every 400 frames (as :func:`_evaluated_flags`), for the tests that damage its
    eval.csv and the stop while it resumes: each changes a copy."""
    return _unfinished_run(tmp_path_factory.mktemp("unfinished_evaluated") / "run", *EVALUATIONS)


@pytest.mark.parametrize("damage", ["truncated", "flipped"])
def test_damaged_replay_chunk_shared_by_every_checkpoint_restarts_the_run_and_keeps_them(
    unfinished_run, tmp_path, capsys, damage
):
    """Both checkpoints need the first replay chunk. Truncated, it is seen as the checkpoints are verified; a byte
    flipped, only as the chunk is read (its CRC), after the model was restored. Either way the run says why it
    restarts from frame 0, keeps the checkpoints aside (nothing is deleted), and finishes. A temporary file that a
    kill in the middle of the final save left is removed."""
    run_dir = tmp_path / "run"
    shutil.copytree(unfinished_run, run_dir)
    checkpoints = checkpoint_folders(run_dir / CHECKPOINTS_DIR)
    manifests = [json.loads((folder / "checkpoint.json").read_text())["replay"]["store"] for folder in checkpoints]
    assert len(manifests) == 2
    shared = manifests[0]["chunks"][0]["file"]
    assert shared == manifests[1]["chunks"][0]["file"]
    chunk = run_dir / CHECKPOINTS_DIR / "replay" / shared
    data = bytearray(chunk.read_bytes())
    if damage == "truncated":
        del data[len(data) // 2 :]
    else:
        data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))
    partial = run_dir / ".final_model.zip.x1y2z3.partial.zip"  # what a kill in the middle of the final save leaves
    partial.write_bytes(b"PK\x03\x04")

    assert main(_flags(run_dir)) == 0
    out = capsys.readouterr().out
    notes = [line for line in out.splitlines() if line.startswith("Note: Every checkpoint")]
    kept = run_dir / "damaged_checkpoints"
    assert len(notes) == 1, out
    assert notes[0].startswith(f"Note: Every checkpoint of {run_dir} is damaged (")
    assert notes[0].endswith(f"): the run restarts from frame 0. They are kept in {kept}.")
    assert all(folder.name in notes[0] for folder in checkpoints) and shared in notes[0]
    assert (kept / "damaged.txt").read_text() == notes[0].removeprefix("Note: ") + "\n"
    assert (kept / "replay" / shared).read_bytes() == bytes(data)  # set aside as it was
    assert sorted(path.name for path in kept.iterdir() if path.name.startswith(("step_", "damaged_step_"))) == sorted(
        ("damaged_" if damage == "flipped" else "") + folder.name for folder in checkpoints
    )
    result = json.loads((run_dir / RESULT_JSON).read_text())
    assert result["frames"] == 800 and result["resumes"] == 0  # restarted from frame 0
    assert not partial.exists() and not (run_dir / CHECKPOINTS_DIR).exists()


def test_leftovers_of_a_run_killed_after_its_result_are_removed_by_the_same_command(tmp_path, capsys):
    """A process killed between writing result.json and deleting its checkpoints and lock: the same command again
    (refused: the run is finished) removes them; a sweep skipping the trial does the same (tidy_finished_run)."""
    from sb3_collapse.run.folder import tidy_finished_run
    from sb3_collapse.run.lock import RunLock

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / CONFIG_JSON).write_text("{}")
    (run_dir / RESULT_JSON).write_text('{"status": "finished"}')
    step = run_dir / CHECKPOINTS_DIR / "step_000000000040"
    step.mkdir(parents=True)
    (step / "model.zip").write_bytes(b"x" * 2_000_000)
    (run_dir / "run.lock").write_text("pid 1 on host h since 2020-01-01 00:00:00\n")
    (run_dir / "snapshots").mkdir()
    (run_dir / "snapshots" / ".snapshot_0000000800_frames.zip.ab12.partial.zip").write_bytes(b"PK")

    with RunLock(run_dir):  # a process still finishing: nothing is touched
        assert tidy_finished_run(run_dir) == []
    assert step.is_dir()

    with pytest.raises(SystemExit) as exit_info:
        main(_flags(run_dir))
    assert exit_info.value.code == 2
    printed = capsys.readouterr()
    assert "holds a finished run (result.json): choose another folder." in printed.err
    assert printed.out.strip() == (
        f"Removed what the finished run in {run_dir} left behind (killed after it finished): checkpoints/ (2.0 MB), "
        ".snapshot_0000000800_frames.zip.ab12.partial.zip, run.lock."
    )
    assert sorted(path.name for path in run_dir.rglob("*")) == [CONFIG_JSON, RESULT_JSON, "snapshots"]


def test_the_run_trains_exactly_its_budget_or_says_why_not():
    """SB3 completes a round of train_freq transitions past the budget: 375 agent steps (3,000 frames at action
    repeat 8) trained 376. A round now stops at the budget; with several environments, the budget rounds up to a
    multiple of n_envs, and the run says so."""
    from sb3_collapse.run.config import TrainConfig
    from sb3_collapse.run.runner import budget_note

    env = RandomObservationEnv(gym.spaces.Box(0, 255, (9, 16, 16), np.uint8), episode_length=50, action_repeat=8)
    model = DrQv2(
        "CnnPolicy", env, buffer_size=400, learning_starts=360, batch_size=4, seed=0,
        policy_kwargs=dict(hidden_dim=16, feature_dim=8),
    )  # fmt: skip
    model.learn(375)
    assert model.num_timesteps == 375 and model.num_frames == 3000
    model.learn(5, reset_num_timesteps=False)  # a resumed run continues to its budget, not past it
    assert model.num_timesteps == 380

    config = dict(env="cartpole-balance", action_repeat=8)
    assert budget_note(TrainConfig(frames=3000, **config).resolve()) is None
    assert budget_note(TrainConfig(frames=3000, n_envs=2, **config).resolve()) == (
        "Note: the budget of 3,000 frames is not a multiple of the action repeat 8 x 2 environments (16): the run "
        "trains 3,008 frames (376 agent steps)."
    )
    assert budget_note(TrainConfig(frames=401, env="cartpole-balance", action_repeat=2).resolve()) == (
        "Note: the budget of 401 frames is not a multiple of the action repeat 2: the run trains 400 frames (200 "
        "agent steps)."
    )


@pytest.mark.parametrize("damage", ["short", "cut mid-row"])
def test_eval_csv_out_of_step_with_the_checkpoint_is_rewritten_from_it_on_resume(
    unfinished_evaluated_run, tmp_path, capsys, damage
):
    """eval.csv shorter than the checkpoint expects (was: unresumable), or cut mid-row (was: the next row appended to
    the cut one): the resume writes it back from the checkpoint, says so in one line, and every evaluation ends as
    the uninterrupted run wrote it (frame and return), once each."""
    run_dir = tmp_path / "run"
    evaluations = list(EVALUATIONS)
    shutil.copytree(unfinished_evaluated_run, run_dir)  # stopped at its final save: checkpoints at frames 400 and 600
    eval_csv = run_dir / "eval.csv"
    uninterrupted = [line.split(",")[:3] for line in eval_csv.read_text().splitlines()]
    assert [row[0] for row in uninterrupted] == ["frame", "0", "400"]
    lines = eval_csv.read_bytes().splitlines(keepends=True)
    eval_csv.write_bytes(b"".join(lines[:2]) if damage == "short" else b"".join(lines[:2]) + lines[2][:5])
    capsys.readouterr()

    assert main([*_flags(run_dir), *evaluations]) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if "rewritten from it" in line]
    why = "1 line(s) short" if damage == "short" else "cut mid-row"
    assert notes == [
        (
            f"Note: eval.csv ({why}) did not hold what the checkpoint at frame 600 recorded: rewritten from it (the "
            "rows after it are written again as the run goes on)."
        )
    ]
    rows = [line.split(",") for line in eval_csv.read_text().splitlines()]
    assert [row[:3] for row in rows] == uninterrupted
    assert {len(row) for row in rows} == {6}
    assert json.loads((run_dir / RESULT_JSON).read_text())["resumes"] == 1


def test_a_run_folder_whose_result_file_is_unreadable_is_refused_in_one_line_with_the_way_out(tmp_path, capsys):
    """A truncated result.json is not repaired: the folder stays failed, `train` refuses it in one line that names
    the file, the reason and the way out (not "choose another folder"), and a sweep would not call it retryable."""
    from sb3_collapse.run.config import TrainConfig
    from sb3_collapse.run.folder import check_run_folder
    from sb3_collapse.runfolder import read_result, run_status
    from sb3_collapse.sweep.runner import retryable

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / CONFIG_JSON).write_text("{}")
    (run_dir / RESULT_JSON).write_text('{"status": "fini')  # truncated
    reason = (
        f"{run_dir / RESULT_JSON}: not a readable JSON file (Unterminated string starting at: line 1 column 12 "
        "(char 11))"
    )
    with pytest.raises(ValueError) as strict:
        read_result(run_dir, strict=True)
    assert str(strict.value) == reason + "."
    before = sorted(path.name for path in run_dir.iterdir())

    with pytest.raises(SystemExit) as exit_info:
        main(_flags(run_dir))
    assert exit_info.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert error[-1].endswith(f"error: --run-dir {run_dir}: {reason}; move the folder aside to train this seed again.")
    assert run_status(run_dir) == "failed" and sorted(path.name for path in run_dir.iterdir()) == before
    with pytest.raises(ValueError) as refused:
        check_run_folder(TrainConfig(env="cartpole-balance", run_dir=str(run_dir)))
    assert not retryable(refused.value)


def _evaluated_flags(run_dir: Path) -> list[str]:
    """A tiny run with a scheduled evaluation at frame 400 and the evaluation of its final model (one episode)."""
    flags = _flags(run_dir)
    flags[flags.index("--eval-every-frames") + 1] = "400"
    return [*flags, "--eval-episodes", "1"]


def _same_end(run_dir: Path, reference: Path) -> None:
    """``run_dir`` finished as the uninterrupted ``reference``: the same weights, evaluations and CSV rows."""
    result, expected = (json.loads((folder / RESULT_JSON).read_text()) for folder in (run_dir, reference))
    for key in ("frames", "agent_steps", "final_eval", "saved_model_eval"):
        assert result[key] == expected[key], key
    weights, reference_weights = (
        load_from_zip_file(folder / FINAL_MODEL)[1]["policy"] for folder in (run_dir, reference)
    )
    assert all(th.equal(weights[name], reference_weights[name]) for name in reference_weights)
    rows, reference_rows = ([row.rsplit(",", 1)[0] for row in (folder / "eval.csv").read_text().splitlines()]
                            for folder in (run_dir, reference))  # fmt: skip
    assert rows == reference_rows  # but the wall time
    assert not (run_dir / CHECKPOINTS_DIR).exists()


@pytest.fixture(scope="module")
def uninterrupted_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("uninterrupted") / "run"
    threads = th.get_num_threads()
    assert main(_evaluated_flags(run_dir)) == 0
    th.set_num_threads(threads)
    return run_dir


@pytest.mark.parametrize("phase", ["resume", "final save", "evaluation", "result file"])
def test_a_stop_after_learn_finishes_or_exits_75_and_the_rerun_ends_as_an_uninterrupted_run(
    tmp_path, monkeypatch, capsys, uninterrupted_run, unfinished_evaluated_run, phase
):
    """SIGTERM while the run resumes, saves its final model, evaluates it or writes its result file (each patched to
    send it to this process): before the result file, a checkpoint at the last step (of the run as it was before the
    evaluation) and exit status 75 with the usual line; while the result file is written, the run finishes. The same
    command then ends as the uninterrupted run did, nothing trained twice."""
    import os
    import signal

    from sb3_collapse.monitoring.evaluation import PeriodicEvaluation
    from sb3_collapse.run import runner
    from sb3_collapse.run.checkpoints import ResumableCheckpoints

    run_dir, flags = tmp_path / "run", _evaluated_flags(tmp_path / "run")

    def sigterm_then(original, when=lambda *args: True):
        def patched(*args, **kwargs):
            if when(*args):
                os.kill(os.getpid(), signal.SIGTERM)
            return original(*args, **kwargs)

        return patched

    if phase == "resume":
        shutil.copytree(unfinished_evaluated_run, run_dir)  # run with the values of flags
        capsys.readouterr()  # what the module's fixture printed, if it ran in this test
        monkeypatch.setattr(ResumableCheckpoints, "resume", sigterm_then(ResumableCheckpoints.resume))
    elif phase == "final save":
        monkeypatch.setattr(DrQv2, "save", sigterm_then(DrQv2.save, lambda _, path: "final_model" in str(path)))
    elif phase == "evaluation":
        patched = sigterm_then(PeriodicEvaluation._run_episodes, lambda _, prefix: prefix == "eval_saved_model")
        monkeypatch.setattr(PeriodicEvaluation, "_run_episodes", patched)
    else:
        monkeypatch.setattr(runner, "write_json_atomically", sigterm_then(runner.write_json_atomically))
    status = main(flags)
    printed = capsys.readouterr()
    monkeypatch.undo()
    if phase == "result file":
        assert status == 0 and "SIGTERM: the training and its evaluation are done; finishing" in printed.out
    else:
        assert status == 75, printed.err
        error = printed.err.strip().splitlines()
        assert len(error) == 1 and error[0].startswith("Stopped by SIGTERM after the checkpoint ")
        assert "(SIGINT again" not in printed.out  # a second SIGTERM does not stop at once
        assert not (run_dir / RESULT_JSON).exists()
        kept = checkpoint_folders(run_dir / CHECKPOINTS_DIR)[0]  # resumed from step 30: stopped there
        assert kept.name == ("step_000000000030" if phase == "resume" else "step_000000000040")
        assert error[0].startswith(f"Stopped by SIGTERM after the checkpoint {kept}: run the same command again")
        assert main(flags) == 0
        rerun = capsys.readouterr().out
        assert "Resuming" in rerun and "Checkpoint at frame" not in rerun  # nothing trained again
    _same_end(run_dir, uninterrupted_run)


def test_full_disk_while_writing_a_replay_chunk_is_one_line_with_one_remedy(tmp_path, monkeypatch, capsys):
    from sb3_collapse.run import replay_checkpoint

    run_dir, original, writes = tmp_path / "run", replay_checkpoint._write, []

    def full_disk(file, data):
        writes.append(1)
        if checkpoint_folders(run_dir / CHECKPOINTS_DIR):  # the first checkpoint fits
            raise OSError(errno.ENOSPC, "No space left on device")
        original(file, data)

    monkeypatch.setattr(replay_checkpoint, "_write", full_disk)
    assert main(_flags(run_dir)) == 1
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1, error
    assert error[0].startswith(f"error: could not write a checkpoint into {run_dir / CHECKPOINTS_DIR} (No space left ")
    assert "bytes of replay chunks to write; none kept" in error[0]
    assert error[0].endswith(
        "the previous checkpoint step_000000000010 is intact. Free space (or fix the folder), then run the same "
        "command again to resume."
    )
    assert error[0].lower().count("free space") == 1 and error[0].count("resume") == 1
    monkeypatch.undo()
    assert main(_flags(run_dir)) == 0
    assert "from its checkpoint at frame 200 (step_000000000010)" in capsys.readouterr().out


def test_a_fallback_to_an_older_checkpoint_announces_only_the_frame_it_resumes_from(tmp_path, monkeypatch, capsys):
    """The newest checkpoint's own replay chunk has a byte changed: found as it is read (its CRC-32), after the
    checkpoint was chosen. The run says it resumes from the one before, at its frame, and never names the newer
    one's frame as where it resumes."""
    run_dir = tmp_path / "run"
    _unfinished_run(run_dir)
    capsys.readouterr()
    newest, older = checkpoint_folders(run_dir / CHECKPOINTS_DIR)
    chunks = [
        {chunk["file"] for chunk in json.loads((folder / "checkpoint.json").read_text())["replay"]["store"]["chunks"]}
        for folder in (newest, older)
    ]
    (own,) = chunks[0] - chunks[1]
    chunk = run_dir / CHECKPOINTS_DIR / "replay" / own
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))
    assert main(_flags(run_dir)) == 0
    out = capsys.readouterr().out.splitlines()
    resuming = [line for line in out if line.startswith("Resuming")]
    assert resuming == [f"Resuming {run_dir} from its checkpoint at frame 400 ({older.name})."]
    assert not [line for line in out[: out.index(resuming[0])] if "600" in line]  # (the resumed run writes one at 600)
    assert any(line.startswith(f"Note: checkpoint {newest} is damaged (") for line in out)
    assert json.loads((run_dir / RESULT_JSON).read_text())["frames"] == 800


def test_only_a_sigint_offers_to_stop_at_once(capsys):
    """A SIGTERM's line does not tell a scheduler about SIGINT (a second SIGTERM changes nothing); a SIGINT's does."""
    import signal

    from sb3_collapse.run.checkpoints import ResumableCheckpoints
    from sb3_collapse.run.signals import stop_signals

    checkpoints = ResumableCheckpoints("unused", every_frames=0)
    with stop_signals(checkpoints):
        signal.raise_signal(signal.SIGTERM)
        signal.raise_signal(signal.SIGTERM)  # nothing more
        assert checkpoints.stop_signal == "SIGTERM"
    lines = capsys.readouterr().out.strip().splitlines()
    assert [line for line in lines if line] == [
        "SIGTERM: writing a checkpoint at the end of this round, then stopping."
    ] * 2
    with stop_signals(ResumableCheckpoints("unused", every_frames=0)):
        signal.raise_signal(signal.SIGINT)
    assert capsys.readouterr().out.strip() == (
        "SIGINT: writing a checkpoint at the end of this round, then stopping (SIGINT again: stop now)."
    )
