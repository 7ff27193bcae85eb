"""
CUDA readiness, checked as far as a CPU allows (the CUDA-only checks are in tests marked ``cuda``, run by
``benchmarks/gpu.sh``): tensors made on their inputs' device, checkpoints of CPU tensors whatever the device,
the CUDA generator of the model's device, backend settings, resets that keep a compiled update, gradient norms
in a handful of kernels, the update timed where it runs.
"""

from __future__ import annotations

import inspect
import json
import os
import pickle
import signal
import threading
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.monitor import Monitor
from torch.overrides import TorchFunctionMode

import sb3_collapse
from sb3_collapse import CollapseMetrics, DrQv2
from sb3_collapse.backends import BackendSettings, configure_backends, current_backends
from sb3_collapse.commands.train import main
from sb3_collapse.common.grad_norms import GradNormRecorder
from sb3_collapse.envs.replay import EpisodeReplay
from sb3_collapse.errors import InputError, ParameterError
from sb3_collapse.monitoring import metrics
from sb3_collapse.monitoring.interventions import INTERVENTIONS, redo
from sb3_collapse.probe.omp import omp_path
from sb3_collapse.protocol import CHECKPOINT_STATE, CHECKPOINTS_DIR, CONFIG_JSON, EXIT_INTERRUPTED, RESULT_JSON
from sb3_collapse.run.checkpoints import (
    ResumableCheckpoints,
    _cuda_rng_state,
    _restore_cuda_rng_state,
    checkpoint_folders,
    load_checkpoint,
    tensors_to,
)
from sb3_collapse.run.timing import PhaseTime, UpdateClock
from tests.random_env import RandomObservationEnv

PACKAGE = str(Path(sb3_collapse.__file__).parent)
FACTORIES = {
    th.tensor,
    th.zeros,
    th.ones,
    th.empty,
    th.full,
    th.arange,
    th.rand,
    th.randn,
    th.randint,
    th.linspace,
    th.eye,
    th.randperm,
    th.as_tensor,
}


def _package_caller() -> str | None:
    """``file:line`` of the package's code that called the torch function being run (``None``: another caller)."""
    caller = inspect.currentframe().f_back.f_back
    while caller is not None and caller.f_code.co_filename.startswith(str(Path(th.__file__).parent)):
        caller = caller.f_back
    if caller is None or not caller.f_code.co_filename.startswith(PACKAGE):
        return None
    return f"{caller.f_code.co_filename}:{caller.f_lineno}"


class DeviceAudit(TorchFunctionMode):
    """Records every tensor factory called from the package's code without ``device=`` (it would make a CPU tensor)."""

    def __init__(self) -> None:
        super().__init__()
        self.found: list[str] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in FACTORIES and "device" not in kwargs:
            takes_device = func is th.as_tensor and args and isinstance(args[0], th.Tensor)  # keeps its device
            caller = _package_caller()
            if caller is not None and not takes_device:
                self.found.append(f"{func.__name__} at {caller}")
        return func(*args, **kwargs)


class DefaultDtypeAudit(TorchFunctionMode):
    """Records every tensor factory called from the package's code that made a tensor of torch's default dtype
    without ``dtype=`` (under a float64 default: a float64 tensor among float32 ones)."""

    def __init__(self) -> None:
        super().__init__()
        self.found: list[str] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        result = func(*args, **kwargs)
        if func in FACTORIES and "dtype" not in kwargs and getattr(result, "dtype", None) == th.get_default_dtype():
            from_data = func in (th.as_tensor, th.tensor) and args and isinstance(args[0], (th.Tensor, np.ndarray))
            caller = _package_caller()
            if caller is not None and not from_data:  # an array or tensor keeps its dtype
                self.found.append(f"{func.__name__} at {caller}")
        return result


def _tiny_model(run_dir: Path) -> tuple[DrQv2, EpisodeReplay]:
    env = EpisodeReplay(sb3_collapse.make_dmc_env("cartpole-balance", seed=0, action_repeat=8, size=36))
    model = DrQv2(
        "CnnPolicy", env, learning_starts=4, batch_size=4, buffer_size=200, seed=0,
        policy_kwargs=dict(hidden_dim=16, feature_dim=4), replay_buffer_kwargs=dict(sampling="sb3"),
    )  # fmt: skip
    return model, env


