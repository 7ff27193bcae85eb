import csv
import glob
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import TD3
from stable_baselines3.common.callbacks import BaseCallback, CallbackList, CheckpointCallback, EvalCallback
from stable_baselines3.common.logger import configure
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from sb3_collapse import ActivationLogger, CollapseMetrics, CollapseReset, DrQv2
from sb3_collapse.common.schedule import due_counts
from sb3_collapse.monitoring import FrameScheduleCallback, MetricsBatchSampler
from tests.random_env import RandomObservationEnv

PIXELS = gym.spaces.Box(0, 255, (9, 32, 32), np.uint8)
METRICS = (
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
LAYERS = ("cnn0", "cnn1", "cnn2", "cnn3", "cnn4", "mlp0", "mlp1", "mlp2", "action")


def pixel_env(action_repeat=2):
    return RandomObservationEnv(PIXELS, action_repeat=action_repeat)


def tiny_model(env=None, **kwargs):
    params = dict(buffer_size=1000, learning_starts=20, batch_size=8, seed=0, policy_kwargs=dict(hidden_dim=32))
    return DrQv2("CnnPolicy", env if env is not None else pixel_env(), **{**params, **kwargs})


def scalars(folder):
    events = glob.glob(str(folder / "events.out.tfevents.*"))
    assert len(events) == 1
    accumulator = EventAccumulator(events[0])
    accumulator.Reload()
    return accumulator


class FrameRecorder(FrameScheduleCallback):
    def __init__(self, every):
        super().__init__(every)
        self.checks = []

    def _on_check(self, frames):
        self.checks.append((self.num_timesteps, frames))


def test_tensorboard_tags_inside_learn_with_sb3_callbacks(tmp_path):
    model = tiny_model(tensorboard_log=str(tmp_path / "tb"))
    metrics = CollapseMetrics(check_every_frames=40, batch_size=16)
    rule = CollapseReset(window_frames=1000, check_every_frames=20, patience=3)
    evaluation = EvalCallback(Monitor(pixel_env()), n_eval_episodes=1, eval_freq=50, verbose=0)
    checkpoints = CheckpointCallback(save_freq=50, save_path=str(tmp_path / "ckpt"))
    model.learn(100, callback=CallbackList([metrics, rule, evaluation, checkpoints]), log_interval=1)

    accumulator = scalars(tmp_path / "tb" / "DrQv2_1")
    tags = set(accumulator.Tags()["scalars"])
    expected = {f"collapse/{layer}/{metric}" for layer in LAYERS for metric in METRICS}
    expected |= {f"collapse/{layer}/grad_norm" for layer in LAYERS[1:]}
    expected |= {"collapse/action_std", "collapse/action_saturation", "collapse/resets", "collapse/escaped"}
    expected |= {"collapse/escape_frame", "collapse/reset_rule/value", "eval/mean_reward", "train/critic_loss"}
    assert expected <= tags
    # One point per check, at the agent step of the check: frames 40, 80, ..., 200 are agent steps 20, ..., 100;
    # the buffer holds 16 transitions from step 16, so every check has a value.
    assert [e.step for e in accumulator.Scalars("collapse/mlp1/numerical_rank")] == [20, 40, 60, 80, 100]
    assert [e.step for e in accumulator.Scalars("collapse/escape_frame")] == [50]  # frames 60, 80, 100
    assert all(0 <= e.value <= 16 for e in accumulator.Scalars("collapse/mlp1/numerical_rank"))
    assert len(glob.glob(str(tmp_path / "ckpt" / "*.zip"))) == 2
    assert rule.escaped and rule.resets == 0


def test_metrics_csv_has_one_group_of_rows_per_check(tmp_path):
    path = tmp_path / "collapse_metrics.csv"
    metrics = CollapseMetrics(check_every_frames=40, batch_size=32, csv_path=path)
    tiny_model().learn(70, callback=metrics)  # checks at frames 40 (20 transitions: skipped), 80 and 120
    with open(path) as file:
        rows = list(csv.DictReader(file))
    groups = [(row["frame"], row["step"]) for row in rows]
    assert sorted(set(groups)) == [("120", "60"), ("80", "40")]  # the skipped check writes nothing
    assert groups.count(("80", "40")) == groups.count(("120", "60"))
    values = {row["tag"]: float(row["value"]) for row in rows if row["frame"] == "120"}
    assert values == metrics.last_metrics and len(rows) == 2 * len(values)
    assert {"collapse/mlp1/grad_norm", "collapse/mlp1/dead_fraction", "collapse/action_std"} <= set(values)


def test_constructor_callback_is_the_headline_usage():
    rule = CollapseReset(window_frames=40, check_every_frames=20, threshold=1e9, max_resets=1)
    model = tiny_model(callback=rule, learning_starts=1000)
    model.learn(30)
    assert rule.resets == 1 and model.reset_step == 20


def test_metrics_batch_does_not_change_training():
    def run(callback):
        env = DummyVecEnv([pixel_env, pixel_env])  # SB3's _get_samples draws env indices from np.random
        model = tiny_model(env, gradient_steps=2)
        model.learn(60, callback=callback)
        return [p.detach().clone() for p in model.policy.parameters()], model

    plain, _ = run(None)
    watched, model = run(CollapseMetrics(check_every_frames=20, batch_size=16))
    assert all(th.equal(a, b) for a, b in zip(plain, watched))
    assert model.num_timesteps == 60


def test_metrics_batch_indices_are_valid_distinct_positions():
    model = tiny_model()
    model.learn(30)
    sampler = MetricsBatchSampler(seed=0)
    observations, indices = sampler.sample(model, 25)
    assert len(set(indices.tolist())) == 25 and indices.max() < 30
    np.testing.assert_array_equal(observations.numpy(), model.replay_buffer.observations[indices, 0])
    assert sampler.sample(model, 31) is None  # fewer transitions than asked


def test_checks_follow_frames_with_several_envs_and_action_repeat():
    # 2 envs: num_timesteps grows by 2 per step of the VecEnv, frames by 4 (action repeat 2).
    recorder, every_step = FrameRecorder(every=30), FrameRecorder(every=3)
    model = tiny_model(DummyVecEnv([pixel_env, pixel_env]), learning_starts=1000)
    model.learn(50, callback=[recorder, every_step])
    assert recorder.checks == [(16, 32), (30, 60), (46, 92)]  # the first frame count >= 30, 60, 90
    # A step that crosses two multiples of 3 (e.g. frames 8 -> 12 cross 9 and 12) gives one check.
    assert every_step.checks == [(t, 2 * t) for t in range(2, 52, 2)]  # learn() ends at 50 (2 transitions per round)
    # The offline count of the same rule (the sweep's plan) finds the same frames: 100 frames in steps of 4.
    for callback in (recorder, every_step):
        assert [frames for _, frames in callback.checks] == due_counts(100, callback.period, per_step=4)


def test_metrics_skip_checks_while_the_buffer_is_small(capsys):
    metrics = CollapseMetrics(check_every_frames=20, batch_size=32, verbose=1)
    tiny_model(learning_starts=1000).learn(40, callback=metrics)
    out = capsys.readouterr().out
    assert out.count("skipped") == 3  # frames 20, 40, 60: 10, 20, 30 transitions
    assert "CollapseMetrics at frame 80" in out and metrics.last_metrics


def test_metrics_on_sb3_td3_mlp_policy():
    env = RandomObservationEnv(
        gym.spaces.Box(-1, 1, (4,), np.float32), gym.spaces.Box(-1, 1, (2,), np.float32), action_repeat=3
    )
    model = TD3("MlpPolicy", env, learning_starts=10, batch_size=8, policy_kwargs=dict(net_arch=[16, 16]), seed=0)
    metrics = CollapseMetrics(check_every_frames=60, batch_size=16)
    model.learn(40, callback=metrics)  # frames = agent steps x 3, read from the env
    values = metrics.last_metrics
    assert {f"collapse/{layer}/numerical_rank" for layer in ("mlp0", "mlp1", "mlp2", "action")} <= set(values)
    assert not any(tag.startswith("collapse/cnn") for tag in values)
    assert values["collapse/mlp1/grad_norm"] > 0 and "collapse/action_std" in values


POLICY_SPACES = {
    "MlpPolicy": gym.spaces.Box(-1, 1, (4,), np.float32),
    "CnnPolicy": gym.spaces.Box(0, 255, (3, 36, 36), np.uint8),
    "MultiInputPolicy": gym.spaces.Dict(
        {"pixels": gym.spaces.Box(0, 255, (3, 36, 36), np.uint8), "state": gym.spaces.Box(-1, 1, (4,), np.float32)}
    ),
}


@pytest.mark.parametrize("policy", list(POLICY_SPACES))
def test_the_three_callbacks_on_every_drqv2_policy(policy, tmp_path):
    kwargs = dict(hidden_dim=16, feature_dim=8)
    if policy != "MlpPolicy":
        kwargs["encoder_kwargs"] = dict(channels=4)
    env = RandomObservationEnv(POLICY_SPACES[policy], gym.spaces.Box(-1, 1, (2,), np.float32), action_repeat=2)
    model = DrQv2(policy, env, buffer_size=100, learning_starts=8, batch_size=4, seed=0, policy_kwargs=kwargs)
    metrics = CollapseMetrics(check_every_frames=20, batch_size=8)
    # An action spread of at most 1e9 is always "collapsed": the rule resets at the end of its first window.
    rule = CollapseReset(
        window_frames=40, check_every_frames=20, threshold=1e9, max_resets=1, metric="action_std", batch_size=8
    )
    logger = ActivationLogger(every_frames=40, path=tmp_path / "acts", batch_size=8, layers=["mlp1", "action"])
    model.learn(30, callback=[metrics, logger, rule])  # the logger reads the buffer before the reset empties it

    layers = ("mlp0", "mlp1", "mlp2", "action") if policy == "MlpPolicy" else LAYERS
    assert {tag.split("/")[1] for tag in metrics.last_metrics if tag.count("/") == 2} == set(layers)
    assert 1 <= metrics.last_metrics["collapse/mlp1/numerical_rank"] <= 8
    assert rule.resets == 1 and model.reset_step == 20  # frames 40 = agent steps 20
    assert rule.history and all(0 <= value <= 1 for _, value in rule.history)  # action spreads, actions in [-1, 1]
    files = sorted((tmp_path / "acts").glob("activations_*.npz"))
    assert [f.name for f in files] == ["activations_0000000020.npz"]
    with np.load(files[0]) as data:
        assert data["mlp1"].shape == (8, 16) and data["action"].shape == (8, 2) and len(set(data["indices"])) == 8


def test_activation_logger_saves_bounded_files(tmp_path):
    logger = ActivationLogger(every_frames=40, path=tmp_path / "acts", batch_size=8, layers=["mlp1", "action"])
    tiny_model().learn(40, callback=logger)
    files = sorted((tmp_path / "acts").glob("activations_*.npz"))
    assert [f.name for f in files] == ["activations_0000000020.npz", "activations_0000000040.npz"]
    with np.load(files[0]) as data:
        assert data["mlp1"].shape == (8, 32) and data["action"].shape == (8, 6)
        assert int(data["step"]) == 20 and int(data["frames"]) == 40 and len(set(data["indices"])) == 8
        assert list(data["layers"]) == ["mlp1", "action"]

    capped = ActivationLogger(
        every_frames=40,
        path=tmp_path / "capped",
        batch_size=8,
        layers=["mlp1", "action"],
        max_bytes=files[0].stat().st_size + 100,
    )
    with pytest.warns(UserWarning, match="max_bytes"):
        tiny_model().learn(60, callback=capped)
    assert len(list((tmp_path / "capped").glob("*.npz"))) == 1 and capped.stopped
    assert capped.bytes_written <= capped.max_bytes


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="check_every_frames"):
        CollapseMetrics(check_every_frames=0)
    with pytest.raises(ValueError, match="batch_size"):
        CollapseMetrics(batch_size=1)
    with pytest.raises(ValueError, match="max_bytes"):
        ActivationLogger(every_frames=10, path="x", max_bytes=0)
    with pytest.raises(ValueError, match="^every_frames must be >= 1, got 0"):
        ActivationLogger(every_frames=0, path="x")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        CollapseMetrics()  # the defaults are the paper's


