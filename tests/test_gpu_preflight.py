"""
The preflight of ``benchmarks/gpu.sh`` (``benchmarks/gpu_preflight.py``) and the shell functions that gpu.sh runs on
its results: a rendering verdict judged by a subprocess that fails, crashes or hangs; verdicts that survive a
preflight killed mid-way; ``limit()`` never giving a timeout of 0 or less; the EGL vendor file exported only where
glvnd would find none; the commit named without ``.git``.
"""

from __future__ import annotations

import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PREFLIGHT = ROOT / "benchmarks" / "gpu_preflight.py"
GPU_SH = ROOT / "benchmarks" / "gpu.sh"


def gpu_sh(script: str, cwd: Path = ROOT, **env: str) -> str:
    """Run ``script`` in bash after sourcing gpu.sh (its functions alone); return what it printed."""
    done = subprocess.run(
        ["bash", "-c", f"source {GPU_SH}\n{script}"], cwd=cwd, env=dict(os.environ, **env), capture_output=True,
        text=True, timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return done.stdout


def preflight(tmp_path: Path, render_code: str | None, timeout: float = 60) -> tuple[dict[str, str], str, float]:
    """The preflight's RENDER check alone on the CPU, with ``render_code`` (``None``: its own): its verdicts read
    back by gpu.sh, what it appended to machine.txt, its seconds."""
    start = time.perf_counter()
    code = [] if render_code is None else ["--render-code", render_code]
    done = subprocess.run(
        [sys.executable, str(PREFLIGHT), "--device", "cpu", "--out", str(tmp_path / "machine.txt"), "--status",
         str(tmp_path / "status"), "--checks", "RENDER", "--timeout", str(timeout), *code],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return read_preflight(tmp_path / "status"), (tmp_path / "machine.txt").read_text(), time.perf_counter() - start


def read_preflight(status: Path) -> dict[str, str]:
    """The verdicts as gpu.sh's ``read_preflight`` leaves them (its defaults, then what the file holds)."""
    names = [f"{check}_{what}" for check in ("DEVICE", "CORE", "RENDER", "COMPILE") for what in ("OK", "WHY")]
    printed = gpu_sh(f"read_preflight {status}\n" + "".join(f'echo "{name}=${name}"\n' for name in names))
    return dict(line.split("=", 1) for line in printed.splitlines())


def test_a_render_that_fails_is_a_verdict_with_its_stage_and_error(tmp_path):
    code = "import sys\nprint('STAGE rendered one frame', flush=True)\nsys.exit('EGLError: no display')"
    verdicts, machine, _ = preflight(tmp_path, code)
    assert verdicts["DEVICE_OK"] == "1"
    assert verdicts["RENDER_OK"] == "0"
    assert "after 'rendered one frame'" in verdicts["RENDER_WHY"] and "EGLError: no display" in verdicts["RENDER_WHY"]
    assert "FAILED: after 'rendered one frame'" in machine
    assert verdicts["CORE_WHY"].startswith("the preflight ended before this check")  # not run: gpu.sh's default


def test_a_crash_after_the_render_is_a_verdict_naming_the_signal(tmp_path):
    """What triton loaded after Mesa's EGL did: a SIGSEGV when the DrQv2's optimizers were built."""
    code = (
        "import os, signal\nprint('STAGE rendered one frame', flush=True)\n"
        "print('STAGE built a DrQv2', flush=True)\nos.kill(os.getpid(), signal.SIGSEGV)"
    )
    verdicts, _, _ = preflight(tmp_path, code)
    assert verdicts["RENDER_OK"] == "0"
    why = verdicts["RENDER_WHY"]
    assert why.startswith("after 'built a DrQv2'; killed by SIGSEGV; Fatal Python error: Segmentation fault"), why
    assert 'File "<string>", line 4' in why  # faulthandler's innermost frame: the line that crashed


def test_a_render_that_hangs_is_a_verdict_within_its_timeout(tmp_path):
    verdicts, _, seconds = preflight(tmp_path, "import time\ntime.sleep(120)", timeout=3)
    assert verdicts["RENDER_OK"] == "0"
    assert verdicts["RENDER_WHY"] == "before its first stage; no answer in 3 s (killed)"
    assert seconds < 100  # the import of torch included, on a busy machine


@pytest.mark.dmc
def test_the_render_check_renders_then_trains_a_drqv2_in_one_process(tmp_path):
    verdicts, machine, _ = preflight(tmp_path, None, timeout=240)
    assert verdicts["RENDER_OK"] == "1", verdicts["RENDER_WHY"]
    assert "then a DrQv2 trained on cpu: ok" in machine
    assert "render and train: rendered one walker-walk frame (OpenGL renderer: " in machine  # Mesa's, here
    assert "built a DrQv2 (Adam: torch._dynamo, triton), trained " in machine


def test_verdicts_written_before_the_preflight_is_killed_survive_it(tmp_path):
    status = tmp_path / "status"
    process = subprocess.Popen(
        [sys.executable, str(PREFLIGHT), "--device", "cpu", "--out", str(tmp_path / "machine.txt"), "--status",
         str(status), "--checks", "RENDER", "--render-code", "import time\ntime.sleep(600)"],
        stdout=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        deadline = time.time() + 120
        while "DEVICE_OK" not in (status.read_text() if status.exists() else "") and time.time() < deadline:
            time.sleep(0.1)
        assert process.poll() is None  # still waiting for its render
    finally:
        process.send_signal(signal.SIGKILL)  # as `timeout --kill-after` ends a preflight that hangs
        process.wait()
    verdicts = read_preflight(status)
    assert verdicts["DEVICE_OK"] == "1" and verdicts["DEVICE_WHY"] == ""
    assert verdicts["RENDER_OK"] == "0"
    assert verdicts["RENDER_WHY"].startswith("the preflight ended before this check (timed out or killed")


def test_read_preflight_without_a_status_file_gives_every_default(tmp_path):
    verdicts = read_preflight(tmp_path / "never-written")
    assert {verdicts[f"{check}_OK"] for check in ("DEVICE", "CORE", "RENDER", "COMPILE")} == {"0"}


@pytest.mark.parametrize(
    ("budget", "elapsed", "asked", "at_least", "expected"),
    [
        (540, 0, 110, 30, "110"),  # the step's own limit (110 s of 530 left)
        (540, 470, 110, 30, "60"),  # cut to what is left, less 10 s to write up
        (540, 505, 110, 30, None),  # 25 s left: under the step's 30
        (540, 530, 110, 10, None),  # 0 s left
        (540, 600, 110, 10, None),  # past the budget: no negative timeout
        (540, 525, 600, None, None),  # 5 s left, under the default minimum of 10
    ],
)
def test_limit_is_never_zero_or_negative(budget, elapsed, asked, at_least, expected):
    call = f"limit {asked}" + (f" {at_least}" if at_least is not None else "")
    printed = gpu_sh(f"START=$(($(date +%s) - {elapsed})) BUDGET={budget}\nif t=$({call}); then echo \"limit $t\";"
                     f" else too_late {at_least or 10}; fi")  # fmt: skip
    if expected is None:
        assert printed.startswith("SKIPPED: ") and f"under the {at_least or 10} s this step needs" in printed
    else:  # a second may tick between setting START and reading the clock
        assert printed in (f"limit {expected}\n", f"limit {int(expected) - 1}\n"), printed


def test_the_nvidia_egl_vendor_file_is_exported_only_where_glvnd_has_none(tmp_path):
    nvidia, empty, holding = tmp_path / "10_nvidia.json", tmp_path / "empty", tmp_path / "holding"
    nvidia.write_text("{}")
    empty.mkdir()
    holding.mkdir()
    (holding / "50_mesa.json").write_text("{}")
    env = {"__EGL_VENDOR_LIBRARY_FILENAMES": ""}
    assert gpu_sh(f"egl_vendor {nvidia} {empty} {tmp_path / 'absent'}", **env) == f"{nvidia}\n"
    assert gpu_sh(f"egl_vendor {nvidia} {empty} {holding}", **env) == ""  # glvnd finds Mesa's (or the driver's)
    assert gpu_sh(f"egl_vendor {tmp_path / 'no-driver.json'} {empty}", **env) == ""
    assert gpu_sh(f"egl_vendor {nvidia} {empty}", __EGL_VENDOR_LIBRARY_FILENAMES="/chosen.json") == ""


def test_the_commit_is_named_without_git(tmp_path):
    wheels = tmp_path / ".whl"
    wheels.mkdir()
    env = {"SB3_COLLAPSE_COMMIT": "", "GIT_CEILING_DIRECTORIES": str(tmp_path)}  # no repository above tmp_path
    assert gpu_sh(f"commit {wheels}", cwd=tmp_path, **env).startswith("unknown (no .git")
    (wheels / "COMMIT").write_text("abc1234, dirty: uncommitted changes when gpu_prepare.sh ran\n")
    assert gpu_sh(f"commit {wheels}", cwd=tmp_path, **env) == (
        f"abc1234, dirty: uncommitted changes when gpu_prepare.sh ran ({wheels}/COMMIT, from gpu_prepare.sh)\n"
    )
    assert gpu_sh(f"commit {wheels}", cwd=tmp_path, SB3_COLLAPSE_COMMIT="f00ba47") == "f00ba47 (SB3_COLLAPSE_COMMIT)\n"


def test_bounded_ends_the_step_and_what_it_left_running(tmp_path):
    """A worker that ignores SIGINT and outlives its parent would hold the step's pipe (and its tee) open; an empty
    library in the inductor cache would fail the next compilation of the same code."""
    pid_file = tmp_path / "worker.pid"
    step = (
        "import signal, subprocess, sys\n"
        "worker = subprocess.Popen(['bash', '-c', 'trap \"\" INT; sleep 120; echo late'])\n"
        f"open({str(pid_file)!r}, 'w').write(str(worker.pid))\n"
        "print('started', flush=True)\n"
        "signal.sigwait([signal.SIGINT])\n"  # the step's own process ends at the SIGINT, leaving its worker
    )
    cache = tmp_path / "inductor"  # a compilation killed mid-way leaves an empty library; a whole one stays
    (cache / "ab").mkdir(parents=True)
    (cache / "ab" / "killed.main.so").write_bytes(b"")
    (cache / "ab" / "whole.main.so").write_bytes(b"\x7fELF")
    start = time.perf_counter()
    printed = gpu_sh(
        f'bounded 3 2 {sys.executable} -c {shlex.quote(step)} | cat; echo "status ${{PIPESTATUS[0]}}"',
        TORCHINDUCTOR_CACHE_DIR=str(cache),
    )
    assert time.perf_counter() - start < 60  # not the worker's 120 s
    assert printed.startswith("started\n") and "late" not in printed
    assert printed.endswith(("status 0\n", "status 124\n")), printed
    status = Path(f"/proc/{pid_file.read_text()}/status")
    deadline = time.time() + 10
    while status.exists() and "State:\tZ" not in status.read_text() and time.time() < deadline:
        time.sleep(0.1)
    assert not status.exists() or "State:\tZ" in status.read_text()  # gone, or dead and not yet reaped
    assert sorted(path.name for path in cache.rglob("*.so")) == ["whole.main.so"]
