"""Time to set up each entry of an rl_zoo3 config through the launcher's ``ZooExperimentManager``.

For every env id in the file (``zoo_configs/drqv2.yml`` by default), runs ``setup_experiment()``: read and
preprocess the hyperparameters, build the training env (an 84x84 DeepMind Control task) and the DrQv2 model with
its networks and replay buffer (reserved lazily), save ``config.yml``; no evaluation env, no training. Prints the
wall time of each entry, their median and total, and the peak RSS of the process. The first entry also pays for
the OpenGL backend's start; most of the rest is the orthogonal initialization of the 1024-unit layers.

    python benchmarks/zoo_config_build.py
    python benchmarks/zoo_config_build.py --config my.yml --buffer-size 10000
"""

from __future__ import annotations

import argparse
import contextlib
import io
import platform
import resource
import statistics
import tempfile
import time

import yaml

from sb3_collapse.zoo import register_with_zoo


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="zoo_configs/drqv2.yml", help="rl_zoo3 config file")
    parser.add_argument("--buffer-size", type=int, default=None, help="override every buffer_size (transitions)")
    args = parser.parse_args()

    register_with_zoo()
    from sb3_collapse.zoo.experiment import ZooExperimentManager

    with open(args.config) as file:
        env_ids = [key for key in yaml.safe_load(file) if "/" in key]
    overrides = None if args.buffer_size is None else {"buffer_size": args.buffer_size}
    print(f"{len(env_ids)} entries of {args.config} on {platform.processor() or platform.machine()}")
    times = {}
    with tempfile.TemporaryDirectory() as logs:
        for env_id in env_ids:
            start = time.perf_counter()
            with contextlib.redirect_stdout(io.StringIO()):  # rl_zoo3 prints every hyperparameter
                manager = ZooExperimentManager(
                    argparse.Namespace(), "drqv2", env_id, logs, eval_freq=-1, seed=0, verbose=0,
                    config=args.config, hyperparams=overrides,
                )  # fmt: skip
                model, _ = manager.setup_experiment()
            times[env_id] = time.perf_counter() - start
            print(f"{env_id:42s} {times[env_id]:6.2f} s  (buffer {model.buffer_size:,} transitions)", flush=True)
            model.env.close()
            del model
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        f"median {statistics.median(times.values()):.2f} s, max {max(times.values()):.2f} s, "
        f"total {sum(times.values()):.1f} s; peak RSS {peak_mb:,.0f} MB"
    )


if __name__ == "__main__":
    main()