def _tiny_drqv2(**kwargs) -> DrQv2:
    return DrQv2(
        "MlpPolicy", gym.make("Pendulum-v1"), learning_starts=20, batch_size=8, buffer_size=200, seed=0,
        policy_kwargs=dict(hidden_dim=16, feature_dim=8), **kwargs,
    )  # fmt: skip


def test_the_audit_finds_a_tensor_made_without_a_device():
    """The audit itself: the mistake of the issue (a CPU threshold tensor next to device values) is found."""

    def old_effective_rank(s: th.Tensor, delta: float) -> int:  # the former metrics._effective_rank
        cumulative = th.cumsum(s, 0) / s.sum()
        return int(th.searchsorted(cumulative, th.tensor([1.0 - delta], dtype=cumulative.dtype))[0]) + 1

    audit = DeviceAudit()
    old_effective_rank.__code__ = old_effective_rank.__code__.replace(co_filename=f"{PACKAGE}/fake.py")
    with audit:
        old_effective_rank(th.tensor([3.0, 2.0, 1.0], device="cpu"), 0.01)
    assert audit.found == [f"tensor at {PACKAGE}/fake.py:{old_effective_rank.__code__.co_firstlineno + 2}"]


def test_metrics_callbacks_interventions_and_probe_make_tensors_on_their_inputs_device():
    """Every tensor that metric, callback, intervention and probe code makes takes ``device=`` (or an input's)."""
    audit = DeviceAudit()
    generator = th.Generator().manual_seed(0)
    dense = th.relu(th.randn(32, 20, generator=generator))
    conv = th.relu(th.randn(16, 4, 5, 5, generator=generator))
    with audit:
        for activations in (dense, conv):
            metrics.layer_metrics(activations)
            metrics.effective_rank(activations)
            metrics.numerical_rank(activations)
            metrics.dormant_units(activations)
        metrics.gradient_norm([th.ones(3), None])
        omp_path(th.randn(40, 12, generator=generator), th.randn(40, 2, generator=generator), max_atoms=4)
        model, _ = _tiny_model(Path("unused"))  # pixels: convolutional channels too
        model.learn(60, callback=CollapseMetrics(check_every_frames=160, batch_size=16))
        for intervention in INTERVENTIONS.values():
            intervention(model)
        model.learn(30, reset_num_timesteps=False)
    assert audit.found == []


@pytest.fixture
def _float64_default():
    before = th.get_default_dtype()
    th.set_default_dtype(th.float64)
    try:
        yield
    finally:
        th.set_default_dtype(before)


@pytest.mark.usefixtures("_float64_default")
@pytest.mark.parametrize("policy", ["CnnPolicy", "MlpPolicy"])
def test_drqv2_trains_under_a_float64_default_dtype(policy):
    """``torch.set_default_dtype(torch.float64)`` in the user's process: the networks stay float32 (SB3's observations
    and replay samples are), and the updates, gradient norms, collapse metrics and interventions run, making no
    tensor of the default dtype."""
    pixels = policy == "CnnPolicy"
    space = gym.spaces.Box(0, 255, (9, 36, 36), np.uint8) if pixels else gym.spaces.Box(-1, 1, (5,), np.float32)
    env = RandomObservationEnv(space, gym.spaces.Box(-1, 1, (2,), np.float32), action_repeat=2)
    audit = DefaultDtypeAudit()
    with audit:
        model = DrQv2(
            policy, env, learning_starts=10, batch_size=8, buffer_size=200, seed=0,
            policy_kwargs=dict(hidden_dim=16, feature_dim=8),
        )  # fmt: skip
        metrics_callback = CollapseMetrics(check_every_frames=20, batch_size=16)
        model.learn(40, callback=metrics_callback)
        assert model._n_updates > 0 and metrics_callback.last_metrics
        assert set(model.last_grad_norms) == set(model.policy.named_layers()) - {"cnn0"}
        redo(model, batch_size=16, conv_channels=pixels)
        for intervention in INTERVENTIONS.values():
            intervention(model)
        updates = model._n_updates
        model.learn(20, reset_num_timesteps=False)
    assert model._n_updates > updates
    assert {param.dtype for param in model.policy.parameters()} == {th.float32}
    assert audit.found == []