def test_a_state_taken_at_step_0_is_continued_and_a_later_one_restarted_by_a_step_count_reset(tmp_path):
    """A run stopped during its first evaluation resumes from a checkpoint at step 0: the evaluation is not run (and
    written) twice. A state taken later, met by a learn() that restarted the step count, is a new run's start."""
    from sb3_collapse.monitoring import PeriodicEvaluation

    model = DrQv2("MlpPolicy", "Pendulum-v1", learning_starts=10, batch_size=8, buffer_size=100, seed=0,
                  policy_kwargs=dict(net_arch=[16], feature_dim=8))  # fmt: skip
    model.set_logger(configure(str(tmp_path / "logs"), ["csv"]))
    csv_path = tmp_path / "eval.csv"

    def evaluation() -> PeriodicEvaluation:
        callback = PeriodicEvaluation(Monitor(gym.make("Pendulum-v1", max_episode_steps=20)), 50, 1, csv_path)
        callback.init_callback(model)
        return callback

    first = evaluation()
    first.on_training_start({}, {})  # the evaluation at frame 0, then the stop
    state = first.state_dict()
    assert state["num_timesteps"] == 0 and first.next_check == 50
    resumed = evaluation()
    resumed.load_state_dict(state)
    resumed.on_training_start({}, {})
    assert resumed.next_check == 50 and len(resumed.rows) == 1
    assert len(csv_path.read_text().splitlines()) == 2  # the header and the one evaluation

    restarted = evaluation()
    restarted.load_state_dict({**state, "num_timesteps": 40})  # taken later; learn() then restarted the count at 0
    restarted.on_training_start({}, {})
    assert restarted.rows != [] and len(csv_path.read_text().splitlines()) == 3  # evaluated afresh at frame 0


