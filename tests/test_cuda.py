"""
What only a CUDA GPU can check (``pytest -m cuda``, run by ``benchmarks/gpu.sh``; skipped without a GPU): the update
on CUDA against the CPU's, the compiled update with CUDA graphs through resets, the gradient-norm recorder, ReDo and
channels_last on CUDA, conv-channel ReDo, a short training run through a collapse check and a checkpoint, resumed on
the CPU (pixels, and a state-observation run's pickled replay buffer), deterministic runs, the update clock on the
current device and on another one, and cuDNN's autotuner left to the user. Only the tests marked ``dmc`` render (the
train CLI on cartpole-balance): the others train on synthetic pixels, so that ``benchmarks/gpu.sh`` runs them where
rendering fails.
"""

from __future__ import annotations

import copy
import json
import os
import signal
import threading
import time

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium.spaces import Box
from stable_baselines3.common.monitor import Monitor

from sb3_collapse import DrQv2, make_dmc_env
from sb3_collapse.backends import configure_backends
from sb3_collapse.commands.train import main
from sb3_collapse.drqv2.encoders import PixelEncoder
from sb3_collapse.envs.replay import EpisodeReplay
from sb3_collapse.monitoring import MetricsBatchSampler, metrics
from sb3_collapse.monitoring.activations import collect_activations
from sb3_collapse.monitoring.interventions import encoder_channels, redo
from sb3_collapse.protocol import CHECKPOINTS_DIR, COLLAPSE_METRICS_CSV, EXIT_INTERRUPTED, RESULT_JSON
from sb3_collapse.run.checkpoints import ResumableCheckpoints, checkpoint_folders, load_checkpoint
from sb3_collapse.run.timing import LearnTimer
from tests.random_env import RandomObservationEnv

pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA GPU (benchmarks/gpu.sh runs these)"),
]


@pytest.fixture(autouse=True)
def _ieee_float32():
    """TF32 off: the CUDA update is compared with the CPU's in float32."""
    configure_backends(tf32=False)
    yield
    configure_backends()


def _pixel_model(device: str, **kwargs) -> DrQv2:
    """Synthetic pixels of cartpole-balance's shapes (9x48x48, a 1-d action): no rendering needed."""
    env = RandomObservationEnv(Box(0, 255, (9, 48, 48), np.uint8), Box(-1.0, 1.0, (1,), np.float32), 125, 8)
    return DrQv2(
        "CnnPolicy", env, buffer_size=300, learning_starts=20, batch_size=16, seed=3, stddev_schedule=0.4,
        device=device, policy_kwargs=dict(hidden_dim=32), replay_buffer_kwargs=dict(sampling="sb3"), **kwargs,
    )  # fmt: skip


def _same_start(source: DrQv2, target: DrQv2) -> None:
    target.policy.load_state_dict(source.policy.state_dict())
    for name in ("encoder", "actor", "critic"):
        state = copy.deepcopy(getattr(source, name).optimizer.state_dict())
        getattr(target, name).optimizer.load_state_dict(state)


def _update_on(model: DrQv2, data, seed: int = 0) -> None:
    moved = type(data)(*(None if x is None else x.to(model.device) for x in data))
    th.manual_seed(seed)
    th.cuda.manual_seed_all(seed)
    model._update(moved, moved.discounts, model.current_stddev)


@pytest.mark.parametrize("compile_update", [False, True])
def test_cuda_update_equals_the_cpu_update(compile_update):
    """The same update from the same weights, batch and random draws (drawn on the CPU and moved) on both devices."""
    cpu = _pixel_model("cpu")
    cpu.learn(40)
    gpu = _pixel_model("cuda", compile_update=compile_update)
    _same_start(cpu, gpu)
    data = cpu.replay_buffer.sample(16)

    def update_with_cpu_draws(model):  # the random draws of the CPU model, so that both updates use the same ones
        from sb3_collapse.drqv2 import drqv2 as module

        original = module.draw_shifts, module.exploration_noise
        generator = th.Generator().manual_seed(1)
        module.draw_shifts = lambda n, pad, device: th.randint(0, 2 * pad + 1, (n, 2), generator=generator).to(device)
        module.exploration_noise = lambda shape, std, clip, device: (
            (th.randn(shape, generator=generator) * std).clamp(-clip, clip).to(device)
        )
        try:
            _update_on(model, data)
        finally:
            module.draw_shifts, module.exploration_noise = original

    update_with_cpu_draws(cpu)
    update_with_cpu_draws(gpu)
    expected = dict(cpu.policy.named_parameters())
    for name, param in gpu.policy.named_parameters():
        assert param.device.type == "cuda"
        assert th.allclose(param.cpu(), expected[name], atol=1e-5, rtol=1e-4), name


