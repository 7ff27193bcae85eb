"""The top of the report (the paper's headline beside the sweep's, Proposition 1) and what Figure 5 compares."""

import json
import math
from statistics import NormalDist

import numpy as np
import pytest
from fabricated_sweep import FRAMES, write_fake_sweep

from sb3_collapse.commands import report_pipelines
from sb3_collapse.commands.report_pipelines import build_report, write_report
from sb3_collapse.errors import InputError
from sb3_collapse.paper import PAPER, PAPER_RESULTS, PROPOSITION_1
from sb3_collapse.report import statistics
from sb3_collapse.report.headline import (
    escape_interval,
    escape_probability,
    headline_rows,
    proposition1_rows,
    wilson_interval,
)
from sb3_collapse.report.loading import Sweep, Trial, load_trial
from sb3_collapse.report.statistics import ReportSettings, VariantSummary, escaped_at

Z = NormalDist().inv_cdf(0.975)


@pytest.fixture(scope="module")
def fake(tmp_path_factory):
    return write_fake_sweep(tmp_path_factory.mktemp("headline") / "sweep")


def test_wilson_interval_on_known_cases():
    # No success: [0, z^2 / (n + z^2)]; all successes: [n / (n + z^2), 1]; k and n - k mirror each other.
    low, high = wilson_interval(0, 40)
    assert low == 0.0 and high == pytest.approx(Z**2 / (40 + Z**2))
    low, high = wilson_interval(40, 40)
    assert low == pytest.approx(40 / (40 + Z**2)) and high == 1.0
    low, high = wilson_interval(13, 40)
    mirror = wilson_interval(27, 40)
    assert (low, high) == pytest.approx((1 - mirror[1], 1 - mirror[0])) and low < 13 / 40 < high
    assert all(math.isnan(v) for v in wilson_interval(0, 0))


def test_proposition1_on_a_constructed_case(tmp_path):
    # Baseline: 5 of 10 seeds never escape, one escapes after the first window (at 300,000 frames): p, no escape
    # within m = 2e5 frames, is 6/10; the rule: 1.1e6 frames in windows of 2e5, n = 5 whole windows.
    trials = []
    for seed in range(8):
        folder = tmp_path / "walker-walk" / "drqv2+reset" / f"seed_{seed}"
        folder.mkdir(parents=True)
        (folder / "config.json").write_text(json.dumps({"frames": 1_100_000, "reset_window_frames": 200_000}))
        trials.append(Trial("walker-walk", "drqv2+reset", seed, folder, "finished", {"escaped": seed < 7}))
    sweep = Sweep(tmp_path, trials)
    rows = [
        VariantSummary("walker-walk", "drqv2", 10, 0, escape_frames=[50_000] * 3 + [200_000, 300_000] + [None] * 5),
        VariantSummary("walker-walk", "drqv2+reset", 8, 0, reset_rule_seeds=8, escape_frames=[90_000] * 7 + [None]),
    ]
    (row,) = proposition1_rows(sweep, rows)
    assert (row.baseline, row.rule, row.windows, row.window_frames) == ("drqv2", "drqv2+reset", 5, 200_000)
    assert (row.stuck.count, row.stuck.total) == (6, 10) and row.predicted.value == pytest.approx(1 - 0.6**5)
    low, high = wilson_interval(6, 10)
    assert row.predicted.interval == pytest.approx((1 - high**5, 1 - low**5))
    assert row.predicted.interval[0] < row.predicted.value < row.predicted.interval[1]
    assert (row.escaped.count, row.escaped.total, row.escaped.interval) == (7, 8, wilson_interval(7, 8))
    # The paper's walker_walk: p = 13/40 and n = 5 give 1 - p^5.
    assert escape_probability(13 / 40, 5) == pytest.approx(1 - (13 / 40) ** 5)
    assert escape_interval((0.0, 1.0), 5) == (0.0, 1.0) and escape_interval((0.5, 0.5), 2) == (0.75, 0.75)


