"""ruff (pyproject.toml's rules, line length included) passes on the package, the tests, the benchmarks and scripts."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CHECKED = ("sb3_collapse", "tests", "benchmarks", "scripts")


def _ruff() -> list[str] | None:
    """The ruff command: the module of this interpreter's environment, else the one on the PATH; ``None``: none."""
    try:
        import ruff  # noqa: F401
    except ImportError:
        executable = shutil.which("ruff")
        return [executable] if executable else None
    return [sys.executable, "-m", "ruff"]


def test_ruff_check_passes():
    ruff = _ruff()
    if ruff is None:
        pytest.skip("ruff is not installed: pip install -e '.[dev]' (bash run.sh setup installs it)")
    result = subprocess.run(
        [*ruff, "check", "--no-cache", "--output-format", "concise", *CHECKED],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, f"ruff check failed (fix the lines below):\n{result.stdout}{result.stderr}"
