"""``python -m sb3_collapse.reproduce``: the paper's protocol at the tiny scale, once per session (tests/conftest.py's
``tiny_reproduction``), its rerun, its plan and its bad input."""

import csv
import json
import re
import shutil

import matplotlib.image
import pytest

from sb3_collapse.commands.reproduce import main, paper_items
from sb3_collapse.paper import PAPER
from sb3_collapse.sweep.reproduction import PAPER_MD, TINY_SCALE, Reproduction, split_classes

# The first test that reads the session's tiny reproduction runs it: minutes on a quiet 2-core CPU, far more on a busy
# one (benchmarks/README.md#reproduce-tiny), above the suite's 600 s per test.
pytestmark = pytest.mark.timeout(2400)
PNG = b"\x89PNG\r\n\x1a\n"
ITEMS = [
    "Figure 2", "Figure 3(a)", "Figure 3(b)", "Figure 4", "Figure 5", "Figure 6", "Figure 7", "Figure 8", "Figure 9",
    "Tables 1-6", "Table 7", "Headline", "Proposition 1",
]  # fmt: skip


def read_csv(path):
    with open(path, newline="") as file:
        return list(csv.DictReader(file))


def finals(sweep, task, variant):
    """seed -> the final return of each trial, read from its result file."""
    folder = sweep / task / variant
    return {
        int(p.name.removeprefix("seed_")): json.loads((p / "result.json").read_text())["final_eval"]["mean_reward"]
        for p in sorted(folder.iterdir())
    }


def mtimes(folder):
    return {path: path.stat().st_mtime_ns for path in folder.rglob("*") if path.is_file()}


def test_split_classes():
    assert split_classes([1.0, 2.0, 3.0, 4.0], "x").success_return == 2.5
    assert split_classes([1.0, 2.0, 2.0, 2.0], "x").success_return == 1.5  # the median ties: the nearest gap
    three = split_classes([1.0, 2.0, 3.0, 4.0, 5.0, 6.0], "x", 3)
    assert (three.failure_return, three.success_return) == (2.5, 4.5)
    assert split_classes([0.0, 0.0], "x").success_return == 0.0  # one value: every agent well-performing


