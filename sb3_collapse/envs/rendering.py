"""Selection of a headless OpenGL backend for MuJoCo / dm_control rendering: :func:`ensure_rendering_backend`.

dm_control reads ``MUJOCO_GL`` once, when it is first imported (``glfw`` by default, which needs a display), so the
backend is chosen before that: :class:`~sb3_collapse.envs.DMCEnv` (hence ``make_dmc_env`` and the registered ids)
calls :func:`ensure_rendering_backend` before it imports dm_control, the train runner before it starts
``SubprocVecEnv`` workers (they inherit ``MUJOCO_GL`` from ``os.environ``), the rl_zoo3 launcher before rl_zoo3.
Importing ``sb3_collapse`` chooses nothing. See docs/environments.md.
"""

from __future__ import annotations

import os
import subprocess
import sys
import warnings

from sb3_collapse.errors import MissingDependencyError

# Backends tried, in order, when ``MUJOCO_GL`` is not set. EGL uses the GPU when there is one
# (and Mesa's software rasterizer otherwise); OSMesa is software only.
HEADLESS_BACKENDS: tuple[str, ...] = ("egl", "osmesa")
# Python code run in a subprocess to check that a backend can create an OpenGL context.
CONTEXT_CHECK_CODE = "import mujoco; c = mujoco.GLContext(8, 8); c.make_current(); c.free()"
# Seconds allowed for one backend check (importing mujoco and creating a context).
CONTEXT_CHECK_TIMEOUT_S = 60.0
# Characters of each failed check's stderr quoted in the error message.
_STDERR_TAIL_CHARS = 600

# Cache of the checks' outcome in this process: the chosen backend, or the report of the failed checks.
_chosen_backend: str | None = None
_failure_report: str | None = None


def ensure_rendering_backend(required: bool = True) -> str | None:
    """
    Make sure MuJoCo can render off-screen, choosing the OpenGL backend if needed: a ``MUJOCO_GL`` already set is
    returned as is; otherwise ``HEADLESS_BACKENDS`` (``egl`` then ``osmesa``) are tried, each in a subprocess, once
    per process, and the first that works is exported as ``MUJOCO_GL`` and ``PYOPENGL_PLATFORM``. Call it before
    ``dm_control`` or ``mujoco`` is imported; building a :class:`~sb3_collapse.envs.DMCEnv` calls it first. See
    docs/environments.md.

    :param required: Whether rendering is needed (pixel observations). If True and no backend works,
        raise :class:`MissingDependencyError`; if False (state observations), return None instead.
    :return: The backend in use (value of ``MUJOCO_GL``), or None if none works and ``required`` is False.
    :raises MissingDependencyError: if no backend works and ``required`` is True.
    """
    global _chosen_backend, _failure_report

    preset = os.environ.get("MUJOCO_GL")
    if preset:
        return preset
    if _chosen_backend is not None:
        _export_backend(_chosen_backend)
        return _chosen_backend

    if _failure_report is None:
        _warn_if_dm_control_imported()
        failures = []
        for backend in HEADLESS_BACKENDS:
            works, stderr = _backend_works(backend)
            if works:
                _chosen_backend = backend
                _export_backend(backend)
                return backend
            failures.append(f"--- MUJOCO_GL={backend} ---\n{stderr.strip()[-_STDERR_TAIL_CHARS:]}")
        _failure_report = "\n".join(failures)

    if required:
        raise MissingDependencyError(_no_backend_message(_failure_report))
    return None


def _backend_works(backend: str, timeout: float = CONTEXT_CHECK_TIMEOUT_S) -> tuple[bool, str]:
    """
    Check, in a subprocess, whether MuJoCo can create an OpenGL context with a backend.

    :param backend: Value tried for ``MUJOCO_GL`` and ``PYOPENGL_PLATFORM`` ("egl" or "osmesa").
    :param timeout: Seconds to wait for the subprocess before counting the backend as not working.
    :return: Whether the backend works, and the subprocess' stderr (to explain a failure).
    """
    env = dict(os.environ, MUJOCO_GL=backend, PYOPENGL_PLATFORM=backend)
    try:
        result = subprocess.run(
            [sys.executable, "-c", CONTEXT_CHECK_CODE],
            check=False,
            env=env,
            stdin=subprocess.DEVNULL,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
    except subprocess.TimeoutExpired:
        return False, f"the check timed out after {timeout:.0f} s"
    except OSError as error:
        return False, f"could not start the check: {error}"
    return result.returncode == 0, result.stderr


def _export_backend(backend: str) -> None:
    """
    Select a backend for this process and the subprocesses it starts from now on.

    :param backend: Value for ``MUJOCO_GL`` and ``PYOPENGL_PLATFORM``.
    """
    os.environ["MUJOCO_GL"] = backend
    os.environ["PYOPENGL_PLATFORM"] = backend


def _warn_if_dm_control_imported() -> None:
    """Warn that the backend choice comes too late if dm_control's rendering is already imported."""
    if "dm_control.mujoco" in sys.modules or "dm_control._render" in sys.modules:
        warnings.warn(
            "dm_control was imported before MUJOCO_GL was set, so it has already picked its OpenGL backend "
            "(glfw by default, which needs a display) and will not use the headless backend chosen now. "
            "Call sb3_collapse.envs.ensure_rendering_backend() before importing dm_control, or set MUJOCO_GL "
            "(e.g. MUJOCO_GL=egl) yourself.",
            RuntimeWarning,
            stacklevel=3,
        )


def _no_backend_message(failure_report: str) -> str:
    """
    :param failure_report: stderr tails of the failed checks.
    :return: The message of the :class:`MissingDependencyError` raised when no backend works.
    """
    return (
        "No headless OpenGL backend works for MuJoCo rendering (tried MUJOCO_GL="
        + ", ".join(HEADLESS_BACKENDS)
        + "), so pixel observations cannot be rendered. To fix it, install one of:\n"
        "  - EGL (GPU driver, or Mesa software rendering): apt-get install libegl1 libgl1-mesa-dri libegl-mesa0\n"
        "  - OSMesa (software rendering): apt-get install libosmesa6\n"
        "or set MUJOCO_GL yourself (egl, osmesa or glfw) before dm_control is imported. "
        "State observations (obs_type='state') need no rendering.\n"
        f"Errors of the checks:\n{failure_report}"
    )
