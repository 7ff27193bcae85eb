"""
The benchmark scripts keep what they measured when a time limit interrupts them, and go on past a failure:
``benchmarks/update_speed.py`` prints the eager rows before the compiled update starts compiling, and
``benchmarks/train_throughput.py`` reports a failed configuration and runs the others (tiny sizes, on the CPU).
"""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
from pathlib import Path

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
    assert after.strip().splitlines()[-1] == "interrupted: the rows above are complete"
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
