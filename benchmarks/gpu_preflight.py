"""
The first step of ``benchmarks/gpu.sh``: what this machine has, in seconds, before any benchmark runs.

Appends to ``--out`` (``machine.txt``), one line as each check ends: the versions of Python and of the packages that
matter (torch and its CUDA, SB3, gymnasium, dm_control, mujoco, shimmy), the imports the steps need, one DeepMind
Control frame rendered (``MUJOCO_GL``, EGL on a GPU; when it fails, the EGL vendor files and
``NVIDIA_DRIVER_CAPABILITIES``, and a second try with the NVIDIA driver's EGL vendor file if there is one), and
whether ``torch.compile`` can compile on the device (a C compiler and Python's headers; Triton on CUDA). Writes
``--status``: shell assignments that ``gpu.sh`` sources to skip, with its reason, each step that needs what failed.

    python benchmarks/gpu_preflight.py --device cuda --out machine.txt --status /tmp/preflight.env
"""

from __future__ import annotations

import argparse
import glob
import importlib.metadata
import os
import platform
import shlex
import shutil
import subprocess
import sys
import sysconfig
import time

RENDER = """
from dm_control import suite
pixels = suite.load("cartpole", "balance").physics.render(84, 84, camera_id=0)
assert pixels.shape == (84, 84, 3) and pixels.std() > 0, "a blank frame"
"""
"""One rendered frame of cartpole-balance, in a subprocess (an OpenGL failure can crash or hang it)."""

COMPILE = """
import sys, torch
f = torch.compile(lambda x: (x.sin() + 1).relu().sum(), mode="default")
x = torch.randn(64, device=sys.argv[1])
assert torch.allclose(f(x), (x.sin() + 1).relu().sum())
"""
"""A tiny ``torch.compile`` on the device (Triton kernels on CUDA, C++ on the CPU), in a subprocess."""

NVIDIA_EGL_VENDOR = "/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json"
"""The NVIDIA driver's EGL vendor file where the driver is mounted (``/usr/local/nvidia``)."""

EGL_VENDOR_FOLDERS = ("/usr/share/glvnd/egl_vendor.d", "/etc/glvnd/egl_vendor.d", os.path.dirname(NVIDIA_EGL_VENDOR))


def version(distribution: str, module: str | None = None) -> str:
    """The installed version of ``distribution``, or of ``module``'s ``__version__`` when it has no metadata (a
    carried, unpacked package), or why there is none."""
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        pass
    try:
        found = __import__(module or distribution.replace("-", "_"))
        return getattr(found, "__version__", f"present, no version ({os.path.dirname(found.__file__)})")
    except Exception as error:  # noqa: BLE001 (any import failure is the finding)
        return f"MISSING ({type(error).__name__}: {error})"


