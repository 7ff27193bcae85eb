"""ruff (pyproject.toml's rules, line length included) passes on the package, the tests, the benchmarks and scripts;
the package holds no module that only tests or benchmarks use (those live in tests/)."""

from __future__ import annotations

import ast
import re
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


PACKAGE = ROOT / "sb3_collapse"
TEST_ONLY_NAME = re.compile(r"^(test|fake|mock|dummy|synthetic|oracle|conftest)|(_test|_fake|_mock|_oracle)$")


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported_by_the_package() -> set[str]:
    """The modules that some module of the package imports (``from a.b import c`` counts ``a.b`` and ``a.b.c``)."""
    imported = set()
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                imported.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module:
                imported.update([node.module, *(f"{node.module}.{alias.name}" for alias in node.names)])
    return imported


def test_the_package_has_no_module_that_only_tests_use():
    """Every module of sb3_collapse/ is a package, a program (``__main__.py``, ``if __name__ == "__main__":``) or
    imported by another module of the package; none is named as a test double (test oracles and test envs live in
    tests/, e.g. tests/drqv2_reference.py and tests/random_env.py)."""
    imported = _imported_by_the_package()
    orphans, test_named = [], []
    for path in sorted(PACKAGE.rglob("*.py")):
        if TEST_ONLY_NAME.search(path.stem):
            test_named.append(str(path.relative_to(ROOT)))
        is_program = path.stem == "__main__" or 'if __name__ == "__main__":' in path.read_text()
        if path.stem != "__init__" and not is_program and _module_name(path) not in imported:
            orphans.append(str(path.relative_to(ROOT)))
    assert not test_named, f"modules named as test doubles in the package (move them to tests/): {test_named}"
    assert not orphans, f"modules that no module of the package imports (move test-only code to tests/): {orphans}"
