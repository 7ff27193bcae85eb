"""
The first step of ``benchmarks/gpu.sh``: what this machine has, in seconds, before any benchmark runs.

Appends to ``--out`` (``machine.txt``), one line as each check ends: the versions of Python and of the packages that
matter (torch and its CUDA, SB3, gymnasium, dm_control, mujoco, shimmy, triton), then four verdicts, each one judged
in its own subprocess under its own time limit (a crash, a hang or a wrong result there is a verdict with its reason,
not the end of the preflight):

- ``DEVICE``: torch sees the device (``--device``);
- ``CORE``: ``import sb3_collapse.train, sb3_collapse.report`` (SB3, gymnasium, torch);
- ``RENDER``: one walker-walk frame rendered through the package (``MUJOCO_GL``, EGL on a GPU), then, in the same
  process, a small ``DrQv2`` built on that environment and trained for a few updates on the device: building its
  Adam optimizers imports ``torch._dynamo`` and triton after the frame, which is what every training step of gpu.sh
  does (a crash there, such as a SIGSEGV of triton loaded after Mesa's EGL, fails this verdict and names the stage).
  When it fails and the NVIDIA driver's EGL vendor file exists, it is tried again with
  ``__EGL_VENDOR_LIBRARY_FILENAMES`` naming it: a pass then sets ``RENDER_EXPORT`` for the steps;
- ``COMPILE``: after ``sb3_collapse.backends.configure_backends()`` (TF32 on, as the train command sets it), a
  ``torch.compile`` of a ``torch.nn.Linear`` forward and backward on the device (Triton on CUDA), checked against the
  eager values.

Each verdict is appended to ``--status`` as soon as it is known (shell assignments ``NAME_OK=0|1``, ``NAME_WHY=...``
that ``gpu.sh`` sources), so a preflight killed later leaves the verdicts it had; gpu.sh gives the others a default.
The three subprocess checks run at once.

    python benchmarks/gpu_preflight.py --device cuda --out machine.txt --status /tmp/preflight.env
"""

from __future__ import annotations

import argparse
import glob
import importlib.metadata
import importlib.util
import os
import platform
import shlex
import shutil
import signal
import subprocess
import sys
import sysconfig
import time
from concurrent.futures import ThreadPoolExecutor, as_completed

CORE = "import sb3_collapse.train, sb3_collapse.report"
"""The package's entry points (SB3, gymnasium, torch): every step needs them."""

RENDER_AND_TRAIN = """
import sys
from sb3_collapse import DrQv2, make_dmc_env
env = make_dmc_env("walker-walk", seed=0, size=32)
obs, _ = env.reset(seed=0)
assert obs.shape == (9, 32, 32) and obs.std() > 0, "a blank frame"
try:
    from OpenGL import GL
    with env.physics.contexts.gl.make_current() as context:
        renderer = context.call(GL.glGetString, GL.GL_RENDERER).decode()
except Exception as error:
    renderer = f"not read ({type(error).__name__})"
print(f"STAGE rendered one walker-walk frame (OpenGL renderer: {renderer})", flush=True)
model = DrQv2("CnnPolicy", env, buffer_size=100, learning_starts=8, batch_size=8, seed=0, device=sys.argv[1],
              policy_kwargs=dict(hidden_dim=32, feature_dim=16, encoder_kwargs=dict(channels=8)))
print("STAGE built a DrQv2 (Adam: torch._dynamo, triton)", flush=True)
model.learn(total_timesteps=12)
assert model._n_updates > 0, "no update ran"
print(f"STAGE trained {model._n_updates} updates", flush=True)
"""
"""A rendered frame, then a DrQv2 built and trained in the same process: what the training steps of gpu.sh do."""

