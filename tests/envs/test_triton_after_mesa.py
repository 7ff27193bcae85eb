"""A DrQv2 built and trained after a DeepMind Control frame was rendered, where triton is installed (PyPI's CUDA build
of torch ships it): building the optimizer imports triton (``torch.optim`` imports ``torch._dynamo``), whose C module
crashed the process when Mesa's LLVM was loaded first (docs/environments.md#rendering-and-triton). Each case runs in a
fresh subprocess: the crash is a SIGSEGV, and this process may have rendered and imported triton already."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from sb3_collapse.envs import rendering

ROOT = Path(__file__).resolve().parents[2]

pytestmark = [
    pytest.mark.dmc,
    pytest.mark.skipif(
        importlib.util.find_spec("triton") is None,
        reason="triton is not installed (torch's CPU build): the crash needs triton's LLVM beside Mesa's",
    ),
]

# Renders a pixel frame through the package (make_dmc_env, reset), then builds a DrQv2 and makes a few updates.
TRAIN_AFTER_RENDER = """
import faulthandler, os, sys
faulthandler.enable()
from sb3_collapse import DrQv2, make_dmc_env

env = make_dmc_env("cartpole-balance", seed=0, size=32, action_repeat=8)
pixels, _ = env.reset(seed=0)
assert pixels.shape == (9, 32, 32) and pixels.any(), pixels.shape
print("rendered with MUJOCO_GL", os.environ["MUJOCO_GL"], flush=True)
tiny = dict(feature_dim=8, hidden_dim=16, encoder_kwargs=dict(channels=4))
model = DrQv2("CnnPolicy", env, buffer_size=100, learning_starts=8, batch_size=4, policy_kwargs=tiny, seed=0)
model.learn(24)
print("triton loaded", "triton._C.libtriton" in sys.modules, "updates", model._n_updates, flush=True)
"""

# A user's script that imports dm_control and renders on its own before sb3_collapse is imported.
RENDER_FIRST = """
from dm_control import suite
frame = suite.load("cartpole", "balance").physics.render(32, 32)
assert frame.any()
"""


def run_python(code: str, mujoco_gl: str | None) -> subprocess.CompletedProcess:
    """:return: ``code`` run by this Python with this checkout first on its path and ``MUJOCO_GL`` (unset: None)"""
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])
    if mujoco_gl is not None:
        env["MUJOCO_GL"] = env["PYOPENGL_PLATFORM"] = mujoco_gl
    command = [sys.executable, "-c", textwrap.dedent(code)]
    return subprocess.run(command, env=env, capture_output=True, text=True, timeout=300, check=False)


def assert_trained(result: subprocess.CompletedProcess) -> str:
    """:return: the backend the subprocess rendered with, after checking that it trained with triton loaded"""
    assert result.returncode == 0, f"exit {result.returncode}\n{result.stdout}\n{result.stderr[-3000:]}"
    lines = result.stdout.splitlines()
    *triton_loaded, _, updates = lines[-1].split()
    assert triton_loaded == ["triton", "loaded", "True"], result.stdout  # torch imported triton: the crash's path
    assert int(updates) > 0, result.stdout
    return lines[0].split()[-1]


@pytest.fixture(scope="module")
def backend() -> str:
    """:return: the first headless backend that makes a context here (checked in a subprocess, as the package does)"""
    for backend in rendering.HEADLESS_BACKENDS:
        if rendering._backend_works(backend)[0]:
            return backend
    pytest.skip("no headless OpenGL backend on this machine")


def test_drqv2_trains_after_a_rendered_frame(backend: str) -> None:
    # MUJOCO_GL unset: the package chooses the backend; then set, as in the subprocesses a run starts (SubprocVecEnv
    # workers, Ray trials) and in a user's shell.
    assert assert_trained(run_python(TRAIN_AFTER_RENDER, None)) == backend
    assert assert_trained(run_python(TRAIN_AFTER_RENDER, backend)) == backend


def test_drqv2_trains_after_the_user_rendered_first(backend: str) -> None:
    result = run_python(RENDER_FIRST + TRAIN_AFTER_RENDER, backend)
    assert assert_trained(result) == backend
    if "Mesa's LLVM" in result.stderr:  # Mesa's llvmpipe rendered (not a GPU driver): triton loaded apart from it
        assert "import triton before rendering" in result.stderr
