import math

import numpy as np
import pytest
import torch as th

from sb3_collapse.monitoring.metrics import (
    action_spread,
    dead_fraction,
    dead_units,
    dormant_ratio,
    effective_rank,
    gradient_norm,
    input_correlation,
    layer_metrics,
    numerical_rank,
    saturated_fraction,
    singular_values,
    unit_activations,
    unit_correlation,
    unit_count,
    zero_fraction,
)


def test_identity_matrix():
    eye = th.eye(10)
    assert numerical_rank(eye) == pytest.approx(10.0)
    assert effective_rank(eye) == 10.0
    assert effective_rank(eye, delta=0.25) == 8.0  # the first 8 of 10 equal values reach 75%
    # Rows e_i, e_j over 10 entries: mean 0.1, covariance -0.1, variance 0.9, so corr = -1/9.
    assert input_correlation(eye) == pytest.approx(-1 / 9)
    assert zero_fraction(eye) == pytest.approx(0.9)
    assert dead_fraction(eye) == 0.0
    assert dormant_ratio(eye) == 0.0


def test_rank_one_matrix_wide_and_tall():
    rng = np.random.default_rng(0)
    for shape in ((64, 1000), (200, 20)):  # Gram path (d > n) and SVD path (d <= n)
        u, v = rng.normal(size=(shape[0], 1)), rng.uniform(0.1, 1, size=(1, shape[1]))
        h = th.as_tensor(u @ v, dtype=th.float32)
        assert numerical_rank(h) == pytest.approx(1.0, abs=1e-4)
        assert effective_rank(h) == 1.0
        # Rows are multiples of one vector: correlation +1 or -1 by the sign of the multiple.
        signs = np.sign(u[:, 0])
        pairs = np.outer(signs, signs)
        expected = (pairs.sum() - shape[0]) / (shape[0] * (shape[0] - 1))
        assert input_correlation(h) == pytest.approx(expected, abs=1e-6)


def test_singular_values_match_numpy():
    h = th.randn(30, 200, generator=th.Generator().manual_seed(1))
    np.testing.assert_allclose(
        singular_values(h).numpy(), np.linalg.svd(h.double().numpy(), compute_uv=False), rtol=1e-7
    )
    s = np.linalg.svd(h.double().numpy(), compute_uv=False)
    assert numerical_rank(h) == pytest.approx(s.sum() ** 2 / (s**2).sum())
    cumulative = np.cumsum(s) / s.sum()
    assert effective_rank(h) == int(np.argmax(cumulative >= 0.99)) + 1


def test_identical_rows_collapse_to_one_point():
    row = th.tensor([0.0, 1.0, 3.0, 0.5, 0.0])
    h = row.repeat(8, 1)
    assert input_correlation(h) == pytest.approx(1.0)
    # every unit is constant over the inputs: no pair of varying units, the paper's correlation is undefined
    assert math.isnan(unit_correlation(h)) and math.isnan(unit_correlation(h, absolute=True))
    assert math.isnan(layer_metrics(h)["correlation"])
    assert numerical_rank(h) == pytest.approx(1.0)
    assert dead_fraction(h) == pytest.approx(2 / 5)
    assert zero_fraction(h) == pytest.approx(2 / 5)


def _mean_off_diagonal(corr):
    return (corr.sum() - np.trace(corr)) / (len(corr) * (len(corr) - 1))


