"""
Collapse metrics of a batch of activations (Section 5.1 of the action-collapse paper), as pure functions.

Every function takes the activations of one named layer for a batch of ``n`` inputs, a tensor of shape
``(n, *unit_shape)``, and returns a Python float. Notation:

- ``H`` is the ``n x d`` matrix of the flattened activations (one row per input, ``d = prod(unit_shape)``);
- a **unit** is a feature of a dense layer (shape ``(n, d)``), or a channel of a convolutional layer (shape
  ``(n, C, height, width)``: its activations over every input and every position), as in ReDo;
- ``s_1 >= s_2 >= ... >= s_min(n, d)`` are the singular values of ``H``, computed in float64 (for ``d > n``
  as the square roots of the eigenvalues of the ``n x n`` Gram matrix ``H H^T``, which is exact to about
  ``1e-8 s_1`` and much faster than an SVD of a wide matrix).

:func:`layer_metrics` computes every metric of a layer at once.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch as th

DORMANT_TAU = 0.025
"""ReDo's threshold of the dormant ratio (Sokar et al., 2023)."""

SRANK_DELTA = 0.01
"""Kumar et al.'s (2021) threshold of the effective rank."""

SATURATION_LIMIT = 0.99
"""An action component is saturated when its absolute value exceeds this."""


def flatten_batch(activations: th.Tensor) -> th.Tensor:
    """
    :param activations: ``(n, *unit_shape)`` activations of ``n`` inputs
    :return: the ``n x d`` matrix ``H``, float64
    :raises ValueError: for a tensor without a batch dimension
    """
    if activations.dim() < 2:
        raise ValueError(
            f"Expected activations of shape (n, ...) with a feature dimension, got {tuple(activations.shape)}."
        )
    return activations.reshape(activations.shape[0], -1).double()


def _gram(h: th.Tensor) -> th.Tensor:
    return h @ h.T


def _singular_values_from(h: th.Tensor, gram: th.Tensor | None) -> th.Tensor:
    n_inputs, n_units = h.shape
    if n_units <= n_inputs:
        return th.linalg.svdvals(h)
    gram = _gram(h) if gram is None else gram
    return th.linalg.eigvalsh(gram).flip(0).clamp(min=0.0).sqrt()


def singular_values(activations: th.Tensor) -> th.Tensor:
    """
    Singular values of ``H``, in decreasing order, float64.

    :param activations: ``(n, *unit_shape)`` activations
    :return: ``min(n, d)`` singular values
    """
    return _singular_values_from(flatten_batch(activations), None)


def _numerical_rank(s: th.Tensor) -> float:
    squares = float((s**2).sum())
    return float(s.sum()) ** 2 / squares if squares > 0 else 0.0


def numerical_rank(activations: th.Tensor) -> float:
    """
    Numerical rank (Zhou et al., 2022) of ``H``: ``(sum_i s_i)^2 / sum_i s_i^2``.

    It is ``k`` for a matrix with ``k`` equal nonzero singular values (``n`` for the ``n x n`` identity, 1 for
    a rank-1 matrix) and discounts small singular values; 0 for an all-zero matrix.

    :param activations: ``(n, *unit_shape)`` activations
    :return: the numerical rank, in ``[0, min(n, d)]``
    """
    return _numerical_rank(singular_values(activations))


def _effective_rank(s: th.Tensor, delta: float) -> float:
    total = float(s.sum())
    if total <= 0:
        return 0.0
    cumulative = th.cumsum(s, 0) / total
    # The smallest k with cumulative[k - 1] >= 1 - delta: one more than the count of partial sums below it (they
    # increase). A reduction on the singular values' own device: no tensor is made on another one.
    return float(int((cumulative < 1.0 - delta).sum()) + 1)


def effective_rank(activations: th.Tensor, delta: float = SRANK_DELTA) -> float:
    """
    Effective rank ``srank_delta`` (Kumar et al., 2021) of ``H``: the smallest ``k`` such that
    ``(s_1 + ... + s_k) / (s_1 + ... + s_min(n,d)) >= 1 - delta``; 0 for an all-zero matrix.

    :param activations: ``(n, *unit_shape)`` activations
    :param delta: threshold, in ``[0, 1)``
    :return: the effective rank, an integer in ``[0, min(n, d)]`` (as a float)
    """
    if not 0.0 <= delta < 1.0:
        raise ValueError(f"delta must be in [0, 1), got {delta}.")
    return _effective_rank(singular_values(activations), delta)


