"""
The sweep command on the sweep of the session's tiny reproduction (tests/conftest.py). Apart from
tests/sweep/test_sweep.py so that under xdist (a file to a worker) the other sweep tests run while the reproduction is
made, and only these wait for it, last.
"""

import itertools
import json
import shutil
import zipfile

import pytest

from sb3_collapse import DrQv2
from sb3_collapse.commands.sweep import main
from sb3_collapse.report.collapse_figure import agent_class
from sb3_collapse.runfolder import run_status
from sb3_collapse.sweep import (
    GRID_VARIANTS,
    Trial,
    expand_trials,
    run_sweep,
    trial_config,
    trial_dir,
)
from sb3_collapse.sweep.reproduction import TINY_SCALE
from tests.sweep.sweeps import TINY, mtimes, own_lines, read_csv

# The session's tiny reproduction (tests/conftest.py) trained its sweep through this package's sweep: Figure 5's trials
# (walker-walk, hopper-stand, finger-spin x drqv2, drqv2+reset x seeds 0-3: 1000 frames = 20 agent steps of 50 frames,
# 32x32, learning from frame 500, evaluations at frames 0 and 500 and the final model's at 1000, collapse checks every
# 250 frames, the rule's window 500 frames: a reset at frame 500 and none at 1000, the budget's end; snapshots only
# for drqv2), then the transplant grid's nine walker-walk cells (seed 0). The tests below read it (never modify it:
# copy it first).
TASKS = ["walker-walk", "hopper-stand", "finger-spin"]
TINY_STEPS = 1000 // TINY_SCALE.training["action_repeat"]  # agent steps of a trial
REPRODUCED_TRIALS = ["--tasks", *TASKS, "--seeds", "4", "--variants", "drqv2", "drqv2+reset"]
RESULT_KEYS = {
    "status", "task", "variant", "seed", "frames", "agent_steps", "final_eval", "saved_model_eval", "resets",
    "reset_frames", "escaped", "escape_frame", "wall_time_s", "timings", "resumes", "divergence_warnings",
}  # fmt: skip


@pytest.fixture
def reproduced_sweep(tiny_reproduction):
    """The sweep folder of the session's tiny reproduction (read it, never modify it)."""
    return tiny_reproduction[0] / "sweep"


def training_flags(sweep):
    """:return: the training settings in the reproduction's ``sweep`` folder as the sweep's command line takes them"""
    training = json.loads((sweep / "sweep.json").read_text())["training"]
    return [item for name, value in training.items() for item in (f"--{name.replace('_', '-')}", str(value))]


def command_line_copy(sweep, out):
    """
    Copy ``sweep`` (the reproduction's, read only) to ``out``, for the sweep's command line to run into: the
    reproduction records the training settings it gives, the command line every one, and a default is no change.

    :return: ``out``
    """
    shutil.copytree(sweep, out)  # copy2 keeps the modification times
    return out


READER = pytest.mark.timeout(2400)  # a test that may be the first reader of the session's tiny reproduction


