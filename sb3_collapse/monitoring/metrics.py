"""
The paper's collapse metrics (Section 5.1) of a ``(n, *unit_shape)`` batch of one layer's activations, as Python
floats; ``H`` the ``n x d`` matrix of the flattened activations, a unit a feature or a channel (docs/monitoring.md).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch as th

DORMANT_TAU = 0.025  # ReDo's threshold of the dormant ratio (Sokar et al., 2023)
SRANK_DELTA = 0.01  # Kumar et al.'s (2021) threshold of the effective rank
SATURATION_LIMIT = 0.99  # an action component is saturated when its absolute value exceeds this


def flatten_batch(activations: th.Tensor) -> th.Tensor:
    """The ``n x d`` matrix ``H`` of ``(n, *unit_shape)`` activations, float64."""
    _check_batch(activations)
    return activations.reshape(activations.shape[0], -1).double()


def _check_batch(activations: th.Tensor) -> None:
    if activations.dim() < 2:
        raise ValueError(
            f"Expected activations of shape (n, ...) with a feature dimension, got {tuple(activations.shape)}."
        )


def _singular_values_from(h: th.Tensor, gram: th.Tensor | None) -> th.Tensor:
    """Those of ``h``; for ``d > n`` the square roots of the eigenvalues of ``h h^T`` (exact to about ``1e-8 s_1``)."""
    n_inputs, n_units = h.shape
    if n_units <= n_inputs:
        return th.linalg.svdvals(h)
    gram = h @ h.T if gram is None else gram
    return th.linalg.eigvalsh(gram).flip(0).clamp(min=0.0).sqrt()


def singular_values(activations: th.Tensor) -> th.Tensor:
    """
    :param activations: ``(n, *unit_shape)`` activations
    :return: the ``min(n, d)`` singular values of ``H``, in decreasing order, float64
    """
    return _singular_values_from(flatten_batch(activations), None)


def _numerical_rank(s: th.Tensor) -> float:
    squares = float((s**2).sum())
    return float(s.sum()) ** 2 / squares if squares > 0 else 0.0


def numerical_rank(activations: th.Tensor) -> float:
    """
    The paper's numerical rank (Section 5.1): "we compute the numerical rank (Zhou et al., 2022) of the matrix of MLP
    activations H": ``(sum_i s_i)^2 / sum_i s_i^2``, ``s_i`` the singular values of ``H`` (0 if all zero).

    :param activations: ``(n, *unit_shape)`` activations
    :return: the numerical rank, in ``[0, min(n, d)]``
    """
    return _numerical_rank(singular_values(activations))


def _effective_rank(s: th.Tensor, delta: float) -> float:
    total = float(s.sum())
    if total <= 0:
        return 0.0
    # The smallest k whose partial sum reaches 1 - delta: one more than the partial sums below it, on s's device.
    return float(int((th.cumsum(s, 0) / total < 1.0 - delta).sum()) + 1)


def effective_rank(activations: th.Tensor, delta: float = SRANK_DELTA) -> float:
    """
    Effective rank ``srank_delta`` (Kumar et al., 2021) of ``H``: the smallest ``k`` with
    ``(s_1 + ... + s_k) / (s_1 + ... + s_min(n,d)) >= 1 - delta``; 0 for an all-zero matrix.

    :param activations: ``(n, *unit_shape)`` activations
    :param delta: threshold, in ``[0, 1)``
    :return: the effective rank, an integer in ``[0, min(n, d)]`` (as a float)
    """
    if not 0.0 <= delta < 1.0:
        raise ValueError(f"delta must be in [0, 1), got {delta}.")
    return _effective_rank(singular_values(activations), delta)


def _input_correlation(h: th.Tensor, gram: th.Tensor) -> float:
    n_units = h.shape[1]
    row_sums, row_max_abs = h.sum(1), h.abs().amax(1)
    centered = gram - th.outer(row_sums, row_sums) / n_units  # sum_k (h_ik - m_i)(h_jk - m_j)
    variance = centered.diagonal()
    # All-zero rows are left out, and constant ones (zero variance up to rounding: Pearson's correlation undefined).
    valid = (row_max_abs > 0) & (variance > 1e-12 * (row_max_abs**2) * n_units)
    m = int(valid.sum())
    if m < 2:
        return math.nan
    std = variance[valid].sqrt()
    corr = centered[valid][:, valid] / th.outer(std, std)
    return float((corr.sum() - corr.diagonal().sum()) / (m * (m - 1)))


def input_correlation(activations: th.Tensor) -> float:
    """
    Mean Pearson correlation between the activation vectors of two different inputs (rows of ``H``), over the
    inputs whose vector is neither all zero nor constant: the pairs-of-inputs reading of the paper's correlation
    (Figures 4, 8, 9 show :func:`unit_correlation`; docs/figures.md#figures-4-8-9-collapse-metrics-of-three-agents).

    :param activations: ``(n, *unit_shape)`` activations
    :return: the mean correlation, in ``[-1, 1]``; NaN when fewer than two inputs qualify
    """
    h = flatten_batch(activations)
    return _input_correlation(h, h @ h.T)


def unit_correlation(activations: th.Tensor, absolute: bool = False) -> float:
    """
    The paper's correlation (Section 5.1): "the average correlation among every two non-zero activations", the
    activations being the units: the mean over ``a != b`` of Pearson's correlation over the inputs (and positions)
    of units ``a`` and ``b`` (:func:`unit_activations`), dead and constant units (std at most ``1e-6`` times the largest
    absolute value) left out; float64 on the activations' device.

    :param activations: ``(n, d)`` dense or ``(n, C, height, width)`` convolutional activations
    :param absolute: average the absolute values of the correlations
    :return: the mean correlation (``[-1/(m-1), 1]`` for ``m`` varying units), NaN when fewer than two units vary
    """
    units = unit_activations(activations).double()  # (units, N): N = n x positions
    largest = th.maximum(units.amax(1), -units.amin(1))
    centered = units - units.mean(1, keepdim=True)
    del units  # at most two (units, N) float64 copies alive at once
    norms = th.linalg.vector_norm(centered, dim=1)  # sqrt(N) x the standard deviation over the inputs
    varies = norms > 1e-6 * largest * math.sqrt(centered.shape[1])
    m = int(varies.sum())
    if m < 2:
        return math.nan
    z = centered[varies] if m < len(varies) else centered
    z /= norms[varies, None]  # in place: z is this function's own tensor
    corr = z @ z.T  # (m, m)
    if absolute:
        corr = corr.abs()
    return float((corr.sum() - corr.diagonal().sum()) / (m * (m - 1)))


def unit_activations(activations: th.Tensor) -> th.Tensor:
    """``(units, n x positions)`` of ``(n, d)`` or ``(n, C, height, width)`` activations: a unit's values a row."""
    _check_batch(activations)
    return activations.transpose(0, 1).reshape(activations.shape[1], -1)


def zero_fraction(activations: th.Tensor) -> float:
    """
    :param activations: ``(n, *unit_shape)`` activations
    :return: the fraction of the entries that are zero (not units: the paper's dead neurons are :func:`dead_units`)
    """
    return float((activations == 0).double().mean())


def dead_fraction(activations: th.Tensor) -> float:
    """
    :param activations: ``(n, d)`` or ``(n, C, height, width)`` activations
    :return: the fraction of the units that are dead (:func:`dead_units`), in ``[0, 1]``
    """
    return float((unit_activations(activations) == 0).all(1).double().mean())


def unit_count(activations: th.Tensor) -> int:
    """
    :param activations: ``(n, d)`` dense or ``(n, C, height, width)`` convolutional activations
    :return: the layer's width in units: ``d`` features, or ``C`` channels
    """
    return int(unit_activations(activations).shape[0])


def dead_units(activations: th.Tensor) -> int:
    """
    The paper's zeros (Section 5.1): "the number of zero activations, also called dead neurons (Lu et al., 2019)":
    the units zero for every input of the batch (a channel: at every position too).

    :param activations: ``(n, d)`` or ``(n, C, height, width)`` activations
    :return: a count in ``[0, units]`` (:func:`unit_count`)
    """
    return int((unit_activations(activations) == 0).all(1).sum())


def dormant_ratio(activations: th.Tensor, tau: float = DORMANT_TAU) -> float:
    """
    Dormant ratio of ReDo (Sokar et al., 2023): the fraction of units ``u`` with ``a_u / (mean_v a_v + 1e-9) <= tau``,
    ``a_u`` the mean absolute activation of ``u`` over the batch (and a channel's positions).

    :param activations: ``(n, d)`` or ``(n, C, height, width)`` activations
    :param tau: threshold, relative to the layer's mean
    :return: a fraction in ``[0, 1]``
    """
    return float(dormant_units(activations, tau).double().mean())


def dormant_units(activations: th.Tensor, tau: float = DORMANT_TAU) -> th.Tensor:
    """
    :param activations: ``(n, d)`` or ``(n, C, height, width)`` activations
    :param tau: threshold, relative to the layer's mean
    :return: ``(units,)`` boolean mask of the dormant units (:func:`dormant_ratio`), those that ReDo recycles
    """
    if tau < 0:
        raise ValueError(f"tau must be >= 0, got {tau}.")
    score = unit_activations(activations).double().abs().mean(1)
    return score / (score.mean() + 1e-9) <= tau


def action_spread(actions: th.Tensor) -> float:
    """
    The spread of the deterministic actions over the batch: the population standard deviation of each action
    dimension, averaged over the dimensions (0: every input gets the same action, action collapse).

    :param actions: ``(n, action_dim)`` actions in ``[-1, 1]``
    :return: the mean standard deviation
    """
    if actions.dim() != 2:
        raise ValueError(f"Expected actions of shape (n, action_dim), got {tuple(actions.shape)}.")
    return float(actions.double().std(0, correction=0).mean())


def saturated_fraction(actions: th.Tensor, limit: float = SATURATION_LIMIT) -> float:
    """
    :param actions: ``(n, action_dim)`` actions in ``[-1, 1]``
    :param limit: saturation threshold
    :return: the fraction of the action components with ``|a| > limit``
    """
    return float((actions.abs() > limit).double().mean())


def gradient_norm(gradients: Iterable[th.Tensor | None]) -> float:
    """
    The paper's gradient norm (Section 5.1: "we check the gradient norm of MLP layers"): the L2 norm of the
    concatenated gradients of a layer's parameters (``None`` counts as zero).

    :param gradients: the ``.grad`` of a layer's parameters
    :return: the norm
    """
    squares = [th.linalg.vector_norm(gradient.detach().double()) ** 2 for gradient in gradients if gradient is not None]
    return float(th.stack(squares).sum().sqrt()) if squares else 0.0


def layer_metrics(activations: th.Tensor, tau: float = DORMANT_TAU, delta: float = SRANK_DELTA) -> dict[str, float]:
    """
    Every activation metric of one layer (float64; the ranks and the input correlation from one Gram matrix).

    :param activations: ``(n, *unit_shape)`` activations
    :param tau: threshold of :func:`dormant_ratio`
    :param delta: threshold of :func:`effective_rank`
    :return: ``numerical_rank``, ``srank``, ``correlation`` (:func:`unit_correlation`), ``input_correlation``,
        ``zero_fraction``, ``dead_fraction``, ``dead_units`` (as a float), ``dormant_ratio``
    """
    h = flatten_batch(activations)
    gram = h @ h.T
    s = _singular_values_from(h, gram)
    return {
        "numerical_rank": _numerical_rank(s),
        "srank": _effective_rank(s, delta),
        "correlation": unit_correlation(activations),
        "input_correlation": _input_correlation(h, gram),
        "zero_fraction": zero_fraction(activations),
        "dead_fraction": dead_fraction(activations),
        "dead_units": float(dead_units(activations)),
        "dormant_ratio": dormant_ratio(activations, tau),
    }