def test_effective_rank_is_the_smallest_k_reaching_one_minus_delta():
    s = th.tensor([4.0, 3.0, 2.0, 1.0], dtype=th.float64)  # partial sums / 10: 0.4, 0.7, 0.9, 1.0
    assert metrics._effective_rank(s, 0.3) == 2.0  # 0.7 >= 0.7
    assert metrics._effective_rank(s, 0.25) == 3.0
    assert metrics._effective_rank(s, 0.0) == 4.0
    assert metrics._effective_rank(th.zeros(3, dtype=th.float64), 0.01) == 0.0


def test_tensors_to_moves_nested_tensors_and_keeps_the_rest():
    state = {"a": [th.ones(2), (th.zeros(1), 3)], "b": "text", "c": {"d": th.arange(3)}}
    moved = tensors_to(state, "meta")
    assert moved["a"][0].device.type == "meta" and moved["a"][1][0].device.type == "meta"
    assert moved["c"]["d"].device.type == "meta" and moved["a"][1][1] == 3 and moved["b"] == "text"
    assert isinstance(moved["a"][1], tuple) and state["a"][0].device.type == "cpu"  # the original is unchanged


def test_checkpoint_state_holds_cpu_tensors_only_and_restores_them_on_the_models_device(tmp_path):
    model, _ = _tiny_model(tmp_path)
    model.learn(12, callback=ResumableCheckpoints(tmp_path, every_frames=80))
    assert model.update_stats.sums  # statistics not logged yet: device tensors of the model
    with (checkpoint_folders(tmp_path)[0] / CHECKPOINT_STATE).open("rb") as file:
        state = pickle.load(file)

    def tensors(value):
        if isinstance(value, th.Tensor):
            yield value
        elif isinstance(value, dict):
            for item in value.values():
                yield from tensors(item)
        elif isinstance(value, (list, tuple)):
            for item in value:
                yield from tensors(item)

    found = list(tensors(state))
    assert found and all(tensor.device.type == "cpu" and not tensor.requires_grad for tensor in found)
    assert state["device"] == "cpu" and state["rng"]["cuda"] is None  # no CUDA generator off CUDA

    resumed, _ = _tiny_model(tmp_path)
    checkpoints = ResumableCheckpoints(tmp_path, every_frames=80)
    checkpoints.init_callback(resumed)
    checkpoint = load_checkpoint(tmp_path)
    checkpoint.state["device"] = "cuda:0"  # as written on a GPU
    _, notes = checkpoints.resume(checkpoint)
    assert any("written on cuda:0 and the run resumes on cpu" in note and "not bit for bit" in note for note in notes)
    assert all(value.device == resumed.device for value in resumed.update_stats.sums.values())
    assert resumed.update_stats.sums.keys() == model.update_stats.sums.keys()
    assert resumed.update_stats.count > 0  # the updates after the checkpoint's last dump


def test_a_pickled_replay_buffer_written_on_cuda_samples_on_the_resuming_models_device(tmp_path):
    """A state-observation run (SB3's n-step buffer, pickled whole into the checkpoint) written on ``cuda:0``: the
    resumed buffer samples onto the CPU model's device and the updates run."""

    def state_model() -> DrQv2:
        env = EpisodeReplay(
            Monitor(sb3_collapse.make_dmc_env("cartpole-balance", seed=0, action_repeat=8, obs_type="state"))
        )
        return DrQv2(
            "MlpPolicy", env, learning_starts=4, batch_size=4, buffer_size=200, seed=0,
            policy_kwargs=dict(hidden_dim=16, feature_dim=4),
        )  # fmt: skip

    model = state_model()
    model.learn(12, callback=ResumableCheckpoints(tmp_path, every_frames=80))
    resumed = state_model()
    checkpoints = ResumableCheckpoints(tmp_path, every_frames=80)
    checkpoints.init_callback(resumed)
    checkpoint = load_checkpoint(tmp_path)
    assert "pickle" in checkpoint.info["replay"] and checkpoint.state["replay_buffer"].device == th.device("cpu")
    checkpoint.state["replay_buffer"].device, checkpoint.state["device"] = th.device("cuda:0"), "cuda:0"  # a GPU's
    checkpoint.state = pickle.loads(pickle.dumps(checkpoint.state))  # read back where there is no GPU
    checkpoints.resume(checkpoint)
    assert resumed.replay_buffer.device == resumed.device == th.device("cpu")
    assert resumed.replay_buffer.sample(4).observations.device == th.device("cpu")
    updates = resumed._n_updates
    resumed.learn(8, reset_num_timesteps=False)
    assert resumed._n_updates > updates


