"""
Two exactness checks that only a GPU run can settle, run by ``benchmarks/gpu.sh`` (any device: ``--device cpu`` is
its rehearsal). Each prints one verdict line (``PASS`` or ``FAIL``, with the figures); the exit status is 1 if one
failed.

- ``replay``: the compiled update (``compile_update=True``: ``mode="reduce-overhead"``, CUDA graphs, on CUDA) against
  the eager one, from the same weights, over ``--updates`` updates with the same batches and random draws: the first
  updates warm up and record the CUDA graphs, the later ones replay them. After each update, the largest difference
  of any parameter between the two models is compared with the largest step the eager update made (TF32 off): a
  replay that read stale inputs or overwrote an output would differ by about a whole step. Synthetic observations,
  no rendering.
- ``resume``: two identical runs of the train CLI with ``--deterministic`` on ``--device`` (cartpole-balance,
  rendered), one of them stopped by SIGTERM after its first checkpoint and resumed by the same command; their final
  weights must be identical, bit for bit.

    python benchmarks/gpu_checks.py --device cuda                          # both, at the paper's batch (512)
    python benchmarks/gpu_checks.py --device cpu --checks replay --size 32 --hidden-dim 32 --batch-size 16
"""

from __future__ import annotations

import argparse
import copy
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch as th
from stable_baselines3.common.save_util import load_from_zip_file
from update_speed import build_model

from sb3_collapse.backends import configure_backends
from sb3_collapse.protocol import CHECKPOINTS_DIR, EXIT_INTERRUPTED, FINAL_MODEL
from sb3_collapse.run.checkpoints import checkpoint_folders


def compiled_replay(device: str, size: int, hidden_dim: int, batch_size: int, updates: int) -> bool:
    """The ``replay`` check: print one line per update and the verdict; return whether it passed."""
    configure_backends(tf32=False)
    kwargs = dict(buffer_size=max(2 * batch_size, 200), size=size, hidden_dim=hidden_dim)
    eager = build_model(device, reference=False, **kwargs)
    compiled = build_model(device, reference=False, compile_update=True, **kwargs)
    compiled.policy.load_state_dict(eager.policy.state_dict())
    for name in ("encoder", "actor", "critic"):
        getattr(compiled, name).optimizer.load_state_dict(copy.deepcopy(getattr(eager, name).optimizer.state_dict()))
    worst = 0.0
    for update in range(updates):
        np.random.seed(update)
        data = eager.replay_buffer.sample(batch_size)
        before = [p.detach().clone() for p in eager.policy.parameters()]
        start = time.perf_counter()
        for model in (eager, compiled):
            th.manual_seed(update)  # the same augmentation shifts and action noises for both
            model._update(data, data.discounts, model.current_stddev)
        pairs = list(zip(eager.policy.parameters(), compiled.policy.parameters()))
        step = max((p - b).abs().max().item() for p, b in zip(eager.policy.parameters(), before))
        difference = max((a - b).abs().max().item() for a, b in pairs)
        norms = eager.last_grad_norms, compiled.last_grad_norms
        norm_difference = max(abs(norms[0][k] - norms[1][k]) / max(abs(norms[0][k]), 1e-12) for k in norms[0])
        worst = max(worst, difference / step if step else float("inf"))
        print(f"  update {update}: largest parameter difference {difference:.2e} (largest eager step {step:.2e}); "
              f"gradient norms within {norm_difference:.1e} (relative); {time.perf_counter() - start:.1f} s",
              flush=True)  # fmt: skip
    passed = worst < 0.01
    print(
        f"{'PASS' if passed else 'FAIL'} replay: compiled against eager update on {device}, batch {batch_size}, "
        f"{updates} updates: largest difference {worst:.1e} of an update's largest step (limit 1e-2)",
        flush=True,
    )
    return passed


