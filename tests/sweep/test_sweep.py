import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time

import pytest

from sb3_collapse import DrQv2
from sb3_collapse.commands.sweep import main
from sb3_collapse.errors import InputError
from sb3_collapse.run.checkpoints import checkpoint_folders, checkpoint_frames
from sb3_collapse.run.config import TrainConfig
from sb3_collapse.runfolder import run_status
from sb3_collapse.sweep import (
    GRID_VARIANTS,
    Trial,
    expand_trials,
    parse_checkpoint_specs,
    settings_changes,
    transplant_of,
    trial_config,
    trial_dir,
    variant_settings,
)
from sb3_collapse.sweep.cluster import check_resources
from tests.sweep.sweeps import TINY, mtimes, own_lines, read_csv

TINY_TRIALS = ["--tasks", "walker-walk", "--seeds", "2", "--variants", "drqv2", "drqv2+reset"]


def test_missing_ray_says_how_to_install_it(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    with pytest.raises(SystemExit) as exit_info:
        main([*TINY_TRIALS, "--out", str(tmp_path / "sweep"), *TINY])
    assert exit_info.value.code == 2
    assert "pip install -e '.[sweep]'" in capsys.readouterr().err
    assert not (tmp_path / "sweep").exists()  # nothing written


def test_trials_variants_and_checkpoints(tmp_path):
    trials = expand_trials(["walker_walk", "cup-catch"], ["drqv2", "drqv2+reset"], [1, 0])
    assert trials[:3] == [Trial("walker-walk", "drqv2", 1), Trial("walker-walk", "drqv2", 0),
                          Trial("walker-walk", "drqv2+reset", 1)]  # fmt: skip
    assert len(trials) == 8 and trials[-1] == Trial("ball_in_cup-catch", "drqv2+reset", 0)
    # The same trial twice is refused, naming what repeats (walker_walk is walker-walk).
    with pytest.raises(InputError, match="seeds lists 1 more than once"):
        expand_trials(["walker-walk"], ["drqv2"], [1, 0, 1])
    with pytest.raises(InputError, match="tasks lists walker-walk more than once"):
        expand_trials(["walker_walk", "walker-walk"], ["drqv2"], [0])
    assert trial_dir("runs", trials[2]).as_posix() == "runs/walker-walk/drqv2+reset/seed_1"
    assert len(GRID_VARIANTS) == 9 and transplant_of("cnn-bad_mlp-good") == {"cnn": "bad", "mlp": "good"}
    assert transplant_of("drqv2") is None
    with pytest.raises(InputError, match="cnn-<src>_mlp-<src>"):
        expand_trials(["walker-walk"], ["cnn-good_mlp-ugly"], [0])
    with pytest.raises(InputError, match="walker-walk"):
        expand_trials(["walker-wlak"], ["drqv2"], [0])

    good, walker_good = tmp_path / "good.zip", tmp_path / "walker=good.zip"
    good.write_bytes(b"")
    walker_good.write_bytes(b"")
    tasks = ["walker-walk", "hopper-stand"]
    assert parse_checkpoint_specs([str(good)], tasks, "--good-cnn") == dict.fromkeys(tasks, str(good))
    by_task = parse_checkpoint_specs([str(good), f"walker_walk={walker_good}"], tasks, "--good-cnn")
    assert by_task == {"walker-walk": str(walker_good), "hopper-stand": str(good)}  # a task name before '='
    assert parse_checkpoint_specs([str(walker_good)], tasks[:1], "--bad-cnn") == {tasks[0]: str(walker_good)}
    with pytest.raises(InputError, match="not a file"):
        parse_checkpoint_specs([f"hopper-stand={tmp_path / 'missing.zip'}"], tasks, "--bad-cnn")
    with pytest.raises(InputError, match="not a task of this sweep"):
        parse_checkpoint_specs([f"finger-spin={good}"], tasks, "--bad-cnn")

    plain = {"algorithm": "drqv2", "reset_rule": False, "intervention": None, "activation": "relu",
             "redo_every_updates": 0}  # fmt: skip
    assert variant_settings("drqv2") == plain
    assert variant_settings("td3+reset") == {**plain, "algorithm": "td3", "reset_rule": True, "intervention": "reset"}
    assert variant_settings("sac+shrink_perturb")["intervention"] == "shrink_perturb"
    assert variant_settings("cnn-good_mlp-bad") == plain
    # the Leaky-ReLU ablation, alone and with an intervention; ReDo every F updates (no rule), alone and with it
    assert variant_settings("drqv2-leaky") == {**plain, "activation": "leaky_relu"}
    assert variant_settings("drqv2-leaky+redo") == {
        **plain, "activation": "leaky_relu", "reset_rule": True, "intervention": "redo"
    }  # fmt: skip
    assert variant_settings("drqv2+redo_periodic") == {**plain, "redo_every_updates": 1000}
    assert variant_settings("drqv2-leaky+redo_periodic")["activation"] == "leaky_relu"
    for unknown in ("td4", "drqv2+restart", "drqv2+", "+redo", "td3-leaky", "drqv2-leaky+redo_periodic+reset"):
        expected = "<algorithm>\\+<intervention> with <algorithm> in drqv2, drqv2-leaky, td3, sac"
        with pytest.raises(InputError, match=expected):
            expand_trials(["walker-walk"], [unknown], [0])
    redo = trial_config(Trial("walker-walk", "sac+redo", 0), tmp_path, {"frames": 800})
    assert (redo.algorithm, redo.reset_rule, redo.intervention, redo.variant_name) == ("sac", True, "redo", "sac+redo")
    for variant in ("drqv2-leaky+shrink_perturb_noise", "drqv2-leaky+redo_periodic", "td3+redo_periodic"):
        config = trial_config(Trial("walker-walk", variant, 0), tmp_path, {"frames": 800})
        config.validate()
        derived = TrainConfig(**variant_settings(variant), env="walker-walk").variant_name  # without the variant name
        assert config.variant_name == variant == derived
    config = trial_config(Trial("walker-walk", "drqv2+reset", 3), tmp_path, {"frames": 800}, torch_threads=2)
    assert config.reset_rule and config.seed == 3 and config.frames == 800 and config.torch_threads == 2
    assert config.run_dir == str(tmp_path / "walker-walk" / "drqv2+reset" / "seed_3") and not config.progress_bar


def test_command_line_errors(tmp_path, capsys):
    out = str(tmp_path / "sweep")
    cases = [
        (["--tasks", "walker-walk", "--seeds", "2", "--transplant-grid"], "--good-mlp PATH"),
        (["--tasks", "walker-walk", "--seeds", "0"], "--seeds must be >= 1"),
        (["--tasks", "walker-walk", "--seed-list", "1", "--variants", "drqv2++"], "Unknown variant 'drqv2++'"),
        (["--tasks", "walker-walk", "--seeds", "1", "--frames", "0"], "--frames must be >= 1"),
        (["--tasks", "walker-walk", "--seeds", "1", "--gpus-per-trial", "1.5"], "--gpus-per-trial must be"),
        (["--tasks", "walker-walk", "--seeds", "1", "--seed-list", "2"], "not allowed with argument"),
    ]
    for argv, message in cases:
        with pytest.raises(SystemExit) as exit_info:
            main([*argv, "--out", out])
        assert exit_info.value.code == 2 and message in capsys.readouterr().err, argv
    assert not (tmp_path / "sweep").exists()
    checkpoint = tmp_path / "agent.zip"
    checkpoint.write_bytes(b"")
    other = tmp_path / "other.zip"
    other.write_bytes(b"")
    grid = ["--transplant-grid", "--good-cnn", str(checkpoint), "--good-mlp", str(other), "--bad-cnn", str(checkpoint),
            "--bad-mlp", str(other)]  # fmt: skip
    assert main(["--tasks", "walker-walk", "--seeds", "2", *grid, "--out", out, "--dry-run"]) == 0
    lines = own_lines(capsys.readouterr().out)
    assert lines[-1].startswith("18 trials: 18 new; 18 would run") and lines[0].endswith("cnn-blank_mlp-blank/seed_0")
    assert not (tmp_path / "sweep").exists()  # a dry run writes nothing
    with pytest.raises(SystemExit):
        main(["--help"])
    help_text = capsys.readouterr().out
    for flag in ("--frames", "--stddev-schedule", "--reset-window-frames", "--address", "--gpus-per-trial"):
        assert flag in help_text
    for train_only in ("--env ", "--seed ", "--logdir", "--run-name", "--reset-rule"):
        assert train_only not in help_text


def test_resources_and_settings_checks():
    with pytest.raises(InputError, match="Ray sees none"):
        check_resources({"CPU": 16.0}, cpus_per_trial=1, gpus_per_trial=0.25)
    with pytest.raises(InputError, match="more than the 2 CPUs"):
        check_resources({"CPU": 2.0}, cpus_per_trial=4, gpus_per_trial=0)
    check_resources({"CPU": 2.0, "GPU": 1.0}, cpus_per_trial=1, gpus_per_trial=0.25)
    previous = {"training": {"frames": 1000}, "checkpoints": {"good_cnn": {"walker-walk": "/a.zip"}}}
    same = {"training": {"frames": 1000}, "checkpoints": {"good_cnn": {"walker-walk": "/a.zip", "hopper-stand": "/b"}}}
    assert settings_changes(previous, same) == []  # a new task's checkpoint is not a change
    moved = {"training": {"frames": 1000}, "checkpoints": {"good_cnn": {"walker-walk": "/c.zip"}}}
    assert settings_changes(previous, moved) == [
        "`good_cnn` checkpoint for walker-walk: /a.zip in sweep.json, /c.zip now"
    ]
    # The reproduction's stages record the settings they set, the command line every one: a default is no change.
    every = {"training": {"frames": 1000, "snapshots": False, "tf32": True, "batch_size": None, "size": 84}}
    assert settings_changes(previous, every) == [] and settings_changes(every, previous) == []
    assert settings_changes(previous, {"training": {"frames": 1000, "snapshots": True}}) == [
        "`snapshots`: False in sweep.json, True now"
    ]


def test_a_rerun_keeps_the_donors_and_snapshot_variants_of_the_settings_file(tmp_path):
    from sb3_collapse.sweep.runner import prepare_sweep_folder

    first = {"training": {"frames": 1000}, "tasks": ["walker-walk"], "seeds": [0], "snapshot_variants": ["drqv2"],
             "donors": {"good_cnn": {"walker-walk": "/a.zip"}}}  # fmt: skip
    prepare_sweep_folder(tmp_path, first)
    prepare_sweep_folder(tmp_path, {"training": {"frames": 1000, "snapshots": False}, "tasks": ["hopper-stand"]})
    kept = json.loads((tmp_path / "sweep.json").read_text())
    assert kept["donors"] == first["donors"] and kept["snapshot_variants"] == ["drqv2"]
    assert kept["tasks"] == ["walker-walk", "hopper-stand"] and kept["training"]["snapshots"] is False


def test_killed_driver_leaves_no_ray_process(tmp_path):
    import psutil

    out = tmp_path / "sweep"
    argv = [sys.executable, "-m", "sb3_collapse.sweep", *TINY_TRIALS[:2], "--seeds", "1", "--variants", "drqv2",
            "--out", str(out), "--no-progress-bar", *TINY, "--frames", "4000"]  # fmt: skip
    driver = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while not (out / "walker-walk" / "drqv2" / "seed_0" / "config.json").exists():  # the trial is training
            assert time.monotonic() < deadline and driver.poll() is None, "the sweep's trial did not start"
            time.sleep(0.5)
        time.sleep(1)
        ray_processes = psutil.Process(driver.pid).children(recursive=True)
        names = {process.name() for process in ray_processes}
        assert any("raylet" in name for name in names) and len(ray_processes) >= 4  # GCS, raylet, agents, worker
    finally:
        driver.kill()  # SIGKILL: Ray's own clean-up never runs
        driver.wait()
    _, alive = psutil.wait_procs(ray_processes, timeout=30)
    assert [process.name() for process in alive] == []  # Ray's agents (ray::DashboardAgent...) included


# Issue 15's comparison: the paper's reset, ReDo and SB3's TD3 with the reset, side by side, one seed each (the
# tiny sweep's report draws several seeds). A few hundred frames: 20 agent steps of 25 frames (a DMC episode is then
# 40 agent steps: rendering is most of a trial's time, so one scheduled evaluation, at frame 0, and the final model's
# at 500), 48x48 images (TD3's NatureCNN takes 36x36 at least), updates from agent step 5, and a window of 200
# frames: every trial intervenes at frames 200 and 400 (not at the budget's end).
COMPARISON = [
    "--tasks", "cartpole-balance", "--seeds", "1", "--variants", "drqv2+reset", "drqv2+redo", "td3+reset",
    "--frames", "500", "--action-repeat", "25", "--size", "48", "--hidden-dim", "64", "--feature-dim", "16",
    "--batch-size", "8", "--seed-frames", "100", "--eval-every-frames", "500", "--eval-episodes", "1",
    "--collapse-metrics-every-frames", "200", "--collapse-metrics-batch", "4", "--reset-window-frames", "200",
    "--replay-sampling", "sb3", "--cpus-per-trial", "1",
]  # fmt: skip


def test_sweep_compares_interventions_and_sb3_algorithms(ray_local, tmp_path, monkeypatch):
    from stable_baselines3 import TD3

    from sb3_collapse.commands.report_pipelines import write_report
    from sb3_collapse.report import plots

    out = tmp_path / "comparison"
    start = time.perf_counter()
    assert main([*COMPARISON, "--out", str(out), "--no-progress-bar"]) == 0
    print(f"comparison sweep: 3 trials in {time.perf_counter() - start:.1f} s")
    expected = {"drqv2+reset": ("drqv2", "reset"), "drqv2+redo": ("drqv2", "redo"), "td3+reset": ("td3", "reset")}
    for variant, (algorithm, intervention) in expected.items():
        folder = out / "cartpole-balance" / variant / "seed_0"
        config = json.loads((folder / "config.json").read_text())
        assert (config["algorithm"], config["intervention"]) == (algorithm, intervention) and config["reset_rule"]
        result = json.loads((folder / "result.json").read_text())
        assert result["variant"] == variant and result["frames"] == 500 and result["agent_steps"] == 20
        assert result["resets"] == 2 and result["reset_frames"] == [200, 400]
        events = read_csv(folder / "collapse_events.csv")
        assert [(row["event"], row["frame"], row["intervention"]) for row in events] == [
            ("reset", "200", intervention),
            ("reset", "400", intervention),
        ]
        what = "hidden units recycled (tau 0.025)" if intervention == "redo" else "replay buffer emptied"
        assert all(what in row["detail"] for row in events)
    td3 = TD3.load(out / "cartpole-balance" / "td3+reset" / "seed_0" / "final_model.zip")
    assert td3.actor.features_extractor.features_dim == 16 and td3.actor.mu[0].out_features == 64
    assert td3.reset_step == 16 and td3.learning_starts == 16 + 4  # the warm-up restarted at the last reset

    figures = []  # the report's figure, kept open to read its legend
    monkeypatch.setattr(plots.plt, "close", figures.append)
    report = write_report(out, out=tmp_path / "report", progress=False)
    rows = {row.variant: row for row in report.rows}
    assert list(rows) == ["drqv2+reset", "drqv2+redo", "td3+reset"]
    for row in rows.values():
        # The last scheduled evaluation: 0 (500, the budget, is the saved model's, outside the statistics).
        assert row.seeds == 1 and row.final_frame == 0 and row.resets_total == 2 and row.seeds_reset == 1
    assert (tmp_path / "report" / "figure5.png").read_bytes().startswith(b"\x89PNG\r\n\x1a\n")
    (axes,) = [ax for ax in figures[0].axes if ax.get_visible()]
    legend = [text.get_text() for text in axes.get_legend().get_texts()]
    assert legend == [
        "drqv2+reset: reset from scratch (n=1)",
        "drqv2+redo: ReDo, one-shot at the rule's trigger (n=1)",
        "td3+reset: reset from scratch (n=1)",
    ]
    colors = {line.get_label(): line.get_color() for line in axes.get_lines()}
    assert len(set(colors.values())) == 3  # one colour per variant
    markdown = (tmp_path / "report" / "summary.md").read_text()
    assert all(f"| {variant} |" in markdown for variant in expected)


# A trial that checkpoints: 60 agent steps of cartpole at action repeat 20 (episodes of 50 steps), a checkpoint every
# 10 steps, updates from agent step 20, a reset at frame 800.
RESUMABLE = [
    "--tasks", "cartpole-balance", "--seeds", "1", "--variants", "drqv2+reset", "--frames", "1200",
    "--action-repeat", "20", "--size", "48", "--hidden-dim", "64", "--feature-dim", "16", "--batch-size", "16",
    "--seed-frames", "400", "--eval-every-frames", "1200", "--eval-episodes", "1", "--checkpoint-every-frames", "200",
    "--collapse-metrics-every-frames", "400", "--collapse-metrics-batch", "16", "--reset-window-frames", "800",
    "--replay-sampling", "sb3", "--cpus-per-trial", "1",
]  # fmt: skip


def test_killed_trial_worker_is_run_again_and_resumes(ray_local, tmp_path, capsys):
    out = tmp_path / "sweep"
    folder = out / "cartpole-balance" / "drqv2+reset" / "seed_0"
    killed = {}

    def kill_the_worker() -> None:  # SIGKILL the Ray worker of the trial once it wrote a checkpoint
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline:
            if checkpoint_folders(folder / "checkpoints"):
                killed["pid"] = int((folder / "run.lock").read_text().split()[1])  # "pid <pid> on host ..."
                killed["frames"] = checkpoint_frames(folder / "checkpoints")
                os.kill(killed["pid"], signal.SIGKILL)
                return
            time.sleep(0.02)

    killer = threading.Thread(target=kill_the_worker, daemon=True)
    killer.start()
    assert main([*RESUMABLE, "--out", str(out), "--no-progress-bar"]) == 0
    killer.join()
    assert killed["frames"] < 1200, "the trial finished before its worker was killed"
    assert "1 finished now (1 resumed from a checkpoint), 0 finished before, 0 failed" in capsys.readouterr().out
    result = json.loads((folder / "result.json").read_text())
    assert result["resumes"] == 1 and result["frames"] == 1200 and result["resets"] == 1
    assert [int(row["frame"]) for row in read_csv(folder / "eval.csv")] == [0]  # 1200: the final model's
    assert [int(row["frame"]) for row in read_csv(folder / "collapse_events.csv")] == [800]


def newest_checkpoint(folder):
    """The newest checkpoint folder of a trial and its checkpoint.json, or (None, None)."""
    kept = checkpoint_folders(folder / "checkpoints")
    return (kept[0], json.loads((kept[0] / "checkpoint.json").read_text())) if kept else (None, None)


def stop_after_first_checkpoint(folder, signum, process_id, record):
    """Send ``signum`` to ``process_id`` once the trial in ``folder`` wrote a periodic checkpoint; ``record`` gets
    that checkpoint's step and the time of the signal."""
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:
        periodic, info = newest_checkpoint(folder)
        if periodic is not None:
            record["periodic_step"], record["signal_time"] = info["agent_steps"], time.time()
            os.kill(process_id, signum)
            return
        time.sleep(0.02)


def test_sigint_to_the_sweep_stops_every_trial_at_a_checkpoint(ray_local, tmp_path, capsys):
    """SIGINT (Ctrl-C) to the driver; SIGTERM, and the rerun that resumes, on a ray start cluster: test_cluster.py."""
    out = tmp_path / "sweep"
    folder = out / "cartpole-balance" / "drqv2+reset" / "seed_0"
    record = {}
    sender = threading.Thread(
        target=stop_after_first_checkpoint, args=(folder, signal.SIGINT, os.getpid(), record), daemon=True
    )
    sender.start()
    assert main([*RESUMABLE, "--out", str(out), "--no-progress-bar"]) == 75
    sender.join()
    stdout = own_lines(capsys.readouterr().out)
    assert "1 trials in" in stdout[-2] and "0 failed, 1 stopped at a checkpoint." in stdout[-2]
    assert stdout[-1] == "Stopped by SIGINT: run the same command again to resume (exit status 75)."
    stopped, info = newest_checkpoint(folder)
    assert info["agent_steps"] > record["periodic_step"] and info["frames"] < 1200  # written at the signal
    assert (stopped / "checkpoint.json").stat().st_mtime >= record["signal_time"]
    assert not (out / ".stop_requested").exists() and run_status(folder) == "unfinished"


def test_second_sweep_into_the_same_out_is_refused_before_its_ray_starts(tmp_path):
    """Two sweeps on one --out each marked the other's trials failed: the second one (a real process) is refused in
    one line while this process holds the sweep folder's lock, as run_sweep does; nothing is written."""
    from sb3_collapse.sweep.runner import sweep_folder_locked

    out = tmp_path / "sweep"
    argv = [sys.executable, "-m", "sb3_collapse.sweep", *TINY_TRIALS, "--out", str(out), "--no-progress-bar", *TINY]
    with sweep_folder_locked(out):
        second = subprocess.run(argv, check=False, capture_output=True, text=True, timeout=300)
        assert sorted(path.name for path in out.iterdir()) == ["sweep.lock"]
    assert second.returncode == 2, second.stderr
    error = second.stderr.strip().splitlines()[-1]
    assert error.startswith(f"python -m sb3_collapse.sweep: error: sweep folder {out} is in use by pid {os.getpid()} ")
    assert error.endswith(": wait for it to end (or stop it), or give this sweep another --out.")
    assert "ray" not in (second.stdout + second.stderr).lower().replace(error.lower(), "")  # Ray never started
    assert not out.exists()  # the lock file and the folder it was created in are gone with the first sweep


def test_failed_trial_keeps_trains_error_header_and_is_called_retryable_only_if_a_rerun_may_fix_it(
    tmp_path, monkeypatch, capsys
):
    """A trial failing after its first checkpoints: the sweep kept train's error file (its first line: the step it
    failed at) instead of writing the bare traceback over it; the rerun resumes and says where the attempt failed. An
    error of the training code is not retryable; a full disk is."""
    import errno

    from sb3_collapse.commands.sweep import failure_advice
    from sb3_collapse.errors import OutputError, ParameterError
    from sb3_collapse.sweep.runner import retryable, run_trial

    trial = Trial("cartpole-balance", "drqv2", 0)
    training = dict(
        frames=800, action_repeat=20, size=36, hidden_dim=16, feature_dim=8, batch_size=8, seed_frames=200,
        eval_every_frames=0, checkpoint_every_frames=200, collapse_metrics_every_frames=0, replay_sampling="sb3",
    )  # fmt: skip
    original = DrQv2.save

    def failing(self, path, *args, **kwargs):
        if "final_model" in str(path):
            raise RuntimeError("a bug at the final save")
        return original(self, path, *args, **kwargs)

    monkeypatch.setattr(DrQv2, "save", failing)
    outcome = run_trial(trial, str(tmp_path), training, torch_threads=1)
    assert outcome["status"] == "failed" and outcome["retryable"] is False
    error = (trial_dir(tmp_path, trial) / "error.txt").read_text()
    assert error.startswith("failed at agent step 40 (frame 800)\nTraceback") and "a bug at the final save" in error
    monkeypatch.setattr(DrQv2, "save", original)
    capsys.readouterr()
    assert run_trial(trial, str(tmp_path), training, torch_threads=1)["status"] == "finished"
    assert "The previous attempt failed at agent step 40 (frame 800); resuming." in capsys.readouterr().out

    assert retryable(OSError(errno.ENOSPC, "No space left on device")) and retryable(OutputError("full"))
    assert retryable(MemoryError()) and not retryable(ParameterError("lr", "bad")) and not retryable(ValueError())
    assert failure_advice(2, 0) == "Rerun the same command to retry the failed trials."
    assert failure_advice(1, 1).startswith("A rerun would fail this trial the same way: fix the cause first")
    assert failure_advice(3, 1).startswith("Rerun the same command to retry the other 2 failed trials; the 1 marked")


def test_unreadable_result_file_is_failed_with_its_reason_and_neither_run_nor_called_retryable(tmp_path, capsys):
    """A trial whose result file was cut short is not repaired: the dry run shows it failed with the reason and the
    way out (not "would run"); the sweep does not train it (nor start Ray for it), says why in one line and does not
    call it retryable."""
    from sb3_collapse.runfolder import read_result

    out = tmp_path / "sweep"
    folder = trial_dir(out, Trial("walker-walk", "drqv2", 0))
    folder.mkdir(parents=True)
    (folder / "config.json").write_text("{}")
    (folder / "result.json").write_text('{"status": "fini')
    with pytest.raises(InputError) as caught:
        read_result(folder, strict=True)
    line = f"{str(caught.value).rstrip('.')}; move the folder aside to train this seed again."
    argv = ["--tasks", "walker-walk", "--seed-list", "0", "--variants", "drqv2", "--out", str(out), *TINY]
    before = mtimes(out)

    assert main([*argv, "--dry-run"]) == 0
    assert own_lines(capsys.readouterr().out) == [
        f"failed     keep   {folder}: {line}",
        (
            "1 trials: 1 failed; 0 would run (frames done: the newest checkpoint of an unfinished trial); 1 kept as "
            "they are (an unreadable result.json)."
        ),
    ]

    assert main([*argv, "--no-progress-bar"]) == 1
    stdout = capsys.readouterr().out
    assert "1 trials in" in stdout and "0 finished before, 1 failed." in stdout
    assert f"  failed: walker-walk/drqv2/seed_0: {line}" in stdout.splitlines()
    assert "retry" not in stdout.lower() and "choose another folder" not in stdout
    assert mtimes(folder) == {path: mtime for path, mtime in before.items() if folder in path.parents}
    assert run_status(folder) == "failed"


# A fabricated preset: cartpole-balance (1-d actions), 4,000 frames of action repeat 4 = 1,000 agent steps, 2 stacked
# 16x16 frames, a replay buffer of 500 transitions, a checkpoint every 800 frames (200 agent steps), a warm-up of 400
# frames (100 agent steps), an update every 2 agent steps, evaluations (and snapshots) every 1,000 frames.
PLAN_PRESET = dict(
    env="cartpole-balance", frames=4000, action_repeat=4, frame_stack=2, size=16, buffer_size=500,
    checkpoint_every_frames=800, seed_frames=400, train_freq=2, eval_every_frames=1000, snapshots=True,
    feature_dim=4, hidden_dim=8,
)  # fmt: skip


def test_plan_of_a_fabricated_preset_by_hand():
    from sb3_collapse.sweep.plan import sweep_plan

    config = TrainConfig(**PLAN_PRESET).resolve()
    new, resumed = Trial("cartpole-balance", "drqv2", 0), Trial("cartpole-balance", "drqv2", 1)
    plan = sweep_plan({new: config, resumed: config}, {new: 0, resumed: 2000}, frames_per_second=0.5)
    # Replay RAM (FrameStackReplayBuffer): frames of 3x16x16 = 768 bytes, 500 + 2 * (1 + ceil(500 / 250)) = 506 of
    # them; per transition a 4-byte action and 20 bytes of index, reward, done, timeout.
    replay = 506 * 768 + 500 * (4 + 20)
    assert replay == 400_608
    # Parameters (float32): encoder 6*32*9+32 + 3*(32*32*9+32) = 29,504 (16x16 -> 7 -> 5 -> 3 -> 1: 32 features);
    # actor trunk 32*4+4 + layer norm 8, then 4*8+8, 8*8+8, 8*1+1 = 261; a critic 140 + 2 heads of (5*8+8 + 8*8+8 +
    # 8+1) = 398, and its target 398. The model file: every weight, and Adam's two moments of encoder, actor, critic.
    model = 4 * (29_504 + 261 + 398 + 398) + 2 * 4 * (29_504 + 261 + 398)
    assert model == 363_548
    snapshot = 4 * (29_504 + 261)  # encoder and actor
    # Checkpoints at their peak: the chunks of 500 + 2 * 200 transitions (2 kept checkpoints and the new one), 3 models.
    checkpoints = round(replay / 500 * (500 + 2 * 200)) + 3 * model
    snapshots = 5 * snapshot  # evaluations at frames 0, 1000, 2000, 3000, and the final model
    assert plan["bytes"] == {
        "cartpole-balance/drqv2": {
            "replay_ram": replay, "checkpoints_peak": checkpoints, "snapshots": snapshots, "model": model
        }
    }  # fmt: skip
    # Evaluations at frames 0, 1000, 2000 and 3000; collapse checks every 10,000 frames (the default): none in 4,000.
    assert plan["events"] == {"cartpole-balance/drqv2": {"evaluations": 4, "snapshots": 5, "collapse_checks": 0}}
    assert plan["trials_pending"] == 2
    assert plan["frames"] == 4000 + 2000 and plan["agent_steps"] == 1000 + 500
    assert plan["updates"] == (1000 - 100) // 2 + (1000 - 500) // 2  # no update in the warm-up
    assert plan["disk_at_end_bytes"] == 2 * (model + snapshots)
    assert plan["trials_at_once"] == min(2, plan["node"]["cpus"])
    assert plan["hours"] == pytest.approx(6000 / (0.5 * plan["trials_at_once"]) / 3600)


def test_dry_run_refuses_a_machine_too_small_for_one_buffer(tmp_path, monkeypatch, capsys):
    import sb3_collapse.sweep.plan as plan_module

    monkeypatch.setattr(plan_module, "physical_memory_bytes", lambda: 400_000)  # < the 400,608 bytes above
    out = tmp_path / "sweep"
    preset = [
        "--frames", "4000", "--action-repeat", "4", "--frame-stack", "2", "--size", "16", "--buffer-size", "500",
        "--hidden-dim", "8", "--feature-dim", "4", "--seed-frames", "400",
    ]  # fmt: skip
    argv = ["--tasks", "cartpole-balance", "--seeds", "2", "--variants", "drqv2", "--out", str(out), *preset]
    with pytest.raises(SystemExit) as stopped:
        main([*argv, "--dry-run"])
    assert stopped.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert "0.0 GB of RAM, less than one trial's replay buffer" in error and "--buffer-size" in error
    assert not out.exists()
    with pytest.raises(SystemExit):  # the sweep itself too, before Ray or the folder
        main(argv)
    assert not out.exists()

    # A machine that holds it: the plan, and --list shortens the list.
    monkeypatch.setattr(plan_module, "physical_memory_bytes", lambda: 10**9)
    capsys.readouterr()
    assert main([*argv, "--dry-run", "--list", "1"]) == 0
    lines = own_lines(capsys.readouterr().out)
    assert lines[0].startswith("new        run             0 of 4,000 frames")
    assert lines[1] == "... 1 more trials (--list)"
    assert lines[2] == "plan of the 2 trials to train: 8,000 frames (2,000 agent steps), 900 updates in all"
    assert lines[-3].startswith("  at once on this machine: 2 trials (by RAM 2,496 of 1.0 GB;")
    assert lines[-2].startswith("  time: no estimate: pass --frames-per-second")
    assert lines[-1].startswith("2 trials: 2 new; 2 would run")
    assert not out.exists()


# The fabricated preset of PLAN_PRESET as flags (the trials write 2.3 MB each at most: 1.9 MB of checkpoints at their
# peak, 0.4 MB of final model).
PLAN_FLAGS = [
    "--frames", "4000", "--action-repeat", "4", "--frame-stack", "2", "--size", "16", "--buffer-size", "500",
    "--hidden-dim", "8", "--feature-dim", "4", "--seed-frames", "400",
]  # fmt: skip


def test_dry_run_compares_the_plans_disk_with_the_free_space_at_out(tmp_path, monkeypatch, capsys):
    """The dry run compared only the RAM: a plan far larger than the disk of --out said nothing. One trial that cannot
    fit is refused as the RAM is (nothing written, the sweep itself too); a plan larger than the free space warns."""
    import sb3_collapse.sweep.plan as plan_module

    asked = []

    def disk_usage(path):
        asked.append(path)
        return shutil._ntuple_diskusage(10**9, 10**9 - free, free)

    monkeypatch.setattr(plan_module.shutil, "disk_usage", disk_usage)
    out = tmp_path / "new" / "sweep"
    argv = ["--tasks", "cartpole-balance", "--seeds", "2", "--variants", "drqv2", "--out", str(out), *PLAN_FLAGS]
    free = 10**6  # 1 MB
    with pytest.raises(SystemExit) as stopped:
        main([*argv, "--dry-run"])
    assert stopped.value.code == 2 and asked[-1] == tmp_path  # the nearest existing parent of --out
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error.endswith(
        "error: --out: its disk has 1.0 MB free, less than one trial writes (2.3 MB: its checkpoints at their peak, "
        "snapshots and final model): free space or give --out on a larger disk (or pass a smaller --buffer-size); "
        "nothing was written."
    )
    with pytest.raises(SystemExit):  # the sweep itself, before Ray or the folder
        main(argv)
    assert not (tmp_path / "new").exists() and "less than one trial writes" in capsys.readouterr().err

    free = 3 * 10**6  # one trial fits, not both at once
    monkeypatch.setattr(plan_module.os, "cpu_count", lambda: 2)  # 2 trials at once
    assert main([*argv, "--dry-run"]) == 0
    captured = capsys.readouterr()
    assert captured.err.strip().splitlines() == [
        (
            "warning: the 2 trials to train write up to 4.5 MB (2 at once) and the disk of --out has 3.0 MB free: the "
            "trials that meet a full disk fail with their checkpoints intact; free space, then run the same command "
            "again to resume them."
        )
    ]
    assert "  disk to write: up to " in captured.out and "; 3.0 MB free at --out" in captured.out
    free = 10**9
    assert main([*argv, "--dry-run"]) == 0 and capsys.readouterr().err == ""
    assert not (tmp_path / "new").exists()


class _Ray:
    """Ray's get, for _collect: the outcome a trial's task returned, or the error its death raised."""

    def __init__(self, outcome):
        self.outcome = outcome

    def get(self, _ref):
        if isinstance(self.outcome, Exception):
            raise self.outcome
        return self.outcome


class _Bar:
    def write(self, line):
        print(line)

    def set_postfix(self, **_):
        pass

    def update(self):
        pass


def test_a_trial_meeting_a_full_disk_at_its_start_reports_its_own_reason(tmp_path, monkeypatch, capsys):
    """A trial that met a full disk at its start became "the Ray task died" (RayTaskError(OSError)): writing its
    error.txt failed on the full disk too. Its own line reaches the summary, naming the files it could not write, and
    the trial is called retryable. (A full disk by patched writes; a real one in the next test, where one can be
    made.)"""
    import errno

    from sb3_collapse.commands.sweep import print_summary
    from sb3_collapse.sweep import runner
    from sb3_collapse.sweep.runner import SweepSummary, _collect, run_trial

    trial, out = Trial("cartpole-balance", "drqv2", 0), tmp_path / "sweep"
    folder = trial_dir(out, trial)

    def full_disk_train(config):  # as train says a run folder it cannot write at its start
        try:
            raise OSError(errno.ENOSPC, "No space left on device", str(folder / "run.lock"))
        except OSError as error:
            raise InputError(f"run folder: could not write {error.filename} (No space left on device): free "
                             "space, then run the same command again.") from None  # fmt: skip

    def full_disk_write(path, _text):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(runner, "train", full_disk_train)
    monkeypatch.setattr(runner, "write_text_atomically", full_disk_write)
    outcome = run_trial(trial, str(out), {"frames": 800})
    line = (
        f"InputError: run folder: could not write {folder / 'run.lock'} (No space left on device): free space, then "
        f"run the same command again (and its error.txt could not be written: {folder / 'error.txt'}: No space left "
        "on device)."
    )
    assert outcome == {"trial": str(trial), "status": "failed", "error": line, "retryable": True}
    summary = SweepSummary(trials=[trial], skipped=[], finished=[], failed={})
    _collect(_Ray(outcome), None, trial, out, summary, _Bar())
    capsys.readouterr()
    assert print_summary(summary, str(out)) == 1
    lines = capsys.readouterr().out.splitlines()
    assert lines[1:] == [f"  failed: {trial}: {line}", "Rerun the same command to retry the failed trials."]

    # The Ray task itself died, and the driver cannot write its error file either: the summary says both.
    summary = SweepSummary(trials=[trial], skipped=[], finished=[], failed={})
    _collect(_Ray(RuntimeError("worker died\ndetails")), None, trial, out, summary, _Bar())
    print_summary(summary, str(out))
    assert (
        f"  failed: {trial}: RuntimeError: worker died (and its error.txt could not be written: "
        f"{folder / 'error.txt'}: No space left on device)."
    ) in capsys.readouterr().out.splitlines()
    assert not (folder / "error.txt").exists()


@pytest.mark.skipif(os.geteuid() != 0, reason="mounting a 1 MB tmpfs needs root")
def test_a_trial_on_a_real_full_disk_at_its_start(tmp_path):
    """The same on a 1 MB tmpfs filled to the last byte, with the real train (where this process may mount one)."""
    from sb3_collapse.sweep.runner import run_trial

    disk = tmp_path / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(disk)], check=False).returncode != 0:
        pytest.skip("no tmpfs can be mounted here")
    try:
        with contextlib.suppress(OSError), open(disk / "fill", "wb", buffering=0) as file:
            while True:  # to the last byte
                file.write(b"\0" * 4096)
        trial, training = Trial("cartpole-balance", "drqv2", 0), {"frames": 800, "action_repeat": 20, "size": 36}
        outcome = run_trial(trial, str(disk / "sweep"), training, torch_threads=1)
        folder = trial_dir(disk / "sweep", trial)
        assert outcome["status"] == "failed" and outcome["retryable"] is True
        assert f"could not write {folder / 'run.lock'} (No space left on device)" in outcome["error"]
        assert f"(and its error.txt could not be written: {folder / 'error.txt'}: No space left" in outcome["error"]
    finally:
        subprocess.run(["umount", str(disk)], check=False)


