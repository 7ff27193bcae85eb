"""Cost of incremental replay buffer checkpoints (ReplayStore) as a buffer fills and wraps around.

For each buffer capacity, a FrameStackReplayBuffer of 3x84x84 uint8 frames (frame_stack 3, 6-d actions, one env)
receives transitions of synthetic episodes of 500 agent steps (frames copied from a pool of 64 random ones: no
rendering), up to its capacity and then ``--wrap`` times its capacity more (at least 3 checkpoints' worth), and is
checkpointed every ``--every`` transitions (5,000 = 10,000 frames at action repeat 2) as a run would:
``ReplayStore.save``, then, the new
checkpoint being complete, ``collect_garbage(keep=[new manifest])``. Printed, per capacity: the last checkpoint's
bytes written and seconds (save, fsync included), the largest over all checkpoints, and the folder's bytes after
garbage collection and at its peak (during a checkpoint, when the new chunks exist beside the previous ones) as a
multiple of the buffer's RAM bytes. Every checkpoint's figures go to ``--csv``. With ``--verify`` (default for
capacities up to 100,000), the last checkpoint is restored into a fresh buffer and compared.

    python benchmarks/replay_checkpoint.py                                # 10,000 and 100,000 transitions
    python benchmarks/replay_checkpoint.py --sizes 550000 --dir /work/tmp  # paper scale: ~11.8 GB RAM and disk
"""

from __future__ import annotations

import argparse
import csv
import os
import shutil
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
from replay_buffer import cpu_name  # benchmarks/replay_buffer.py, beside this script

from sb3_collapse.drqv2 import FrameStackReplayBuffer
from sb3_collapse.run.replay_checkpoint import ReplayStore

FRAME_STACK = 3
FRAME = (3, 84, 84)
OBSERVATIONS = gym.spaces.Box(0, 255, (FRAME[0] * FRAME_STACK, *FRAME[1:]), np.uint8)
ACTIONS = gym.spaces.Box(-1.0, 1.0, (6,), np.float32)
FIELDS = (
    "capacity",
    "transitions",
    "checkpoint",
    "bytes_written",
    "seconds",
    "gc_seconds",
    "folder_bytes",
    "peak_folder_bytes",
    "buffer_bytes",
)


class Episodes:
    """Synthetic transitions of one env: episodes of ``length`` agent steps ending with a time limit."""

    def __init__(self, length: int, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)
        self.pool = self.rng.integers(0, 256, (64, *FRAME), dtype=np.uint8)
        self.length = length
        self.step = 0
        self.obs = self._reset()

    def _reset(self) -> np.ndarray:
        return np.concatenate([self.pool[self.rng.integers(64)]] * FRAME_STACK)[None]

    def add(self, buffer: FrameStackReplayBuffer, count: int) -> None:
        for _ in range(count):
            new = self.pool[self.rng.integers(64)][None]
            next_obs = np.concatenate([self.obs[:, FRAME[0] :], new], axis=1)
            self.step += 1
            truncated = self.step % self.length == 0
            action = self.rng.uniform(-1, 1, (1, 6)).astype(np.float32)
            buffer.add(
                self.obs,
                next_obs,
                action,
                self.rng.random(1),
                np.array([truncated]),
                [{"TimeLimit.truncated": truncated}],
            )
            self.obs = self._reset() if truncated else next_obs


def make_buffer(capacity: int) -> FrameStackReplayBuffer:
    return FrameStackReplayBuffer(capacity, OBSERVATIONS, ACTIONS, "cpu", frame_stack=FRAME_STACK)