def test_headline_sets_the_papers_numbers_beside_the_sweeps(fake, tmp_path):
    report = write_report(fake.path, out=tmp_path / "report", progress=False)
    assert [row.task for row in report.headline] == ["walker-walk", "hopper-stand"]  # the paper's order
    walker = report.headline[0]
    paper = {result.task: result for result in PAPER_RESULTS}["walker-walk"]
    assert (paper.stuck_baseline, paper.never_escaped_rule, paper.std_baseline, paper.std_rule) == (13, 0, 418.2, 38.2)
    assert walker.paper == paper
    # The fabricated walker-walk: seeds 1 and 3 of drqv2's 5 finished seeds never escape; the rule's 5 escape.
    assert (walker.never_escaped_baseline.count, walker.never_escaped_baseline.total) == (2, 5)
    assert walker.never_escaped_baseline.interval == wilson_interval(2, 5)
    assert (walker.stuck_end_baseline.count, walker.stuck_end_baseline.total) == (2, 5)
    assert (walker.stuck_end_rule.count, walker.stuck_end_rule.total) == (0, 5)
    assert (walker.never_escaped_rule.count, walker.never_escaped_rule.total) == (0, 5)
    # The std over the last ten evaluations, from the written returns.
    returns = np.array([t.returns for t in fake.select("walker-walk", "drqv2")])
    expected = np.mean(np.std(returns[:, -PAPER.last_evals :], axis=0, ddof=1))
    assert walker.std_baseline.value == pytest.approx(expected)
    low, high = walker.std_baseline.interval
    assert 0 <= low <= high and math.isfinite(high)
    markdown = (tmp_path / "report" / "summary.md").read_text()
    top = markdown.split("## Proposition 1")[0]
    assert markdown.startswith("# Sweep report\n\n## The paper's headline beside this sweep's")
    assert "| walker-walk | 13/40 | 2/5 (40%, CI " in top
    assert "| 0/40 | 0/5 (0%, CI 0%-43%) | 2/5 (40%, CI " in top  # the rule never escaped; DrQ-v2 stuck at the end
    assert (
        "| stuck continuously (never escaped), DrQ-v2: paper | this sweep | with the rule: paper | this sweep |" in top
    )
    assert "| stuck at the end, DrQ-v2: this sweep | with the rule: this sweep |" in top
    assert "| 418.2 | " in top and "| 38.2 | " in top and "| hopper-stand | 8/40 |" in top
    assert f"> {PROPOSITION_1}" in markdown and "| walker-walk | drqv2 |" in markdown  # the summary table follows
    page = (tmp_path / "report" / "index.html").read_text()
    assert page.index("headline beside this sweep") < page.index("Summary table") and "1 - p^n" in page
    # Proposition 1 from the fabricated sweep: p = 2/5 (no escape within m = 200,000 frames, the whole run: seeds 1
    # and 3), n = 200,000 // 200,000 = 1 window; observed 5/5 by the same test.
    walker_rule = next(row for row in report.proposition if row.task == "walker-walk")
    assert walker_rule.windows == FRAMES // PAPER.window_frames == 1
    assert walker_rule.predicted.value == pytest.approx(1 - 2 / 5) and walker_rule.escaped.count == 5


def test_both_arms_are_counted_by_the_rules_escape_test(fake, tmp_path, monkeypatch):
    # One function counts both arms: the rule's own escape test over each seed's logged checks.
    counted = []

    def spy(trial, settings):
        counted.append((trial.task, trial.variant, trial.seed))
        return escaped_at(trial, settings)

    monkeypatch.setattr(statistics, "escaped_at", spy)
    report = build_report(fake.path, tasks=["walker-walk", "hopper-stand"], variants=["drqv2", "drqv2+reset"],
                          progress=False)  # fmt: skip
    assert {("walker-walk", "drqv2", 0), ("walker-walk", "drqv2", 1), ("walker-walk", "drqv2+reset", 2)} <= set(counted)
    walker, hopper = report.headline
    # walker-walk / drqv2: seed 0 escapes mid-run (healthy checks from 50,000 frames: the fifth at 90,000) and ends
    # fine; seed 1 never escapes. Both are read by the function that counts the rule's seeds.
    seed0, seed1 = (load_trial("walker-walk", "drqv2", s, fake.path / "walker-walk" / "drqv2" / f"seed_{s}")
                    for s in (0, 1))  # fmt: skip
    assert escaped_at(seed0, ReportSettings()) == 90_000 and escaped_at(seed1, ReportSettings()) is None
    assert walker.baseline.escape_frames[:2] == [90_000, None] and walker.never_escaped_baseline.count == 2
    # walker-walk / drqv2+reset, seed 2: reset at 60,000 and 120,000, healthy from 140,000: escapes at 180,000.
    assert walker.rule.escape_frames[2] == 180_000 and walker.never_escaped_rule.count == 0
    # hopper-stand / drqv2, seed 2 escaped (from 90,000 frames) then its last five checks have a median of 9e-4: it is
    # stuck at the end, not stuck continuously; seed 0 is both; seed 4 logged nothing (unknown, in neither total).
    assert (hopper.never_escaped_baseline.count, hopper.never_escaped_baseline.total) == (1, 4)
    assert (hopper.stuck_end_baseline.count, hopper.stuck_end_baseline.total) == (2, 4)
    low, high = wilson_interval(1, 4)
    assert f"| hopper-stand | 8/40 | 1/4 (25%, CI {100 * low:.0f}%-{100 * high:.0f}%) |" in report.markdown