def _hold_run_lock(folder):
    """A process that holds ``folder``'s run lock (as a live train does) until its stdin closes."""
    code = (
        "import sys; from sb3_collapse.run.lock import RunLock\n"
        f"with RunLock({str(folder)!r}):\n    print('held', flush=True); sys.stdin.read()"
    )
    holder = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    return holder


def test_a_trial_folder_held_by_another_process_is_left_as_it_is(tmp_path, monkeypatch, capsys):
    """A sweep wrote error.txt into a trial folder a live train held, called the trial permanently failed and the
    folder then failed every rerun. Now it is in use: nothing is written into it, the dry run and the summary say so,
    and the same command once the holder ended trains it."""
    from sb3_collapse.runfolder import run_folder_owner as owner_of
    from sb3_collapse.sweep import runner
    from sb3_collapse.sweep.runner import run_trial

    out = tmp_path / "sweep"
    trial = Trial("cartpole-balance", "drqv2", 0)
    folder = trial_dir(out, trial)
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({"env": "cartpole-balance", "lr": "other settings"}))
    argv = ["--tasks", "cartpole-balance", "--seed-list", "0", "--variants", "drqv2", "--out", str(out), *PLAN_FLAGS]
    holder = _hold_run_lock(folder)
    try:
        owner = f"pid {holder.pid} on host "
        before = mtimes(folder)
        assert main([*argv, "--dry-run"]) == 0
        lines = own_lines(capsys.readouterr().out)
        assert lines[0].startswith(f"running    in use {folder}: held by {owner}")
        assert lines[0].endswith("; left as it is, run the same command once it ends")
        assert lines[-1] == (
            "1 trials: 1 running; 0 would run (frames done: the newest checkpoint of an unfinished trial); 1 in use "
            "by another process (run once it ends)."
        )
        # The sweep: no Ray task for it (none started: it is the only trial); exit status 75, run again later.
        assert main([*argv, "--no-progress-bar"]) == 75
        stdout = capsys.readouterr().out
        assert "0 finished before, 0 failed, 1 in use by another process." in stdout
        assert f"  in use: {trial}: its folder is held by {owner}" in stdout
        assert "Run the same command again once the process holding it has ended: the sweep trains it then (exit " \
            "status 75)." in stdout  # fmt: skip
        # A trial's task finds it held (it was taken after the driver looked): the same, with other settings too
        # (its folder would have been deleted).
        assert run_trial(trial, str(out), {"frames": 800}) == {"trial": str(trial), "status": "in use", "error": ANY}
        # Taken between that look and train's lock: train's lock says so, and nothing is written either.
        looks = [None]  # the first look misses the holder, the look after train's refusal sees it
        monkeypatch.setattr(runner, "run_folder_owner", lambda folder: looks.pop() if looks else owner_of(folder))
        monkeypatch.setattr(runner, "settings_differences", lambda saved, config: [])
        outcome = run_trial(trial, str(out), {"frames": 800, "action_repeat": 20, "size": 36}, torch_threads=1)
        assert outcome["status"] == "in use" and outcome["error"].startswith(owner)
        assert mtimes(folder) == before and not (folder / "error.txt").exists()
    finally:
        holder.stdin.close()
        holder.wait(timeout=60)
    monkeypatch.undo()
    assert run_status(folder) != "running"