def run(capacity: int, every: int, wrap: float, episode_length: int, folder: Path, verify: bool) -> list[dict]:
    """Fill and checkpoint one buffer; return one row per checkpoint."""
    buffer = make_buffer(capacity)
    store = ReplayStore(folder)
    episodes = Episodes(episode_length)
    total = capacity + max(int(wrap * capacity), 3 * every)
    rows: list[dict] = []
    previous: set[str] = set()
    manifest: dict = {}
    checkpoint = 0
    while buffer.transitions_added < total:
        episodes.add(buffer, min(every, total - buffer.transitions_added))
        checkpoint += 1
        start = time.perf_counter()
        manifest = store.save(buffer)
        seconds = time.perf_counter() - start
        peak = store.disk_bytes()
        start = time.perf_counter()
        store.collect_garbage(keep=[manifest])
        gc_seconds = time.perf_counter() - start
        written = sum(chunk["bytes"] for chunk in manifest["chunks"] if chunk["file"] not in previous)
        previous = {chunk["file"] for chunk in manifest["chunks"]}
        rows.append(
            {
                "capacity": capacity,
                "transitions": buffer.transitions_added,
                "checkpoint": checkpoint,
                "bytes_written": written,
                "seconds": round(seconds, 3),
                "gc_seconds": round(gc_seconds, 3),
                "folder_bytes": store.disk_bytes(),
                "peak_folder_bytes": peak,
                "buffer_bytes": buffer.nbytes,
            }
        )
        print(
            f"  {capacity:,}: {buffer.transitions_added:>9,} transitions, checkpoint {checkpoint}: "
            f"{written / 1e6:7.1f} MB in {seconds:5.2f} s, folder {rows[-1]['folder_bytes'] / buffer.nbytes:.3f}x",
            flush=True,
        )
    if verify:
        restored = make_buffer(capacity)
        start = time.perf_counter()
        ReplayStore(folder).restore(restored, manifest)
        restore_s = time.perf_counter() - start
        same = all(
            np.array_equal(array, restored.storage_arrays[name]) for name, array in buffer.storage_arrays.items()
        )
        same &= restored.pos == buffer.pos and restored.full == buffer.full
        print(f"  {capacity:,}: restored in {restore_s:.1f} s (files in the page cache); identical: {same}")
        if not same:
            raise SystemExit("restore differs from the saved buffer")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--sizes",
        type=int,
        nargs="+",
        default=[10_000, 100_000],
        help="buffer capacities in transitions (550000: paper scale, ~11.8 GB of RAM and of disk)",
    )
    parser.add_argument("--every", type=int, default=5_000, help="transitions between checkpoints")
    parser.add_argument(
        "--wrap",
        type=float,
        default=0.2,
        help="transitions added after the buffer is full, as a fraction of its capacity",
    )
    parser.add_argument("--episode-length", type=int, default=500, help="agent steps per episode")
    parser.add_argument(
        "--dir", type=Path, default=None, help="folder for the chunks (default: a temporary one; deleted afterwards)"
    )
    parser.add_argument("--csv", type=Path, default=Path("replay_checkpoint.csv"), help="every checkpoint's figures")
    parser.add_argument(
        "--verify",
        choices=("auto", "on", "off"),
        default="auto",
        help="restore the last checkpoint into a fresh buffer and compare (auto: up to 100,000)",
    )
    args = parser.parse_args()

    base = Path(tempfile.mkdtemp(prefix="replay_checkpoint_", dir=args.dir))
    print(
        f"machine: {cpu_name()}, {os.cpu_count()} cores; numpy {np.__version__}; chunks in {base}; "
        f"{args.every:,} transitions per checkpoint, episodes of {args.episode_length} steps"
    )
    rows: list[dict] = []
    try:
        for capacity in args.sizes:
            verify = args.verify == "on" or (args.verify == "auto" and capacity <= 100_000)
            rows += run(capacity, args.every, args.wrap, args.episode_length, base / str(capacity), verify)
            shutil.rmtree(base / str(capacity))
    finally:
        shutil.rmtree(base, ignore_errors=True)

    with args.csv.open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    header = (
        f"{'capacity':>9} {'transitions':>11} {'last MB':>8} {'last s':>7} {'max MB':>7} {'max s':>6} "
        f"{'folder GB':>9} {'folder/RAM':>10} {'max':>6} {'peak/RAM':>8}"
    )
    print(header)
    for capacity in args.sizes:
        mine = [row for row in rows if row["capacity"] == capacity]
        last = mine[-1]
        ram = last["buffer_bytes"]
        print(
            f"{capacity:>9,} {last['transitions']:>11,} {last['bytes_written'] / 1e6:>8.1f} {last['seconds']:>7.2f} "
            f"{max(row['bytes_written'] for row in mine) / 1e6:>7.1f} {max(row['seconds'] for row in mine):>6.2f} "
            f"{last['folder_bytes'] / 1e9:>9.3f} {last['folder_bytes'] / ram:>10.3f} "
            f"{max(row['folder_bytes'] for row in mine) / ram:>6.3f} "
            f"{max(row['peak_folder_bytes'] for row in mine) / ram:>8.3f}"
        )
    print(f"every checkpoint: {args.csv}")


if __name__ == "__main__":
    main()