def resume(device: str, size: int, hidden_dim: int, batch_size: int, frames: int, seed_frames: int) -> bool:
    """The ``resume`` check: print the verdict; return whether it passed."""
    with tempfile.TemporaryDirectory() as folder:
        straight, stopped = Path(folder, "straight"), Path(folder, "stopped")

        def command(run_dir: Path) -> list[str]:
            return [sys.executable, "-m", "sb3_collapse.train", "--env", "cartpole-balance", "--frames", str(frames),
                    "--seed-frames", str(seed_frames), "--action-repeat", "8", "--size", str(size), "--hidden-dim",
                    str(hidden_dim), "--batch-size", str(batch_size), "--eval-every-frames", "0",
                    "--collapse-metrics-every-frames", "0", "--checkpoint-every-frames", str(seed_frames + 8 * 8),
                    "--replay-sampling", "sb3", "--deterministic", "--device", device, "--run-dir", str(run_dir),
                    "--no-progress-bar", "--seed", "1"]  # fmt: skip

        start = time.perf_counter()
        # Their errors show; their progress does not.
        runs = [subprocess.Popen(command(run), stdout=subprocess.DEVNULL) for run in (straight, stopped)]
        try:
            while not checkpoint_folders(stopped / CHECKPOINTS_DIR) and runs[1].poll() is None:
                time.sleep(0.05)
            runs[1].send_signal(signal.SIGTERM)  # stops it somewhere after its first checkpoint, updates begun
            if runs[1].wait() != EXIT_INTERRUPTED:
                print(f"FAIL resume: the stopped run exited {runs[1].returncode}, not {EXIT_INTERRUPTED}", flush=True)
                return False
            stopped_at = time.perf_counter() - start
            resumed = subprocess.run(command(stopped), check=False, stdout=subprocess.DEVNULL)
            status = resumed.returncode, runs[0].wait()
        finally:
            for run in runs:
                run.kill()
        if status != (0, 0):
            print(f"FAIL resume: exit statuses (resumed, straight) {status}", flush=True)
            return False
        weights = [load_from_zip_file(run / FINAL_MODEL)[1]["policy"] for run in (stopped, straight)]
        differing = [name for name in weights[1] if not th.equal(weights[0][name], weights[1][name])]
        passed = not differing and weights[0].keys() == weights[1].keys()
        print(f"{'PASS' if passed else 'FAIL'} resume: --deterministic on {device}, stopped at {stopped_at:.0f} s and "
              f"resumed, against a straight run ({frames} frames, batch {batch_size}): "
              f"{'identical weights' if passed else 'different: ' + ', '.join(differing)} "
              f"({len(weights[1])} tensors; {time.perf_counter() - start:.0f} s)", flush=True)  # fmt: skip
        return passed


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checks", nargs="+", choices=["replay", "resume"], default=["replay", "resume"])
    parser.add_argument("--device", default="cuda", help="cuda (default), cuda:1, cpu...")
    parser.add_argument("--size", type=int, default=84, help="image height and width")
    parser.add_argument("--hidden-dim", type=int, default=1024, help="hidden units of the actor and critic")
    parser.add_argument("--batch-size", type=int, default=512, help="replay: the paper's walker-walk batch, 512")
    parser.add_argument("--updates", type=int, default=8, help="replay: updates compared")
    parser.add_argument("--resume-batch-size", type=int, default=256, help="resume: the runs' batch")
    parser.add_argument("--frames", type=int, default=4000, help="resume: each run's budget, in frames")
    parser.add_argument("--seed-frames", type=int, default=2000, help="resume: frames of random actions first")
    args = parser.parse_args()
    passed = []
    try:
        if "replay" in args.checks:
            passed.append(compiled_replay(args.device, args.size, args.hidden_dim, args.batch_size, args.updates))
        if "resume" in args.checks:
            passed.append(resume(args.device, args.size, args.hidden_dim, args.resume_batch_size, args.frames,
                                 args.seed_frames))  # fmt: skip
    except KeyboardInterrupt:
        print("interrupted: the verdicts above are complete", flush=True)
    return 0 if all(passed) else 1


if __name__ == "__main__":
    sys.exit(main())
