"""The headless OpenGL backend of MuJoCo rendering, chosen by :func:`ensure_rendering_backend` before dm_control is
imported (it reads ``MUJOCO_GL`` once). See docs/environments.md."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings

from sb3_collapse.errors import MissingDependencyError

HEADLESS_BACKENDS: tuple[str, ...] = ("egl", "osmesa")  # tried in order when MUJOCO_GL is not set
CONTEXT_CHECK_CODE = "import mujoco; c = mujoco.GLContext(8, 8); c.make_current(); c.free()"
CONTEXT_CHECK_TIMEOUT_S = 60.0
_STDERR_TAIL_CHARS = 600  # of each failed check, quoted in the error

# This process's outcome of the checks: the chosen backend, or the report of the failed checks.
_chosen_backend: str | None = None
_failure_report: str | None = None


def ensure_rendering_backend(required: bool = True) -> str | None:
    """
    Make sure MuJoCo can render off-screen: a ``MUJOCO_GL`` already set is kept; otherwise ``egl`` then ``osmesa``
    are tried, each in a subprocess, once per process, and the first that works is exported as ``MUJOCO_GL`` and
    ``PYOPENGL_PLATFORM``. Call it before ``dm_control`` or ``mujoco`` is imported.

    :param required: whether rendering is needed (pixel observations): if no backend works, ``MissingDependencyError``
        if True, else None is returned
    :return: the backend in use (``MUJOCO_GL``)
    """
    global _chosen_backend, _failure_report

    if os.environ.get("MUJOCO_GL"):
        return os.environ["MUJOCO_GL"]
    if _chosen_backend is None and _failure_report is None:
        if "dm_control.mujoco" in sys.modules or "dm_control._render" in sys.modules:
            warnings.warn(
                "dm_control was imported before MUJOCO_GL was set, so it has already picked its OpenGL backend "
                "(glfw by default, which needs a display) and will not use the headless backend chosen now. "
                "Call sb3_collapse.envs.ensure_rendering_backend() before importing dm_control, or set MUJOCO_GL "
                "(e.g. MUJOCO_GL=egl) yourself.",
                RuntimeWarning,
                stacklevel=2,
            )
        failures = []
        for backend in HEADLESS_BACKENDS:
            works, stderr = _backend_works(backend)
            if works:
                _chosen_backend = backend
                break
            failures.append(f"--- MUJOCO_GL={backend} ---\n{stderr.strip()[-_STDERR_TAIL_CHARS:]}")
        else:
            _failure_report = "\n".join(failures)
    if _chosen_backend is not None:  # exported again, for the subprocesses started from now on
        os.environ["MUJOCO_GL"] = os.environ["PYOPENGL_PLATFORM"] = _chosen_backend
        return _chosen_backend
    if required:
        raise MissingDependencyError(
            f"No headless OpenGL backend works for MuJoCo rendering (tried MUJOCO_GL={', '.join(HEADLESS_BACKENDS)}), "
            "so pixel observations cannot be rendered. To fix it, install one of:\n"
            "  - EGL (GPU driver, or Mesa software rendering): apt-get install libegl1 libgl1-mesa-dri libegl-mesa0\n"
            "  - OSMesa (software rendering): apt-get install libosmesa6\n"
            "or set MUJOCO_GL yourself (egl, osmesa or glfw) before dm_control is imported. "
            "State observations (obs_type='state') need no rendering.\n"
            f"Errors of the checks:\n{_failure_report}"
        )
    return None


def _backend_works(backend: str, timeout: float = CONTEXT_CHECK_TIMEOUT_S) -> tuple[bool, str]:
    """:return: whether an OpenGL context is made in a subprocess with ``backend`` as ``MUJOCO_GL`` (within
    ``timeout`` seconds), and its stderr"""
    env = dict(os.environ, MUJOCO_GL=backend, PYOPENGL_PLATFORM=backend)
    try:
        command = [sys.executable, "-c", CONTEXT_CHECK_CODE]
        result = subprocess.run(
            command, check=False, env=env, stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=timeout
        )
    except subprocess.TimeoutExpired:
        return False, f"the check timed out after {timeout:.0f} s"
    except OSError as error:
        return False, f"could not start the check: {error}"
    return result.returncode == 0, result.stderr
