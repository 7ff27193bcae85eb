"""The algorithm package stands alone: importing it imports none of the experiment code."""

import subprocess
import sys

import pytest

EXPERIMENT_PACKAGES = ("monitoring", "train", "sweep", "probe", "report", "run", "zoo", "checkpoints")


def test_importing_the_algorithm_imports_no_experiment_code():
    """``import sb3_collapse.drqv2`` (which runs ``sb3_collapse/__init__.py`` first) in a fresh interpreter."""
    prefixes = tuple(f"sb3_collapse.{name}" for name in EXPERIMENT_PACKAGES)
    code = f"import sys, sb3_collapse.drqv2; print([m for m in sys.modules if m.startswith({prefixes!r})])"
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert out.strip() == "[]"


def test_the_package_still_offers_the_callbacks():
    import sb3_collapse
    from sb3_collapse.monitoring import CollapseReset

    assert sb3_collapse.CollapseReset is CollapseReset
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        sb3_collapse.nope  # noqa: B018