def test_evaluation_calls_its_after_eval_callback_after_each_evaluation_and_stops_when_it_says(tmp_path):
    """Evaluations at frames 0, 50, 100 (not at the last step, 120), then the saved model's: the hook follows each;
    a hook that returns False stops learn() at its evaluation."""
    from sb3_collapse.monitoring import PeriodicEvaluation

    class Hook(BaseCallback):
        def __init__(self, stop_at=None):
            super().__init__()
            self.calls, self.stop_at = [], stop_at

        def _on_step(self):
            self.calls.append((self.num_timesteps, len(self.parent.rows)))
            return self.num_timesteps != self.stop_at

    def run(hook, steps):
        model = DrQv2("MlpPolicy", "Pendulum-v1", learning_starts=200, batch_size=8, buffer_size=200, seed=0,
                      policy_kwargs=dict(net_arch=[16], feature_dim=8))  # fmt: skip
        model.set_logger(configure(str(tmp_path / "logs"), ["csv"]))
        env = Monitor(gym.make("Pendulum-v1", max_episode_steps=5))
        evaluation = PeriodicEvaluation(env, 50, 1, tmp_path / f"eval_{steps}.csv", callback_after_eval=hook)
        model.learn(steps, callback=evaluation)
        return model, evaluation

    hook = Hook()
    model, evaluation = run(hook, 120)
    assert [row["frame"] for row in evaluation.rows] == [0, 50, 100] and evaluation.n_checks == 3
    assert hook.calls == [(0, 1), (50, 2), (100, 3)] and hook.parent is evaluation and hook.model is model
    assert evaluation.evaluate_saved_model()["frame"] == 120 and hook.calls[-1] == (120, 3)

    stopping = Hook(stop_at=50)
    model, evaluation = run(stopping, 120)
    assert model.num_timesteps == 50 and [row["frame"] for row in evaluation.rows] == [0, 50]