def test_tiny_reproduction_holds_every_figure_and_table(tiny_reproduction):
    out, status, output = tiny_reproduction
    assert status == 0, output
    sweep = out / "sweep"
    items = {name: paths for name, _, paths in paper_items(_job(out))}
    assert list(items) == ITEMS
    for name, paths in items.items():
        for path in paths:
            assert path.is_file() and path.stat().st_size > 0, (name, path)
            if path.suffix == ".png":
                assert path.read_bytes().startswith(PNG)
                assert matplotlib.image.imread(path)[..., :3].std() > 0.01, path  # not a blank image
    text = (out / PAPER_MD).read_text()
    assert "missing" not in text and all(f"| {name} |" in text for name in ITEMS)
    assert "tiny scale: the 2-way split" in text and "not the paper's 900/30" in text  # the classes said
    stages = {p.stem: json.loads(p.read_text()) for p in (out / "stages").glob("*.json")}
    assert set(stages) == {"sweep", "transplant", "probe", "film", "report"}
    # Figure 5 and its table: each task and variant's mean final return is that of its trials' result files
    for row in read_csv(out / "report" / "summary.csv"):
        if row["variant"] in ("drqv2", "drqv2+reset"):
            values = finals(sweep, row["task"], row["variant"])
            assert int(row["seeds"]) == len(values) == 4
            assert float(row["final_mean"]) == pytest.approx(sum(values.values()) / 4, rel=1e-6)
    # Snapshots: the DrQ-v2 trials only (Figure 2 and Figures 4/8/9 read them), at frames 0, 500 and 1000
    for task in PAPER.figure5_tasks:
        for seed in range(4):
            names = sorted(p.name for p in (sweep / task / "drqv2" / f"seed_{seed}" / "snapshots").iterdir())
            assert names == [f"snapshot_{f:010d}_frames.zip" for f in (0, 500, 1000)]
            assert not (sweep / task / "drqv2+reset" / f"seed_{seed}" / "snapshots").exists()
    assert not list((sweep / "walker-walk").glob("cnn-*/seed_*/snapshots"))
    # Study 2: two different good and two different bad donors, in their classes; Figure 3(a) counts the cells'
    # trials at the report's threshold
    donors = stages["transplant"]["donors"]
    picked = donors["tasks"]["walker-walk"]
    walker = finals(sweep, "walker-walk", "drqv2")
    assert len({picked[k]["seed"] for k in ("good_cnn", "good_mlp", "bad_cnn", "bad_mlp")}) == 4
    for key, donor in picked.items():
        assert donor["final_return"] == walker[donor["seed"]]
        good = walker[donor["seed"]] >= donors["success_return"]
        assert good == key.startswith("good") and (good or walker[donor["seed"]] < donors["failure_return"])
    success = stages["report"]["classes"]["success_return"]
    grid = {f"cnn-{row['cnn']}_mlp-{row['mlp']}": row for row in read_csv(out / "report" / "transplant_grid.csv")}
    assert len(grid) == 9
    for variant, row in grid.items():
        cell = finals(sweep, "walker-walk", variant)
        assert int(row["seeds"]) == len(cell) and int(row["successes"]) == sum(v >= success for v in cell.values())
    assert (out / "report" / "table7.md").read_text().count("|") > 10
    # Figure 2, Tables 1-6: the probed agents are the sweep's walker-walk DrQ-v2 trials, both rows, 3 snapshots each
    probe = json.loads((sweep / "probe" / "walker-walk_drqv2" / "summary.json").read_text())
    assert {a["seed"]: a["final_return"] for a in probe["agents"]} == walker
    assert {a["row"] for a in probe["agents"]} == {"well-performing", "poorly performing"}
    assert all(a["checkpoints"] == 3 for a in probe["agents"])
    tables = read_csv(sweep / "probe" / "walker-walk_drqv2" / "tables_1_6.csv")
    assert {t["table"] for t in tables} >= {"1", "2", "3", "4", "5", "6"}
    # Figures 4, 8, 9: the picked agents are trials of the sweep, with their final returns
    for row in read_csv(out / "report" / "collapse_agents.csv"):
        if row["seed"]:
            assert float(row["final_return"]) == finals(sweep, row["task"], row["variant"])[int(row["seed"])]
    for task in PAPER.figure5_tasks:
        assert read_csv(out / "report" / f"collapse_metrics_{task}_drqv2.csv")
    # Figures 6-7: the good and the poor agent named, filmed from their final models
    for name, film in stages["film"]["films"].items():
        good, poor = film["good"], film["poor"]
        assert good["final_return"] >= poor["final_return"] and good["seed"] != poor["seed"]
        labels = {r["film"] for r in read_csv(out / "films" / f"{name}_{film['task']}" / "actions.csv")}
        assert any(f"seed_{good['seed']}" in label for label in labels), labels
        assert any(f"seed_{poor['seed']}" in label for label in labels), labels
        assert f"{name}: {film['task']}, good agent seed {good['seed']}" in text
    # the headline and Proposition 1, beside the paper's numbers
    summary = (out / "report" / "summary.md").read_text()
    assert "Proposition 1" in summary and all(task in summary for task in PAPER.figure5_tasks)
    assert "13/40" in text  # the paper's DrQ-v2 walker-walk seeds stuck


def _job(out):
    return Reproduction(out, TINY_SCALE, TINY_SCALE.tasks, TINY_SCALE.seeds, TINY_SCALE.transplant_seeds)


def test_a_rerun_trains_nothing(tiny_reproduction, capsys):
    out, _, _ = tiny_reproduction
    before = mtimes(out)
    assert main(["--out", str(out), "--scale", "tiny", "--no-progress-bar"]) == 0
    printed = capsys.readouterr().out
    for stage in ("sweep", "transplant", "probe", "film", "report"):
        assert f"stage {stage}: done before ({out / 'stages' / stage}.json): skipped" in printed
    assert mtimes(out) == before  # no trial trained, no file written again