def run_python(code: str, *args: str, timeout: float, env: dict | None = None) -> str | None:
    """Run ``code`` in a fresh interpreter: ``None`` when it succeeded, else the end of its error."""
    try:
        done = subprocess.run(
            [sys.executable, "-c", code, *args], check=False, capture_output=True, text=True, timeout=timeout, env=env
        )
    except subprocess.TimeoutExpired:
        return f"no answer in {timeout:.0f} s"
    if done.returncode == 0:
        return None
    lines = [line for line in done.stderr.strip().splitlines() if line.strip()]
    return " | ".join(lines[-3:]) or f"exit status {done.returncode}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda", help="the device the steps use: cuda (the GPU) or cpu")
    parser.add_argument("--out", required=True, help="the file to append the findings to (machine.txt)")
    parser.add_argument("--status", required=True, help="the shell assignments for gpu.sh")
    args = parser.parse_args()
    start = time.perf_counter()
    status: dict[str, str] = {}
    out = open(args.out, "a")  # noqa: SIM115 (appended to line by line, closed at the end)

    def log(line: str) -> None:
        line = f"[{time.perf_counter() - start:5.1f} s] {line}"
        print(line, flush=True)
        out.write(line + "\n")
        out.flush()

    def verdict(name: str, error: str | None, what: str) -> None:
        status[f"{name}_OK"] = "0" if error else "1"
        status[f"{name}_WHY"] = error or ""
        log(f"{what}: {'FAILED: ' + error if error else 'ok'}")

    log(f"python {platform.python_version()} ({sys.executable}), {platform.platform()}")
    import torch

    cuda = torch.cuda.is_available()
    log(f"torch {torch.__version__}, CUDA {torch.version.cuda}, cuDNN {torch.backends.cudnn.version()}, "
        f"GPU: {torch.cuda.get_device_name() if cuda else 'none seen'}")  # fmt: skip
    device_error = None
    if args.device.startswith("cuda") and not cuda:
        device_error = "torch sees no CUDA GPU (torch.cuda.is_available() is False)"
    verdict("DEVICE", device_error, f"device {args.device}")
    packages = [("stable_baselines3", None), ("gymnasium", None), ("dm_control", None), ("mujoco", None),
                ("shimmy", None), ("numpy", None), ("triton", None)]  # fmt: skip
    log("packages: " + ", ".join(f"{name} {version(name, module)}" for name, module in packages))

    try:
        import sb3_collapse.report
        import sb3_collapse.train  # noqa: F401

        core_error = None
    except Exception as error:  # noqa: BLE001
        core_error = f"import sb3_collapse.train, sb3_collapse.report: {type(error).__name__}: {error}"
    verdict("CORE", core_error, "import sb3_collapse.train, sb3_collapse.report (SB3, gymnasium, torch)")
    try:
        import shimmy  # noqa: F401
        from dm_control import suite  # noqa: F401

        dmc_error = None
    except Exception as error:  # noqa: BLE001
        dmc_error = f"import shimmy; from dm_control import suite: {type(error).__name__}: {error}"
    log(f"import shimmy; from dm_control import suite (MUJOCO_GL={os.environ.get('MUJOCO_GL')}): "
        f"{'FAILED: ' + dmc_error if dmc_error else 'ok'}")  # fmt: skip

    render_error = run_python(RENDER, timeout=60)
    if render_error and os.path.exists(NVIDIA_EGL_VENDOR) and "__EGL_VENDOR_LIBRARY_FILENAMES" not in os.environ:
        log(f"render: {render_error}; again with __EGL_VENDOR_LIBRARY_FILENAMES={NVIDIA_EGL_VENDOR}")
        env = dict(os.environ, __EGL_VENDOR_LIBRARY_FILENAMES=NVIDIA_EGL_VENDOR)
        if run_python(RENDER, timeout=60, env=env) is None:
            render_error = None
            status["RENDER_EXPORT"] = f"__EGL_VENDOR_LIBRARY_FILENAMES={NVIDIA_EGL_VENDOR}"
    if render_error:
        vendors = [path for folder in EGL_VENDOR_FOLDERS for path in glob.glob(os.path.join(folder, "*.json"))]
        log(
            f"  EGL vendor files: {', '.join(vendors) or 'none'}; NVIDIA_DRIVER_CAPABILITIES="
            f"{os.environ.get('NVIDIA_DRIVER_CAPABILITIES', '(unset)')} (rendering needs 'graphics' or 'all'); "
            f"__EGL_VENDOR_LIBRARY_FILENAMES={os.environ.get('__EGL_VENDOR_LIBRARY_FILENAMES', '(unset)')}"
        )
    verdict("RENDER", dmc_error or render_error, f"one DeepMind Control frame, MUJOCO_GL={os.environ.get('MUJOCO_GL')}")

    compiler = shutil.which(os.environ.get("CC", "cc")) or shutil.which("gcc")
    headers = os.path.join(sysconfig.get_paths()["include"], "Python.h")
    log(f"C compiler: {compiler or 'none'}; Python headers: {headers if os.path.exists(headers) else 'none'}")
    compile_error = device_error or run_python(COMPILE, args.device, timeout=120)
    triton = " (Triton)" if "cuda" in args.device else ""
    verdict("COMPILE", compile_error, f"torch.compile on {args.device}{triton}")
    out.close()
    with open(args.status, "w") as file:
        file.writelines(f"{key}={shlex.quote(value)}\n" for key, value in status.items())
    return 0


if __name__ == "__main__":
    sys.exit(main())