def test_a_state_of_another_version_is_refused_in_one_line():
    rule = CollapseReset()
    older = {"next_check_frame": 20_000, "n_checks": 2, "num_timesteps": 10_000}  # the schedule under an older name
    older |= {name: getattr(rule, name) for name in rule.state_attributes if name not in ("next_check", "n_checks")}
    with pytest.raises(ValueError, match="^CollapseReset: the saved state lacks next_check: it was written by another"):
        rule.load_state_dict(older)
    with pytest.raises(ValueError, match="^CollapseMetrics: the saved state lacks num_timesteps: "):
        CollapseMetrics().load_state_dict({"next_check": 10_000, "n_checks": 0, "last_metrics": {}})


def test_every_schedule_period_is_checked_for_type_and_finiteness():
    """CollapseMetrics(check_every_frames="1000") raised a raw TypeError and nan was accepted (then a check at every
    step): each period of the one schedule is refused unless an integer, naming its parameter."""
    from sb3_collapse.errors import ParameterError
    from sb3_collapse.monitoring import PeriodicReDo

    for value in ("1000", float("nan"), float("inf"), 2.5, 1000.0, True, None):
        with pytest.raises(ParameterError, match="^check_every_frames must be an integer >= 1, got ") as caught:
            CollapseMetrics(check_every_frames=value)
        assert caught.value.parameter == "check_every_frames"
        with pytest.raises(ParameterError, match="^check_every_frames must be an integer >= 1"):
            CollapseReset(check_every_frames=value)
        with pytest.raises(ParameterError, match="^every_frames must be an integer >= 1"):
            ActivationLogger(every_frames=value, path="unused")
    with pytest.raises(ParameterError, match=r"^check_every_frames must be >= 1, got 0\.$"):
        CollapseMetrics(check_every_frames=0)
    assert CollapseMetrics(check_every_frames=np.int64(1000)).period == 1000
    with pytest.raises(ValueError, match="^every_updates must be an integer >= 1, got nan"):
        PeriodicReDo(float("nan"))
    from sb3_collapse.run.checkpoints import ResumableCheckpoints

    with pytest.raises(ParameterError, match="^every_frames must be an integer >= 0, got nan"):
        ResumableCheckpoints("unused", float("nan"))