def _input_correlation(gram: th.Tensor, row_sums: th.Tensor, row_max_abs: th.Tensor, n_units: int) -> float:
    # Centered Gram matrix: sum_k (h_ik - m_i)(h_jk - m_j) = (H H^T)_ij - r_i r_j / n_units, with r the row sums.
    centered = gram - th.outer(row_sums, row_sums) / n_units
    variance = centered.diagonal()
    # Inputs with an all-zero vector are left out (the definition); so are those with a constant vector, whose
    # Pearson correlation is undefined (zero variance, up to rounding).
    scale = (row_max_abs**2) * n_units
    valid = (row_max_abs > 0) & (variance > 1e-12 * scale)
    m = int(valid.sum())
    if m < 2:
        return math.nan
    std = variance[valid].sqrt()
    corr = centered[valid][:, valid] / th.outer(std, std)
    return float((corr.sum() - corr.diagonal().sum()) / (m * (m - 1)))


def input_correlation(activations: th.Tensor) -> float:
    """
    Mean Pearson correlation between the activation vectors of two different inputs:
    ``mean over i != j of corr(H_i, H_j)``, where ``corr`` is Pearson's correlation of the ``d`` entries of the
    two rows, over the inputs whose activation vector is not all zero (and not constant, where Pearson's
    correlation is undefined). 1.0 means that every input maps to the same point (up to an affine map).

    This is the pairs-of-inputs reading of the paper's correlation; its value follows the units' mean profile
    (units with large biases make every two inputs alike, however well the layer separates them). Figures 4, 8,
    9 show :func:`unit_correlation`, the reading of the paper's words.

    :param activations: ``(n, *unit_shape)`` activations
    :return: the mean correlation, in ``[-1, 1]``; NaN when fewer than two inputs qualify
    """
    h = flatten_batch(activations)
    return _input_correlation(_gram(h), h.sum(1), h.abs().amax(1), h.shape[1])


CONSTANT_UNIT_RTOL = 1e-6
"""A unit whose standard deviation over the inputs is at most this times its largest absolute value is constant."""


def unit_correlation(activations: th.Tensor, absolute: bool = False) -> float:
    """
    The paper's correlation (Section 5.1): "the average correlation among every two non-zero activations", the
    activations being the units: ``mean over a != b of corr(u_a, u_b)``, Pearson's correlation over the inputs of
    the vectors ``u_a`` of the units that vary (a column of ``H``; a channel of a conv layer, over the inputs and
    positions, as :func:`unit_activations`). Dead units and constant units (std at most
    :data:`CONSTANT_UNIT_RTOL` times the largest absolute value) are left out. Computed in float64 on the
    activations' device. The reading: docs/figures.md#figures-4-8-9-collapse-metrics-of-three-agents.

    :param activations: ``(n, d)`` dense or ``(n, C, height, width)`` convolutional activations
    :param absolute: average the absolute values of the correlations
    :return: the mean correlation, in ``[-1 / (m - 1), 1]`` for ``m`` varying units (in ``[0, 1]`` with
        ``absolute``); NaN when fewer than two units vary over the inputs
    """
    units = unit_activations(activations).double()  # (units, N): N = n x positions
    largest = th.maximum(units.amax(1), -units.amin(1))
    centered = units - units.mean(1, keepdim=True)
    del units  # at most two (units, N) float64 copies alive at once
    norms = th.linalg.vector_norm(centered, dim=1)  # sqrt(N) x the standard deviation over the inputs
    varies = norms > CONSTANT_UNIT_RTOL * largest * math.sqrt(centered.shape[1])
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
    """
    :param activations: ``(n, d)`` dense or ``(n, C, height, width)`` convolutional activations
    :return: ``(units, n x positions)``: every value of each unit (feature, or channel) in one row
    """
    if activations.dim() < 2:
        raise ValueError(
            f"Expected activations of shape (n, ...) with a feature dimension, got {tuple(activations.shape)}."
        )
    units = activations.shape[1]
    return activations.transpose(0, 1).reshape(units, -1)


def zero_fraction(activations: th.Tensor) -> float:
    """
    Fraction of the entries of ``H`` that are exactly zero (entry level: a unit that is zero for some inputs
    counts for those; the paper's "number of zero activations, also called dead neurons" is :func:`dead_units`).

    :param activations: ``(n, *unit_shape)`` activations
    :return: a fraction in ``[0, 1]``
    """
    return float((activations == 0).double().mean())