COMPILE = """
import sys, torch
from sb3_collapse.backends import configure_backends
configure_backends()
device = sys.argv[1]
torch.manual_seed(0)
layer = torch.nn.Linear(64, 32, device=device)
x = torch.randn(16, 64, device=device)
def loss(x):
    return layer(x).relu().square().mean()
expected = loss(x)
expected.backward()
eager_grad = layer.weight.grad.clone()
layer.weight.grad = None
got = torch.compile(loss)(x)
got.backward()
assert torch.allclose(got, expected, rtol=1e-2, atol=1e-4), (got.item(), expected.item())
assert torch.allclose(layer.weight.grad, eager_grad, rtol=1e-2, atol=1e-4), "the compiled backward differs"
"""
"""``torch.compile`` of a Linear forward and backward after ``configure_backends()`` (Triton kernels on CUDA)."""

NVIDIA_EGL_VENDOR = "/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json"
"""The NVIDIA driver's EGL vendor file where the driver is mounted (``/usr/local/nvidia``)."""

EGL_VENDOR_FOLDERS = ("/usr/share/glvnd/egl_vendor.d", "/etc/glvnd/egl_vendor.d", os.path.dirname(NVIDIA_EGL_VENDOR))


def version(distribution: str, module: str | None = None) -> str:
    """The installed version of ``distribution``, or of ``module``'s ``__version__`` when it has no metadata (a
    carried, unpacked package), or why there is none (found without importing it: an import can crash)."""
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        pass
    spec = importlib.util.find_spec(module or distribution.replace("-", "_"))
    return f"present, no version ({spec.origin})" if spec else "MISSING"