# The tags the default CollapseMetrics logs (the report's figures read them): pinned, whatever it can also measure.
DEFAULT_TAGS_PIXELS = (
    {f"collapse/{layer}/{metric}" for layer in LAYERS for metric in METRICS}
    | {f"collapse/{layer}/grad_norm" for layer in LAYERS[1:]}
    | {"collapse/action_std", "collapse/action_saturation"}
)


def test_default_tags_are_pinned_on_drqv2_pixels_and_td3_mlp():
    metrics = CollapseMetrics(check_every_frames=40, batch_size=16)
    tiny_model().learn(60, callback=metrics)
    assert set(metrics.last_metrics) == DEFAULT_TAGS_PIXELS

    env = RandomObservationEnv(gym.spaces.Box(-1, 1, (5,), np.float32))
    model = TD3("MlpPolicy", env, learning_starts=10, batch_size=8, policy_kwargs=dict(net_arch=[16, 16]), seed=0)
    metrics = CollapseMetrics(check_every_frames=30, batch_size=16)
    model.learn(40, callback=metrics)
    layers = ("mlp0", "mlp1", "mlp2", "action")
    expected = {f"collapse/{layer}/{metric}" for layer in layers for metric in METRICS}
    expected |= {f"collapse/{layer}/grad_norm" for layer in layers[1:]}
    assert set(metrics.last_metrics) == expected | {"collapse/action_std", "collapse/action_saturation"}


def test_collapse_metrics_arguments_are_checked_naming_each():
    from sb3_collapse.errors import ParameterError

    for kwargs, parameter in (
        (dict(metrics=["numerical_rank", "rank"]), "metrics"),
        (dict(networks=["actor", "target"]), "networks"),
        (dict(taus=[0.1, -0.5]), "taus"),
        (dict(taus=[]), "taus"),
    ):
        with pytest.raises(ParameterError, match=f"^{parameter}") as raised:
            CollapseMetrics(**kwargs)
        assert raised.value.parameter == parameter
    chosen = CollapseMetrics(metrics=["stable_rank"], networks=["critic"], taus=[0.5])
    assert chosen.get_config()["metrics"] == ["stable_rank"] and chosen.get_config()["taus"] == [0.5]


def layout_of(folder):
    """The one custom-scalars layout of a run folder, over its event files (one per learn() call)."""
    from tensorboard.plugins.custom_scalar import layout_pb2

    layouts = []
    for events in glob.glob(str(folder / "events.out.tfevents.*")):
        accumulator = EventAccumulator(events)
        accumulator.Reload()
        if "custom_scalars__config__" in accumulator.Tags()["tensors"]:
            layouts += accumulator.Tensors("custom_scalars__config__")
    assert len(layouts) == 1
    return layout_pb2.Layout.FromString(layouts[0].tensor_proto.string_val[0])


