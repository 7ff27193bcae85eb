"""
The rehearsal of ``benchmarks/gpu.sh`` on the CPU: its import guard (``benchmarks/rehearsal/``), and its
install-and-import part (``gpu.sh --rehearse --install-only``): the carried wheels installed as on the GPU machine,
and the imports the script needs, with nothing else than the GPU machine's packages. The whole rehearsal (every step
at tiny sizes, several minutes) is ``bash benchmarks/gpu.sh --rehearse``.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
GUARD = ROOT / "benchmarks" / "rehearsal"


def test_the_import_guard_refuses_what_the_gpu_machine_lacks_and_nothing_else(tmp_path):
    carried = tmp_path / "site"
    (carried / "carried_module").mkdir(parents=True)
    (carried / "carried_module" / "__init__.py").write_text("VALUE = 7\n")
    code = (
        "import json, numpy, torch, carried_module\n"  # the standard library, the image's packages, the carried ones
        "assert carried_module.VALUE == 7\n"
        "try:\n    import stable_baselines3\nexcept ModuleNotFoundError as error:\n    print(error)\n"
        "else:\n    print('imported')\n"
    )
    env = dict(os.environ, PYTHONPATH=f"{GUARD}{os.pathsep}{carried}{os.pathsep}{ROOT}")
    env["SB3_COLLAPSE_REHEARSAL_SITE"] = str(carried)
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("No module named 'stable_baselines3' on the GPU machine"), done.stdout
    assert "distribution stable_baselines3" in done.stdout or "distribution stable-baselines3" in done.stdout


def test_the_rehearsal_installs_the_carried_wheels_and_imports_only_what_the_gpu_machine_has(tmp_path):
    """
    The wheels come from ``gpu_prepare.sh`` for this Python (kept in /tmp/sb3-collapse-rehearsal/wheels-cpXY between
    runs), so the first run needs PyPI: without network the test is skipped, saying so. ``PYTHON`` is the test's own
    interpreter: the whole rehearsal's (Python 3.12, torch 2.11, numpy 2.5: ``benchmarks/rehearsal/venv.sh``) takes
    5 GB and minutes to make once.
    """
    env = dict(os.environ, PYTHON=sys.executable, OUT=str(tmp_path / "out"), REHEARSAL_SITE=str(tmp_path / "site"))
    done = subprocess.run(
        ["bash", str(ROOT / "benchmarks" / "gpu.sh"), "--rehearse", "--install-only"],
        env=env, capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    if done.returncode == 3:
        pytest.skip("gpu_prepare.sh could not download the wheels to carry (no network to PyPI?)")
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert f"stable_baselines3 2.9.2 from {tmp_path / 'site' / 'stable_baselines3'}" in done.stdout
    assert (tmp_path / "site" / "dm_control" / "suite").is_dir()  # unpacked from the trimmed zip
    assert (tmp_path / "out" / "gpu.log").exists()
