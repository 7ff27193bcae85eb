"""benchmarks/learning_curve.py end to end with a tiny budget (the benchmark itself trains 60,000 frames)."""

import csv
import importlib.util
import json
from pathlib import Path

import matplotlib.image

SCRIPT = Path(__file__).resolve().parent.parent / "benchmarks" / "learning_curve.py"
TINY = ["--size", "32", "--hidden-dim", "32", "--feature-dim", "16", "--batch-size", "8", "--seed-frames", "100",
        "--eval-every-frames", "100", "--eval-episodes", "1", "--collapse-metrics-every-frames", "0",
        "--replay-sampling", "sb3", "--action-repeat", "25"]  # fmt: skip


def test_learning_curve_trains_draws_and_does_not_train_a_finished_run_again(tmp_path, capsys):
    spec = importlib.util.spec_from_file_location("learning_curve", SCRIPT)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    run_dir, png = tmp_path / "run", tmp_path / "curve.png"
    argv = ["--env", "cartpole-balance", "--frames", "200", "--target-frames", "200", "--run-dir", str(run_dir),
            "--out", str(png), *TINY]  # fmt: skip
    assert script.main(argv) == 0
    printed = capsys.readouterr().out
    with open(run_dir / "eval.csv") as file:
        rows = list(csv.DictReader(file))
    assert [int(row["frame"]) for row in rows] == [0, 100]  # the scheduled evaluations; 200: the final model
    result = json.loads((run_dir / "result.json").read_text())
    assert result["saved_model_eval"]["frame"] == 200
    config = json.loads((run_dir / "config.json").read_text())
    assert (config["size"], config["action_repeat"], config["torch_threads"]) == (32, 25, 1)  # passed through
    best = max([float(row["mean_reward"]) for row in rows] + [result["saved_model_eval"]["mean_reward"]])
    verdict = "met" if best >= 800 else "not met"
    assert f"target (>= 800 by 200 frames): {verdict}; best {best:.1f}" in printed
    assert f"frame       200: {result['saved_model_eval']['mean_reward']:8.1f}  (saved final model)" in printed
    assert matplotlib.image.imread(png).shape[2] in (3, 4)
    # The same command again: the finished run is drawn, not trained again.
    before = (run_dir / "result.json").stat().st_mtime_ns
    assert script.main(argv) == 0
    assert "Training" not in capsys.readouterr().out and (run_dir / "result.json").stat().st_mtime_ns == before


def test_an_unfinished_run_is_drawn_as_unfinished_and_its_target_judged_so_far(tmp_path, capsys, monkeypatch):
    spec = importlib.util.spec_from_file_location("learning_curve", SCRIPT)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    figures = []
    monkeypatch.setattr(script.plt, "close", figures.append)
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    argv = ["--run-dir", str(run_dir), "--out", str(tmp_path / "curve.png"), "--plot-only"]
    evaluations = [(0, 375.0), (10_000, 262.1), (20_000, 585.2)]
    (run_dir / "eval.csv").write_text(
        "frame,step,mean_reward,std_reward,episodes,wall_time_s\n"
        + "".join(f"{frame},{frame // 2},{value},1.0,10,1.0\n" for frame, value in evaluations)
        + "30000,15000,,,,\n"  # a row being written: left out
    )
    assert script.main(argv) == 0
    printed = capsys.readouterr().out
    verdict = "not met yet; best 585.2 at frame 20,000 (evaluations up to frame 20,000)"
    assert f"target (>= 800 by 60,000 frames): {verdict}" in printed
    assert figures[-1].axes[0].get_title().endswith("(unfinished: evaluated up to frame 20,000)")
    assert [int(x) for x in figures[-1].axes[0].lines[1].get_xdata()] == [0, 10_000, 20_000]  # after the reference
    with (run_dir / "eval.csv").open("a") as file:
        file.write("40000,20000,853.4,5.0,10,2.0\n")
    assert script.main(argv) == 0
    assert "target (>= 800 by 60,000 frames): met; best 853.4 at frame 40,000" in capsys.readouterr().out