@READER
def test_tiny_sweep_writes_the_trial_contract(reproduced_sweep):
    sweep = reproduced_sweep
    settings = json.loads((sweep / "sweep.json").read_text())
    assert settings["tasks"] == TASKS and settings["variants"] == ["drqv2", "drqv2+reset", *GRID_VARIANTS]
    assert settings["seeds"] == [0, 1, 2, 3] and settings["training"]["frames"] == 1000
    assert settings["snapshot_variants"] == ["drqv2"]
    assert settings["resources"] == {"cpus_per_trial": 1, "gpus_per_trial": 0, "address": None}
    assert not (sweep / "sweep.lock").exists()  # held while the sweep ran, deleted at its end
    for task, variant, seed in itertools.product(TASKS, ("drqv2", "drqv2+reset"), range(4)):
        folder = sweep / task / variant / f"seed_{seed}"
        config = json.loads((folder / "config.json").read_text())
        assert config["variant"] == variant and config["transplant"] is None and config["env"] == task
        assert config["reset_rule"] == (variant == "drqv2+reset") and config["run_dir"] == str(folder)
        assert config["device"] == "cpu" and config["torch_threads"] == 1 and config["progress_bar"] is False

        evaluations = read_csv(folder / "eval.csv")
        assert list(evaluations[0]) == ["frame", "step", "mean_reward", "std_reward", "episodes", "wall_time_s"]
        assert [int(row["frame"]) for row in evaluations] == [0, 500]  # scheduled; 1000 (the budget): the final model's
        assert (folder / "progress.csv").stat().st_size > 0 and list(folder.glob("events.out.tfevents.*"))
        assert zipfile.is_zipfile(folder / "final_model.zip")
        assert config["snapshots"] is (variant == "drqv2")  # the reproduction's snapshot variants
        if variant == "drqv2":
            snapshots = sorted(p.name for p in (folder / "snapshots").iterdir())
            assert snapshots == [f"snapshot_{frame:010d}_frames.zip" for frame in (0, 500, 1000)]
        else:
            assert not (folder / "snapshots").exists()

        metrics = read_csv(folder / "collapse_metrics.csv")
        assert list(metrics[0]) == ["frame", "step", "tag", "value"]
        frames = {int(row["frame"]) for row in metrics}
        assert frames <= {250, 500, 750, 1000} and 1000 in frames
        tags = {row["tag"] for row in metrics if row["frame"] == "1000"}
        assert {"collapse/mlp1/dead_fraction", "collapse/mlp1/srank", "collapse/action_std"} <= tags
        # Gradient norms once an update happened: with the rule, the reset at frame 500 restarts the warm-up.
        assert ("collapse/mlp1/grad_norm" in tags) == (variant == "drqv2")

        result = json.loads((folder / "result.json").read_text())
        assert set(result) == RESULT_KEYS
        assert result["status"] == "finished" and result["task"] == task and result["variant"] == variant
        assert result["seed"] == seed and result["frames"] == 1000 and result["agent_steps"] == TINY_STEPS
        assert result["final_eval"]["frame"] == 500  # the last scheduled evaluation
        assert result["final_eval"]["mean_reward"] == float(evaluations[-1]["mean_reward"])
        assert result["saved_model_eval"]["frame"] == 1000 and result["saved_model_eval"]["episodes"] == 1
        assert result["wall_time_s"] > 0
        assert run_status(folder) == "finished" and not list(folder.glob(".*.tmp"))
        if variant == "drqv2":
            assert result["escaped"] is None and result["resets"] == 0 and result["reset_frames"] == []
            assert not (folder / "collapse_events.csv").exists()
        else:
            events = read_csv(folder / "collapse_events.csv")
            # No reset at frame 1000: that window ends with the budget (the saved model is the evaluated one).
            assert [(row["event"], int(row["frame"])) for row in events] == [("reset", 500)]
            assert result["resets"] == 1 and result["reset_frames"] == [500]
            assert result["escaped"] is False and result["escape_frame"] is None


