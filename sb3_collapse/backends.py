"""Process-wide settings of torch's CUDA backends for training (TensorFloat-32, reproducibility), set by the train CLI
and every sweep trial, never by building a model. What is exact where: docs/checkpoints.md."""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch as th

CUBLAS_WORKSPACE_CONFIG = ":4096:8"  # deterministic cuBLAS (CUDA's documentation: "Results reproducibility")


@dataclass(frozen=True)
class BackendSettings:
    """Torch's CUDA flags: ``tf32``, float32 matmuls and convolutions may use TensorFloat-32 (Ampere and later);
    ``deterministic``, kernels are chosen for reproducibility rather than speed."""

    tf32: bool
    deterministic: bool


def configure_backends(tf32: bool = True, deterministic: bool = False) -> BackendSettings:
    """Set torch's process-wide CUDA flags (no GPU needed; nothing changes on the CPU).

    :param tf32: TensorFloat-32 for float32 matmuls and cuDNN convolutions, else IEEE float32
    :param deterministic: torch's deterministic algorithms (``warn_only``), cuDNN's deterministic kernels without its
        autotuner, ``CUBLAS_WORKSPACE_CONFIG`` (unless set; before any CUDA work); ``False``: cuDNN's autotuner on
    :return: the settings applied (``TypeError`` naming a parameter that is not a bool)
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