def test_compiled_update_with_cuda_graphs_survives_resets():
    from torch._dynamo.eval_frame import _debug_get_cache_entry_list

    model = _pixel_model("cuda", compile_update=True)  # reduce-overhead: CUDA graphs
    model.learn(60)
    losses = (DrQv2._critic_loss, DrQv2._actor_loss)
    compiled = [len(_debug_get_cache_entry_list(loss.__code__)) for loss in losses]  # other tests' entries included
    assert all(count >= 1 for count in compiled)
    for _ in range(3):
        model.reset_from_scratch()
        model.learn(60, reset_num_timesteps=False)
    assert [len(_debug_get_cache_entry_list(loss.__code__)) for loss in losses] == compiled  # nothing compiled again
    assert all(th.isfinite(p).all() for p in model.policy.parameters())
    assert set(model.last_grad_norms) >= {"cnn1", "mlp1"}


def test_gradient_norm_recorder_on_cuda_equals_the_norms_of_the_gradients():
    model = _pixel_model("cuda")
    model.learn(40)
    recorded = model.last_grad_norms
    layers = model.policy.named_layers()
    for name in ("mlp0", "mlp1", "mlp2", "action"):  # the actor's optimizer stepped last on these gradients
        expected = metrics.gradient_norm(p.grad for p in layers[name].parameters())
        assert abs(recorded[name] - expected) <= 1e-5 * max(1.0, expected), name


def test_redo_and_channels_last_on_cuda():
    model = _pixel_model("cuda")
    model.learn(40)
    observations = np.stack([model.replay_buffer.sample(8).observations.cpu().numpy() for _ in range(2)]).reshape(
        16, *model.observation_space.shape
    )
    activations = collect_activations(model, observations, device="cuda")
    assert all(value.device.type == "cuda" for value in activations.values() if value.numel())
    encoder = model.policy.encoder
    nchw = PixelEncoder(model.observation_space, channels_last=False).to("cuda")
    nchw.load_state_dict(encoder.state_dict())
    batch = th.as_tensor(observations, device="cuda")
    with th.no_grad():
        a, b = (
            encoder.cnn4(encoder.cnn3(encoder.cnn2(encoder.cnn1(encoder.cnn0(batch))))),
            nchw.cnn4(nchw.cnn3(nchw.cnn2(nchw.cnn1(nchw.cnn0(batch))))),
        )
    assert a.is_contiguous(memory_format=th.channels_last) and th.allclose(a, b, atol=1e-5)
    with th.no_grad():
        for param in model.policy.named_layers()["mlp1"].parameters():
            param.mul_(0.0)  # mlp1's units become dead, hence dormant
    result = redo(model)
    assert result.scalars["units_recycled"] > 0
    assert all(th.isfinite(p).all() and p.device.type == "cuda" for p in model.policy.parameters())


FLAGS = [
    "--env", "cartpole-balance", "--frames", "4000", "--action-repeat", "8", "--size", "64", "--batch-size", "64",
    "--seed-frames", "800", "--eval-every-frames", "2000", "--eval-episodes", "1", "--checkpoint-every-frames", "800",
    "--collapse-metrics-every-frames", "800", "--collapse-metrics-batch", "64", "--reset-rule",
    "--reset-window-frames", "1600", "--no-progress-bar", "--replay-sampling", "sb3",
]  # fmt: skip


@pytest.mark.dmc
def test_cuda_run_through_a_collapse_check_and_a_checkpoint_resumes_on_the_cpu(tmp_path, capsys):
    run_dir = tmp_path / "run"

    def stop_after_two_checkpoints() -> None:
        deadline = time.time() + 300
        while time.time() < deadline:
            folders = checkpoint_folders(run_dir / CHECKPOINTS_DIR)
            if folders and int(folders[0].name.split("_")[1]) >= 200:  # frame 1,600: after a collapse check
                os.kill(os.getpid(), signal.SIGTERM)
                return
            time.sleep(0.05)

    watcher = threading.Thread(target=stop_after_two_checkpoints, daemon=True)
    watcher.start()
    assert main([*FLAGS, "--device", "cuda", "--run-dir", str(run_dir)]) == EXIT_INTERRUPTED
    watcher.join()
    assert (run_dir / COLLAPSE_METRICS_CSV).read_text().count("\n") >= 2  # the check ran on CUDA
    capsys.readouterr()
    assert main([*FLAGS, "--device", "cpu", "--run-dir", str(run_dir)]) == 0
    printed = capsys.readouterr().out
    assert "Resuming" in printed and "written on cuda" in printed
    result = json.loads((run_dir / RESULT_JSON).read_text())
    assert result["resumes"] == 1


@pytest.mark.dmc
def test_deterministic_cuda_runs_are_identical(tmp_path):
    weights = []
    for name in ("a", "b"):
        run_dir = tmp_path / name
        assert main([*FLAGS, "--frames", "2400", "--device", "cuda", "--deterministic", "--run-dir", str(run_dir)]) == 0
        from stable_baselines3.common.save_util import load_from_zip_file

        weights.append(load_from_zip_file(run_dir / "final_model.zip")[1]["policy"])
    configure_backends()
    assert weights[0].keys() == weights[1].keys()
    assert all(th.equal(weights[0][name], weights[1][name]) for name in weights[0])