@READER
def test_resume_skips_finished_trials_and_reruns_unfinished_ones(reproduced_sweep, ray_local, tmp_path, capsys):
    out = command_line_copy(reproduced_sweep, tmp_path / "sweep")
    before = {path: mtime for path, mtime in mtimes(out).items() if path.name != "sweep.json"}
    # The same command again: nothing to run, no trial file touched (Ray is not even needed).
    assert main([*REPRODUCED_TRIALS, "--out", str(out), "--no-progress-bar", *training_flags(reproduced_sweep)]) == 0
    assert "0 finished now (0 resumed from a checkpoint), 24 finished before, 0 failed" in capsys.readouterr().out
    assert {path: mtime for path, mtime in mtimes(out).items() if path.name != "sweep.json"} == before

    # An interrupted trial: no result.json, a leftover file. It runs again from an empty folder; the other is kept.
    partial = out / "walker-walk" / "drqv2" / "seed_0"
    kept = out / "walker-walk" / "drqv2+reset" / "seed_0"
    (partial / "result.json").unlink()
    (partial / "leftover.txt").write_text("from the interrupted attempt")
    assert run_status(partial) == "unfinished"
    settings = json.loads((out / "sweep.json").read_text())
    trials = expand_trials(["walker-walk"], ["drqv2", "drqv2+reset"], [0])
    # the library call behind the CLI, as the reproduction made it (snapshots for drqv2 only)
    summary = run_sweep(trials, out, settings["training"], progress_bar=False, snapshot_variants=["drqv2"])
    assert summary.finished == [Trial("walker-walk", "drqv2", 0)] and summary.skipped == [trials[1]] and summary.ok
    assert run_status(partial) == "finished" and not (partial / "leftover.txt").exists()
    assert [int(row["frame"]) for row in read_csv(partial / "eval.csv")] == [0, 500]
    assert mtimes(kept) == {path: mtime for path, mtime in before.items() if kept in path.parents}


@READER
def test_changed_training_settings_are_refused(reproduced_sweep, tmp_path, capsys):
    sweep = command_line_copy(reproduced_sweep, tmp_path / "sweep")
    before = mtimes(sweep)
    argv = [*REPRODUCED_TRIALS, "--out", str(sweep), *training_flags(reproduced_sweep),
            "--frames", "2000", "--lr", "0.001"]  # fmt: skip
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "--frames: 1000 in sweep.json, 2000 now" in err and "--lr: the presets' in sweep.json, 0.001 now" in err
    named = {line.split()[0].rstrip(":") for line in err.splitlines() if " in sweep.json, " in line}
    assert named == {"--frames", "--lr", "--buffer-size"}  # each task's buffer: from the frames; nothing else
    assert "--allow-changed-settings" in err
    assert json.loads((sweep / "sweep.json").read_text())["training"]["frames"] == 1000
    assert main([*argv, "--allow-changed-settings", "--dry-run"]) == 0
    assert mtimes(sweep) == before  # neither the refused run nor the dry run wrote anything


@READER
def test_dry_run_lists_trials_and_their_status(reproduced_sweep, tmp_path, capsys):
    sweep = command_line_copy(reproduced_sweep, tmp_path / "reproduced")
    argv = ["--tasks", "walker-walk", "--seeds", "5", "--variants", "drqv2", "drqv2+reset", "--out", str(sweep)]
    before = mtimes(sweep)
    assert main([*argv, *training_flags(reproduced_sweep), "--dry-run"]) == 0
    lines = own_lines(capsys.readouterr().out)
    for seed in range(4):
        assert lines[seed] == (
            f"finished   skip        1,000 of 1,000 frames  {sweep / 'walker-walk' / 'drqv2' / f'seed_{seed}'}"
        )
    assert lines[4] == f"new        run             0 of 1,000 frames  {sweep / 'walker-walk' / 'drqv2' / 'seed_4'}"
    assert lines[-1].startswith("10 trials: 2 new, 8 finished; 2 would run")
    assert mtimes(sweep) == before

    # Every status, on fabricated folders.
    out = tmp_path / "sweep"
    finished, failed, partial = (trial_dir(out, Trial("walker-walk", "drqv2", seed)) for seed in (0, 1, 2))
    for folder in (finished, failed, partial):
        folder.mkdir(parents=True)
    (finished / "result.json").write_text(json.dumps({"status": "finished"}))
    (failed / "error.txt").write_text("Traceback ...")
    (partial / "config.json").write_text("{}")
    assert [run_status(f) for f in (finished, failed, partial, out / "nothing")] == [
        "finished", "failed", "unfinished", "new"
    ]  # fmt: skip
    # An unfinished trial with a checkpoint is resumed: the dry run says from which frame.
    (partial / "checkpoints" / "step_000000000100").mkdir(parents=True)
    (partial / "checkpoints" / "step_000000000100" / "checkpoint.json").write_text(json.dumps({"frames": 400}))
    capsys.readouterr()
    assert (
        main(["--tasks", "walker-walk", "--seeds", "3", "--variants", "drqv2", "--out", str(out), *TINY, "--dry-run"])
        == 0
    )
    assert f"unfinished resume        400 of 1,000 frames  {partial}" in own_lines(capsys.readouterr().out)


