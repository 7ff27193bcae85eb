"""Process-wide settings of torch's CUDA backends for training (TensorFloat-32, reproducibility), set by the train CLI
and every sweep trial, never by building a model. What is exact where: docs/checkpoints.md."""

from __future__ import annotations

__all__ = ["BackendSettings", "configure_backends", "current_backends"]

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
    _set_tf32(tf32)
    if deterministic:
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", CUBLAS_WORKSPACE_CONFIG)
    th.backends.cudnn.benchmark = not deterministic
    th.backends.cudnn.deterministic = deterministic
    if deterministic or th.are_deterministic_algorithms_enabled():
        # Only when it changes something: the call imports torch's compiler (torch._inductor), seconds per process.
        th.use_deterministic_algorithms(deterministic, warn_only=True)
    return BackendSettings(tf32=tf32, deterministic=deterministic)


def _set_tf32(tf32: bool) -> None:
    """Set TensorFloat-32 of float32 CUDA matmuls and cuDNN convolutions in torch's legacy flags and in its new ones
    (``fp32_precision``, torch >= 2.9), so that both agree and both can be read.

    Torch refuses to read a legacy flag that disagrees with the new API ("a mix of the legacy and new APIs",
    ``RuntimeError``): after ``cuda.matmul.fp32_precision = "tf32"`` alone, ``cuda.matmul.allow_tf32`` and
    ``torch.get_float32_matmul_precision()`` raise; after ``cudnn.conv.fp32_precision = "ieee"`` alone,
    ``cudnn.allow_tf32`` raises (convolutions and RNNs then differ). Torch's compiler reads both kinds: on torch 2.13,
    inductor reads ``cudnn.allow_tf32`` in its Triton convolution templates and ``get_float32_matmul_precision()`` in
    its autotuning cache keys, dynamo's graph-region tracker the legacy cuBLAS flag. The legacy setters also write the
    new flags; the new setters after them leave both in agreement (convolutions at ``"ieee"``, not inherited, when
    off). The CPU's flags (``torch.backends.mkldnn``) are left as they are.

    :param tf32: TensorFloat-32 for float32 matmuls and cuDNN convolutions, else IEEE float32
    """
    th.backends.cuda.matmul.allow_tf32 = tf32  # first: the legacy setters rewrite the new flags
    th.backends.cudnn.allow_tf32 = tf32
    if hasattr(th.backends.cuda.matmul, "fp32_precision"):  # torch >= 2.9
        precision = "tf32" if tf32 else "ieee"
        th.backends.cuda.matmul.fp32_precision = precision
        th.backends.cudnn.conv.fp32_precision = precision


def current_backends() -> BackendSettings:
    """:return: the settings torch's flags hold now (what :func:`configure_backends` set, or torch's defaults)"""
    if hasattr(th.backends.cuda.matmul, "fp32_precision"):
        tf32 = th.backends.cuda.matmul.fp32_precision == "tf32"
    else:
        tf32 = bool(th.backends.cuda.matmul.allow_tf32)
    return BackendSettings(tf32=tf32, deterministic=th.are_deterministic_algorithms_enabled())
