import pytest

from sb3_collapse.sweep import ray_session


@pytest.fixture(scope="module")
def ray_local():
    """One local Ray instance (2 CPUs) for each module that asks: its sweeps use it instead of starting their own."""
    pytest.importorskip("ray", reason="the sweep extra is not installed: pip install -e '.[sweep]'")
    with ray_session(num_cpus=2):
        yield