def test_cuda_generator_of_the_models_device_is_saved_and_restored_on_the_resuming_device(monkeypatch):
    calls = []
    monkeypatch.setattr(th.cuda, "is_available", lambda: True)
    monkeypatch.setattr(th.cuda, "current_device", lambda: 0)
    monkeypatch.setattr(th.cuda, "get_rng_state", lambda index: th.full((4,), index, dtype=th.uint8))
    monkeypatch.setattr(th.cuda, "set_rng_state", lambda state, index: calls.append((state.tolist(), index)))
    saved = _cuda_rng_state(th.device("cuda:3"))  # written by a model on the fourth GPU
    assert saved["device"] == 3 and saved["state"].tolist() == [3, 3, 3, 3]
    _restore_cuda_rng_state(saved, th.device("cuda"))  # resumed where one GPU is visible
    _restore_cuda_rng_state({"device": 0, "state": th.full((4,), 7, dtype=th.uint8)}, th.device("cuda:1"))
    _restore_cuda_rng_state(saved, th.device("cpu"))  # resumed on the CPU: nothing to restore
    assert calls == [([3, 3, 3, 3], 0), ([7, 7, 7, 7], 1)]
    assert _cuda_rng_state(th.device("cpu")) is None


@pytest.fixture
def _restore_backends():
    before = current_backends(), th.backends.cudnn.benchmark, th.backends.cudnn.deterministic
    yield
    configure_backends(tf32=before[0].tf32, deterministic=before[0].deterministic)
    th.backends.cudnn.benchmark, th.backends.cudnn.deterministic = before[1], before[2]


@pytest.mark.usefixtures("_restore_backends")
def test_backend_settings_are_applied_and_checked(monkeypatch):
    monkeypatch.delenv("CUBLAS_WORKSPACE_CONFIG", raising=False)
    th.backends.cudnn.benchmark = True
    assert configure_backends(tf32=False, deterministic=True) == current_backends()
    assert current_backends().deterministic and not current_backends().tf32
    assert th.are_deterministic_algorithms_enabled() and th.backends.cudnn.deterministic
    assert not th.backends.cudnn.benchmark and os.environ["CUBLAS_WORKSPACE_CONFIG"] == ":4096:8"
    configure_backends(tf32=True, deterministic=False)
    assert current_backends().tf32 and not th.are_deterministic_algorithms_enabled()
    with pytest.raises(TypeError, match="deterministic must be True or False"):
        configure_backends(deterministic="yes")  # type: ignore[arg-type]


@pytest.mark.usefixtures("_restore_backends")
def test_tf32_legacy_and_new_flags_agree_and_can_be_read():
    """After configure_backends, torch's legacy TF32 flags (which torch's compiler reads on CUDA) and its new
    ``fp32_precision`` ones say the same and can be read, even from a state that mixed the two APIs; the CPU's
    (oneDNN's) flags are left alone. The flags are process-wide: no GPU needed."""
    new_api = hasattr(th.backends.cuda.matmul, "fp32_precision")  # torch >= 2.9

    def mkldnn() -> tuple:
        return (th.backends.mkldnn.fp32_precision, th.backends.mkldnn.matmul.fp32_precision) if new_api else ()

    cpu_flags = mkldnn()
    for tf32 in (True, False, True, False):
        if new_api:  # the new API alone, the opposite way: torch then refuses to read a legacy flag
            th.backends.cuda.matmul.fp32_precision = "ieee" if tf32 else "tf32"
            th.backends.cudnn.conv.fp32_precision = "ieee" if tf32 else "tf32"
        configure_backends(tf32=tf32)
        assert th.backends.cuda.matmul.allow_tf32 is tf32 and th.backends.cudnn.allow_tf32 is tf32
        assert th.get_float32_matmul_precision() == ("high" if tf32 else "highest")
        if new_api:
            precision = "tf32" if tf32 else "ieee"
            assert th.backends.cuda.matmul.fp32_precision == th.backends.cudnn.conv.fp32_precision == precision
        assert current_backends().tf32 is tf32
        assert mkldnn() == cpu_flags


