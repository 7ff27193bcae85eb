"""
``FrameStackReplayBuffer(sampling="drqv2")`` against an independent implementation of DrQ-v2's reference rule
(facebookresearch/drqv2 ``replay_buffer.py``): only transitions of finished episodes are sampled, an n-step
return never starts in an episode's last ``n - 1`` transitions, and it sums exactly ``n`` rewards.
"""

from dataclasses import dataclass

import numpy as np
import pytest
from gymnasium import spaces
from hypothesis import given, settings
from hypothesis import strategies as st

from sb3_collapse.drqv2 import FrameStackReplayBuffer

FRAME_STACK, GAMMA = 2, 0.9


@dataclass
class Step:
    """One transition of one env, as the reference stores it in its episode."""

    obs: np.ndarray
    next_obs: np.ndarray
    action: np.ndarray
    reward: float
    terminated: bool
    truncated: bool
    episode: int
    index: int  # in its episode


def frame(number: int) -> np.ndarray:
    """A unique 1x2x2 uint8 frame for each number."""
    return np.array([number % 256, number // 256 % 256, number // 65536, 7], dtype=np.uint8).reshape(1, 2, 2)


def simulate(rng: np.random.Generator, n_envs: int, total_steps: int, max_length: int) -> list[list[Step]]:
    """Random episodes per env: lengths 1..max_length, each ending by termination or time limit (or unfinished)."""
    streams, counter = [], 1
    for env in range(n_envs):
        steps: list[Step] = []
        episode = 0
        while len(steps) < total_steps:
            length = int(rng.integers(1, max_length + 1))
            terminated_end = bool(rng.random() < 0.4)
            frames = [frame(counter + i) for i in range(length + FRAME_STACK)]
            counter += length + FRAME_STACK
            for index in range(length):
                last = index == length - 1
                steps.append(
                    Step(
                        obs=np.concatenate(frames[index : index + FRAME_STACK]),
                        next_obs=np.concatenate(frames[index + 1 : index + 1 + FRAME_STACK]),
                        action=rng.uniform(-1, 1, size=1).astype(np.float32),
                        reward=float(rng.normal()),
                        terminated=last and terminated_end,
                        truncated=last and not terminated_end,
                        episode=episode,
                        index=index,
                    )
                )
            episode += 1
        streams.append(steps[:total_steps])  # the last episode may be cut: unfinished
    return streams


def episode_lengths(stream: list[Step]) -> dict[int, int]:
    """Lengths of the episodes that finished within the stream."""
    return {s.episode: s.index + 1 for s in stream if s.terminated or s.truncated}


def reference_samples(streams: list[list[Step]], capacity: int, n_steps: int) -> dict[tuple[int, int], dict]:
    """
    The reference's sampleable transitions among those the ring still holds (the last ``capacity`` per env), by
    ``(ring position, env)``, with what it returns for each: obs, action, n-step reward, discount, next_obs, done.
    """
    expected = {}
    for env, stream in enumerate(streams):
        lengths = episode_lengths(stream)
        for t in range(max(0, len(stream) - capacity), len(stream)):
            step = stream[t]
            length = lengths.get(step.episode)
            if length is None or step.index > length - n_steps:  # unfinished, or in the last n-1 steps
                continue
            window = stream[t : t + n_steps]
            reward = sum(GAMMA**i * s.reward for i, s in enumerate(window))
            expected[(t % capacity, env)] = {
                "obs": step.obs, "action": step.action, "reward": reward, "discount": GAMMA**n_steps,
                "next_obs": window[-1].next_obs, "done": float(window[-1].terminated),
            }  # fmt: skip
    return expected


def fill(streams: list[list[Step]], capacity: int, n_steps: int) -> FrameStackReplayBuffer:
    n_envs = len(streams)
    buffer = FrameStackReplayBuffer(
        capacity * n_envs,
        spaces.Box(0, 255, (FRAME_STACK, 2, 2), np.uint8),
        spaces.Box(-1, 1, (1,), np.float32),
        device="cpu",
        n_envs=n_envs,
        n_steps=n_steps,
        gamma=GAMMA,
        frame_stack=FRAME_STACK,
        min_episode_length=1,  # frames of every stored transition kept: the test is about the sampling rule
        sampling="drqv2",
    )
    for t in range(len(streams[0])):
        steps = [stream[t] for stream in streams]
        buffer.add(
            np.stack([s.obs for s in steps]),
            np.stack([s.next_obs for s in steps]),
            np.stack([s.action for s in steps]),
            np.array([s.reward for s in steps], dtype=np.float32),
            np.array([s.terminated or s.truncated for s in steps]),
            [{"TimeLimit.truncated": s.truncated} for s in steps],
        )
    return buffer


@settings(max_examples=150, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n_envs=st.integers(1, 3),
    capacity=st.integers(4, 30),
    total_steps=st.integers(1, 70),  # past the capacity: wrap-around
    max_length=st.integers(1, 12),
    n_steps=st.integers(1, 4),
)
def test_drqv2_sampling_matches_the_reference_rule(seed, n_envs, capacity, total_steps, max_length, n_steps):
    streams = simulate(np.random.default_rng(seed), n_envs, total_steps, max_length)
    buffer = fill(streams, capacity, n_steps)
    expected = reference_samples(streams, capacity, n_steps)

    stored = min(total_steps, capacity)
    positions = np.repeat(np.arange(stored), n_envs)
    envs = np.tile(np.arange(n_envs), stored)
    sampleable = buffer.is_sampleable(positions, envs)
    assert {(int(p), int(e)) for p, e, ok in zip(positions, envs, sampleable) if ok} == set(expected)
    assert buffer.ready_to_sample == bool(expected)  # finished episodes, all shorter than n_steps: not ready

    if not expected:
        if any(episode_lengths(stream) for stream in streams):  # sample() says why, never loops
            with pytest.raises(ValueError, match="No transition of the replay buffer can be sampled"):
                buffer.sample(4)
        return
    keys = sorted(expected)
    batch = buffer._get_samples(np.array([k[0] for k in keys]), env_indices=np.array([k[1] for k in keys]))
    for i, key in enumerate(keys):
        want = expected[key]
        np.testing.assert_array_equal(batch.observations[i].numpy(), want["obs"])
        np.testing.assert_array_equal(batch.next_observations[i].numpy(), want["next_obs"])
        np.testing.assert_allclose(batch.actions[i].numpy(), want["action"])
        assert batch.rewards[i].item() == pytest.approx(want["reward"], rel=1e-5, abs=1e-5)
        assert batch.discounts[i].item() == pytest.approx(want["discount"], rel=1e-6)
        assert batch.dones[i].item() == want["done"]

    # sample() draws only those transitions, and all of them in time.
    np.random.seed(seed % 2**31)
    drawn = buffer.sample(512)
    allowed = {want["obs"].tobytes() for want in expected.values()}
    assert {obs.numpy().tobytes() for obs in drawn.observations} <= allowed
    if len(expected) <= 8:
        assert {obs.numpy().tobytes() for obs in drawn.observations} == allowed


def test_sampling_must_be_known():
    with pytest.raises(ValueError, match="sampling must be one of 'sb3', 'drqv2', got 'reference'"):
        FrameStackReplayBuffer(
            16,
            spaces.Box(0, 255, (6, 2, 2), np.uint8),
            spaces.Box(-1, 1, (1,), np.float32),
            frame_stack=2,
            sampling="reference",
        )
