"""
The benchmark scripts keep what they measured when a time limit interrupts them, and go on past a failure:
``benchmarks/update_speed.py`` prints the eager rows before the compiled update starts compiling, and
``benchmarks/train_throughput.py`` reports a failed configuration and runs the others (tiny sizes, on the CPU).
"""

from __future__ import annotations

import argparse
import csv
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TINY_SPEED = ["--device", "cpu", "--size", "32", "--hidden-dim", "16", "--batch-sizes", "8", "4", "--rounds", "1",
              "--updates", "1", "--buffer-size", "20"]  # fmt: skip


def _environment() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")


def _group_is_gone(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return True
    return False


def test_update_speed_prints_the_eager_rows_before_compiling_and_keeps_them_when_interrupted():
    """SIGINT to the process group (what ``timeout --signal=INT`` sends) while ``ours-compiled`` starts: the eager
    table's rows, printed before, stay the output; the workers ignore the signal and are stopped by the script."""
    command = [sys.executable, str(ROOT / "benchmarks" / "update_speed.py"), *TINY_SPEED,
               "--impls", "reference", "ours", "ours-compiled"]  # fmt: skip
    process = subprocess.Popen(command, cwd=ROOT, env=_environment(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, start_new_session=True)  # fmt: skip
    try:
        before = []
        for line in process.stdout:
            before.append(line)
            if line.startswith("ours-compiled (compiling"):  # printed after the eager rows, as it starts compiling
                break
        assert before and before[-1].startswith("ours-compiled (compiling"), "".join(before) + process.stderr.read()
        os.killpg(process.pid, signal.SIGINT)
        after, errors = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    output = "".join(before) + after
    assert process.returncode == 0, output + errors
    header = next(i for i, line in enumerate(before) if line.split()[:1] == ["batch"])
    assert before[header].split() == ["batch", "reference", "(ms)", "ours", "(ms)", "ours", "/", "reference"]
    rows = [line.split() for line in before[header + 1 : header + 3]]
    assert [row[0] for row in rows] == ["8", "4"]
    for row in rows:  # milliseconds of both, and the ratio with its range
        assert float(row[1]) > 0 and float(row[2]) > 0 and float(row[3]) > 0, row
    assert after.strip().splitlines()[-1] == "interrupted: the rows above are complete", output + errors
    assert "ours-compiled (ms)" not in output
    assert "KeyboardInterrupt" not in errors  # the workers ignored the SIGINT
    assert _group_is_gone(process.pid)  # every worker stopped


def _run(command: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, *command],
        cwd=ROOT,
        env=_environment(),
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def test_update_speed_reports_an_implementation_not_ready_and_exits_1():
    done = _run(["benchmarks/update_speed.py", *TINY_SPEED, "--ready-timeout", "0.01", "--impls", "reference", "ours"])
    assert done.returncode == 1, done.stdout + done.stderr
    for impl in ("reference", "ours"):
        assert f"{impl}: not ready after 0.01 s; skipped" in done.stdout


def test_train_throughput_reports_a_failed_configuration_and_runs_the_next(tmp_path):
    """``--envs 0 1``: the first configuration fails (the train CLI refuses 0 environments), the second runs; both
    are reported, the table and the CSV hold the second, the exit status is 1."""
    table = tmp_path / "throughput.csv"
    tiny = ["--size", "32", "--hidden-dim", "16", "--batch-size", "8", "--seed-frames", "40", "--frames", "16",
            "--buffer-size", "1000"]  # fmt: skip
    done = _run(["benchmarks/train_throughput.py", "--envs", "0", "1", "--compile", "off", *tiny, "--csv", str(table)])
    assert done.returncode == 1, done.stdout + done.stderr
    lines = done.stdout.splitlines()
    failed = next(line for line in lines if line.strip().startswith("failed: 0 envs"))
    assert "compiled False, overlap False, 1 at once: run 0 exited with status 2" in failed
    assert "--n-envs must be >= 1, got 0." in failed  # its error, in the same line
    assert any(line.strip().startswith("done: 1 envs, compiled False") for line in lines)
    assert lines[-1] == (
        "failed: 1 configuration(s), left out of the table: 0 envs, compiled False, overlap False, 1 at once"
    )
    with open(table) as file:
        assert [row["envs"] for row in csv.DictReader(file)] == ["1"]
    assert "--n-envs must be >= 1, got 0." in done.stderr  # the run's own error output, kept in the log


FAKE_DMC = """
import numpy as np
class Spec:
    def __init__(self, dtype):
        self.dtype = dtype
    def replace(self, dtype):
        return Spec(dtype)
class Env:
    def action_spec(self):
        return Spec(np.float64)  # what dm_control 1.0's action_scale.Wrapper leaves
def make(*args, **kwargs):
    return Env()
"""
FAKE_TRAIN = """
import os, sys
from pathlib import Path

import pytest
import numpy as np
import dmc, replay_buffer
overrides = dict(argument.split("=", 1) for argument in sys.argv[1:])
assert os.environ["MUJOCO_GL"] == "egl"
assert dmc.make("walker_walk", 3, 2, 1).action_spec().dtype == np.float32, "actions not declared float32"
replay_buffer._worker_init_fn(1)
if overrides["task@_global_"] != "walker_walk":
    sys.exit("error: no task " + overrides["task@_global_"])
assert overrides["eval_every_frames"] == "null" and overrides["num_seed_frames"] == "4000"
Path(overrides["hydra.run.dir"], "train.csv").write_text("frame,fps\\n5000,20.0\\n6000,100.0\\n7000,110.0\\n")
"""


def _fake_reference(folder: Path) -> Path:
    """A stand-in for a facebookresearch/drqv2 checkout: its train.py checks the launcher's two changes and writes the
    train.csv that the reference writes (frames/s per episode)."""
    folder.mkdir()
    (folder / "dmc.py").write_text(FAKE_DMC)
    (folder / "replay_buffer.py").write_text("def _worker_init_fn(worker_id):\n    raise TypeError('numpy seed')\n")
    (folder / "train.py").write_text(FAKE_TRAIN)
    return folder


def _throughput_module():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import train_throughput
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    return train_throughput


def test_train_throughput_times_the_reference_loop_and_prints_the_ratios(tmp_path, capsys):
    """``--reference``: the reference's train.py runs through the launcher (float32 actions, int seeds), its
    learning frames/s is the median of its logged episodes after the first; a failure is one line; each configuration
    gets its ratio to the reference."""
    throughput = _throughput_module()
    reference = str(_fake_reference(tmp_path / "drqv2"))
    sizes = dict(seed_frames=4000, frames=3000, batch_size=512, n_steps=1, hidden_dim=1024)
    args = argparse.Namespace(reference=reference, task="walker-walk", device="cpu", **sizes)
    result = throughput.measure_reference(args, tmp_path / "runs")
    assert result["episodes"] == [(5000, 20.0), (6000, 100.0), (7000, 110.0)]
    assert result["learning_fps"] == 105.0
    args.task = "cartpole-balance"
    with pytest.raises(RuntimeError, match=r"^exited with status 1: error: no task cartpole_balance$"):
        throughput.measure_reference(args, tmp_path / "failed")
    rows = [
        dict(envs=1, compiled=False, overlap=False, concurrent=1, learning_fps=315.0),
        dict(envs=4, compiled=True, overlap=False, concurrent=1, learning_fps=420.0),
        dict(envs=4, compiled=True, overlap=False, concurrent=3, learning_fps=1.0),  # several at once: no ratio
    ]
    throughput.print_reference_ratios(rows, [100.0, 110.0])
    assert capsys.readouterr().out == (
        "reference: 105.00 learning frames/s; ours / reference: 1 envs eager 3.00x; 4 envs compiled 4.00x\n"
    )


def test_train_throughput_refuses_a_reference_run_too_short_to_measure(tmp_path, monkeypatch, capsys):
    throughput = _throughput_module()
    reference = _fake_reference(tmp_path / "drqv2")
    monkeypatch.setattr(sys, "argv", ["train_throughput.py", "--reference", str(reference), "--seed-frames", "2000"])
    with pytest.raises(SystemExit):
        throughput.main()
    assert "--reference needs --frames >= 2000 and --seed-frames >= 4000" in capsys.readouterr().err
