import csv
import dataclasses
import fcntl
import gzip
import html
import json
import shutil

import matplotlib.image
import numpy as np
import pytest
from fabricated_sweep import FakeSweep, FakeTrial, write_fake_sweep

from sb3_collapse.commands import report_pipelines
from sb3_collapse.commands.report import main
from sb3_collapse.commands.report_pipelines import build_report, write_report
from sb3_collapse.errors import InputError
from sb3_collapse.report import ReportSettings, load_reference_curves, reference_task_name, stuck_in_collapse
from sb3_collapse.report import pipeline as report_pipeline
from sb3_collapse.report.reference import pack_reference_curves

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


# Independent expectations, from what the fabricator wrote (not from the report's readers).


def _shared_grid(trials: list[FakeTrial]) -> list[int]:
    return sorted(set.intersection(*(set(t.frames.tolist()) for t in trials)))


def _on_grid(trial: FakeTrial, frames: list[int]) -> np.ndarray:
    lookup = dict(zip(trial.frames.tolist(), trial.returns.tolist()))
    return np.array([lookup[f] for f in frames])


def _expected_row(sweep: FakeSweep, task: str, variant: str) -> dict:
    trials = sweep.select(task, variant)
    grid = _shared_grid(trials)
    returns = np.stack([_on_grid(t, grid) for t in trials])
    finals = returns[:, -1]
    last = returns[:, -10:]
    stuck = unknown = 0
    for t in trials:
        norms = [] if t.grad_norms is None else [v for v in t.grad_norms if not np.isnan(v)]
        if not norms:
            unknown += 1
        elif np.median(norms[-5:]) <= 1e-3:
            stuck += 1
    return {
        "seeds": len(trials),
        "unfinished": len(sweep.select(task, variant, finished=False)),
        "final_frame": grid[-1],
        "final_mean": finals.mean(),
        "final_std": finals.std(ddof=1),
        "stuck": stuck,
        "collapse_unknown": unknown,
        "resets_total": sum(t.resets for t in trials),
        "seeds_reset": sum(t.resets > 0 for t in trials),
        "escaped": sum(t.escaped is True for t in trials),
        "reset_rule_seeds": sum(t.escaped is not None for t in trials),
        "last_evals": min(10, len(grid)),
        "last_evals_std_mean": np.mean([last[:, j].std(ddof=1) for j in range(last.shape[1])]),
    }


@pytest.fixture(scope="module")
def fake_sweep(tmp_path_factory):
    return write_fake_sweep(tmp_path_factory.mktemp("sweep") / "runs")


