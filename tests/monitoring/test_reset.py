import csv
import glob

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import PPO, SAC, TD3
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from sb3_collapse import CollapseMetrics, CollapseReset, DrQv2
from sb3_collapse.monitoring import grad_norms_of
from sb3_collapse.monitoring.reset import escape_step, first_escape
from tests.random_env import RandomObservationEnv

PIXELS = gym.spaces.Box(0, 255, (9, 32, 32), np.uint8)
# A window of 200 frames checked every 20 frames, on an env of action repeat 2: 100 agent steps per window.
RULE = dict(window_frames=200, check_every_frames=20, patience=3)


def tiny_model(seed=0, **kwargs):
    params = dict(buffer_size=1000, learning_starts=20, batch_size=8, seed=seed, policy_kwargs=dict(hidden_dim=32))
    params.update(stddev_schedule="linear(1.0,0.1,100)", **kwargs)
    return DrQv2("CnnPolicy", RandomObservationEnv(PIXELS, action_repeat=2), **params)


def collapse(model):
    """Kill every mlp1 unit: a bias of -1000 makes every ReLU input negative for inputs in [-1, 1]."""
    with th.no_grad():
        model.actor.mlp1[0].bias.fill_(-1e3)


def weights(model):
    return [p.detach().clone() for p in model.policy.parameters()]


def differ_everywhere(a, b):
    """Every weight tensor that is not all-zero biases or LayerNorm ones differs."""
    return all(not th.equal(x, y) for x, y in zip(a, b) if x.dim() > 1)


def optimizers_of(model):
    if isinstance(model, DrQv2):
        return model.policy.optimizers
    return [
        model.actor.optimizer,
        model.critic.optimizer,
        *([model.ent_coef_optimizer] if isinstance(model, SAC) else []),
    ]


