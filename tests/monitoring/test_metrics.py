import math

import numpy as np
import pytest
import torch as th

from sb3_collapse.monitoring.metrics import (
    CORRELATION_READINGS,
    EXTRA_LAYER_METRICS,
    FIGURE_CORRELATION,
    action_spread,
    active_fraction,
    dead_fraction,
    dead_units,
    dormant_ratio,
    dormant_ratios,
    dormant_units,
    effective_rank,
    entropy_effective_rank,
    feature_norm,
    gradient_norm,
    input_correlation,
    layer_metrics,
    numerical_rank,
    persistent_dormant_fraction,
    saturated_fraction,
    singular_values,
    stable_rank,
    unit_abs_correlation,
    unit_activations,
    unit_correlation,
    unit_count,
    weight_change,
    weight_magnitude,
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
    assert math.isnan(unit_correlation(h)) and math.isnan(unit_abs_correlation(h))
    assert math.isnan(layer_metrics(h)["unit_correlation"]) and math.isnan(layer_metrics(h)["unit_abs_correlation"])
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
    assert unit_abs_correlation(h) == pytest.approx((1 + 2 / math.sqrt(5)) / 3)
    corr = np.corrcoef(h[:, :3].numpy().T)
    assert unit_correlation(h) == pytest.approx(_mean_off_diagonal(corr))
    assert unit_abs_correlation(h) == pytest.approx(_mean_off_diagonal(np.abs(corr)))
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
    assert unit_abs_correlation(h) < 0.06  # |corr| of independent units over 512 inputs ~ 0.035
    live = h.numpy().std(0) > 0
    assert unit_correlation(h) == pytest.approx(_mean_off_diagonal(np.corrcoef(h.numpy()[:, live].T)), abs=1e-9)


def test_all_zero_rows_are_left_out_of_the_correlation():
    h = th.tensor([[1.0, 2.0, 3.0], [2.0, 4.0, 6.5], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    expected = np.corrcoef(h[0].numpy(), h[1].numpy())[0, 1]
    assert input_correlation(h) == pytest.approx(expected)
    assert math.isnan(input_correlation(th.zeros(5, 4)))  # no pair to correlate


def test_input_correlation_leaves_the_dead_units_out():
    # Units 1 and 3 are zero for every input: the paper's zeros, not among its "non-zero activations". Over the
    # other three units the two inputs are 1, 2, 4 and 2, 4, 7.
    h = th.tensor([[1.0, 0.0, 2.0, 0.0, 4.0], [2.0, 0.0, 4.0, 0.0, 7.0]])
    expected = np.corrcoef([1.0, 2.0, 4.0], [2.0, 4.0, 7.0])[0, 1]
    assert input_correlation(h) == pytest.approx(expected)
    assert input_correlation(h) != pytest.approx(np.corrcoef(h.numpy())[0, 1])  # the dead units would count
    # undefined cases: a single non-zero unit; inputs constant over the non-zero units (left out)
    assert math.isnan(input_correlation(th.tensor([[0.0, 1.0], [0.0, 2.0], [0.0, 3.0]])))
    assert math.isnan(input_correlation(th.tensor([[1.0, 1.0, 0.0], [2.0, 2.0, 0.0], [1.0, 3.0, 0.0]])))


def _relu_layer(directions, bias, n=512, width=256, dim=50, eps=0.05, seed=0):
    """``relu(W z + b)`` of ``n`` inputs: ``z ~ N(0, I)`` (healthy, ``directions`` None) or one point plus a variation
    of size ``eps`` in ``directions`` orthonormal directions (0: every input at the point)."""
    gen = th.Generator().manual_seed(seed)
    w = th.randn(width, dim, generator=gen, dtype=th.float64) / math.sqrt(dim)
    b = th.randn(width, generator=gen, dtype=th.float64) if bias else th.zeros(width, dtype=th.float64)
    if directions is None:
        return th.relu(th.randn(n, dim, generator=gen, dtype=th.float64) @ w.T + b)
    z = th.randn(dim, generator=gen, dtype=th.float64).expand(n, dim).clone()
    if directions:
        basis, _ = th.linalg.qr(th.randn(dim, directions, generator=gen, dtype=th.float64))
        z += eps * th.randn(n, directions, generator=gen, dtype=th.float64) @ basis.T
    return th.relu(z @ w.T + b)


@pytest.mark.parametrize("bias", [False, True])
@pytest.mark.parametrize("directions", [0, 1, 3, 50])
def test_the_figures_correlation_is_high_on_a_collapsed_layer_and_low_on_a_healthy_one(directions, bias):
    """Figures 4, 8, 9's reading (FIGURE_CORRELATION): a layer whose inputs "collapse to a single point" (up to a
    small variation in 1, 3 or 50 directions, or exactly) reads near 1; random features of inputs that differ read
    far lower. The unit readings do not separate them: the signed one cancels to about 0 on both, the absolute one
    is high only for a variation along one direction, and both are undefined on an exact collapse."""
    collapsed = layer_metrics(_relu_layer(directions, bias), metrics=CORRELATION_READINGS)
    healthy = layer_metrics(_relu_layer(None, bias), metrics=CORRELATION_READINGS)
    assert FIGURE_CORRELATION == "input_correlation"
    assert collapsed[FIGURE_CORRELATION] > 0.99
    assert healthy[FIGURE_CORRELATION] < 0.5
    if directions == 0:  # every unit constant: no pair of varying units
        assert math.isnan(collapsed["unit_correlation"]) and math.isnan(collapsed["unit_abs_correlation"])
    else:
        assert abs(collapsed["unit_correlation"]) < 0.05 and abs(healthy["unit_correlation"]) < 0.05
        assert (collapsed["unit_abs_correlation"] > 0.95) == (directions == 1)


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
    assert metrics["unit_correlation"] == pytest.approx(unit_correlation(h))
    assert metrics["unit_abs_correlation"] == pytest.approx(unit_abs_correlation(h))
    assert metrics["input_correlation"] == pytest.approx(input_correlation(h))
    assert metrics["zero_fraction"] == zero_fraction(h)
    assert metrics["dead_fraction"] == dead_fraction(h)
    assert metrics["dormant_ratio"] == dormant_ratio(h)
    assert metrics["dead_units"] == dead_units(h)
    flat = h.reshape(40, -1).numpy()
    assert metrics["input_correlation"] == pytest.approx(_mean_off_diagonal(np.corrcoef(flat)))
    channels = h.transpose(0, 1).reshape(3, -1).double().numpy()  # every channel varies
    assert metrics["unit_correlation"] == pytest.approx(_mean_off_diagonal(np.corrcoef(channels)))
    assert metrics["unit_abs_correlation"] == pytest.approx(_mean_off_diagonal(np.abs(np.corrcoef(channels))))


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="shape"):
        numerical_rank(th.ones(5))
    with pytest.raises(ValueError, match="delta"):
        effective_rank(th.eye(3), delta=1.0)
    with pytest.raises(ValueError, match="action_dim"):
        action_spread(th.ones(4, 2, 2))


# The plasticity literature's metrics (docs/monitoring.md#metrics): by hand, then against numpy.


@pytest.mark.parametrize("shape", [(40, 12), (8, 30)])  # SVD path (d <= n) and Gram path (d > n)
@pytest.mark.parametrize("k", [1, 3, 5])
def test_ranks_of_a_rank_k_matrix_with_equal_singular_values(shape, k):
    h = th.zeros(shape)
    h[:k, :k] = th.eye(k) * 2.0  # singular values 2 (k times), then 0
    assert stable_rank(h) == k
    assert effective_rank(h) == k
    assert entropy_effective_rank(h) == pytest.approx(k)  # exp(log k)
    assert numerical_rank(h) == pytest.approx(k)


def test_ranks_of_unequal_singular_values_by_hand():
    h = th.zeros(10, 4)
    h[0, 0], h[1, 1], h[2, 2] = 6.0, 3.0, 1.0  # s = (6, 3, 1, 0): partial sums 0.6, 0.9, 1.0
    assert stable_rank(h) == 3 and stable_rank(h, mass=0.9) == 2 and stable_rank(h, mass=0.5) == 1
    p = np.array([0.6, 0.3, 0.1])
    assert entropy_effective_rank(h) == pytest.approx(math.exp(-(p * np.log(p)).sum()))
    assert stable_rank(th.zeros(5, 3)) == 0.0 and entropy_effective_rank(th.zeros(5, 3)) == 0.0


def test_dormant_ratios_of_a_layer_with_known_scores():
    # Five units whose mean |activation| is 0, 0.02, 0.08, 1.9, 3.0: the layer mean is 1, so the scores are those.
    magnitudes = th.tensor([0.0, 0.02, 0.08, 1.9, 3.0])
    signs = th.tensor([1.0, -1.0, 1.0, -1.0])[:, None]
    h = signs * magnitudes  # (4 inputs, 5 units), |h| constant per unit
    assert dormant_ratios(h) == pytest.approx({0.0: 1 / 5, 0.025: 2 / 5, 0.1: 3 / 5})
    assert dormant_ratios(h, (0.5, 2.0)) == pytest.approx({0.5: 3 / 5, 2.0: 4 / 5})
    assert dormant_ratios(h)[0.025] == dormant_ratio(h, 0.025)
    # Channels of a conv layer: a channel's score is its mean over inputs and positions.
    conv = magnitudes[None, :, None, None].expand(3, 5, 2, 2)
    assert dormant_ratios(conv) == pytest.approx({0.0: 1 / 5, 0.025: 2 / 5, 0.1: 3 / 5})
    with pytest.raises(ValueError, match="taus must be >= 0"):
        dormant_ratios(h, (-0.1,))


def test_persistent_dormant_fraction_counts_units_dormant_at_both_checks():
    now = th.tensor([True, True, False, False])
    before = th.tensor([True, False, True, False])
    assert persistent_dormant_fraction(now, before) == 0.25
    assert persistent_dormant_fraction(now, now) == 0.5
    with pytest.raises(ValueError, match="previous must have the shape"):
        persistent_dormant_fraction(now, before[:3])


def test_active_fraction_and_feature_norm_by_hand():
    h = th.tensor([[3.0, 4.0, 0.0, -1.0], [0.0, 0.0, 0.0, 0.0]])
    assert active_fraction(h) == 2 / 8  # (2/4 + 0/4) / 2
    assert feature_norm(h) == pytest.approx((math.sqrt(26.0) + 0.0) / 2)
    assert active_fraction(th.ones(3, 2, 4, 4)) == 1.0


def test_weight_magnitude_and_change_by_hand():
    weight, bias = th.full((2, 2), 2.0), th.zeros(4)
    assert weight_magnitude([weight, bias]) == pytest.approx(math.sqrt(16 / 8))  # root mean square
    assert weight_change([weight, bias], [weight.clone(), bias.clone()]) == 0.0  # identical weights: no change
    assert weight_change([weight + 1, bias], [weight, bias]) == pytest.approx(math.sqrt(4 / 8))
    assert weight_magnitude([]) == 0.0
    with pytest.raises(ValueError, match="reference must hold"):
        weight_change([weight], [bias])


def test_plasticity_metrics_match_numpy():
    rng = np.random.default_rng(3)
    for shape in ((50, 20), (16, 3, 5, 5), (10, 64)):
        a = np.maximum(
            rng.normal(size=shape)
            * rng.uniform(0, 2, size=shape[1])[None, :, None, None].reshape((1, shape[1]) + (1,) * (len(shape) - 2)),
            0.0,
        )
        h = th.as_tensor(a, dtype=th.float32)
        flat = a.reshape(shape[0], -1).astype(np.float32).astype(np.float64)
        s = np.linalg.svd(flat, compute_uv=False)
        cumulative = np.cumsum(s) / s.sum()
        assert stable_rank(h) == np.sum(cumulative < 0.99) + 1  # Plasticine's compute_stable_rank
        p = s / s.sum()
        p = p[p > 0]
        assert entropy_effective_rank(h) == pytest.approx(np.exp(-(p * np.log(p)).sum()), rel=1e-6)
        assert active_fraction(h) == pytest.approx((flat > 0).mean())
        assert feature_norm(h) == pytest.approx(np.linalg.norm(flat, axis=1).mean())
        per_unit = np.moveaxis(np.abs(a), 1, -1).reshape(-1, shape[1]).mean(0)  # dopamine: mean over all but units
        score = per_unit / (per_unit.mean() + 1e-9)
        expected = {tau: float((score <= tau).mean()) for tau in (0.0, 0.025, 0.1, 0.5)}
        assert dormant_ratios(h, tuple(expected)) == pytest.approx(expected)
        assert th.equal(dormant_units(h, 0.5), th.as_tensor(score <= 0.5))
    w, w0 = rng.normal(size=(7, 3)), rng.normal(size=(7, 3))
    b, b0 = rng.normal(size=7), rng.normal(size=7)
    tensors = [th.as_tensor(x) for x in (w, b)]
    assert weight_magnitude(tensors) == pytest.approx(np.sqrt((np.sum(w**2) + np.sum(b**2)) / 28))
    change = np.sqrt((np.sum((w - w0) ** 2) + np.sum((b - b0) ** 2)) / 28)
    assert weight_change(tensors, [th.as_tensor(w0), th.as_tensor(b0)]) == pytest.approx(change)


def test_layer_metrics_extra_names_equal_the_single_functions():
    h = th.relu(th.randn(64, 32, generator=th.Generator().manual_seed(2)))
    values = layer_metrics(h, metrics=EXTRA_LAYER_METRICS, taus=(0.0, 0.1))
    assert values == pytest.approx(
        {
            "dormant_ratio_tau0": dormant_ratio(h, 0.0),
            "dormant_ratio_tau0.1": dormant_ratio(h, 0.1),
            "stable_rank": stable_rank(h),
            "entropy_effective_rank": entropy_effective_rank(h),
            "active_fraction": active_fraction(h),
            "feature_norm": feature_norm(h),
        }
    )
    assert list(layer_metrics(h)) == list(layer_metrics(h, metrics=reversed(list(layer_metrics(h)))))  # fixed order
    with pytest.raises(ValueError, match="Unknown layer metric"):
        layer_metrics(h, metrics=("rank",))


def test_plasticity_metrics_keep_the_device_and_take_float64():
    h = th.relu(th.randn(20, 6, dtype=th.float64, generator=th.Generator().manual_seed(4)))
    assert dormant_units(h).device == h.device
    assert stable_rank(h) == stable_rank(h.float())
    assert entropy_effective_rank(h) == pytest.approx(entropy_effective_rank(h.float()), rel=1e-6)
