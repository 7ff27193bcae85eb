"""
Process-wide settings of torch's CUDA backends for a training run: TensorFloat-32 and reproducibility.

``python -m sb3_collapse.train`` (and every sweep trial) calls :func:`configure_backends` before it builds the model,
with the run's ``tf32`` and ``deterministic`` settings, which the run's settings file records. These flags belong to
the process: building a ``DrQv2`` changes none of them (with ``cudnn_benchmark=True`` it turns cuDNN's autotuner on
for a CUDA model, unless torch's deterministic algorithms are on). Library users call :func:`configure_backends`
themselves, or set torch's flags directly.

What is exact where (see docs/checkpoints.md): on the CPU, a seeded run is bit-for-bit repeatable on one machine with
one number of threads. On a GPU, only with ``deterministic=True`` (cuDNN's autotuner off, its deterministic
convolution algorithms, deterministic cuBLAS workspaces, and torch's deterministic implementations where it has
them; ``warn_only``, so an operation without one warns instead of stopping a run), and only on the same GPU model,
driver and library versions. With the defaults (autotuner on), two GPU runs of one seed differ from the first
updates on, in the last bits at first; a resumed GPU run is not bit-identical to an uninterrupted one.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch as th

CUBLAS_WORKSPACE_CONFIG = ":4096:8"
"""cuBLAS's workspace setting that makes its results deterministic (CUDA's documentation: "Results reproducibility")."""


@dataclass(frozen=True)
class BackendSettings:
    """
    :param tf32: whether float32 matmuls and convolutions on CUDA may use TensorFloat-32 (10-bit mantissa inputs,
        float32 accumulation) on GPUs that have it (Ampere and later)
    :param deterministic: whether CUDA kernels are chosen for reproducibility rather than speed
    """

    tf32: bool
    deterministic: bool


def configure_backends(tf32: bool = True, deterministic: bool = False) -> BackendSettings:
    """
    Set torch's process-wide CUDA flags for training. They are plain flags: setting them needs no GPU, and they
    change nothing on the CPU.

    - ``tf32``: TensorFloat-32 for float32 matmuls and cuDNN convolutions (``fp32_precision = "tf32"``), or IEEE
      float32 for both (``"ieee"``).
    - ``deterministic``: ``torch.use_deterministic_algorithms(True, warn_only=True)``, cuDNN's deterministic
      algorithms without its autotuner, and ``CUBLAS_WORKSPACE_CONFIG`` (unless already set; it must be set before
      the first cuBLAS call of the process, so it holds only when this runs before any CUDA work). ``False`` turns
      torch's deterministic algorithms off again and cuDNN's autotuner on (``cudnn.benchmark``: DrQ-v2's fixed input
      shapes, the kernels picked by timing them, as DrQ-v2's reference does).

    :param tf32: allow TensorFloat-32 on CUDA
    :param deterministic: ask for reproducible CUDA kernels
    :return: the settings applied
    :raises TypeError: naming the parameter, for a value that is not a bool
    """
    for name, value in (("tf32", tf32), ("deterministic", deterministic)):
        if not isinstance(value, bool):
            raise TypeError(f"{name} must be True or False, got {value!r}.")
    precision = "tf32" if tf32 else "ieee"
    if hasattr(th.backends.cuda.matmul, "fp32_precision"):  # torch >= 2.9
        th.backends.cuda.matmul.fp32_precision = precision
        th.backends.cudnn.conv.fp32_precision = precision
    else:
        th.backends.cuda.matmul.allow_tf32 = tf32
        th.backends.cudnn.allow_tf32 = tf32
    if deterministic:
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", CUBLAS_WORKSPACE_CONFIG)
    th.backends.cudnn.benchmark = not deterministic
    th.backends.cudnn.deterministic = deterministic
    th.use_deterministic_algorithms(deterministic, warn_only=True)
    return BackendSettings(tf32=tf32, deterministic=deterministic)


def current_backends() -> BackendSettings:
    """:return: the settings torch's flags hold now (what :func:`configure_backends` set, or torch's defaults)"""
    if hasattr(th.backends.cuda.matmul, "fp32_precision"):
        tf32 = th.backends.cuda.matmul.fp32_precision == "tf32"
    else:
        tf32 = bool(th.backends.cuda.matmul.allow_tf32)
    return BackendSettings(tf32=tf32, deterministic=th.are_deterministic_algorithms_enabled())