@READER
def test_failing_trial_is_reported_and_a_transplant_grid_cell_starts_from_the_checkpoints(
    reproduced_sweep, ray_local, tmp_path, capsys
):
    """One sweep of two grid cells (run side by side): the one whose checkpoint is not a zip fails, is reported and not
    called retryable; the other starts from the reproduction's checkpoints (the networks' sizes of TINY) and
    finishes."""
    good = reproduced_sweep / "walker-walk" / "drqv2" / "seed_0" / "final_model.zip"
    bad = reproduced_sweep / "walker-walk" / "drqv2+reset" / "seed_0" / "final_model.zip"
    broken = tmp_path / "broken.zip"
    broken.write_text("not a checkpoint")
    out = tmp_path / "grid"
    argv = ["--tasks", "walker-walk", "--seed-list", "1", "--variants", "cnn-bad_mlp-blank", "cnn-good_mlp-bad",
            "--out", str(out), "--good-cnn", str(good), "--bad-cnn", str(broken), "--bad-mlp", f"walker-walk={bad}",
            "--no-progress-bar", *TINY, "--frames", "250", "--action-repeat", "25",
            "--eval-every-frames", "1000"]  # fmt: skip
    assert main(argv) == 1
    stdout = capsys.readouterr().out
    failed = out / "walker-walk" / "cnn-bad_mlp-blank" / "seed_1"
    assert "1 finished now (0 resumed from a checkpoint), 0 finished before, 1 failed" in stdout
    # A checkpoint that is not a zip fails every rerun the same way: not called retryable.
    assert (
        f"failed, and would again at a rerun: walker-walk/cnn-bad_mlp-blank/seed_1 (see {failed / 'error.txt'})"
        in stdout
    )
    assert "A rerun would fail this trial the same way: fix the cause first" in stdout
    assert "Rerun the same command" not in stdout
    error = (failed / "error.txt").read_text()
    assert error.startswith("Traceback (most recent call last)") and "is not a zip file" in error
    folder = out / "walker-walk" / "cnn-good_mlp-bad" / "seed_1"
    assert run_status(failed) == "failed" and run_status(folder) == "finished"
    assert json.loads((out / "sweep.json").read_text())["checkpoints"] == {
        "good_cnn": {"walker-walk": str(good)}, "bad_cnn": {"walker-walk": str(broken)},
        "bad_mlp": {"walker-walk": str(bad)},
    }  # fmt: skip

    # The transplant grid cell: the good run's encoder, the reset run's actor.
    config = json.loads((folder / "config.json").read_text())
    assert config["transplant"] == {"cnn": "good", "mlp": "bad"} and config["variant"] == "cnn-good_mlp-bad"
    assert (config["init_cnn"], config["init_mlp"], config["init_critic"]) == (str(good), str(bad), None)
    assert config["reset_rule"] is False
    assert DrQv2.load(folder / "final_model.zip").init_from == {"cnn": str(good), "mlp": str(bad)}
    assert json.loads((folder / "result.json").read_text())["variant"] == "cnn-good_mlp-bad"


