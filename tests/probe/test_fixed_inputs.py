"""The fixed observation set of Figures 4, 8, 9 (sb3_collapse/probe/fixed_inputs.py)."""

import numpy as np

from sb3_collapse.commands.report_pipelines import FixedInputSettings
from sb3_collapse.probe import ProbeSettings, Rollouts
from sb3_collapse.probe.fixed_inputs import load_fixed_inputs
from sb3_collapse.probe.probing import split_by_episode


def test_fixed_set_from_the_probes_training_episodes(tmp_path):
    """Figures 4, 8, 9's H from the probe's training episodes (Figure 1's H): the rows the probe's default split
    trains on, then the seeded draw among them; the default set draws from every episode."""
    episodes = np.repeat(np.arange(10), 7)
    n = len(episodes)
    observations = np.arange(n, dtype=np.uint8)[:, None]  # each observation its own row number
    zeros = np.zeros(n, np.int64)
    rollouts = Rollouts(observations, {"x": np.zeros((n, 1), np.float32)}, np.zeros((n, 1), np.float32),
                        np.zeros(n, np.float32), episodes, zeros, {"task_id": "walker-walk"})  # fmt: skip
    path = rollouts.save(tmp_path / "rollouts.npz")
    defaults = ProbeSettings()
    split = split_by_episode(episodes, defaults.fractions, defaults.split_seed)
    train_rows = np.sort(split.order[: split.n_train])
    inputs = load_fixed_inputs(path, samples=None, train_episodes=True)
    np.testing.assert_array_equal(inputs.indices, train_rows)
    np.testing.assert_array_equal(inputs.observations[:, 0], train_rows)
    assert inputs.train_episodes == split.episodes["train"] and len(inputs.train_episodes) == 6
    assert "the probe's training episodes (42 observations of 6 of the 10 episodes" in inputs.describe()
    drawn = load_fixed_inputs(path, samples=20, seed=3, train_episodes=True)
    assert len(drawn.indices) == 20 and set(drawn.indices) <= set(train_rows)
    assert list(drawn.indices) == sorted(drawn.indices)
    every = load_fixed_inputs(path, samples=None)
    assert len(every.indices) == n and every.train_episodes is None and "all 70 observations" in every.describe()
    # the report's setting (--train-episodes) reads the same set
    settings = FixedInputSettings(fixed_samples=None, train_episodes=True)
    np.testing.assert_array_equal(settings.load(path).indices, train_rows)
