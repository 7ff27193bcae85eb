import numpy as np
import pytest
import torch as th

from sb3_collapse.errors import InputError, ParameterError
from sb3_collapse.probe import ProbeSettings, Rollouts
from sb3_collapse.probe.pipeline import RecordOptions
from sb3_collapse.probe.probing import (
    plan_passes,
    probe_layer,
    probe_warnings,
    split_by_episode,
    standardize_features_,
    standardize_targets,
)
from sb3_collapse.report.probe_outputs import staged_output, training_order


def test_split_never_cuts_an_episode():
    episode_ids = np.repeat(np.arange(10), 7)
    split = split_by_episode(episode_ids, (0.6, 0.2, 0.2), seed=3)
    assert (split.n_train, split.n_validation, split.n_test) == (42, 14, 14)
    assert sorted(split.order.tolist()) == list(range(70))
    sets = [
        split.order[: split.n_train],
        split.order[split.n_train : split.n_train + split.n_validation],
        split.order[split.n_train + split.n_validation :],
    ]
    episodes = [set(episode_ids[s]) for s in sets]
    assert [sorted(e) for e in episodes] == [split.episodes[k] for k in ("train", "validation", "test")]
    assert not (episodes[0] & episodes[1] or episodes[0] & episodes[2] or episodes[1] & episodes[2])
    assert split_by_episode(episode_ids, seed=3).episodes == split.episodes  # seeded
    with pytest.raises(InputError, match="at least 3 episodes"):
        split_by_episode(np.array([0, 0, 1, 1]))
    with pytest.raises(InputError, match="fractions"):
        split_by_episode(episode_ids, (0.5, 0.2, 0.2))


def test_features_standardized_in_place_with_train_statistics():
    rng = np.random.default_rng(0)
    values = rng.normal(3.0, 2.0, (50, 12)).astype(np.float32)
    values[:, [2, 7]] = 1.5  # constant columns
    values[:30, 9] = 0.0  # constant on the train rows only: dropped too
    features = th.as_tensor(values.copy())
    standardized, keep = standardize_features_(features, n_train=30, chunk_rows=7)
    assert keep.tolist() == [c not in (2, 7, 9) for c in range(12)]
    assert standardized.data_ptr() == features.data_ptr()  # no copy
    kept = values[:, keep.numpy()]
    expected = (kept - kept[:30].mean(0)) / kept[:30].std(0)
    np.testing.assert_allclose(standardized.numpy(), expected, rtol=1e-5, atol=1e-5)

    targets, _mean, scale = standardize_targets(np.stack([values[:, 0], np.full(50, 2.0)], 1), n_train=30)
    np.testing.assert_allclose(targets[:30, 0].mean(), 0, atol=1e-12)
    np.testing.assert_allclose(targets[:30, 0].std(), 1)
    assert scale[1] == 1.0 and (targets[:, 1] == 0).all()  # a constant target is only centred


def test_probe_layer_finds_a_sparse_linear_code():
    rng = np.random.default_rng(1)
    n, d = 300, 500
    features = rng.standard_normal((n, d)).astype(np.float32)
    episode_ids = np.repeat(np.arange(10), 30)
    split = split_by_episode(episode_ids)
    linear = features[:, [3, 50, 400]] @ np.array([1.0, -2.0, 0.5]) + 0.05 * rng.standard_normal(n)
    noise = rng.standard_normal(n)
    targets, _, _ = standardize_targets(np.stack([linear, noise], 1)[split.order], split.n_train)
    probe = probe_layer("cnn4", th.as_tensor(features[split.order]), targets, split, max_tau=16)
    assert probe.n_features == probe.n_features_kept == d and probe.max_tau == 16
    assert probe.validation_curve.shape == (2, 16)
    assert probe.tau[0] >= 3 and probe.test_mse[0] < 0.01  # the 3 atoms explain it
    assert probe.test_mse[1] > 0.8  # nothing explains noise
    assert probe.validation_mse[0] == probe.validation_curve[0].min()


def test_probe_layer_without_varying_features_predicts_the_train_mean():
    split = split_by_episode(np.repeat(np.arange(5), 4))
    targets, _, _ = standardize_targets(np.arange(20.0)[split.order, None], split.n_train)
    probe = probe_layer("mlp2", th.zeros(20, 8), targets, split, max_tau=4)
    assert probe.n_features_kept == 0 and probe.tau.tolist() == [0]
    n_val = split.n_validation
    np.testing.assert_allclose(probe.test_mse, (targets[split.n_train + n_val :] ** 2).mean(0))