def _process_settings() -> tuple:
    """torch's process-wide flags that a training run sets (``sb3_collapse.backends``), and cuBLAS's workspace."""
    return (
        current_backends(),  # TF32 of the matmuls, deterministic algorithms
        th.backends.cudnn.conv.fp32_precision if hasattr(th.backends.cudnn, "conv") else th.backends.cudnn.allow_tf32,
        th.backends.cudnn.benchmark,
        th.backends.cudnn.deterministic,
        th.are_deterministic_algorithms_enabled(),
        os.environ.get("CUBLAS_WORKSPACE_CONFIG"),
    )


def _fake_cuda_setup(monkeypatch, **kwargs) -> DrQv2:
    """A DrQv2 whose ``_setup_model`` runs as on CUDA, without a GPU (the flags only: no tensor goes to CUDA)."""
    monkeypatch.setattr(th.cuda, "is_available", lambda: True)
    model = _tiny_drqv2(_init_setup_model=False, **kwargs)
    model.device = th.device("cuda")
    monkeypatch.setattr(type(model), "_create_aliases", lambda self: None)
    monkeypatch.setattr(type(model), "_index_grad_layers", lambda self: None)
    monkeypatch.setattr(
        "stable_baselines3.common.off_policy_algorithm.OffPolicyAlgorithm._setup_model", lambda self: None
    )
    model.policy = type("P", (), {"exploration_std": 0.0})()
    return model


@pytest.mark.usefixtures("_restore_backends")
def test_building_a_drqv2_leaves_the_process_wide_settings_unchanged(monkeypatch):
    """Neither a CPU model (pixels and states) nor a CUDA one changes torch's process-wide flags or cuBLAS's
    workspace, whatever they hold; ``cudnn_benchmark=True`` turns cuDNN's autotuner on for a CUDA model only, and
    not under deterministic algorithms."""
    monkeypatch.delenv("CUBLAS_WORKSPACE_CONFIG", raising=False)
    for benchmark in (False, True):
        th.backends.cudnn.benchmark = benchmark
        before = _process_settings()
        _tiny_drqv2()
        _tiny_model(Path("unused"))
        _tiny_drqv2(cudnn_benchmark=True)  # on the CPU: nothing to tune
        assert _process_settings() == before
    th.backends.cudnn.benchmark = False
    before = _process_settings()
    _fake_cuda_setup(monkeypatch)._setup_model()
    assert _process_settings() == before
    for deterministic, benchmark in ((True, False), (False, True)):
        configure_backends(deterministic=deterministic)
        th.backends.cudnn.benchmark = False
        _fake_cuda_setup(monkeypatch, cudnn_benchmark=True)._setup_model()
        assert th.backends.cudnn.benchmark is benchmark
    with pytest.raises(ParameterError, match="cudnn_benchmark must be True or False, got 1"):
        _tiny_drqv2(cudnn_benchmark=1)


@pytest.mark.usefixtures("_restore_backends")
def test_the_train_command_sets_the_process_wide_settings_before_it_builds_the_model(monkeypatch, tmp_path):
    """``--deterministic`` or not, the train command (and so every sweep trial) sets the flags before the model."""
    seen = []

    def build(*args, **kwargs):
        seen.append(_process_settings())
        raise InputError("stop before building anything")

    monkeypatch.setattr("sb3_collapse.run.runner.build_envs_and_model", build)
    monkeypatch.delenv("CUBLAS_WORKSPACE_CONFIG", raising=False)
    flags = ["--env", "cartpole-balance", "--run-dir", str(tmp_path / "run")]
    for extra in (["--no-tf32", "--deterministic"], []):
        th.backends.cudnn.benchmark = not extra
        with pytest.raises(SystemExit):
            main([*flags, *extra])
    deterministic, default = seen
    assert deterministic[0] == BackendSettings(tf32=False, deterministic=True) and deterministic[2:] == (
        False, True, True, ":4096:8"
    )  # fmt: skip
    assert default[0] == BackendSettings(tf32=True, deterministic=False) and default[2:5] == (True, False, False)