def test_unit_correlation_by_hand():
    # Units (columns) over 4 inputs: u0 = 0, 1, 2, 3; u1 = 3 - u0 (corr -1 with u0); u2 = 0, 1, 0, 1; a dead
    # unit and a constant one (left out). Centred: u0 -1.5, -0.5, 0.5, 1.5 and u2 -0.5, 0.5, -0.5, 0.5, so
    # corr(u0, u2) = 1 / (sqrt(5) * 1) and corr(u1, u2) = -1 / sqrt(5): signed mean (-1 + 0) / 3, absolute mean
    # (1 + 2 / sqrt(5)) / 3.
    u0 = [0.0, 1.0, 2.0, 3.0]
    h = th.tensor([[a, 3.0 - a, b, 0.0, 2.0] for a, b in zip(u0, [0.0, 1.0, 0.0, 1.0])])
    assert unit_correlation(h) == pytest.approx(-1 / 3)
    assert unit_correlation(h, absolute=True) == pytest.approx((1 + 2 / math.sqrt(5)) / 3)
    corr = np.corrcoef(h[:, :3].numpy().T)
    assert unit_correlation(h) == pytest.approx(_mean_off_diagonal(corr))
    assert unit_correlation(h, absolute=True) == pytest.approx(_mean_off_diagonal(np.abs(corr)))
    assert math.isnan(unit_correlation(h[:, [0, 3, 4]]))  # one varying unit: no pair
    assert math.isnan(unit_correlation(th.zeros(5, 4)))  # every unit dead
    # a convolutional unit is a channel, its vector every input at every position
    conv = th.relu(th.randn(6, 4, 3, 3, generator=th.Generator().manual_seed(3)) + 0.3)
    conv[:, 2] = 0.0
    channels = unit_activations(conv).double().numpy()[[0, 1, 3]]
    assert unit_correlation(conv) == pytest.approx(_mean_off_diagonal(np.corrcoef(channels)))


@pytest.mark.parametrize("bias_std", [1.0, 2.0])
def test_unit_and_input_correlations_of_a_healthy_layer(bias_std):
    # A full-rank random ReLU layer whose units have their own biases: 512 Gaussian inputs of dimension 512 through
    # 512 units. The units vary nearly independently (pairwise correlations ~ 1/sqrt(512) of either sign, mean
    # near 0), while every two inputs share the units' mean profile (a unit with a large bias is large for every
    # input), so the input reading is large.
    rng = np.random.default_rng(0)
    n = d = k = 512
    x = rng.standard_normal((n, k))
    w = rng.standard_normal((d, k)) / np.sqrt(k)
    b = rng.standard_normal(d) * bias_std
    h = th.as_tensor(np.maximum(x @ w.T + b, 0.0), dtype=th.float32)
    assert input_correlation(h) > {1.0: 0.35, 2.0: 0.65}[bias_std]
    assert abs(unit_correlation(h)) < 0.01
    assert unit_correlation(h, absolute=True) < 0.06  # |corr| of independent units over 512 inputs ~ 0.035
    live = h.numpy().std(0) > 0
    assert unit_correlation(h) == pytest.approx(_mean_off_diagonal(np.corrcoef(h.numpy()[:, live].T)), abs=1e-9)