class SpyReset(CollapseReset):
    """Records the model's state right after each reset, and the number of updates at every step."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.before, self.after, self.updates = [], [], {}

    def _reset(self, frames):
        self.before.append(weights(self.model))
        super()._reset(frames)
        model = self.model
        self.after.append(
            dict(
                weights=weights(model),
                buffer_size=model.replay_buffer.size(),
                optimizer_states=[len(o.state) for o in optimizers_of(model)],
                stddev=getattr(model, "current_stddev", None),
                step=model.num_timesteps,
                grad_norms=grad_norms_of(model),
            )
        )

    def _on_step(self):
        self.updates[self.num_timesteps] = self.model._n_updates
        return super()._on_step()


def test_collapsed_actor_has_collapse_metrics_and_zero_gradient():
    model = tiny_model()
    collapse(model)
    metrics = CollapseMetrics(check_every_frames=100, batch_size=32)
    model.learn(60, callback=metrics)  # frame 100: 30 updates done, 60 transitions stored
    values = metrics.last_metrics
    assert values["collapse/mlp1/dead_fraction"] == 1.0 and values["collapse/mlp2/dead_fraction"] == 1.0
    assert values["collapse/mlp1/zero_fraction"] == 1.0
    assert values["collapse/mlp1/numerical_rank"] <= 1.0  # 0: the activation matrix is all zeros
    assert values["collapse/action/numerical_rank"] <= 1.0 + 1e-6  # every input gets the same action
    assert values["collapse/action_std"] < 1e-6
    assert values["collapse/mlp1/grad_norm"] < 1e-3 and model.last_grad_norms["mlp1"] == 0.0
    assert values["collapse/cnn1/numerical_rank"] > 5  # the encoder is not collapsed


def test_collapsed_actor_is_reset_from_scratch_at_the_end_of_the_window(tmp_path):
    model = tiny_model()
    initial = weights(model)
    collapse(model)
    rule = SpyReset(**RULE, verbose=1, events_path=tmp_path / "collapse_events.csv")
    model.learn(170, callback=rule)

    assert model.num_timesteps == 170  # the budget is spent, not extended
    assert rule.resets == 1 and rule.reset_frames == [200]
    after = rule.after[0]
    assert after["step"] == 100 and model.reset_step == 100
    # New random weights: neither the collapsed ones nor the initial ones again.
    assert differ_everywhere(after["weights"], rule.before[0])
    assert differ_everywhere(after["weights"], initial)
    assert model.actor.mlp1[0].bias.abs().max() < 1.0  # zero-initialized again, then trained a little
    assert after["optimizer_states"] == [0, 0, 0]  # fresh Adam state
    assert after["buffer_size"] == 0 and after["grad_norms"] == {}
    assert after["stddev"] == 1.0  # the exploration schedule restarts (it was 0.1 at step 100)
    # Warm-up again: no update from the reset until learning_starts=20 agent steps were collected.
    assert rule.updates[100] == rule.updates[120] > 0
    assert rule.updates[130] > rule.updates[120]
    # The aliases and the gradient norms follow the new networks.
    assert model.actor is model.policy.actor and model.encoder is model.policy.encoder
    assert model.grad_norm_recorder.watches(model.policy.optimizers)
    assert model.last_grad_norms["mlp1"] > 1e-3
    # The fresh actor is healthy: it escapes, and the rule stops.
    assert rule.escaped and rule.escape_frame > 240
    # The report's reading of the logged checks is the rule's own test: the same escape frame.
    frames, values = zip(*rule.history)
    assert first_escape(frames, values, patience=RULE["patience"], restarts=rule.reset_frames) == rule.escape_frame
    # The events file: one row per reset and the escape, in frames and agent steps.
    with open(tmp_path / "collapse_events.csv") as file:
        rows = list(csv.DictReader(file))
    detail = (
        "new encoder, actor, critic, target critic and their optimizers; replay buffer emptied (99 transitions); "
        "warm-up restarted"
    )
    assert rows == [
        {"frame": "200", "step": "100", "event": "reset", "resets": "1", "intervention": "reset", "detail": detail},
        {
            "frame": str(rule.escape_frame),
            "step": str(rule.escape_frame // 2),
            "event": "escape",
            "resets": "1",
            "intervention": "reset",
            "detail": "",
        },
    ]
    assert rule.interventions[0].scalars["transitions_dropped"] == 99


def test_the_escape_test_over_logged_checks():
    # Section 5.2: "a gradient norm larger than 0.001 of consecutive five computations".
    assert (
        escape_step(4, 2e-3) == (5, True) and escape_step(4, 1e-3) == (0, False) and escape_step(4, None) == (4, False)
    )
    frames = list(range(10, 130, 10))
    healthy = [1e-6, 1e-6, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05, 1e-6]
    assert first_escape(frames, healthy) == 70  # the fifth healthy check in a row
    assert first_escape(frames, healthy[:6] + [1e-6] * 6) is None  # four in a row: no escape
    gaps = [1e-6, 1e-6, 0.05, 0.05, float("nan"), 0.05, None, 0.05, 0.05, 1e-6, 1e-6, 1e-6]
    assert first_escape(frames, gaps) == 90  # a check without a value leaves the streak as it is
    # A reset at frame 50 starts a new window: the streak starts again after it (the check at 50 is the old window's).
    assert first_escape(frames, healthy, restarts=[50]) == 100
    assert first_escape(frames, healthy, restarts=[40]) == 90
    assert first_escape([], []) is None


def test_events_file_has_a_header_when_nothing_happens(tmp_path):
    rule = CollapseReset(**RULE, events_path=tmp_path / "events.csv")
    tiny_model(learning_starts=1000).learn(20, callback=rule)  # 40 frames: no update, no window end
    assert (tmp_path / "events.csv").read_text().splitlines() == ["frame,step,event,resets,intervention,detail"]


def test_healthy_actor_escapes_and_is_never_reset():
    # A fresh tiny actor on random rewards has an mlp1 gradient norm of 0.04..0.2 here, far above 1e-3.
    model = tiny_model(seed=1)
    rule = SpyReset(**RULE)
    model.learn(160, callback=rule)
    assert rule.escaped and rule.resets == 0 and model.reset_step == 0
    assert rule.escape_frame == 100  # updates from agent step 21: healthy checks at frames 60, 80, 100
    assert rule.streak >= 3 and not rule.before
    assert model.num_timesteps == 160


def test_max_resets_caps_the_resets(tmp_path):
    # No update (learning_starts > budget): only the schedule of the rule is tested.
    model = tiny_model(learning_starts=1000, tensorboard_log=str(tmp_path))
    # An impossible threshold: every window ends without escape.
    rule = CollapseReset(window_frames=100, check_every_frames=20, threshold=1e9, max_resets=2)
    model.learn(200, callback=rule)
    assert rule.resets == 2 and rule.reset_frames == [100, 200] and not rule.escaped
    assert model.reset_step == 100 and model.num_timesteps == 200
    accumulator = EventAccumulator(glob.glob(str(tmp_path / "DrQv2_1" / "events.out.tfevents.*"))[0])
    accumulator.Reload()
    resets = accumulator.Scalars("collapse/reset_frame")
    assert [(e.step, e.value) for e in resets] == [(50, 100.0), (100, 200.0)]  # at agent steps 50 and 100
    assert accumulator.Scalars("collapse/resets")[-1].value == 2.0
    assert all(e.value == 0.0 for e in accumulator.Scalars("collapse/escaped"))


@pytest.mark.parametrize("metric", ["action_std", lambda model: model.actor.mlp1[0].bias.max().item() + 1.0])
def test_other_trigger_metrics(metric):
    model = tiny_model()
    collapse(model)
    rule = CollapseReset(**RULE, metric=metric, batch_size=16)
    model.learn(110, callback=rule)
    assert rule.resets == 1  # action std 0 (or bias + 1 < 0) on the collapsed actor
    before_reset = [value for frame, value in rule.history if frame <= 200 and value is not None]
    assert before_reset and max(before_reset) <= 1e-3


def test_reset_step_is_saved_and_restarts_with_learn(tmp_path):
    model = tiny_model()
    model.learn(30)
    model.reset_from_scratch()
    assert model.reset_step == 30 and model.replay_buffer.size() == 0
    model.save(tmp_path / "model.zip")
    loaded = DrQv2.load(tmp_path / "model.zip", env=RandomObservationEnv(PIXELS, action_repeat=2))
    assert loaded.reset_step == 30
    loaded.learn(10, reset_num_timesteps=True)
    assert loaded.reset_step == 0


def test_reset_rule_refuses_models_it_cannot_reset(tmp_path):
    model = PPO("MlpPolicy", RandomObservationEnv(gym.spaces.Box(-1, 1, (4,), np.float32)), n_steps=8, batch_size=8)
    with pytest.raises(TypeError, match="DrQv2 and on SB3's TD3, DDPG and SAC; PPO"):
        model.learn(10, callback=CollapseReset(metric=lambda model: 1.0))
    with pytest.raises(ValueError, match="layer='cnn0'"):
        tiny_model().learn(10, callback=CollapseReset(layer="cnn0"))
    with pytest.raises(ValueError, match="metric"):
        CollapseReset(metric="rank")
    with pytest.raises(ValueError, match="intervention must be one of reset, reset_actor, reset_mlp, redo"):
        CollapseReset(intervention="restart")
    # An events file of an older version (four columns) is not appended to.
    old = tmp_path / "collapse_events.csv"
    old.write_text("frame,step,event,resets\n200,100,reset,1\n")
    with pytest.raises(ValueError, match="has the columns frame,step,event,resets, not"):
        tiny_model().learn(10, callback=CollapseReset(events_path=old))
    assert old.read_text() == "frame,step,event,resets\n200,100,reset,1\n"


SB3_PIXELS = gym.spaces.Box(0, 255, (9, 36, 36), np.uint8)  # NatureCNN needs at least 36x36


def tiny_sb3(algo, seed=0, policy="CnnPolicy", **kwargs):
    space = SB3_PIXELS if policy == "CnnPolicy" else gym.spaces.Box(-1, 1, (5,), np.float32)
    env = RandomObservationEnv(space, gym.spaces.Box(-1, 1, (2,), np.float32), action_repeat=2)
    policy_kwargs = dict(net_arch=[32, 32])
    if policy == "CnnPolicy":
        policy_kwargs["features_extractor_kwargs"] = dict(features_dim=32)
    # DrQ-v2's learning rate: at TD3's 1e-3 the tiny actor saturates its tanh (zero gradients) within ~100 updates.
    params = dict(buffer_size=500, learning_starts=20, batch_size=8, seed=seed, policy_kwargs=policy_kwargs)
    params.update(learning_rate=1e-4)
    return algo(policy, env, **{**params, **kwargs})


def collapse_sb3(model):
    """Kill every mlp1 unit of an SB3 actor (mu[0] for TD3, latent_pi[0] for SAC)."""
    linear = model.actor.latent_pi[0] if isinstance(model, SAC) else model.actor.mu[0]
    with th.no_grad():
        linear.bias.fill_(-1e3)


@pytest.mark.parametrize("algo", [TD3, SAC])
def test_collapsed_sb3_actor_is_reset_from_scratch_then_escapes(algo, tmp_path):
    model = tiny_sb3(algo, tensorboard_log=str(tmp_path))
    initial = weights(model)
    collapse_sb3(model)
    rule = SpyReset(**RULE, events_path=tmp_path / "collapse_events.csv")
    model.learn(170, callback=rule)

    assert model.num_timesteps == 170
    # Stuck: mlp1's gradient norm is 0 at every check of the first window (updates from agent step 21).
    first_window = [value for frame, value in rule.history if frame <= 200]
    assert first_window[-1] == 0.0 and all(value is None or value <= 1e-3 for value in first_window)
    assert rule.resets == 1 and rule.reset_frames == [200]
    after = rule.after[0]
    assert after["step"] == 100 and model.reset_step == 100 and model.learning_starts == 120
    assert differ_everywhere(after["weights"], rule.before[0]) and differ_everywhere(after["weights"], initial)
    assert after["buffer_size"] == 0 and after["grad_norms"] == {}
    assert after["optimizer_states"] == [0, 0, 0] if algo is SAC else [0, 0]  # new optimizers (entropy's too)
    # Warm-up again: no update from the reset until learning_starts=20 agent steps were collected.
    assert rule.updates[100] == rule.updates[120] > 0 and rule.updates[130] > rule.updates[120]
    assert grad_norms_of(model)["mlp1"] > 1e-3  # recorded on the new optimizers
    assert rule.escaped and rule.escape_frame > 240
    with open(tmp_path / "collapse_events.csv") as file:
        rows = list(csv.DictReader(file))
    assert [(row["event"], row["frame"], row["intervention"]) for row in rows] == [
        ("reset", "200", "reset"),
        ("escape", str(rule.escape_frame), "reset"),
    ]
    assert "replay buffer emptied (99 transitions)" in rows[0]["detail"]
    accumulator = EventAccumulator(glob.glob(str(tmp_path / f"{algo.__name__}_1" / "events.out.tfevents.*"))[0])
    accumulator.Reload()
    assert [(e.step, e.value) for e in accumulator.Scalars("collapse/intervention/transitions_dropped")] == [
        (100, 99.0)
    ]

    # A new run from agent step 0: the warm-up has its length back.
    model.learn(10, callback=rule)
    assert model.reset_step == 0 and model.learning_starts == 20 and rule.resets == 0


@pytest.mark.parametrize("algo", [TD3, SAC])
def test_healthy_sb3_actor_escapes_and_is_never_reset(algo):
    model = tiny_sb3(algo, seed=1)
    rule = SpyReset(**RULE)
    model.learn(160, callback=rule)
    assert rule.escaped and rule.resets == 0 and not rule.before
    assert rule.escape_frame == 100  # updates from agent step 21: healthy checks at frames 60, 80, 100
    assert all(value > 1e-3 for frame, value in rule.history if value is not None)


@pytest.mark.parametrize("intervention", ["reset_actor", "reset_mlp", "redo", "shrink_perturb"])
def test_rule_applies_the_chosen_intervention(intervention, tmp_path):
    model = tiny_model(tensorboard_log=str(tmp_path))
    collapse(model)
    rule = CollapseReset(
        window_frames=200,
        check_every_frames=20,
        patience=3,
        max_resets=1,
        batch_size=16,
        intervention=intervention,
        events_path=tmp_path / "events.csv",
    )
    model.learn(110, callback=rule)  # the window ends at frame 200, agent step 100
    assert rule.resets == 1 and rule.reset_frames == [200] and rule.interventions[0].name == intervention
    assert model.replay_buffer.size() == model.num_timesteps == 110  # the buffer is kept
    assert model.reset_step == 0
    with open(tmp_path / "events.csv") as file:
        row = next(csv.DictReader(file))
    assert row["intervention"] == intervention and row["detail"] == rule.interventions[0].detail
    if intervention == "redo":  # every mlp1 unit of the collapsed actor is dormant
        assert len(rule.interventions[0].units["mlp1"]) == 32 and "mlp1 32/32" in row["detail"]
        assert model.actor.mlp1[0].bias.max() > -1.0
        # the rule's batch and sampler are given at each call: its config holds the constructor's arguments only
        assert rule.get_config()["intervention_kwargs"] == {} and "sampler" not in rule.get_config()
    accumulator = EventAccumulator(glob.glob(str(tmp_path / "DrQv2_1" / "events.out.tfevents.*"))[0])
    accumulator.Reload()
    assert accumulator.Scalars("collapse/intervention/weights_changed")[0].value > 0