def dead_fraction(activations: th.Tensor) -> float:
    """
    Fraction of the units that are zero for every input of the batch (dead ReLU units; a channel of a
    convolutional layer is dead when it is zero at every position too).

    :param activations: ``(n, d)`` or ``(n, C, height, width)`` activations
    :return: a fraction in ``[0, 1]``
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
    The number of dead units: units that are zero for every input of the batch (a channel of a convolutional
    layer counts when it is zero at every position too). The paper's "zeros" (Section 5.1): "the number of zero
    activations, also called dead neurons (Lu et al., 2019)". Unlike :func:`zero_fraction` (entries that are
    zero), a unit that is zero for some inputs only does not count.

    :param activations: ``(n, d)`` or ``(n, C, height, width)`` activations
    :return: a count in ``[0, units]`` (:func:`unit_count`)
    """
    return int((unit_activations(activations) == 0).all(1).sum())


def dormant_ratio(activations: th.Tensor, tau: float = DORMANT_TAU) -> float:
    """
    Dormant ratio of ReDo (Sokar et al., 2023): with ``a_u`` the mean absolute activation of unit ``u`` over
    the batch (and the positions of a channel), the fraction of units with ``a_u / (mean_v a_v + 1e-9) <= tau``
    (every unit is dormant in an all-zero layer).

    :param activations: ``(n, d)`` or ``(n, C, height, width)`` activations
    :param tau: threshold, relative to the layer's mean (``0.025`` in ReDo's reinforcement-learning experiments)
    :return: a fraction in ``[0, 1]``
    """
    return float(dormant_units(activations, tau).double().mean())


def dormant_units(activations: th.Tensor, tau: float = DORMANT_TAU) -> th.Tensor:
    """
    Which units are dormant in the sense of :func:`dormant_ratio` (the units that ReDo recycles).

    :param activations: ``(n, d)`` or ``(n, C, height, width)`` activations
    :param tau: threshold, relative to the layer's mean
    :return: boolean mask of shape ``(units,)``
    """
    if tau < 0:
        raise ValueError(f"tau must be >= 0, got {tau}.")
    score = unit_activations(activations).double().abs().mean(1)
    return score / (score.mean() + 1e-9) <= tau


def action_spread(actions: th.Tensor) -> float:
    """
    Spread of the actor's deterministic actions across the batch: the standard deviation over the inputs
    (population std, divisor ``n``) of each action dimension, averaged over the dimensions. 0 means that every
    input gets the same action (action collapse).

    :param actions: ``(n, action_dim)`` actions in ``[-1, 1]``
    :return: the mean standard deviation
    """
    if actions.dim() != 2:
        raise ValueError(f"Expected actions of shape (n, action_dim), got {tuple(actions.shape)}.")
    return float(actions.double().std(0, correction=0).mean())


def saturated_fraction(actions: th.Tensor, limit: float = SATURATION_LIMIT) -> float:
    """
    Fraction of the action components with ``|a| > limit``.

    :param actions: ``(n, action_dim)`` actions in ``[-1, 1]``
    :param limit: saturation threshold
    :return: a fraction in ``[0, 1]``
    """
    return float((actions.abs() > limit).double().mean())


def gradient_norm(gradients: Iterable[th.Tensor | None]) -> float:
    """
    L2 norm of the concatenation of gradients: ``sqrt(sum over tensors and entries of g^2)`` (missing
    gradients, ``None``, count as zero).

    :param gradients: the ``.grad`` of a layer's parameters
    :return: the norm
    """
    squares = [th.linalg.vector_norm(gradient.detach().double()) ** 2 for gradient in gradients if gradient is not None]
    return float(th.stack(squares).sum().sqrt()) if squares else 0.0


def layer_metrics(activations: th.Tensor, tau: float = DORMANT_TAU, delta: float = SRANK_DELTA) -> dict[str, float]:
    """
    Every activation metric of one layer; the ranks and the input correlation share one Gram matrix ``H H^T``
    (float64).

    :param activations: ``(n, *unit_shape)`` activations
    :param tau: threshold of :func:`dormant_ratio`
    :param delta: threshold of :func:`effective_rank`
    :return: ``numerical_rank`` (:func:`numerical_rank`), ``srank`` (:func:`effective_rank`), ``correlation``
        (:func:`unit_correlation`, the paper's), ``input_correlation`` (:func:`input_correlation`),
        ``zero_fraction``, ``dead_fraction``, ``dead_units`` (a count, as a float), ``dormant_ratio``
    """
    h = flatten_batch(activations)
    gram = _gram(h)
    s = _singular_values_from(h, gram)
    return {
        "numerical_rank": _numerical_rank(s),
        "srank": _effective_rank(s, delta),
        "correlation": unit_correlation(activations),
        "input_correlation": _input_correlation(gram, h.sum(1), h.abs().amax(1), h.shape[1]),
        "zero_fraction": zero_fraction(activations),
        "dead_fraction": dead_fraction(activations),
        "dead_units": float(dead_units(activations)),
        "dormant_ratio": dormant_ratio(activations, tau),
    }