def test_tiny_trials_share_their_worker_processes(tiny_reproduction, tmp_path):
    from sb3_collapse.errors import ParameterError
    from sb3_collapse.sweep import expand_trials, run_sweep

    out, _, _ = tiny_reproduction
    # TensorBoard names its event file after the writing process: a worker ran trial after trial.
    pids = {path.name.split(".")[-2] for path in (out / "sweep").glob("*/*/seed_*/events.out.tfevents.*")}
    trials = list((out / "sweep").glob("*/*/seed_*"))
    assert TINY_SCALE.trials_per_worker == 0 and len(trials) == 33 and 1 <= len(pids) < len(trials) / 2
    with pytest.raises(ParameterError, match="trials_per_worker must be an integer >= 0, got -1"):
        run_sweep(expand_trials(["walker-walk"], ["drqv2"], [0]), tmp_path / "sweep", {}, trials_per_worker=-1)
    assert not (tmp_path / "sweep").exists()


def test_dry_run_writes_nothing_and_prints_gpu_hours_and_disk(tiny_reproduction, tmp_path, capsys):
    out = tmp_path / "new"
    assert main(["--out", str(out), "--dry-run", "--stages", "sweep", "--frames-per-second", "200"]) == 0
    printed = capsys.readouterr().out
    assert not out.exists()
    assert "stage sweep (to run): 240 trials (3 tasks x drqv2, drqv2+reset x 40 seeds), 240 to train" in printed
    assert re.search(r"compute: 366\.7 trial-hours at 200 frames/s per trial \(--frames-per-second\)", printed)
    assert re.search(r"disk at the peak [\d.,]+ GB, at the end [\d.,]+ GB", printed)
    assert "snapshots kept by: drqv2" in printed
    # of the finished tiny reproduction: every stage done, nothing to train, nothing written
    done, before = tiny_reproduction[0], mtimes(tiny_reproduction[0])
    assert main(["--out", str(done), "--scale", "tiny", "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert "stage sweep (done: skipped): 24 trials" in printed and ", 0 to train" in printed
    assert mtimes(done) == before


@pytest.mark.parametrize(
    ("argv", "line"),
    [
        (["--stages", "sweep", "plot"], "argument --stages: invalid choice: 'plot'"),
        (["--stages", "probe"], "--stages: probe reads the outputs of sweep, which"),
        (["--seeds", "0"], "--seeds must be >= 1, got 0."),
        (["--tasks", "walker-walk", "nothing-here"], "--tasks: "),
        (["--tasks", "hopper-stand"], "--tasks must hold walker-walk"),
    ],
)
def test_bad_input_is_one_line_naming_the_flag(argv, line, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--out", str(tmp_path / "new"), "--scale", "tiny", *argv])
    assert stop.value.code == 2
    assert line in capsys.readouterr().err and not (tmp_path / "new").exists()


def test_out_holding_something_else_is_refused(tiny_reproduction, tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path), "--scale", "tiny"])
    assert "--out " in capsys.readouterr().err and (tmp_path / "notes.txt").read_text() == "mine"
    with pytest.raises(SystemExit):  # another count than the reproduction's
        main(["--out", str(tiny_reproduction[0]), "--scale", "tiny", "--seeds", "5"])
    assert "--seeds: " in capsys.readouterr().err


def test_a_damaged_trial_is_named_and_the_rest_goes_on(tiny_reproduction, tmp_path, capsys):
    out = tmp_path / "copy"
    shutil.copytree(tiny_reproduction[0], out)
    damaged = out / "sweep" / "hopper-stand" / "drqv2+reset" / "seed_1"
    (damaged / "result.json").write_text('{"status": "fini')  # truncated: a rerun would not change it
    for stage in ("sweep", "report"):
        (out / "stages" / f"{stage}.json").unlink()
    trials = mtimes(out / "sweep" / "walker-walk")
    assert main(["--out", str(out), "--scale", "tiny", "--no-progress-bar", "--stages", "sweep", "report"]) == 0
    printed = capsys.readouterr().out
    assert "  failed: hopper-stand/drqv2+reset/seed_1: " in printed and "not a readable JSON file" in printed  # named
    assert "stage sweep: done in" in printed and "stage report: done in" in printed  # the rest went on
    assert list(json.loads((out / "stages" / "sweep.json").read_text())["damaged"]) == [
        "hopper-stand/drqv2+reset/seed_1"
    ]
    unfinished = (out / "report" / "summary.md").read_text().split("## Unfinished trials")[1]
    assert "| hopper-stand | drqv2+reset | 1 |" in unfinished and mtimes(out / "sweep" / "walker-walk") == trials