@READER
def test_report_renders_from_the_tiny_real_sweep(reproduced_sweep, tmp_path):
    from sb3_collapse.commands.report_pipelines import write_report
    from sb3_collapse.report import ReportSettings

    sweep = reproduced_sweep
    # At frame 1000 the plain runs have an mlp1 gradient norm, the reset runs (reset at frame 500, no update since:
    # the warm-up restarts) have none: collapse "unknown" for them, not stuck. Figure 5's walker-walk trials only.
    report = write_report(
        sweep,
        out=tmp_path / "report",
        settings=ReportSettings(collapse_checks=1),
        tasks=["walker-walk"],
        variants=["drqv2", "drqv2+reset"],
        progress=False,
    )
    assert {path.name for path in report.files} == {
        "figure5.png",
        "summary.csv",
        "summary.md",
        "index.html",
        "collapse_metrics_online_walker-walk_drqv2.png",
        "collapse_metrics_online_walker-walk_drqv2+reset.png",
        "collapse_agents.csv",
        # Figure 4 on the fixed probing set: the rollouts the reproduction's probe recorded for walker-walk/drqv2
        "collapse_metrics_walker-walk_drqv2.png",
        "collapse_metrics_walker-walk_drqv2.csv",
    }
    for path in report.files:
        assert path.parent == tmp_path / "report" and path.stat().st_size > 0
    assert (tmp_path / "report" / "figure5.png").read_bytes().startswith(b"\x89PNG\r\n\x1a\n")
    rows = {row.variant: row for row in report.rows}
    assert set(rows) == {"drqv2", "drqv2+reset"}
    for variant, row in rows.items():
        folders = [sweep / "walker-walk" / variant / f"seed_{seed}" for seed in range(4)]
        finals = [json.loads((folder / "result.json").read_text())["final_eval"]["mean_reward"] for folder in folders]
        assert row.task == "walker-walk" and row.seeds == 4 and row.unfinished == 0 and row.final_frame == 500
        assert row.final_mean == pytest.approx(sum(finals) / 4)
        assert row.last_evals == 2  # the scheduled evaluations at frames 0 and 500 (1000: the final model's, apart)
    assert rows["drqv2"].resets_total == 0 and rows["drqv2"].reset_rule_seeds == 0
    last_grad_norms = [
        float(
            [r for r in read_csv(folder / "collapse_metrics.csv") if r["tag"] == "collapse/mlp1/grad_norm"][-1]["value"]
        )
        for folder in (sweep / "walker-walk" / "drqv2" / f"seed_{seed}" for seed in range(4))
    ]
    assert rows["drqv2"].collapse_unknown == 0
    assert rows["drqv2"].stuck == sum(norm <= 1e-3 for norm in last_grad_norms)
    assert rows["drqv2+reset"].resets_total == 4 and rows["drqv2+reset"].seeds_reset == 4
    assert rows["drqv2+reset"].collapse_unknown == 4 and rows["drqv2+reset"].stuck == 0
    markdown = (tmp_path / "report" / "summary.md").read_text()
    assert "drqv2+reset" in markdown and "walker-walk" in markdown
    assert read_csv(tmp_path / "report" / "summary.csv")[0]["task"] == "walker-walk"
    # Figure 4's rows (online): one seed per class of final return; the reset at frame 500 marked
    agents = [a for a in report.collapse_online[("walker-walk", "drqv2+reset")] if a.trial is not None]
    assert agents and {a.trial.seed for a in agents} <= set(range(4)) and all(a.resets == [500] for a in agents)
    assert all(agent_class(a.final_return) == a.role for a in agents)