def test_train_records_the_backend_settings_and_a_run_resumes_with_another_thread_count(tmp_path, capsys):
    """A run stopped by SIGTERM resumes with another ``--torch-threads`` (another device is the GPU script's)."""
    run_dir = tmp_path / "run"
    flags = [
        "--env", "cartpole-balance", "--frames", "800", "--action-repeat", "20", "--size", "36", "--hidden-dim", "16",
        "--feature-dim", "8", "--batch-size", "8", "--seed-frames", "200", "--eval-every-frames", "0",
        "--checkpoint-every-frames", "200", "--collapse-metrics-every-frames", "0", "--no-progress-bar",
        "--replay-sampling", "sb3", "--run-dir", str(run_dir), "--no-tf32", "--deterministic",
    ]  # fmt: skip
    threads = th.get_num_threads()

    def stop_after_first_checkpoint() -> None:
        deadline = time.time() + 120
        while time.time() < deadline and not checkpoint_folders(run_dir / CHECKPOINTS_DIR):
            time.sleep(0.02)
        os.kill(os.getpid(), signal.SIGTERM)

    try:
        watcher = threading.Thread(target=stop_after_first_checkpoint, daemon=True)
        watcher.start()
        assert main([*flags, "--torch-threads", "2"]) == EXIT_INTERRUPTED
        watcher.join()
        assert main([*flags, "--torch-threads", "1"]) == 0
    finally:
        th.set_num_threads(threads)
        configure_backends()
    assert "Resuming" in capsys.readouterr().out
    config = json.loads((run_dir / CONFIG_JSON).read_text())
    assert config["tf32"] is False and config["deterministic"] is True
    assert json.loads((run_dir / RESULT_JSON).read_text())["resumes"] == 1


def test_reset_keeps_the_parameter_tensors_and_draws_the_fresh_weights(tmp_path):
    model = _tiny_drqv2()
    model.learn(40)
    before = {name: param for name, param in model.policy.named_parameters()}
    pointers = {name: param.data_ptr() for name, param in before.items()}
    rng = th.get_rng_state()
    model.reset_from_scratch()
    after = dict(model.policy.named_parameters())
    assert all(after[name] is before[name] and after[name].data_ptr() == pointers[name] for name in before)
    th.set_rng_state(rng)  # the same draws, on a policy built anew: the weights of the reset
    fresh = _tiny_drqv2(_init_setup_model=False)
    fresh._setup_lr_schedule()
    rebuilt = model.policy_class(model.observation_space, model.action_space, fresh.lr_schedule, **model.policy_kwargs)
    th.set_rng_state(rng)
    rebuilt._build(fresh.lr_schedule)
    assert all(th.equal(after[name], param) for name, param in rebuilt.named_parameters())
    optimizers = model.policy.optimizers
    assert all(not optimizer.state for optimizer in optimizers)  # empty Adam state
    assert {id(p) for optimizer in optimizers for group in optimizer.param_groups for p in group["params"]} == {
        id(p) for name, p in before.items() if not name.startswith("critic_target")
    }
    model.learn(40, reset_num_timesteps=False)  # trains on


def test_gradient_norms_in_one_pass_equal_the_per_layer_norms():
    layers = {"a": [th.nn.Parameter(th.randn(3, 4)), th.nn.Parameter(th.randn(3))], "b": [th.nn.Parameter(th.randn(5))]}
    unused = {"c": [th.nn.Parameter(th.randn(2))]}
    optimizer = th.optim.SGD([p for params in layers.values() for p in params] + unused["c"], lr=0.0)
    recorder = GradNormRecorder({**layers, **unused}, [optimizer])
    for params in layers.values():
        for p in params:
            p.grad = th.randn_like(p)
    optimizer.step()
    expected = {
        name: float(th.sqrt(sum((p.grad.double() ** 2).sum() for p in params))) for name, params in layers.items()
    }
    last = recorder.last()
    assert last.keys() == {"a", "b", "c"} and last["c"] == 0.0  # no gradient: zero
    assert all(abs(last[name] - value) < 1e-5 * value for name, value in expected.items())