def test_the_rules_record_does_not_decide_its_cell(fake, tmp_path):
    # Seed 4 of walker-walk / drqv2+reset: its result file says the rule never saw an escape, yet its logged mlp1
    # gradient norms pass the escape test: the headline counts what the test finds in the logged checks (0/5 never
    # escaped), as for DrQ-v2's seeds, which have no such record; the summary table keeps the rule's record.
    path = fake.path / "walker-walk" / "drqv2+reset" / "seed_4" / "result.json"
    result = json.loads(path.read_text())
    path.write_text(json.dumps(result | {"escaped": False, "escape_frame": None}))
    try:
        report = write_report(fake.path, out=tmp_path / "report", progress=False)
    finally:
        path.write_text(json.dumps(result))
    walker = report.headline[0]
    never, stuck = walker.never_escaped_rule, walker.stuck_end_rule
    assert (never.count, never.total) == (0, 5) and (stuck.count, stuck.total) == (0, 5)
    assert walker.rule.escaped == 4  # the rule's own record, in the summary table
    page = (tmp_path / "report" / "index.html").read_text()
    for text in ("stuck continuously (never escaped), DrQ-v2: paper", "stuck at the end, DrQ-v2: this sweep",
                 "own escape test over each seed"):  # fmt: skip
        assert text in page
    walker_rule = next(row for row in report.proposition if row.task == "walker-walk")
    assert (walker_rule.escaped.count, walker_rule.escaped.total) == (5, 5)


def test_figure5_has_no_transplant_series(fake, monkeypatch, tmp_path):
    drawn = {}

    def record(curves, path, references=None, partial=None, percentiles=(5.0, 95.0)):
        drawn["curves"], drawn["partial"] = curves, partial
        return plot(curves, path, references, partial, percentiles)

    plot = report_pipelines.plot_figure5
    monkeypatch.setattr(report_pipelines, "plot_figure5", record)
    report = write_report(fake.path, out=tmp_path / "report", include_unfinished=True, progress=False)
    names = {task: [curve.name for curve in curves] for task, curves in drawn["curves"].items()}
    assert names == {"hopper-stand": ["drqv2", "drqv2+reset"], "walker-walk": ["drqv2", "drqv2+reset"]}
    # The running transplant seed (cnn-blank_mlp-blank) is not drawn dotted either; drqv2's unfinished seeds are.
    assert sorted((t.variant, t.seed) for t in drawn["partial"]["walker-walk"]) == [("drqv2", 5), ("drqv2", 6)]
    assert report.grid and "figure3b.png" in {p.name for p in report.files}  # the cells stay in Figure 3
    # A sweep of transplant cells only has no Figure 5 panel.
    only_grid = build_report(fake.path, variants=["cnn-good_mlp-good", "cnn-bad_mlp-bad"], progress=False)
    assert only_grid.curves == {} and only_grid.grid


def test_a_result_file_of_another_version_is_refused(fake):
    folder = fake.path / "walker-walk" / "drqv2" / "seed_0"
    result = json.loads((folder / "result.json").read_text())
    assert load_trial("walker-walk", "drqv2", 0, folder).frames[-1] == result["frames"] == FRAMES
    old = {key: value for key, value in result.items() if key != "saved_model_eval"}
    (folder / "result.json").write_text(json.dumps(old))
    try:
        with pytest.raises(InputError, match=r"result\.json has no 'saved_model_eval': it was written by another"):
            load_trial("walker-walk", "drqv2", 0, folder)
    finally:
        (folder / "result.json").write_text(json.dumps(result))


def test_headline_of_a_task_without_the_rule(fake):
    sweep = build_report(fake.path, variants=["drqv2"], progress=False)
    rows = headline_rows(sweep.sweep, sweep.rows, ReportSettings())
    assert rows[0].stuck_end_rule is None and rows[0].never_escaped_rule is None
    assert rows[0].never_escaped_baseline.count == rows[0].stuck_end_baseline.count == 2
    assert "not in this sweep" in sweep.markdown and "No rule variant with its baseline" in sweep.markdown