def run_python(
    code: str, *args: str, timeout: float, env: dict | None = None, stages: list[str] | None = None
) -> str | None:
    """Run ``code`` in a fresh interpreter: ``None`` when it succeeded, else why not, in one line: the last
    ``STAGE`` line it printed (how far it got), then how it ended (a signal, no answer in ``timeout`` seconds), then
    the end of its error output (for a crash, faulthandler's error and the innermost frame of its own code).
    ``stages``, when given, receives the text of its ``STAGE`` lines."""
    with subprocess.Popen(
        [sys.executable, "-X", "faulthandler", "-c", code, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True, env=env,
    ) as process:  # fmt: skip
        try:
            stdout, stderr = process.communicate(timeout=timeout)
            ended = None
        except subprocess.TimeoutExpired:
            process.kill()
            stdout, stderr = process.communicate()
            ended = f"no answer in {timeout:.0f} s (killed)"
    printed = [line[6:] for line in stdout.splitlines() if line.startswith("STAGE ")]
    if stages is not None:
        stages.extend(printed)
    if ended is None and process.returncode == 0:
        return None
    if ended is None and process.returncode < 0:
        ended = f"killed by {signal.Signals(-process.returncode).name}"
    errors = [line.strip() for line in stderr.strip().splitlines() if line.strip()]
    fatal = [i for i, line in enumerate(errors) if line.startswith("Fatal Python error")]
    if fatal:  # faulthandler: the error, then the innermost frame (printed first) not in importlib
        frames = [line for line in errors[fatal[-1] :] if line.startswith("File ") and "<frozen" not in line]
        errors = [errors[fatal[-1]], *frames[:1]]
    why = [f"after '{printed[-1]}'" if printed else "before its first stage", ended or ""] + errors[-2:]
    return "; ".join(part for part in why if part) or f"exit status {process.returncode}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda", help="the device the steps use: cuda (the GPU) or cpu")
    parser.add_argument("--out", required=True, help="the file to append the findings to (machine.txt)")
    parser.add_argument("--status", required=True, help="the shell assignments for gpu.sh, appended as they come")
    parser.add_argument("--timeout", type=float, default=120, help="seconds each subprocess check may take")
    parser.add_argument(
        "--render-code", default=RENDER_AND_TRAIN, help="the Python code of the RENDER check (default: a rendered "
        "frame, then a DrQv2 trained in the same process; its argument is --device)",
    )  # fmt: skip
    parser.add_argument(
        "--checks", nargs="+", choices=["CORE", "RENDER", "COMPILE"], default=["CORE", "RENDER", "COMPILE"],
        help="the subprocess checks to run (default: all three)",
    )  # fmt: skip
    args = parser.parse_args()
    start = time.perf_counter()
    out = open(args.out, "a")  # noqa: SIM115 (appended to line by line, closed at the end)
    status = open(args.status, "a")  # noqa: SIM115 (idem)

    def log(line: str) -> None:
        line = f"[{time.perf_counter() - start:5.1f} s] {line}"
        print(line, flush=True)
        out.write(line + "\n")
        out.flush()

    def verdict(name: str, error: str | None, what: str, export: str = "") -> None:
        """Log the verdict and append it to the status file at once (a later hang or kill keeps it)."""
        assignments = {f"{name}_OK": "0" if error else "1", f"{name}_WHY": error or ""}
        if export:
            assignments[f"{name}_EXPORT"] = export
        status.writelines(f"{key}={shlex.quote(value)}\n" for key, value in assignments.items())
        status.flush()
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
    compiler = shutil.which(os.environ.get("CC", "cc")) or shutil.which("gcc")
    headers = os.path.join(sysconfig.get_paths()["include"], "Python.h")
    log(f"C compiler: {compiler or 'none'}; Python headers: {headers if os.path.exists(headers) else 'none'}")

    def render() -> tuple[str | None, str]:
        stages: list[str] = []
        error = run_python(args.render_code, args.device, timeout=args.timeout, stages=stages)
        log(f"render and train: {', '.join(stages) or 'no stage reached'}")
        vendor = os.environ.get("__EGL_VENDOR_LIBRARY_FILENAMES")
        # Software rendering (Mesa) on a GPU machine: the frames/s would be the CPU's. A hang is not retried.
        software = "cuda" in args.device and any("llvmpipe" in stage or "softpipe" in stage for stage in stages)
        retry_vendor = os.path.exists(NVIDIA_EGL_VENDOR) and vendor != NVIDIA_EGL_VENDOR
        if (software or (error and "no answer in" not in error)) and retry_vendor:
            log(f"  again with __EGL_VENDOR_LIBRARY_FILENAMES={NVIDIA_EGL_VENDOR}")
            env = dict(os.environ, __EGL_VENDOR_LIBRARY_FILENAMES=NVIDIA_EGL_VENDOR)
            stages = []
            retry = run_python(args.render_code, args.device, timeout=args.timeout, env=env, stages=stages)
            log(f"render and train with the NVIDIA vendor file: {', '.join(stages) or 'no stage reached'}")
            if retry is None:
                return None, f"__EGL_VENDOR_LIBRARY_FILENAMES={NVIDIA_EGL_VENDOR}"
            if error:
                error = f"{error}; with the NVIDIA vendor file: {retry}"
        if software and not error:
            log("  rendering on the CPU (Mesa): the steps' frames/s include software rendering")
        if error:
            vendors = [path for folder in EGL_VENDOR_FOLDERS for path in glob.glob(os.path.join(folder, "*.json"))]
            log(f"  EGL vendor files: {', '.join(vendors) or 'none'}; NVIDIA_DRIVER_CAPABILITIES="
                f"{os.environ.get('NVIDIA_DRIVER_CAPABILITIES', '(unset)')} (rendering needs 'graphics' or 'all'); "
                f"__EGL_VENDOR_LIBRARY_FILENAMES={vendor or '(unset)'}")  # fmt: skip
        return error, ""

    gl = os.environ.get("MUJOCO_GL")
    checks = {
        "CORE": (lambda: (run_python(CORE, timeout=args.timeout), ""), CORE),
        "RENDER": (render, f"a walker-walk frame (MUJOCO_GL={gl}), then a DrQv2 trained on {args.device}"),
        "COMPILE": (
            lambda: (device_error or run_python(COMPILE, args.device, timeout=args.timeout), ""),
            (
                f"torch.compile of a Linear forward and backward on {args.device}{' (Triton)' if cuda else ''}, "
                "after configure_backends()"
            ),
        ),
    }
    with ThreadPoolExecutor(len(args.checks)) as pool:
        futures = {pool.submit(checks[name][0]): name for name in args.checks}
        for future in as_completed(futures):
            name = futures[future]
            error, export = future.result()
            verdict(name, error, checks[name][1], export)
    log(f"preflight done in {time.perf_counter() - start:.0f} s")
    out.close()
    status.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