def test_update_clock_counts_device_time_beyond_the_host_time():
    class Event:
        def __init__(self, at: float) -> None:
            self.at, self.done = at, False

        def query(self) -> bool:
            return self.done

        def synchronize(self) -> None:
            self.done = True

        def elapsed_time(self, end) -> float:
            return (end.at - self.at) * 1000.0

    clock, phase = UpdateClock(), PhaseTime(update_s=0.5, total_s=2.0)
    start, end = Event(0.0), Event(1.5)
    clock._pending.append((start, end, phase, 0.5))  # 0.5 s on the host, 1.5 s on the device
    clock.collect()
    assert phase.update_s == 0.5  # still running: nothing counted, nothing waited for
    end.done = True
    clock.collect()
    assert phase.update_s == 1.5 and phase.overhead_s == 0.5 and clock._pending == []
    clock.stop(None, phase, 1.0)  # off CUDA: nothing to time
    assert clock._pending == [] and clock.start(th.device("cpu")) is None


def test_update_clock_records_both_events_on_the_models_device_stream(monkeypatch):
    """A model on ``cuda:1`` while ``cuda:0`` is current: both events of a round on ``cuda:1``'s current stream, with
    ``cuda:1`` current while they are recorded (``elapsed_time`` refuses events of two devices)."""
    current = ["cuda:0"]
    recorded: list[tuple[str, str]] = []

    class DeviceGuard:  # torch.cuda.device
        def __init__(self, device: th.device) -> None:
            self.device = str(device)

        def __enter__(self) -> None:
            self.previous, current[0] = current[0], self.device

        def __exit__(self, *exc) -> None:
            current[0] = self.previous

    class Event:  # torch.cuda.Event: recorded on the given stream, else on the current device's
        def __init__(self, enable_timing: bool = False) -> None:
            assert enable_timing

        def record(self, stream: str | None = None) -> None:
            recorded.append((stream or f"stream of {current[0]}", current[0]))

    monkeypatch.setattr(th.cuda, "device", DeviceGuard)
    monkeypatch.setattr(th.cuda, "Event", Event)
    monkeypatch.setattr(th.cuda, "current_stream", lambda device=None: f"stream of {device or current[0]}")
    clock, phase = UpdateClock(), PhaseTime()
    start = clock.start(th.device("cuda:1"))
    clock.stop(start, phase, 0.1)
    assert recorded == [("stream of cuda:1", "cuda:1")] * 2 and current == ["cuda:0"]
    assert len(clock._pending) == 1 and clock._pending[0][2] is phase


def test_no_host_synchronization_in_an_update(monkeypatch):
    """An update reads nothing back to the host: ``.item()``, ``float``, ``.cpu()``, ``.tolist()``, ``.numpy()``."""
    model = DrQv2(
        "CnnPolicy", sb3_collapse.make_dmc_env("cartpole-balance", seed=0, action_repeat=8, size=36),
        learning_starts=10, batch_size=8, buffer_size=100, seed=0, policy_kwargs=dict(hidden_dim=16, feature_dim=8),
        replay_buffer_kwargs=dict(sampling="sb3"),
    )  # fmt: skip
    model.learn(20)
    reads = []

    class SyncAudit(TorchFunctionMode):
        def __torch_function__(self, func, types, args=(), kwargs=None):
            name = getattr(func, "__name__", "")
            if name in ("item", "tolist", "cpu", "numpy", "__float__", "__int__", "__bool__", "nonzero"):
                reads.append(name)
            return func(*args, **(kwargs or {}))

    with SyncAudit():
        model.train(gradient_steps=2, batch_size=8)
    assert reads == []
    assert np.isfinite(model.last_grad_norms["cnn1"])