def test_extended_set_actor_and_critic_with_a_reset_and_the_dashboard(tmp_path):
    from sb3_collapse.monitoring.health import HEALTH_METRICS

    path = tmp_path / "collapse_metrics.csv"
    metrics = CollapseMetrics(20, batch_size=8, metrics=HEALTH_METRICS, networks=("actor", "critic"), csv_path=path)
    rule = CollapseReset(window_frames=70, check_every_frames=20, threshold=1e9, max_resets=1)
    model = tiny_model(tensorboard_log=str(tmp_path / "tb"))
    history = []
    metrics_check = metrics._on_check
    metrics._on_check = lambda frames: (metrics_check(frames), history.append((frames, dict(metrics.last_metrics))))
    model.learn(50, callback=CallbackList([rule, metrics]), log_interval=1)
    assert rule.resets == 1 and model.reset_step == 35  # frame 70
    values = dict(history)
    # Updates from step 21 to the reset at step 35; none in the warm-up after it, to step 50 (frame 100).
    assert values[60]["collapse/mlp1/weight_change"] > 0 and values[60]["collapse/q1.mlp1/weight_change"] > 0
    assert values[100]["collapse/mlp1/weight_change"] == 0 and values[100]["collapse/q2.mlp2/weight_change"] == 0
    assert np.isnan(values[100]["collapse/mlp1/persistent_dormant_fraction"])  # the memory restarted at the reset
    assert 0 <= values[60]["collapse/mlp1/persistent_dormant_fraction"] <= values[60]["collapse/mlp1/dormant_ratio"]
    for tag in (
        "collapse/q1/q_mean",
        "collapse/q2/q_std",
        "collapse/q1.mlp0/stable_rank",
        "collapse/cnn2/active_fraction",
    ):
        assert tag in values[100]
    with open(path) as file:
        logged = {row["tag"] for row in csv.DictReader(file) if row["frame"] == "100"}
    assert logged == set(values[100])
    accumulator = scalars(tmp_path / "tb" / "DrQv2_1")
    assert {"collapse/q1.mlp1/entropy_effective_rank", "collapse/reset_rule/threshold"} <= set(
        accumulator.Tags()["scalars"]
    )
    assert {e.value for e in accumulator.Scalars("collapse/reset_rule/threshold")} == {1e9}

    layout = layout_of(tmp_path / "tb" / "DrQv2_1")
    charts = {
        category.title: {chart.title: list(chart.multiline.tag) for chart in category.chart}
        for category in layout.category
    }
    figure4 = charts["collapse: Figure 4"]
    assert list(figure4) == ["numerical rank", "correlation", "dead units", "gradient norm", "action spread"]
    assert figure4["dead units"] == [r"^collapse/mlp[1-9][0-9]*/dead_units$"]
    rule_chart = charts["collapse: reset rule"]["rule value against its threshold"]
    assert rule_chart == [r"^collapse/reset_rule/value$", r"^collapse/reset_rule/threshold$"]
    assert "collapse: critic" in charts and "stable_rank" in charts["collapse: all layers"]


def test_dashboard_is_written_once_per_run_folder(tmp_path):
    metrics = CollapseMetrics(check_every_frames=40, batch_size=16)
    model = tiny_model(tensorboard_log=str(tmp_path / "tb"))
    model.learn(30, callback=metrics)
    model.learn(30, callback=metrics, reset_num_timesteps=False)  # the same folder, DrQv2_1, a second event file
    assert len(glob.glob(str(tmp_path / "tb" / "DrQv2_1" / "events.out.tfevents.*"))) == 2
    model.learn(30, callback=metrics)  # a new one, DrQv2_2
    for run in ("DrQv2_1", "DrQv2_2"):
        layout = layout_of(tmp_path / "tb" / run)
        titles = [category.title for category in layout.category]
        assert titles == ["collapse: Figure 4", "collapse: reset rule", "collapse: all layers"]
    silent = CollapseMetrics(check_every_frames=40, batch_size=16, dashboard=False)
    tiny_model(tensorboard_log=str(tmp_path / "quiet")).learn(30, callback=silent)
    events = glob.glob(str(tmp_path / "quiet" / "DrQv2_1" / "events.out.tfevents.*"))
    accumulator = EventAccumulator(events[0])
    accumulator.Reload()
    assert "custom_scalars__config__" not in accumulator.Tags()["tensors"]
