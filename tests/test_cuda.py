"""
What only a CUDA GPU can check (``pytest -m cuda``, run by ``benchmarks/gpu.sh``; skipped without a GPU): the update
on CUDA against the CPU's, the compiled update with CUDA graphs through resets, the gradient-norm recorder, ReDo and
channels_last on CUDA, a short training run through a collapse check and a checkpoint, resumed on the CPU, and
deterministic runs. Only the tests marked ``dmc`` render (the train CLI on cartpole-balance): the others train on
synthetic pixels, so that ``benchmarks/gpu.sh`` runs them where rendering fails.
"""

from __future__ import annotations

import copy
import json
import os
import signal
import threading
import time

import numpy as np
import pytest
import torch as th
from gymnasium.spaces import Box

from sb3_collapse import DrQv2
from sb3_collapse.backends import configure_backends
from sb3_collapse.drqv2.encoders import PixelEncoder
from sb3_collapse.envs.synthetic import RandomObservationEnv
from sb3_collapse.monitoring import metrics
from sb3_collapse.monitoring.activations import collect_activations
from sb3_collapse.monitoring.interventions import redo
from sb3_collapse.protocol import CHECKPOINTS_DIR, COLLAPSE_METRICS_CSV, EXIT_INTERRUPTED, RESULT_JSON
from sb3_collapse.run.checkpoints import checkpoint_folders
from sb3_collapse.run.timing import LearnTimer
from sb3_collapse.train import main

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
    for _ in range(3):
        model.reset_from_scratch()
        model.learn(60, reset_num_timesteps=False)
    for loss in (DrQv2._critic_loss, DrQv2._actor_loss):
        assert len(_debug_get_cache_entry_list(loss.__code__)) == 1, loss.__name__
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


def test_update_clock_counts_the_update_where_it_runs():
    model, timer = _pixel_model("cuda"), LearnTimer()
    model.learn(200, callback=timer)
    learning = timer.timings.learning
    assert learning.updates > 0 and learning.update_s > 0
    assert learning.overhead_s >= -1e-3  # the device time moved from the overhead, never more than the round's time