@pytest.mark.timeout(2400)  # it may be the first reader of the session's tiny reproduction (tests/test_reproduce.py)
def test_probe_sweep_on_the_tiny_real_sweep(tiny_reproduction):
    """``probe sweep`` of real trials: the probe stage of the session's tiny reproduction (tests/conftest.py) on its
    four walker-walk DrQ-v2 trials, split at the median of their final returns (tiny runs do not reach 900)."""
    sweep = tiny_reproduction[0] / "sweep"
    finals = {
        seed: json.loads((sweep / "walker-walk" / "drqv2" / f"seed_{seed}" / "result.json").read_text())["final_eval"][
            "mean_reward"
        ]
        for seed in range(4)
    }
    summary = json.loads((sweep / "probe" / "walker-walk_drqv2" / "summary.json").read_text())
    cut = summary["success_return"]
    assert summary["failure_return"] == cut and sorted(finals.values())[1] < cut < sorted(finals.values())[2]
    rows = {a["seed"]: a["row"] for a in summary["agents"]}
    assert rows == {s: "well-performing" if v >= cut else "poorly performing" for s, v in finals.items()}
    assert all(a["checkpoints"] == 3 for a in summary["agents"])  # snapshots at frames 0, 500 and 1000
    assert (sweep / "probe" / "walker-walk_drqv2" / "figure2.png").read_bytes().startswith(b"\x89PNG\r\n\x1a\n")


@READER
def test_tiny_sweep_records_its_plan_and_the_report_shows_it(reproduced_sweep, ray_local, tmp_path, capsys):
    """The reproduction's sweep records no plan (its stages call the library): one of its trials, made unfinished in
    a copy, is trained again through the command line, which records its plan."""
    from sb3_collapse.report.html import settings_table
    from sb3_collapse.sweep.plan import trial_events

    out = command_line_copy(reproduced_sweep, tmp_path / "sweep")
    (out / "walker-walk" / "drqv2+reset" / "seed_0" / "result.json").unlink()  # unfinished: trained again
    argv = ["--tasks", "walker-walk", "--seeds", "4", "--variants", "drqv2+reset", "--out", str(out)]
    assert main([*argv, "--no-progress-bar", *training_flags(reproduced_sweep)]) == 0
    assert "1 finished now (0 resumed from a checkpoint), 3 finished before, 0 failed" in capsys.readouterr().out
    settings = json.loads((out / "sweep.json").read_text())
    plan = settings["plan"]  # as the sweep planned its pending trial: 1,000 frames
    assert plan["trials_pending"] == 1 and plan["frames"] == 1000 and plan["agent_steps"] == TINY_STEPS
    assert set(plan["bytes"]) == {"walker-walk/drqv2+reset"}
    assert "trials_pending" in settings_table(settings)
    # The plan's counts (by the callbacks' own rule) are what each trial wrote (the one trained now and the
    # reproduction's): evaluations at frames 0 and 500 (1000 is the budget's end), no snapshots (the command line
    # gave none), collapse checks at frames 250, 500, 750 and 1000.
    assert plan["events"] == {"walker-walk/drqv2+reset": {"evaluations": 2, "snapshots": 0, "collapse_checks": 4}}

    def written(folder):
        return {
            "evaluations": len(read_csv(folder / "eval.csv")),
            "snapshots": len(list((folder / "snapshots").glob("*.zip"))),
            "collapse_checks": len({row["frame"] for row in read_csv(folder / "collapse_metrics.csv")}),
        }

    for folder in (out / "walker-walk" / "drqv2+reset").glob("seed_*"):
        assert written(folder) == plan["events"]["walker-walk/drqv2+reset"], folder
    # The same rule for the reproduction's trials of every task: its drqv2 ones kept snapshots of both evaluations
    # and of the final model.
    reproduced = json.loads((reproduced_sweep / "sweep.json").read_text())
    for task, variant, seed in itertools.product(TASKS, ("drqv2", "drqv2+reset"), range(4)):
        trial = Trial(task, variant, seed)
        config = trial_config(trial, reproduced_sweep, reproduced["training"], {}, snapshot_variants=["drqv2"])
        events = trial_events(config)
        assert events == {"evaluations": 2, "snapshots": 3 if variant == "drqv2" else 0, "collapse_checks": 4}
        assert written(trial_dir(reproduced_sweep, trial)) == events, trial