def test_all_zero_rows_are_left_out_of_the_correlation():
    h = th.tensor([[1.0, 2.0, 3.0], [2.0, 4.0, 6.5], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    expected = np.corrcoef(h[0].numpy(), h[1].numpy())[0, 1]
    assert input_correlation(h) == pytest.approx(expected)
    assert math.isnan(input_correlation(th.zeros(5, 4)))  # no pair to correlate


def test_all_zero_columns_are_dead_and_dormant():
    h = th.rand(16, 10, generator=th.Generator().manual_seed(0)) + 0.5
    h[:, [1, 4, 7]] = 0.0
    assert dead_fraction(h) == pytest.approx(0.3)
    assert zero_fraction(h) == pytest.approx(0.3)
    assert dormant_ratio(h) == pytest.approx(0.3)
    zero = th.zeros(4, 6)
    assert dead_fraction(zero) == 1.0 and dormant_ratio(zero) == 1.0 and zero_fraction(zero) == 1.0
    assert numerical_rank(zero) == 0.0 and effective_rank(zero) == 0.0


def test_dormant_ratio_threshold_is_relative_to_the_layer_mean():
    # Mean |activation| per unit: 1, 1, 1, 0.05 -> layer mean 0.7625; 0.05 / 0.7625 = 0.066.
    h = th.tensor([[1.0, 1.0, 1.0, 0.05], [-1.0, 1.0, 1.0, -0.05]])
    assert dormant_ratio(h, tau=0.025) == 0.0
    assert dormant_ratio(h, tau=0.1) == pytest.approx(0.25)


def test_convolutional_units_are_channels():
    h = th.ones(4, 3, 5, 5)
    h[:, 1] = 0.0  # channel 1 dead everywhere
    h[0, 2, 0, 0] = 0.0  # channel 2 has one zero: not dead
    assert dead_fraction(h) == pytest.approx(1 / 3)
    assert zero_fraction(h) == pytest.approx((4 * 25 + 1) / (4 * 75))


def test_dead_units_count_units_zero_on_every_input_not_zero_entries():
    # 6 inputs x 8 units: unit 2 is zero on every input (dead); units 0, 3, 5 are zero on some inputs only (half
    # of unit 0's, one of unit 3's, all but one of unit 5's): 1 dead unit, while 6 + 3 + 1 + 5 = 15 of 48 entries
    # are zero.
    h = th.ones(6, 8)
    h[:, 2] = 0.0
    h[:3, 0] = 0.0
    h[4, 3] = 0.0
    h[1:, 5] = 0.0
    assert unit_count(h) == 8
    assert dead_units(h) == 1 and dead_fraction(h) == pytest.approx(1 / 8)
    assert zero_fraction(h) == pytest.approx(15 / 48)
    # every unit zero on some input, none on all: no dead unit, a large zero fraction
    checker = th.ones(4, 8)
    checker[::2, ::2] = 0.0
    checker[1::2, 1::2] = 0.0
    assert dead_units(checker) == 0 and zero_fraction(checker) == pytest.approx(0.5)
    # a channel of a convolutional layer is one unit: dead only when zero at every position of every input
    conv = th.ones(3, 4, 5, 5)
    conv[:, 1] = 0.0
    conv[:, 3, 2, 2] = 0.0
    assert unit_count(conv) == 4 and dead_units(conv) == 1
    assert dead_units(th.zeros(5, 7)) == 7


def test_action_spread_and_saturation():
    actions = th.tensor([[1.0, 0.5], [-1.0, 0.5], [1.0, 0.5], [-1.0, 0.5]])
    assert action_spread(actions) == pytest.approx(0.5)  # std 1 and 0, averaged
    assert saturated_fraction(actions) == pytest.approx(0.5)
    assert action_spread(th.full((10, 3), 0.2)) == 0.0
    assert saturated_fraction(th.tensor([[0.995, -0.999, 0.98, 0.0]])) == pytest.approx(0.5)


def test_gradient_norm():
    assert gradient_norm([th.tensor([3.0]), th.tensor([[4.0, 0.0]]), None]) == pytest.approx(5.0)
    assert gradient_norm([None]) == 0.0


def test_layer_metrics_equal_the_single_functions():
    h = th.relu(th.randn(40, 3, 6, 6, generator=th.Generator().manual_seed(2)))
    metrics = layer_metrics(h)
    assert metrics["numerical_rank"] == pytest.approx(numerical_rank(h))
    assert metrics["srank"] == effective_rank(h)
    assert metrics["correlation"] == pytest.approx(unit_correlation(h))
    assert metrics["input_correlation"] == pytest.approx(input_correlation(h))
    assert metrics["zero_fraction"] == zero_fraction(h)
    assert metrics["dead_fraction"] == dead_fraction(h)
    assert metrics["dormant_ratio"] == dormant_ratio(h)
    assert metrics["dead_units"] == dead_units(h)
    flat = h.reshape(40, -1).numpy()
    assert metrics["input_correlation"] == pytest.approx(_mean_off_diagonal(np.corrcoef(flat)))
    channels = h.transpose(0, 1).reshape(3, -1).double().numpy()  # every channel varies
    assert metrics["correlation"] == pytest.approx(_mean_off_diagonal(np.corrcoef(channels)))


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="shape"):
        numerical_rank(th.ones(5))
    with pytest.raises(ValueError, match="delta"):
        effective_rank(th.eye(3), delta=1.0)
    with pytest.raises(ValueError, match="action_dim"):
        action_spread(th.ones(4, 2, 2))