def test_passes_respect_the_memory_budget():
    dims = {"cnn0": 63_504, "cnn1": 53_792, "cnn2": 39_200, "cnn3": 39_200, "cnn4": 39_200, "mlp0": 50, "mlp1": 1024}
    passes = plan_passes(dims, 10_000, 4e9)
    assert passes == [["cnn0", "mlp0", "mlp1"], ["cnn1", "cnn2"], ["cnn3", "cnn4"]]
    without_cnn0 = {name: dim for name, dim in dims.items() if name != "cnn0"}  # cnn0 reused: one pass less
    assert plan_passes(without_cnn0, 10_000, 4e9) == [["cnn1", "cnn2", "mlp0", "mlp1"], ["cnn3", "cnn4"]]
    assert plan_passes(dims, 10_000, 1e9) == [[name] for name in list(dims)[:5]] + [["mlp0", "mlp1"]]


def test_training_order_needs_distinct_steps():
    rows = [{"checkpoint": "b", "num_timesteps": 20}, {"checkpoint": "a", "num_timesteps": 10}]
    assert training_order(rows) == ["a", "b"]
    assert training_order(rows + [{"checkpoint": "c", "num_timesteps": 10}]) is None
    assert training_order(rows[:1]) is None


def test_staged_outputs_appear_only_on_commit(tmp_path):
    out = tmp_path / "probe"
    with pytest.raises(RuntimeError), staged_output(out) as staged:
        staged.path("probe.csv").write_text("partial")
        raise RuntimeError("interrupted while writing")
    assert not out.exists()
    out.mkdir()
    (out / "summary.json").write_text("old run")
    (out / "mse_over_training.png").write_text("old plot")
    with pytest.raises(InputError, match="overwrite=True"):
        staged_output(out)
    with staged_output(out, overwrite=True) as staged:
        staged.path("probe.csv").write_text("new")
        staged.path("summary.json").write_text("new run")
        assert (out / "summary.json").read_text() == "old run"  # untouched until the commit
        staged.commit()
    assert sorted(p.name for p in out.iterdir()) == ["probe.csv", "summary.json"]  # the stale plot is gone
    assert (out / "summary.json").read_text() == "new run"


def test_settings_and_record_options_are_checked_against_their_declared_ranges():
    ProbeSettings().validate()
    RecordOptions().check()
    for settings, message in [
        (ProbeSettings(max_tau=0), "max_tau must be >= 1, got 0."),
        (ProbeSettings(memory_gb=0.0), "memory_gb must be > 0, got 0.0."),
        (ProbeSettings(min_std=-1.0), "min_std must be >= 0, got -1.0."),
        (ProbeSettings(fractions=(0.5, 0.5, 0.5)), "fractions must be 3 positive fractions summing to 1"),
    ]:
        with pytest.raises(InputError, match=message):
            settings.validate()
    for options, message in [
        (RecordOptions(episodes=0), "episodes must be >= 1, got 0."),
        (RecordOptions(max_steps=0), "max_steps must be >= 1, got 0."),
        (RecordOptions(noise_std=float("nan")), "noise_std must be >= 0, got nan."),
    ]:
        with pytest.raises(ParameterError, match=message):
            options.check()


def test_probe_warns_of_barely_varying_targets_and_of_too_few_test_samples():
    n = 50
    episodes = np.repeat(np.arange(5), 10)
    split = split_by_episode(episodes)  # 3 train, 1 validation, 1 test episodes
    train = np.isin(episodes, split.episodes["train"])
    noise = np.random.default_rng(0).normal(size=n)
    columns = {
        "varying": noise,
        "constant": np.full(n, 2.5),  # std 0 everywhere
        "near": np.where(train, 1.0 + 1e-3 * noise, 1.0 + noise),  # train std ~1e-3, ~0.6 over the rollouts
        "tiny": 1e-9 * noise,  # below min_std on train
    }
    states = {name: values[:, None].astype(np.float32) for name, values in columns.items()}
    zeros = np.zeros(n, dtype=np.int64)
    actions, rewards = np.zeros((n, 1), np.float32), np.zeros(n, np.float32)
    rollouts = Rollouts(np.zeros((n, 1), np.uint8), states, actions, rewards, episodes, zeros, {})
    rows = [{"layer": "cnn1", "n_test": split.n_test, "max_tau": 64}, {"layer": "mlp0", "n_test": 10, "max_tau": 10}]
    assert split.n_test == 10
    flat, few = probe_warnings(rollouts, split, rows, ProbeSettings())
    assert flat["targets"] == ["constant", "near", "tiny"]
    assert few["layers"] == ["cnn1"]  # 10 test samples < max_tau 64; mlp0: 10 samples for 10 atoms is enough
    for warning in (flat, few):
        assert "well-performing agent" in warning["message"]
    assert "constant, near, tiny barely vary" in flat["message"] and "cnn1: the split leaves 10" in few["message"]
    # A smaller ratio keeps the near-constant target out; nothing to say when every layer has the samples it needs.
    (flat,) = probe_warnings(rollouts, split, rows[1:], ProbeSettings(target_std_ratio=1e-4))
    assert flat["targets"] == ["constant", "tiny"]
