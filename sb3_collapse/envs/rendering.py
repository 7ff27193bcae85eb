"""The headless OpenGL backend of MuJoCo rendering, chosen by :func:`ensure_rendering_backend` before dm_control is
imported (it reads ``MUJOCO_GL`` once), and triton's LLVM loaded before Mesa's (:func:`load_triton_before_mesa`). See
docs/environments.md."""

from __future__ import annotations

import importlib
import importlib.util
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
_triton_checked = False  # whether load_triton_before_mesa has run in this process


def ensure_rendering_backend(required: bool = True) -> str | None:
    """
    Make sure MuJoCo can render off-screen: a ``MUJOCO_GL`` already set is kept; otherwise ``egl`` then ``osmesa``
    are tried, each in a subprocess, once per process, and the first that works is exported as ``MUJOCO_GL`` and
    ``PYOPENGL_PLATFORM``. Call it before ``dm_control`` or ``mujoco`` is imported: it also loads triton's C module
    first where triton is installed (:func:`load_triton_before_mesa`), in every process that calls it.

    :param required: whether rendering is needed (pixel observations): if no backend works, ``MissingDependencyError``
        if True, else None is returned
    :return: the backend in use (``MUJOCO_GL``)
    """
    global _chosen_backend, _failure_report

    load_triton_before_mesa()  # before any return: subprocesses and Ray workers inherit MUJOCO_GL
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


def load_triton_before_mesa() -> None:
    """
    Load triton's C module (``triton._C.libtriton``) now, once per process, where triton is installed (PyPI's CUDA
    build of torch ships it); where it is not, this costs one ``importlib.util.find_spec``.

    Mesa's EGL and OSMesa (llvmpipe, its software renderer) open their driver with ``RTLD_GLOBAL``, which puts the
    system's ``libLLVM-<n>.so`` in the process's global symbol scope. ``libtriton.so`` carries an LLVM of its own and
    exports its symbols, so when it is loaded after that, the dynamic linker binds its LLVM references to Mesa's LLVM
    (another version) and the process dies of SIGSEGV while loading it. Loaded first, as a Python extension (with
    ``RTLD_LOCAL``), it keeps its own LLVM and Mesa's binds to itself. torch imports triton when ``torch._dynamo`` is
    first imported, which building a ``torch.optim`` optimizer does: without this, a process that renders a frame
    before it builds its model dies.

    When an LLVM library is loaded already (the process rendered before calling this), triton's C module is loaded
    with ``RTLD_DEEPBIND`` (its own LLVM before the global scope's), with a ``RuntimeWarning``.
    """
    global _triton_checked

    if _triton_checked:
        return
    _triton_checked = True
    if "triton._C.libtriton" in sys.modules or importlib.util.find_spec("triton") is None:
        return
    flags = sys.getdlopenflags()
    llvm = _loaded_llvm_libraries()
    if llvm and hasattr(os, "RTLD_DEEPBIND"):
        warnings.warn(
            f"Mesa's LLVM ({', '.join(llvm)}) was loaded before triton, so triton's C module is loaded with "
            "RTLD_DEEPBIND (loaded the ordinary way it would crash the process). To load it the ordinary way, "
            "import triton before rendering: call sb3_collapse.envs.ensure_rendering_backend() before importing "
            "dm_control, or `import triton._C.libtriton` first.",
            RuntimeWarning,
            stacklevel=3,
        )
        sys.setdlopenflags(flags | os.RTLD_DEEPBIND)
    try:
        importlib.import_module("triton._C.libtriton")
    except ImportError:
        pass  # a broken triton: torch, which imports it under `except ImportError`, then runs without it as well
    finally:
        sys.setdlopenflags(flags)


def _loaded_llvm_libraries() -> list[str]:
    """:return: the file names of the LLVM libraries mapped into this process (Linux; elsewhere none)"""
    try:
        with open("/proc/self/maps") as maps:
            paths = {line.split(maxsplit=5)[-1].strip() for line in maps if "libLLVM" in line}
    except OSError:
        return []
    return sorted(os.path.basename(path) for path in paths)


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
