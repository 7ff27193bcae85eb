"""Seconds of our batched OMP against scikit-learn's, and of a full probe of one walker checkpoint.

OMP (default): synthetic data of the real shapes, 10,000 samples x 39,200 features (cnn2..cnn4 at 84x84),
24 targets (walker's state components), ``tau`` = 32:

- ``ours``: ``sb3_collapse.probe.omp.omp_path`` on all targets at once (float32 products, float64 least squares),
  which also gives the solutions for every smaller ``tau``;
- ``sklearn``: ``OrthogonalMatchingPursuit(n_nonzero_coefs=tau, fit_intercept=False, precompute=False)``, one
  fit per target. It gets ``X`` in Fortran order (its preferred layout; the conversion is not timed), which
  makes it faster than with the C-ordered activations the probe holds (``--sklearn-layout C``).

The features are standard normal (float32); each target is a random combination of 20 features plus noise
(as a state component coded by a few units). Both fit the same arrays; the script checks that each target
selects the same atoms and reports the largest coefficient difference.

Full probe (``--probe``): 10,000 random 9x84x84 observations in 20 episodes of 500 agent steps, 24 random
targets, a freshly initialised DrQv2 (84x84, hidden_dim 1024), all 8 layers, ``max_tau`` 64: the wall time of
``probe_checkpoint`` (forward passes, standardization, OMP and evaluation), per layer and in total.

    python benchmarks/omp_speed.py                                   # OMP, real shapes
    python benchmarks/omp_speed.py --samples 2000 --features 5000    # smaller
    python benchmarks/omp_speed.py --probe --skip-omp                # full probe of one checkpoint
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch as th
from sklearn.linear_model import OrthogonalMatchingPursuit
from stable_baselines3.common.utils import get_device

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for tests/ (no install)

from sb3_collapse.probe.omp import omp_path


def synthetic_data(samples: int, features: int, targets: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Standard normal float32 features; targets = 20-feature combinations + noise, centred."""
    rng = np.random.default_rng(seed)
    X = rng.standard_normal((samples, features), dtype=np.float32)
    Y = np.empty((samples, targets), dtype=np.float32)
    for j in range(targets):
        support = rng.choice(features, size=20, replace=False)
        Y[:, j] = X[:, support] @ rng.standard_normal(20).astype(np.float32) + rng.standard_normal(
            samples, dtype=np.float32
        )
    return X, Y - Y.mean(0)


def time_ours(X: np.ndarray, Y: np.ndarray, tau: int, device: th.device) -> tuple[float, th.Tensor, np.ndarray]:
    """Seconds, selected atoms ``(m, tau)`` and dense coefficients ``(m, d)`` of :func:`omp_path`."""
    Xt, Yt = th.as_tensor(X).to(device), th.as_tensor(Y).to(device)
    if device.type == "cuda":
        th.cuda.synchronize()
    start = time.perf_counter()
    path = omp_path(Xt, Yt, tau)
    if device.type == "cuda":
        th.cuda.synchronize()
    seconds = time.perf_counter() - start
    return seconds, path.indices.cpu(), path.coefficients(tau, X.shape[1]).cpu().numpy()


def time_sklearn(X: np.ndarray, Y: np.ndarray, tau: int, targets: int) -> tuple[float, np.ndarray]:
    """Seconds and coefficients ``(targets, d)`` of one scikit-learn fit per target."""
    coefs = []
    start = time.perf_counter()
    for j in range(targets):
        fit = OrthogonalMatchingPursuit(n_nonzero_coefs=tau, fit_intercept=False, precompute=False).fit(X, Y[:, j])
        coefs.append(fit.coef_)
        print(f"  sklearn target {j + 1}/{targets}: {time.perf_counter() - start:.1f} s", flush=True)
    return time.perf_counter() - start, np.stack(coefs)


def benchmark_omp(args: argparse.Namespace, device: th.device) -> None:
    X, Y = synthetic_data(args.samples, args.features, args.targets)
    print(f"data: {args.samples:,} x {args.features:,} float32, {args.targets} targets, tau {args.max_tau}", flush=True)
    # Untimed warm-up of both on a small slice: library initialisation is not part of either's speed.
    small = (slice(0, min(1000, args.samples)), slice(0, min(2000, args.features)))
    time_ours(X[small], Y[small[0]], min(4, args.max_tau), device)
    OrthogonalMatchingPursuit(n_nonzero_coefs=min(4, args.max_tau), fit_intercept=False, precompute=False).fit(
        np.asfortranarray(X[small]), Y[small[0], 0]
    )
    ours_s, indices, ours_coef = time_ours(X, Y, args.max_tau, device)
    print(f"ours: {ours_s:.2f} s", flush=True)
    m = args.sklearn_targets or args.targets
    X_sk = np.asfortranarray(X) if args.sklearn_layout == "F" else X
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sk_s, sk_coef = time_sklearn(X_sk, Y, args.max_tau, m)
    same = [set(indices[j].tolist()) == set(np.flatnonzero(sk_coef[j]).tolist()) for j in range(m)]
    scale = np.abs(sk_coef).max()
    diff = np.abs(ours_coef[:m] - sk_coef).max() / scale
    print(
        f"sklearn ({m} fits, X in {args.sklearn_layout} order): {sk_s:.1f} s"
        + (
            ""
            if m == args.targets
            else f", i.e. {sk_s * args.targets / m:.1f} s for {args.targets} targets (extrapolated)"
        )
    )
    per_target_ratio = (sk_s / m) / (ours_s / args.targets)
    print(f"sklearn / ours: {per_target_ratio:.1f}x  (per target)")
    print(
        f"same selected atoms: {sum(same)}/{m} targets; largest coefficient difference {diff:.1e} (relative to the "
        "largest)"
    )