class _Anything:
    def __eq__(self, other):
        return isinstance(other, str) and other.startswith("pid ")


ANY = _Anything()


def test_dry_run_says_what_the_real_command_would_refuse(tmp_path, capsys):
    """The dry run of a folder another sweep holds said "2 would run" without saying the command would be refused, and
    called a checkpoint of another version "resume" (train refuses it): it now says both, and the sweep leaves such a
    trial as it is, failed with the way out, without starting Ray for it."""
    from sb3_collapse import __version__
    from sb3_collapse.sweep.runner import sweep_folder_locked

    out = tmp_path / "sweep"
    old = trial_dir(out, Trial("walker-walk", "drqv2", 0))
    step = old / "checkpoints" / "step_000000000100"
    step.mkdir(parents=True)
    (old / "config.json").write_text("{}")
    (step / "checkpoint.json").write_text(json.dumps({"frames": 400, "format": 1, "version": "0.0.1"}))
    argv = ["--tasks", "walker-walk", "--seed-list", "0", "1", "--variants", "drqv2", "--out", str(out), *TINY]
    line = (
        f"its checkpoint {step} was written by sb3-collapse 0.0.1, this is {__version__}: rerun with the version that "
        "wrote it, or move the folder aside to train this seed again."
    )
    before = mtimes(out)
    with sweep_folder_locked(out):
        assert main([*argv, "--dry-run"]) == 0
    lines = own_lines(capsys.readouterr().out)
    assert lines[0] == f"unfinished keep   {old}: {line}"
    assert lines[-2] == (
        "2 trials: 1 new, 1 unfinished; 1 would run (frames done: the newest checkpoint of an unfinished trial); 1 "
        "kept as they are (a checkpoint of another version)."
    )
    assert lines[-1].startswith(f"Note: sweep folder {out} is in use by pid {os.getpid()} on host ")
    assert lines[-1].endswith(
        ": without --dry-run this command is refused until it ends; wait for it to end (or stop it), or give this "
        "sweep another --out."
    )
    assert main([*argv, "--dry-run"]) == 0 and "Note: sweep folder" not in capsys.readouterr().out  # once it ended

    argv = ["--tasks", "walker-walk", "--seed-list", "0", "--variants", "drqv2", "--out", str(out), *TINY]
    assert main([*argv, "--no-progress-bar"]) == 1
    stdout = capsys.readouterr().out
    assert f"  failed: walker-walk/drqv2/seed_0: {line}" in stdout.splitlines() and "retry" not in stdout.lower()
    assert {path: mtime for path, mtime in mtimes(out).items() if old in path.parents} == before
