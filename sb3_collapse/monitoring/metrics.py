"""
The paper's collapse metrics (Section 5.1) of a ``(n, *unit_shape)`` batch of one layer's activations, as Python
floats; ``H`` the ``n x d`` matrix of the flattened activations, a unit a feature or a channel (docs/monitoring.md).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Sequence

import torch as th

DORMANT_TAU = 0.025  # ReDo's threshold of the dormant ratio (Sokar et al., 2023)
DORMANT_TAUS = (0.0, 0.025, 0.1)  # the thresholds of ReDo's paper (Sokar et al., 2023, Figures 1-3), in one check
STABLE_RANK_MASS = 0.99  # Plasticine's stable rank: singular values up to 99% of their sum
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


CORRELATION_READINGS = ("input_correlation", "unit_correlation", "unit_abs_correlation")
"""The three readings of the paper's correlation (Section 5.1, "the average correlation among every two non-zero
activations"), by metric name: between inputs over the non-zero units (:func:`input_correlation`), between units,
signed (:func:`unit_correlation`) and absolute (:func:`unit_abs_correlation`)."""
FIGURE_CORRELATION = "input_correlation"
"""The reading of :data:`CORRELATION_READINGS` that Figures 4, 8, 9 and the dashboard draw by default: the one of the
three that is high on a layer collapsed to a point and low on a healthy one (the choice and its reasons:
docs/figures.md#figures-4-8-9-collapse-metrics-of-three-agents; measured: benchmarks/README.md#correlation-readings)."""


def _input_correlation(h: th.Tensor, gram: th.Tensor) -> float:
    # The units zero for every input add nothing to h h^T nor to the row sums: leaving them out only changes the
    # count the means divide by.
    nonzero = int((h != 0).any(0).sum())
    if nonzero < 2:
        return math.nan
    row_sums, row_max_abs = h.sum(1), h.abs().amax(1)
    centered = gram - th.outer(row_sums, row_sums) / nonzero  # sum_k (h_ik - m_i)(h_jk - m_j) over non-zero units
    variance = centered.diagonal()
    # All-zero rows are left out, and constant ones (zero variance up to rounding: Pearson's correlation undefined).
    valid = (row_max_abs > 0) & (variance > 1e-12 * (row_max_abs**2) * nonzero)
    m = int(valid.sum())
    if m < 2:
        return math.nan
    std = variance[valid].sqrt()
    corr = centered[valid][:, valid] / th.outer(std, std)
    return float((corr.sum() - corr.diagonal().sum()) / (m * (m - 1)))


def input_correlation(activations: th.Tensor) -> float:
    """
    The paper's correlation read between inputs (Section 5.1: "the average correlation among every two non-zero
    activations", a reflection of "the similarity of MLP activations" that is "high for a poorly performing agent",
    whose features "collapse to a single point"): the mean over two different inputs ``i != j`` of Pearson's
    correlation between their activation vectors (rows of ``H``), restricted to the **non-zero units**, those not
    zero for every input of the batch (the paper's zeros, :func:`dead_units`, are the others; a flattened entry for
    a convolutional layer). 1 when every input maps to the same point.

    Undefined cases: an input whose restricted vector is constant (all zero included) has no correlation and is
    left out (variance at most ``1e-12`` times its largest square, per unit); NaN when fewer than two non-zero units
    or fewer than two inputs remain.

    :param activations: ``(n, *unit_shape)`` activations
    :return: the mean correlation, in ``[-1, 1]``; NaN as above
    """
    h = flatten_batch(activations)
    return _input_correlation(h, h @ h.T)


def _unit_correlations(activations: th.Tensor) -> tuple[float, float]:
    """:return: the signed and the absolute mean correlation between units (:func:`unit_correlation`), from one
    correlation matrix"""
    units = unit_activations(activations).double()  # (units, N): N = n x positions
    largest = th.maximum(units.amax(1), -units.amin(1))
    centered = units - units.mean(1, keepdim=True)
    del units  # at most two (units, N) float64 copies alive at once
    norms = th.linalg.vector_norm(centered, dim=1)  # sqrt(N) x the standard deviation over the inputs
    varies = norms > 1e-6 * largest * math.sqrt(centered.shape[1])
    m = int(varies.sum())
    if m < 2:
        return math.nan, math.nan
    z = centered[varies] if m < len(varies) else centered
    z /= norms[varies, None]  # in place: z is this function's own tensor
    corr = z @ z.T  # (m, m), unit diagonal up to rounding
    pairs = m * (m - 1)
    signed = (corr.sum() - corr.diagonal().sum()) / pairs
    absolute = (corr.abs().sum() - corr.diagonal().abs().sum()) / pairs
    return float(signed), float(absolute)


def unit_correlation(activations: th.Tensor) -> float:
    """
    The paper's correlation read between units, signed (Section 5.1: "the average correlation among every two
    non-zero activations", the activations being the units as in its zeros, "the number of zero activations, also
    called dead neurons"): the mean over units ``a != b`` of Pearson's correlation over the inputs (and positions)
    of ``a`` and ``b`` (:func:`unit_activations`); float64 on the activations' device. Units that follow a collapsed
    layer's small residual motion with either sign cancel: near 0 on a layer collapsed to a point.

    Undefined cases: dead and constant units (std at most ``1e-6`` times the largest absolute value) are left out;
    NaN when fewer than two units vary, as on a layer where every input gives the same activations.

    :param activations: ``(n, d)`` dense or ``(n, C, height, width)`` convolutional activations
    :return: the mean correlation (``[-1/(m-1), 1]`` for ``m`` varying units); NaN as above
    """
    return _unit_correlations(activations)[0]


def unit_abs_correlation(activations: th.Tensor) -> float:
    """
    The paper's correlation read between units, absolute (Section 5.1: "the average correlation among every two
    non-zero activations"): :func:`unit_correlation` with ``|corr|`` averaged, so that units moving with opposite
    signs count as alike; 1 when the varying units follow one direction, whatever its size.

    Undefined cases: as :func:`unit_correlation` (NaN when fewer than two units vary).

    :param activations: ``(n, d)`` dense or ``(n, C, height, width)`` convolutional activations
    :return: the mean absolute correlation, in ``[0, 1]``; NaN as above
    """
    return _unit_correlations(activations)[1]


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


def dormant_ratios(activations: th.Tensor, taus: Sequence[float] = DORMANT_TAUS) -> dict[float, float]:
    """
    ReDo's dormant ratio (:func:`dormant_ratio`) at several thresholds from one score per unit, as dopamine's ReDo
    code scores a layer (``labs/redo/weight_recyclers.py``, ``estimate_neuron_score``: ``score = mean |a|`` over every
    axis but the unit's, ``score /= mean(score) + 1e-9``; dormant when ``score <= tau``).

    :param activations: ``(n, d)`` or ``(n, C, height, width)`` activations
    :param taus: thresholds, each >= 0, relative to the layer's mean
    :return: tau -> the fraction of dormant units, in ``[0, 1]``
    """
    if any(tau < 0 for tau in taus):
        raise ValueError(f"taus must be >= 0, got {list(taus)}.")
    score = unit_activations(activations).double().abs().mean(1)
    score = score / (score.mean() + 1e-9)
    thresholds = th.as_tensor(list(taus), dtype=score.dtype, device=score.device)
    values = (score[None, :] <= thresholds[:, None]).double().mean(1).tolist()  # one host transfer for every tau
    return dict(zip(taus, values, strict=True))


def persistent_dormant_fraction(dormant: th.Tensor, previous: th.Tensor) -> float:
    """
    The fraction of a layer's units dormant at this check and at the previous one (dopamine's ReDo follows the units
    that stay dormant; Sokar et al., 2023, Section 3): ``mean(dormant & previous)``.

    :param dormant: ``(units,)`` boolean mask of this check (:func:`dormant_units`)
    :param previous: ``(units,)`` boolean mask of the previous check, same layer
    :return: a fraction in ``[0, 1]``, at most each mask's dormant ratio
    """
    if dormant.shape != previous.shape:
        raise ValueError(
            f"previous must have the shape of dormant {tuple(dormant.shape)}, got {tuple(previous.shape)}."
        )
    return float((dormant & previous.to(dormant.device)).double().mean())


def active_fraction(activations: th.Tensor) -> float:
    """
    Fraction of active units, FAU (Ma et al., 2024, "Revisiting plasticity in visual reinforcement learning", eq. 1):
    ``FAU = (1 / n) sum_i (1 / M) sum_m 1[a_m(x_i) > 0]``, the mean over the inputs of the fraction of the ``M``
    activations (a feature, or a channel at one position) that are positive.

    :param activations: ``(n, *unit_shape)`` activations
    :return: a fraction in ``[0, 1]``
    """
    _check_batch(activations)
    return float((activations > 0).double().mean())


def _stable_rank(s: th.Tensor, mass: float) -> float:
    return _effective_rank(s, 1.0 - mass)


def stable_rank(activations: th.Tensor, mass: float = STABLE_RANK_MASS) -> float:
    """
    Stable rank as Plasticine computes it (RLE-Foundation/Plasticine, ``plasticine/metrics.py``,
    ``compute_stable_rank``, after Dohare et al. (2024)'s loss-of-plasticity code): the number of partial sums
    ``(s_1 + ... + s_k) / sum_i s_i`` below ``mass``, plus one; the smallest ``k`` whose partial sum reaches ``mass``.
    With ``mass = 0.99`` it equals Kumar et al.'s ``srank`` (:func:`effective_rank`) at ``delta = 0.01``; both names
    are kept as the two literatures use them. 0 for an all-zero matrix.

    :param activations: ``(n, *unit_shape)`` activations
    :param mass: fraction of the sum of the singular values, in ``(0, 1]``
    :return: an integer in ``[0, min(n, d)]`` (as a float)
    """
    if not 0.0 < mass <= 1.0:
        raise ValueError(f"mass must be in (0, 1], got {mass}.")
    return _stable_rank(singular_values(activations), mass)


def _entropy_effective_rank(s: th.Tensor) -> float:
    total = s.sum()
    if float(total) <= 0:
        return 0.0
    p = s / total
    p = p[p > 0]
    return float(th.exp(-(p * p.log()).sum()))


def entropy_effective_rank(activations: th.Tensor) -> float:
    """
    Effective rank of Roy and Vetterli (2007, "The effective rank: a measure of effective dimensionality"):
    ``exp(-sum_i p_i log p_i)``, ``p_i = s_i / sum_j s_j`` the normalized singular values of ``H`` (``0 log 0 = 0``),
    as Plasticine's ``compute_effective_rank``; 0 for an all-zero matrix.

    :param activations: ``(n, *unit_shape)`` activations
    :return: a real number in ``[1, min(n, d)]`` (0 for an all-zero matrix)
    """
    return _entropy_effective_rank(singular_values(activations))


def feature_norm(activations: th.Tensor) -> float:
    """
    Feature norm (Plasticine's ``compute_feature_norm``; Lyle et al., 2024): the mean over the inputs of the L2 norm
    of an input's flattened activations, ``(1 / n) sum_i ||h_i||_2``.

    :param activations: ``(n, *unit_shape)`` activations
    :return: the mean norm, >= 0
    """
    return float(th.linalg.vector_norm(flatten_batch(activations), dim=1).mean())


def weight_magnitude(parameters: Iterable[th.Tensor]) -> float:
    """
    Weight norm of a layer as Plasticine's weight magnitude (``compute_weight_magnitude``): the root mean square of
    its parameters, ``sqrt(sum_j w_j^2 / N)`` over the ``N`` entries of every parameter of the layer.

    :param parameters: the layer's parameters (weight, bias)
    :return: the norm, >= 0; 0 for a layer without parameters
    """
    tensors = [p.detach() for p in parameters]
    if not tensors:
        return 0.0
    squares = th.stack([th.linalg.vector_norm(p.double()) ** 2 for p in tensors]).sum()
    return float((squares / sum(p.numel() for p in tensors)).sqrt())


def weight_change(parameters: Iterable[th.Tensor], reference: Iterable[th.Tensor]) -> float:
    """
    Weight change (Plasticine's ``compute_l2_norm_difference``; Lyle et al., 2023): the distance of a layer's
    parameters from their values at a reference point (the last reset), as a root mean square,
    ``sqrt(sum_j (w_j - w0_j)^2 / N)``; 0 for identical weights.

    :param parameters: the layer's parameters now
    :param reference: the same parameters (same order and shapes) at the reference point, on any device
    :return: the distance, >= 0
    """
    now, then = [p.detach() for p in parameters], [p.detach() for p in reference]
    if len(now) != len(then) or any(a.shape != b.shape for a, b in zip(now, then, strict=False)):
        raise ValueError(
            f"reference must hold the parameters' shapes {[tuple(p.shape) for p in now]}, "
            f"got {[tuple(p.shape) for p in then]}."
        )
    if not now:
        return 0.0
    squares = th.stack([th.linalg.vector_norm(a.double() - b.to(a.device).double()) ** 2 for a, b in zip(now, then)])
    return float((squares.sum() / sum(p.numel() for p in now)).sqrt())


LAYER_METRICS = (
    "numerical_rank",
    "srank",
    "input_correlation",
    "unit_correlation",
    "unit_abs_correlation",
    "zero_fraction",
    "dead_fraction",
    "dead_units",
    "dormant_ratio",
)
"""The activation metrics :func:`layer_metrics` computes by default (those :class:`CollapseMetrics` logs by default)."""
EXTRA_LAYER_METRICS = ("dormant_ratios", "stable_rank", "entropy_effective_rank", "active_fraction", "feature_norm")
"""The other activation metrics :func:`layer_metrics` can compute; ``dormant_ratios`` gives ``dormant_ratio_tau<tau>``
for each of ``taus``."""


def dormant_ratio_name(tau: float) -> str:
    """:return: the name of the dormant ratio at ``tau`` among several, ``dormant_ratio_tau<tau>`` (``%g``)"""
    return f"dormant_ratio_tau{tau:g}"


def layer_metrics(
    activations: th.Tensor,
    tau: float = DORMANT_TAU,
    delta: float = SRANK_DELTA,
    metrics: Collection[str] = LAYER_METRICS,
    taus: Sequence[float] = DORMANT_TAUS,
) -> dict[str, float]:
    """
    Activation metrics of one layer (float64; every rank and the input correlation from one Gram matrix).

    :param activations: ``(n, *unit_shape)`` activations
    :param tau: threshold of :func:`dormant_ratio`
    :param delta: threshold of :func:`effective_rank`
    :param metrics: which, of :data:`LAYER_METRICS` and :data:`EXTRA_LAYER_METRICS`
    :param taus: thresholds of ``dormant_ratios``
    :return: name -> value, in the order of the two tuples: ``numerical_rank``, ``srank``, ``input_correlation``,
        ``unit_correlation``, ``unit_abs_correlation`` (:data:`CORRELATION_READINGS`), ``zero_fraction``,
        ``dead_fraction``, ``dead_units`` (as a float), ``dormant_ratio``, ``dormant_ratio_tau<tau>``
        (:func:`dormant_ratio_name`) for each of ``taus``,
        ``stable_rank``, ``entropy_effective_rank``, ``active_fraction``, ``feature_norm``
    """
    metrics = tuple(metrics)
    unknown = [name for name in metrics if name not in LAYER_METRICS + EXTRA_LAYER_METRICS]
    if unknown:
        raise ValueError(
            f"Unknown layer metric(s) {unknown}; choose among {list(LAYER_METRICS + EXTRA_LAYER_METRICS)}."
        )
    h = flatten_batch(activations)
    needs_gram = {"numerical_rank", "srank", "input_correlation", "stable_rank", "entropy_effective_rank"}
    gram = h @ h.T if needs_gram.intersection(metrics) else None
    s = _singular_values_from(h, gram) if gram is not None else None
    units = _unit_correlations(activations) if {"unit_correlation", "unit_abs_correlation"} & set(metrics) else None
    compute = {
        "numerical_rank": lambda: _numerical_rank(s),
        "srank": lambda: _effective_rank(s, delta),
        "input_correlation": lambda: _input_correlation(h, gram),
        "unit_correlation": lambda: units[0],
        "unit_abs_correlation": lambda: units[1],
        "zero_fraction": lambda: zero_fraction(activations),
        "dead_fraction": lambda: dead_fraction(activations),
        "dead_units": lambda: float(dead_units(activations)),
        "dormant_ratio": lambda: dormant_ratio(activations, tau),
        "stable_rank": lambda: _stable_rank(s, STABLE_RANK_MASS),
        "entropy_effective_rank": lambda: _entropy_effective_rank(s),
        "active_fraction": lambda: active_fraction(activations),
        "feature_norm": lambda: float(th.linalg.vector_norm(h, dim=1).mean()),
    }
    values: dict[str, float] = {}
    for name in LAYER_METRICS + EXTRA_LAYER_METRICS:
        if name not in metrics:
            continue
        if name == "dormant_ratios":
            values.update({dormant_ratio_name(t): value for t, value in dormant_ratios(activations, taus).items()})
        else:
            values[name] = compute[name]()
    return values