def benchmark_probe(args: argparse.Namespace, device: th.device) -> None:
    from sb3_collapse import DrQv2
    from sb3_collapse.probe.checkpoints import Checkpoint
    from sb3_collapse.probe.probing import ProbeSettings, probe_checkpoint, split_by_episode
    from sb3_collapse.probe.rollouts import Rollouts
    from tests.random_env import RandomObservationEnv

    n, episodes = args.probe_samples, 20
    rng = np.random.default_rng(0)
    model = DrQv2("CnnPolicy", RandomObservationEnv(), buffer_size=1, device=device, seed=0)
    rollouts = Rollouts(
        observations=rng.integers(0, 256, (n, 9, 84, 84), dtype=np.uint8),
        states={
            "orientations": rng.standard_normal((n, 14), dtype=np.float32),
            "height": rng.standard_normal((n, 1), dtype=np.float32),
            "velocity": rng.standard_normal((n, 9), dtype=np.float32),
        },
        actions=np.zeros((n, 6), np.float32),
        rewards=np.zeros(n, np.float32),
        episode_ids=np.repeat(np.arange(episodes), -(-n // episodes))[:n],
        steps=np.tile(np.arange(-(-n // episodes)), episodes)[:n],
        env_config={"task_id": "walker-walk", "action_repeat": 2, "frame_stack": 3, "size": 84, "camera_id": 0},
    )
    checkpoint = Checkpoint(Path("fresh.zip"), model, "DrQv2", 0, 2)
    settings = ProbeSettings(max_tau=args.probe_max_tau, device=str(device), memory_gb=args.memory_gb, progress=False)
    split = split_by_episode(rollouts.episode_ids)
    print(
        f"probe: {n:,} observations 9x84x84, 24 targets, 8 layers, max_tau {settings.max_tau}, "
        f"memory budget {settings.memory_gb} GB",
        flush=True,
    )
    start = time.perf_counter()
    result = probe_checkpoint(checkpoint, rollouts, split, settings)
    total = time.perf_counter() - start
    for layer in result.layers:
        print(
            f"  {layer.layer}: {layer.n_features:>6,} features, standardize + OMP + evaluation "
            f"{layer.fit_seconds:6.1f} s"
        )
    print(f"  forward passes (all layers): {result.extract_seconds:.1f} s")
    print(f"full probe of one checkpoint: {total:.1f} s ({total / 60:.1f} min)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=int, default=10_000, help="rows of X")
    parser.add_argument("--features", type=int, default=39_200, help="columns of X")
    parser.add_argument("--targets", type=int, default=24, help="columns of Y")
    parser.add_argument("--max-tau", type=int, default=32, help="atoms per target")
    parser.add_argument("--sklearn-targets", type=int, help="fit sklearn on the first N targets only and extrapolate")
    parser.add_argument("--sklearn-layout", choices=["F", "C"], default="F", help="memory order of X given to sklearn")
    parser.add_argument("--skip-omp", action="store_true", help="skip the OMP comparison")
    parser.add_argument("--probe", action="store_true", help="also time a full probe of one checkpoint")
    parser.add_argument("--probe-samples", type=int, default=10_000, help="observations of the full probe")
    parser.add_argument("--probe-max-tau", type=int, default=64, help="max_tau of the full probe")
    parser.add_argument("--memory-gb", type=float, default=4.0, help="activation memory budget of the full probe")
    parser.add_argument("--device", default="auto", help="cpu, cuda or auto")
    args = parser.parse_args()
    device = get_device(args.device)
    name = (
        th.cuda.get_device_name(device)
        if device.type == "cuda"
        else f"cpu ({platform.processor() or platform.machine()}), {th.get_num_threads()} threads"
    )
    print(f"device: {name}; torch {th.__version__}", flush=True)
    if not args.skip_omp:
        benchmark_omp(args, device)
    if args.probe:
        benchmark_probe(args, device)


if __name__ == "__main__":
    main()