def _synthetic_pixel_model(device: str, **kwargs) -> DrQv2:
    """A pixel model on random 9x36x36 frames (``RandomObservationEnv``): no rendering needed."""
    env = RandomObservationEnv(
        gym.spaces.Box(0, 255, (9, 36, 36), np.uint8), gym.spaces.Box(-1, 1, (2,), np.float32), action_repeat=2
    )
    return DrQv2(
        "CnnPolicy", env, buffer_size=300, learning_starts=20, batch_size=16, seed=3, device=device,
        policy_kwargs=dict(hidden_dim=32, feature_dim=16, encoder_kwargs=dict(channels=8)), **kwargs,
    )  # fmt: skip


@pytest.mark.parametrize("device", ["cuda:0", "cuda:1"])
def test_update_clock_counts_the_update_where_it_runs(device):
    """On the current device, and on another one (``cuda:1`` while ``cuda:0`` is current: both events of a round on
    ``cuda:1``'s stream, else ``elapsed_time`` raises at the first round)."""
    if th.device(device).index >= th.cuda.device_count():
        pytest.skip(f"needs {device}; {th.cuda.device_count()} GPU(s) here")
    with th.cuda.device(0):
        model, timer = _synthetic_pixel_model(device), LearnTimer()
        model.learn(200, callback=timer)
        assert th.cuda.current_device() == 0
    learning = timer.timings.learning
    assert model.device == th.device(device) and learning.updates > 0 and learning.update_s > 0
    assert learning.overhead_s >= -1e-3  # the device time moved from the overhead, never more than the round's time


def test_a_cuda_model_leaves_cudnns_autotuner_as_it_is_unless_asked():
    before = th.backends.cudnn.benchmark
    try:
        for benchmark in (False, True):
            th.backends.cudnn.benchmark = benchmark
            _synthetic_pixel_model("cuda")
            assert th.backends.cudnn.benchmark is benchmark
        th.backends.cudnn.benchmark = False
        _synthetic_pixel_model("cuda", cudnn_benchmark=True)
        assert th.backends.cudnn.benchmark
    finally:
        th.backends.cudnn.benchmark = before


def test_conv_channel_redo_on_cuda():
    """ReDo of ``cnn1``..``cnn4``'s channels on CUDA: the killed channels are recycled (new filters, bias 0), their
    outgoing weights (``cnn3``'s input channel, the trunks' columns of a ``cnn4`` channel) and Adam moments are zero,
    everything stays on the GPU and trains on."""
    model = _synthetic_pixel_model("cuda")
    model.learn(40)
    layers = {layer.name: layer for layer in encoder_channels(model)}
    with th.no_grad():  # dead channels: ReLU output 0 on every input
        layers["cnn2"].linear.bias[3] = -1e3
        layers["cnn4"].linear.bias[[1, 5]] = -1e3
    samples, _ = MetricsBatchSampler(0).sample_transitions(model, 16)
    result = redo(model, samples=samples, conv_channels=True)
    assert 3 in result.units["cnn2"] and {1, 5} <= set(result.units["cnn4"])
    assert layers["cnn2"].linear.bias[3].item() == 0.0 and layers["cnn4"].linear.bias[1].item() == 0.0
    assert (layers["cnn3"].linear.weight[:, list(result.units["cnn2"])] == 0).all()
    policy = model.policy
    columns = layers["cnn4"].consumer_columns(th.tensor(result.units["cnn4"], device="cuda"))
    for part in (policy.actor, policy.critic):
        trunk = part.trunk[0].weight
        assert (trunk[:, columns] == 0).all()
        state = part.optimizer.state[trunk]
        assert (state["exp_avg"][:, columns] == 0).all() and (state["exp_avg_sq"][:, columns] == 0).all()
    assert all(p.device.type == "cuda" for p in policy.parameters())
    model.learn(20, reset_num_timesteps=False)
    assert all(th.isfinite(p).all() for p in policy.parameters())


def test_a_state_observation_run_checkpointed_on_cuda_resumes_on_the_cpu(tmp_path):
    """The pickled n-step replay buffer of a state-observation run written on CUDA samples on the CPU after a
    resume, and the updates run."""

    def state_model(device: str) -> DrQv2:
        env = EpisodeReplay(Monitor(make_dmc_env("cartpole-balance", seed=0, action_repeat=8, obs_type="state")))
        return DrQv2(
            "MlpPolicy", env, learning_starts=4, batch_size=4, buffer_size=200, seed=0, device=device,
            policy_kwargs=dict(hidden_dim=16, feature_dim=4),
        )  # fmt: skip

    state_model("cuda").learn(12, callback=ResumableCheckpoints(tmp_path, every_frames=80))
    resumed = state_model("cpu")
    checkpoints = ResumableCheckpoints(tmp_path, every_frames=80)
    checkpoints.init_callback(resumed)
    checkpoint = load_checkpoint(tmp_path)
    assert checkpoint.state["device"].startswith("cuda") and checkpoint.state["replay_buffer"].device.type == "cuda"
    checkpoints.resume(checkpoint)
    assert resumed.replay_buffer.device == th.device("cpu")
    updates = resumed._n_updates
    resumed.learn(8, reset_num_timesteps=False)
    assert resumed._n_updates > updates