@pytest.fixture(scope="module")
def written(fake_sweep, tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    report = write_report(fake_sweep.path, out=out, include_unfinished=True, progress=False)
    return fake_sweep, report, out


def _read_csv(path):
    with path.open(newline="") as file:
        return list(csv.DictReader(file))


def _assert_png(path):
    assert path.read_bytes()[:8] == PNG_SIGNATURE
    image = matplotlib.image.imread(path)
    assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 100


def test_summary_table_matches_independent_computation(written):
    sweep, _, out = written
    rows = _read_csv(out / "summary.csv")
    pairs = [(t.task, t.variant) for t in sweep.trials]
    assert sorted((r["task"], r["variant"]) for r in rows) == sorted(set(pairs))
    for row in rows:
        expected = _expected_row(sweep, row["task"], row["variant"])
        for key, value in expected.items():
            assert float(row[key]) == pytest.approx(value, rel=1e-9, abs=1e-9), (row["task"], row["variant"], key)
    # The fabricated collapse states, by construction.
    by_key = {(r["task"], r["variant"]): r for r in rows}
    assert by_key[("walker-walk", "drqv2")]["stuck"] == "2"
    assert by_key[("walker-walk", "drqv2")]["unfinished"] == "2"
    assert by_key[("walker-walk", "drqv2+reset")]["stuck"] == "0"
    assert by_key[("walker-walk", "drqv2+reset")]["resets_total"] == "3"
    assert by_key[("walker-walk", "drqv2+reset")]["seeds_reset"] == "2"
    assert (
        by_key[("walker-walk", "drqv2")]["escaped"] == "0"
        and by_key[("walker-walk", "drqv2")]["reset_rule_seeds"] == "0"
    )
    assert by_key[("hopper-stand", "drqv2")]["stuck"] == "2"  # seed 0 and the median-9e-4 middle agent
    assert by_key[("hopper-stand", "drqv2")]["collapse_unknown"] == "1"
    assert by_key[("hopper-stand", "drqv2+reset")]["collapse_unknown"] == "1"
    assert by_key[("walker-walk", "cnn-good_mlp-good")]["last_evals"] == "6"  # fewer than 10 evaluations
    # The reset rule shrinks the spread over the last evaluations, as in the paper.
    for task in ("walker-walk", "hopper-stand"):
        assert float(by_key[(task, "drqv2+reset")]["last_evals_std_mean"]) < float(
            by_key[(task, "drqv2")]["last_evals_std_mean"]
        )


def test_markdown_printed_and_written(written, capsys):
    sweep, report, out = written
    text = (out / "summary.md").read_text()
    assert text == report.markdown
    assert "| walker-walk | drqv2 | 5 | 2 | 200,000 |" in text
    assert "walker-walk / drqv2: 2 unfinished, not in the statistics: seed 5 (running), seed 6 (failed)" in text
    assert "hopper-stand / drqv2+reset: 1 evaluation frame(s) not shared" in text
    expected = _expected_row(sweep, "walker-walk", "drqv2")
    assert f"{expected['final_mean']:.1f} ± {expected['final_std']:.1f}" in text


def test_percentile_bands(written):
    sweep, report, _ = written
    for task in ("walker-walk", "hopper-stand"):
        curves = {c.name: c for c in report.curves[task]}
        for variant in ("drqv2", "drqv2+reset"):
            trials = sweep.select(task, variant)
            grid = _shared_grid(trials)
            returns = np.stack([_on_grid(t, grid) for t in trials])
            curve = curves[variant]
            assert curve.frames.tolist() == grid and curve.seeds == 5
            np.testing.assert_allclose(curve.mean, returns.mean(axis=0))
            np.testing.assert_allclose(curve.low, np.percentile(returns, 5, axis=0))
            np.testing.assert_allclose(curve.high, np.percentile(returns, 95, axis=0))
            # With 5 seeds the 5th percentile lies between the two lowest returns: 0.2 of the way.
            ordered = np.sort(returns, axis=0)
            np.testing.assert_allclose(curve.low, ordered[0] + 0.2 * (ordered[1] - ordered[0]))
    assert report.curves["hopper-stand"][1].frames[-1] == 200_000  # seed 4's extra 210,000 is dropped


def test_transplant_grid_counts(written):
    sweep, _, out = written
    rows = _read_csv(out / "transplant_grid.csv")
    assert len(rows) == 9 and {r["task"] for r in rows} == {"walker-walk"}
    for row in rows:
        trials = sweep.select("walker-walk", f"cnn-{row['cnn']}_mlp-{row['mlp']}")
        assert int(row["seeds"]) == len(trials)
        assert int(row["successes"]) == sum(t.returns[-1] >= 900 for t in trials)
    cells = {(r["cnn"], r["mlp"]): (int(r["successes"]), int(r["seeds"]), int(r["unfinished"])) for r in rows}
    assert cells[("good", "good")] == (2, 3, 0)  # 900.0 succeeds, 899.99 does not
    assert cells[("bad", "blank")] == (0, 0, 0)
    assert cells[("blank", "blank")] == (1, 2, 1)
    assert all(cells[(cnn, "bad")][0] == 0 for cnn in ("blank", "good", "bad"))
    text = (out / "transplant_grid.md").read_text()
    assert "| good CNN | 2/2 | 2/3 | 0/2 |" in text and "| bad CNN | - | 1/2 | 0/2 |" in text
    # Another success threshold, from the library.
    strict = build_report(sweep.path, settings=ReportSettings(success_return=950), progress=False)
    assert [(c.successes, c.seeds) for c in strict.grid["walker-walk"]][:2] == [(1, 2), (0, 2)]


def test_pngs_written_and_valid(written):
    _, report, out = written
    assert sorted(p.name for p in out.iterdir()) == [  # no rollouts: the online collapse figures only
        "collapse_agents.csv",
        "collapse_metrics_online_hopper-stand_drqv2+reset.png",
        "collapse_metrics_online_hopper-stand_drqv2.png",
        "collapse_metrics_online_walker-walk_drqv2+reset.png",
        "collapse_metrics_online_walker-walk_drqv2.png",
        "figure3b.png",
        "figure5.png",
        "index.html",
        "summary.csv",
        "summary.md",
        "table7.csv",
        "table7.md",
        "transplant_grid.csv",
        "transplant_grid.md",
        "transplant_grid.png",
    ]
    assert [p.name for p in report.files][-1] == "summary.md"
    _assert_png(out / "figure5.png")
    _assert_png(out / "transplant_grid.png")


def test_unfinished_excluded_and_partial_curves(written):
    _, report, _ = written
    unfinished = {(t.variant, t.seed): t for t in report.sweep.unfinished}
    assert set(unfinished) == {("drqv2", 5), ("drqv2", 6), ("cnn-blank_mlp-blank", 2)}
    # The running trial's eval.csv ends mid-line: that row is dropped from its partial curve.
    assert unfinished[("drqv2", 5)].frames.tolist() == [0, 10_000, 20_000, 30_000, 40_000, 50_000]
    assert unfinished[("drqv2", 6)].status == "failed"
    row = next(r for r in report.rows if (r.task, r.variant) == ("walker-walk", "drqv2"))
    assert row.seeds == 5 and row.unfinished == 2 and row.seed_ids == [0, 1, 2, 3, 4]


def test_reference_curves_walker_walk():
    reference = load_reference_curves("walker-walk")
    assert reference.task == "walker_walk"
    assert reference.seeds.tolist() == list(range(1, 11))
    assert reference.frames[0] == 0 and reference.frames[-1] == 1_000_000 and len(reference.frames) == 51
    # ../shared/reference/README.md: 767 ± 390 at 1M frames; 2 of the 10 seeds stay near 25.
    assert reference.returns[:, -1].mean() == pytest.approx(766.87, abs=0.01)
    assert reference.returns[:, -1].std(ddof=1) == pytest.approx(390.45, abs=0.01)
    assert (reference.returns[:, -1] < 100).sum() == 2
    for name in ("cup-catch", "ball_in_cup-catch", "cup_catch", "sb3_collapse/cup-catch-v0"):
        assert reference_task_name(name) == "cup_catch"
    assert load_reference_curves("ball_in_cup-catch").returns.shape == (8, 50)
    assert load_reference_curves("no-such-task") is None


def test_cli_reference_overlay(fake_sweep, tmp_path, capsys):
    out = tmp_path / "figures"
    assert (
        main(
            [
                str(fake_sweep.path),
                "--reference",
                "--out",
                str(out),
                "--tasks",
                "walker-walk",
                "--variants",
                "drqv2",
                "drqv2+reset",
                "--no-progress",
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "| walker-walk | drqv2+reset | 5 | 0 |" in printed and "hopper-stand" not in printed
    assert sorted(p.name for p in out.iterdir()) == [
        "collapse_agents.csv",
        "collapse_metrics_online_walker-walk_drqv2+reset.png",
        "collapse_metrics_online_walker-walk_drqv2.png",
        "figure5.png",
        "index.html",
        "summary.csv",
        "summary.md",
    ]
    _assert_png(out / "figure5.png")


def test_reference_packing_round_trip(tmp_path):
    source = tmp_path / "curves"
    source.mkdir()
    (source / "dmc_walker_walk.csv").write_text(
        ",agent,task,seed,frame,episode_reward,hour\n0,DrQ-v2,walker_walk,1,0,25.397,0.0\n"
        "1,DrQ-v2,walker_walk,1,20000,19.844,0.07\n"
    )
    assert pack_reference_curves(source, tmp_path / "curves.csv.gz") == 2
    text = gzip.decompress((tmp_path / "curves.csv.gz").read_bytes()).decode()
    assert text == "task,seed,frame,episode_reward\nwalker_walk,1,0,25.40\nwalker_walk,1,20000,19.84\n"


def test_stuck_in_collapse_rule():
    assert stuck_in_collapse(np.array([0.05, 0.06, 1e-6, 2e-6, 1e-6, 3e-6, 1e-6])) is True
    assert stuck_in_collapse(np.array([1e-6, 0.05, 1e-6, 0.04, 0.05])) is False  # median of the last 5: 0.04
    assert stuck_in_collapse(np.array([1e-3])) is True  # <= threshold
    assert stuck_in_collapse(np.array([0.002, 1e-6]), threshold=1e-3, checks=1) is True
    assert stuck_in_collapse(np.array([0.002, 1e-6]), threshold=1e-7, checks=1) is False
    assert stuck_in_collapse(np.zeros(0)) is None


def test_collapse_settings_change_the_count(fake_sweep):
    # With the last check only, the middle agent of hopper-stand (last value 9e-4) is still stuck, and a
    # threshold below 1e-6 makes the collapsed seeds healthy.
    loose = build_report(
        fake_sweep.path,
        settings=ReportSettings(collapse_threshold=1e-8),
        tasks=["hopper-stand"],
        progress=False,
    )
    assert [r.stuck for r in loose.rows] == [0, 0]
    one = build_report(
        fake_sweep.path,
        settings=ReportSettings(collapse_checks=1),
        tasks=["hopper-stand"],
        progress=False,
    )
    assert [r.stuck for r in one.rows] == [2, 0]


def _copy(sweep: FakeSweep, tmp_path):
    root = tmp_path / "runs"
    shutil.copytree(sweep.path, root, ignore=shutil.ignore_patterns("report"))
    return root


@pytest.mark.parametrize(
    "case, message",
    [
        ("missing", "does not exist"),
        ("empty", "no trial folders"),
        ("unknown_task", "--tasks cheetah-run not in"),
        ("bad_setting", "--collapse-threshold must be a finite number"),
        ("all_damaged", "no trial of"),
    ],
)
def test_cli_errors(fake_sweep, tmp_path, capsys, case, message):
    root = _copy(fake_sweep, tmp_path) if case not in ("missing", "empty") else tmp_path / "runs"
    extra = []
    if case == "empty":
        (root / "walker-walk" / "drqv2").mkdir(parents=True)
    elif case == "unknown_task":
        extra = ["--tasks", "cheetah-run"]
    elif case == "bad_setting":
        extra = ["--collapse-threshold", "nan"]
    elif case == "all_damaged":
        extra = ["--tasks", "hopper-stand"]
        for result in root.glob("hopper-stand/*/seed_*/result.json"):
            result.write_text('{"status": "finished", ')
    assert main([str(root), "--no-progress", *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err
    assert not (root / "report").exists()  # nothing written, not even an empty folder
    if case == "missing":
        with pytest.raises(InputError, match="does not exist"):
            write_report(root, progress=False)


# Each damage, its trial (several per cell: every cell but hopper-stand / drqv2 keeps finished seeds) and the reason
# the report gives for it.
DAMAGES = [
    ("result_truncated", "walker-walk/drqv2/seed_0", "result.json: not a readable JSON file"),
    ("eval_cut_mid_row", "walker-walk/drqv2/seed_1", "eval.csv, line 22: the number of fields differs"),
    ("eval_number", "walker-walk/drqv2/seed_2", "eval.csv, line 3: column 'mean_reward' is 'abc'"),
    ("eval_column", "walker-walk/drqv2+reset/seed_0", "eval.csv: missing column(s) mean_reward"),
    ("eval_missing", "walker-walk/drqv2+reset/seed_1", "eval.csv is missing"),
    ("result_resets", "hopper-stand/drqv2+reset/seed_0", "result.json: 'resets' must be an integer"),
    ("metrics_number", "hopper-stand/drqv2+reset/seed_1", "collapse_metrics.csv, line 2: column 'value' is 'x'"),
]


def test_a_damaged_trial_is_listed_and_the_rest_drawn(fake_sweep, tmp_path, capsys):
    """Seven trials, each damaged its own way, in one report: each is listed failed with its reason and the way out
    (once), in the printed summary and the page; the other seeds of their cells and the other cells are drawn."""
    root = _copy(fake_sweep, tmp_path)
    for case, name, _ in DAMAGES:
        trial = root / name
        if case == "result_truncated":
            text = (trial / "result.json").read_text()
            (trial / "result.json").write_text(text[: len(text) // 2])
        elif case == "eval_cut_mid_row":
            text = (trial / "eval.csv").read_text()
            (trial / "eval.csv").write_text(text[: text.rindex(",", 0, len(text) - 1)])
        elif case == "eval_number":
            lines = (trial / "eval.csv").read_text().splitlines()
            lines[2] = "10000,5000,abc,1.0,10,1.0"
            (trial / "eval.csv").write_text("\n".join(lines) + "\n")
        elif case == "eval_column":
            (trial / "eval.csv").write_text("frame,step,reward\n0,0,1.0\n")
        elif case == "eval_missing":
            (trial / "eval.csv").unlink()
        elif case == "result_resets":
            result = json.loads((trial / "result.json").read_text())
            (trial / "result.json").write_text(json.dumps({**result, "resets": "two"}))
        elif case == "metrics_number":
            lines = (trial / "collapse_metrics.csv").read_text().splitlines()
            lines[1] = "10000,5000,collapse/mlp1/grad_norm,x"
            (trial / "collapse_metrics.csv").write_text("\n".join(lines) + "\n")
    assert main([str(root), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    markdown = (root / "report" / "summary.md").read_text()
    unfinished = markdown[markdown.index("## Unfinished trials") :]
    assert unfinished in printed
    page = (root / "report" / "index.html").read_text()
    section = page[page.index('<section id="unfinished-trials">') :]
    section = section[: section.index("</section>")]
    for case, name, message in DAMAGES:
        reason = f"{name}/{message}"
        task, variant, seed = name.split("/")
        start = f"| {task} | {variant} | {seed.removeprefix('seed_')} | failed |"
        line = next(line for line in unfinished.splitlines() if line.startswith(start))
        assert reason in line and line.count("move the folder aside to train this seed again") == 1, case
        assert html.escape(reason) in section, case
    assert section.count("move the folder aside to train this seed again") >= len(DAMAGES)
    summary = {(r["task"], r["variant"]): r for r in _read_csv(root / "report" / "summary.csv")}
    # Finished seeds left, and the unfinished ones: walker-walk / drqv2's running and failed seeds besides.
    counts = {(task, variant): (r["seeds"], r["unfinished"]) for (task, variant), r in summary.items()}
    assert counts[("walker-walk", "drqv2")] == ("2", "5") and counts[("walker-walk", "drqv2+reset")] == ("3", "2")
    assert counts[("hopper-stand", "drqv2+reset")] == ("3", "2")
    assert counts[("hopper-stand", "drqv2")] == ("5", "0")  # the rest is drawn as before
    _assert_png(root / "report" / "figure5.png")


def test_progress_writes_no_bar_frames_into_a_captured_stderr(fake_sweep, tmp_path, capfd):
    root = _copy(fake_sweep, tmp_path)
    assert main([str(root), "--variants", "drqv2"]) == 0  # the progress is on, stderr is not a terminal
    err = capfd.readouterr().err
    assert "\r" not in err and "it/s" not in err and "%|" not in err
    assert err.splitlines() == ["reading trials: 12 trials", "collapse figures: 2 figures"]


def test_failed_report_keeps_the_previous_one(fake_sweep, tmp_path, monkeypatch):
    root = _copy(fake_sweep, tmp_path)
    write_report(root, progress=False)
    before = {p.name: p.read_bytes() for p in (root / "report").iterdir()}

    def broken(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(report_pipelines, "plot_transplant_grid", broken)
    with pytest.raises(RuntimeError, match="disk full"):
        write_report(root, progress=False, overwrite=True)
    assert {p.name: p.read_bytes() for p in (root / "report").iterdir()} == before  # no .partial-* left either


def test_stale_outputs_removed(fake_sweep, tmp_path):
    root = _copy(fake_sweep, tmp_path)
    write_report(root, progress=False)
    assert (root / "report" / "transplant_grid.png").exists()
    # A second report into the same folder is refused without overwrite, before the sweep is read.
    with pytest.raises(InputError, match="already holds outputs .* pass `overwrite=True`"):
        write_report(root, progress=False)
    report = write_report(root, variants=["drqv2"], progress=False, overwrite=True)
    assert sorted(p.name for p in (root / "report").iterdir()) == [  # the collapse figures of drqv2+reset too
        "collapse_agents.csv",
        "collapse_metrics_online_hopper-stand_drqv2.png",
        "collapse_metrics_online_walker-walk_drqv2.png",
        "figure5.png",
        "index.html",
        "summary.csv",
        "summary.md",
    ]
    assert report.grid == {} and report.transplant == {} and len(report.collapse_online) == 2
    # Figure 3 and Table 7 are missing with a note that says which variants would produce them.
    note = "Figure 3 and Table 7 not drawn: no transplant variant in this sweep; the layer-transplant variants"
    page = (root / "report" / "index.html").read_text()
    assert note in report.markdown and note in page and "cnn-&lt;src&gt;_mlp-&lt;src&gt;" in page
    assert "--transplant-grid" in report.markdown
    # A fresh sweep with nothing finished yet still reports, with the counts of unfinished trials.
    for result in root.glob("*/*/seed_*/result.json"):
        result.unlink()
    report = write_report(root, progress=False, overwrite=True)
    assert all(r.seeds == 0 for r in report.rows) and report.notes[0].startswith("no finished trial")


def test_fabricator_is_reproducible(tmp_path):
    a = write_fake_sweep(tmp_path / "a", seed=3)
    b = write_fake_sweep(tmp_path / "b", seed=3)
    assert (tmp_path / "a/walker-walk/drqv2/seed_0/eval.csv").read_text() == (
        tmp_path / "b/walker-walk/drqv2/seed_0/eval.csv"
    ).read_text()
    assert len(a.trials) == len(b.trials) == 40


def test_reference_is_cut_at_the_sweeps_last_frame():
    from sb3_collapse.report.plots import _clip_reference
    from sb3_collapse.report.statistics import BandCurve

    frames = np.array([0, 20_000, 40_000])
    reference = BandCurve("published", frames, np.array([0.0, 200.0, 400.0]), np.zeros(3), np.array([10.0, 30, 50]), 10)
    clipped = _clip_reference(reference, 30_000)  # between two published frames: interpolated there
    np.testing.assert_allclose(clipped[0], [0, 20_000, 30_000])
    np.testing.assert_allclose(clipped[1], [0, 200, 300])
    np.testing.assert_allclose(clipped[3], [10, 30, 40])
    whole = _clip_reference(reference, 40_000)
    np.testing.assert_allclose(whole[1], reference.mean)
    assert len(_clip_reference(reference, None)[0]) == 3


def test_legend_names_the_intervention_of_a_variant():
    from sb3_collapse.report.plots import variant_label

    assert variant_label("drqv2+redo") == "drqv2+redo: ReDo, one-shot at the rule's trigger"
    assert variant_label("drqv2+redo_periodic") == "drqv2+redo_periodic: ReDo every 1000 updates, whole run"
    assert variant_label("td3+reset") == "td3+reset: reset from scratch"
    assert variant_label("sac+shrink_perturb") == "sac+shrink_perturb: shrink & perturb, interpolation to a fresh init"
    assert variant_label("drqv2-leaky+shrink_perturb_noise").endswith("Ash & Adams (lambda theta + sigma noise)")
    for other in ("drqv2", "cnn-good_mlp-bad", "mine+tweak"):  # other names are kept
        assert variant_label(other) == other


def test_a_trial_without_a_result_is_running_only_while_its_lock_is_held(tmp_path):
    import socket

    from sb3_collapse.report.loading import load_trial
    from sb3_collapse.run.lock import RunLock

    folder = tmp_path / "walker-walk" / "drqv2" / "seed_0"
    folder.mkdir(parents=True)
    (folder / "config.json").write_text("{}")

    def status() -> str:
        return load_trial("walker-walk", "drqv2", 0, folder).status

    assert status() == "unfinished"  # no lock file: stopped (or failed) before its end
    with RunLock(folder):  # a process trains into it
        assert status() == "running"
    assert (folder / "run.lock").exists() and status() == "unfinished"  # the process ended: its lock is free
    lock = folder / "run.lock"
    lock.write_text(f"pid 999999999 on host {socket.gethostname()} since 2026-01-01 00:00:00\n")
    assert status() == "unfinished"  # killed: the lock file stays, its process is gone
    lock.write_text("pid 1 on host another-node since 2026-01-01 00:00:00\n")
    assert status() == "unfinished"  # a process on another node: the lock itself is tried, and it is free
    with open(lock) as held:
        fcntl.flock(held.fileno(), fcntl.LOCK_EX)
        assert status() == "running"


def test_html_tables_show_a_dash_for_a_missing_std(tmp_path):
    path = tmp_path / "tables_1_6.csv"
    path.write_text(
        "table,row,column,layer,agents,stage,frame,std\n"
        "1,well-performing,torso velocity,cnn1,1,0,0,nan\n"
        "1,well-performing,torso velocity,cnn1,1,1,350000,\n"
        "2,poorly performing,torso velocity,cnn1,2,0,0,0.25\n"
    )
    one, two = report_pipeline._tables_1_6(path)
    assert "nan" not in one and one.count("<td>-</td>") == 2 and "<td>0.25</td>" in two


def test_settings_values_stay_on_screen_in_chromium(tmp_path):
    from browser import check_page

    from sb3_collapse.report import html as report_html

    settings = {"env": "walker-walk", "policy_kwargs": {"net_arch": list(range(400))}, "seed": 3}
    section = report_html.Section("Settings", [report_html.settings_table(settings, "config.json")])
    page = tmp_path / "index.html"
    page.write_text(report_html.html_page("settings", [section]))
    result = check_page(page, tmp_path)
    (table,) = result["tables"]
    assert table["css_class"] == "settings" and table["body_rows"] == 3
    assert 0 < table["right"] <= result["width"]  # every value, the long one wrapped, within the page


@pytest.mark.parametrize(
    "changes, name",
    [
        ({"collapse_checks": 0}, "collapse_checks"),
        ({"last_evals": 0}, "last_evals"),
        ({"collapse_threshold": float("nan")}, "collapse_threshold"),
        ({"percentiles": (50.0, 50.0)}, "percentiles"),
    ],
)
def test_report_settings_refuse_a_value_out_of_range_with_an_input_error(changes, name):
    with pytest.raises(InputError, match=f"^{name} must"):
        ReportSettings(**changes).validate()


def test_the_preset_table_shows_every_setting_of_a_task_preset():
    from sb3_collapse.presets import preset
    from sb3_collapse.report.pipeline import PRESET_COLUMNS, _preset_rows

    walker, other = _preset_rows(["walker-walk", "not_a_task"])
    assert walker == list(dataclasses.astuple(preset("walker-walk")))  # the task, then every setting in order
    assert other[:2] == ["not_a_task", "(not a DeepMind Control suite task)"] and len(other) == 1 + len(PRESET_COLUMNS)
