#!/usr/bin/env bash
# Replays the bad inputs and faults of docs/reliability.md as a user would type them, and counts tracebacks.
#   bash scripts/replay_bad_input.sh            (after `bash run.sh setup`; about 3 minutes on 2 CPU cores)
# Prints one line per case: exit status, then the last line the command printed on stderr. Ends with the number
# of "Traceback" lines in all the outputs (0 expected) and exits 1 if there is any.
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
work=$(mktemp -d)
log="$work/all-output.log"
export OMP_NUM_THREADS=1
trap 'rm -rf "$work"' EXIT

"$PY" - "$work" <<'PYTHON'
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
from stable_baselines3 import PPO

from sb3_collapse import DrQv2, make_dmc_env
from tests.random_env import RandomObservationEnv

work = Path(sys.argv[1])
(work / "text.zip").write_text("not a zip")
DrQv2("CnnPolicy", make_dmc_env("walker-walk", size=48), buffer_size=10, policy_kwargs=dict(hidden_dim=64)).save(
    work / "walker.zip"
)
(work / "truncated.zip").write_bytes((work / "walker.zip").read_bytes()[:5000])
PPO("MlpPolicy", RandomObservationEnv(gym.spaces.Box(-1, 1, (3,), np.float32)), n_steps=8, batch_size=8).save(
    work / "ppo.zip"
)
from sb3_collapse.baselines import build_baseline

cartpole = make_dmc_env("cartpole-balance", size=48, action_repeat=20)
build_baseline("td3", cartpole, learning_rate=1e-4, buffer_size=10, learning_starts=0, batch_size=4, hidden_dim=16).save(
    work / "td3.zip"
)
DrQv2("CnnPolicy", make_dmc_env("walker-walk", size=36), buffer_size=10, policy_kwargs=dict(hidden_dim=64)).save(
    work / "walker36.zip"
)
(work / "afile").write_text("")
(work / "bad.yml").write_text("a: [")
(work / "folder").mkdir()
(work / "report").mkdir()
(work / "report" / "summary.md").write_text("a previous report")
PYTHON

TRAIN="-m sb3_collapse.train --env cartpole-balance --frames 400 --seed-frames 200 --batch-size 16 --eval-every-frames 400 --eval-episodes 1 --collapse-metrics-every-frames 0 --size 48 --hidden-dim 64 --no-progress-bar --torch-threads 1"
SWEEP="-m sb3_collapse.sweep --tasks walker-walk --variants drqv2 --no-progress-bar"
cases=(
  "$TRAIN --run-dir $work/r --init-cnn $work/text.zip"
  "$TRAIN --run-dir $work/r --init-mlp $work/truncated.zip"
  "$TRAIN --run-dir $work/r --init-mlp $work/ppo.zip"
  "$TRAIN --run-dir $work/r --init-mlp $work/walker.zip"
  "$TRAIN --run-dir $work/r --device tpu"
  "$TRAIN --run-dir $work/r --lr -1"
  "$TRAIN --run-dir $work/r --lr nan"
  "$TRAIN --run-dir $work/r --stddev-clip -1"
  "$TRAIN --run-dir $work/r --size 5"
  "$TRAIN --run-dir $work/r --buffer-size 1000000000"
  "$TRAIN --run-dir $work/r --seed -1"
  "$TRAIN --logdir $work/afile"
  "$TRAIN --run-dir $work/r --batch-size 0"
  "$SWEEP --seeds 1 --out $work/afile"
  "$SWEEP --seed-list 1 1 --out $work/s"
  "$SWEEP --seeds 1 --cpus-per-trial 0 --out $work/s"
  "$SWEEP --seeds 1 --eval-every-frames 0 --out $work/s"
  "-m sb3_collapse.probe record $work/walker.zip --out $work/folder --overwrite"
  "-m sb3_collapse.probe $work/walker.zip --out $work/p --episodes 1"
  "-m sb3_collapse.probe $work/walker.zip --out $work/p --device cuda"
  "-m sb3_collapse.probe $work/td3.zip --out $work/p --episodes 3"
  "-m sb3_collapse.probe $work/walker.zip $work/walker36.zip --out $work/p"
  # No Ray cluster at the address: one line within --connect-timeout, exit 1, nothing written into --out.
  "$SWEEP --seeds 1 --out $work/s --address 127.0.0.1:1 --connect-timeout 5"
  "$SWEEP --seeds 1 --out $work/s --address nosuchhost:6379"
  "-m sb3_collapse.report $work/sweep-missing --out $work/report"
  "-m sb3_collapse.report $work/s --out $work/report --no-progress"
  "-m sb3_collapse.zoo train --algo drqv2 --env sb3_collapse/walker-wlak-v0 -conf zoo_configs/drqv2.yml"
  "-m sb3_collapse.zoo train --algo drqv2 --env sb3_collapse/walker-walk-v0 -conf $work/bad.yml"
  # A diverging learning rate: exit 1 when a value becomes non-finite, else exit 0 with one warning (docs/reliability.md).
  "$TRAIN --run-dir $work/diverged --lr 1000 --action-repeat 8 --frames 1600 --seed-frames 400 --replay-sampling sb3"
)
# A read-only folder for every command's outputs: a read-only mount where this user may mount one (root), else skipped.
readonly_dir="$work/read-only"
mkdir -p "$readonly_dir"
if mount -t tmpfs -o ro,size=1m tmpfs "$readonly_dir" 2>/dev/null; then
  trap 'umount "$readonly_dir" 2>/dev/null; rm -rf "$work"' EXIT
  cases+=(
    "$TRAIN --run-dir $readonly_dir/run"
    "$TRAIN --logdir $readonly_dir/runs"
    "$SWEEP --seeds 1 --out $readonly_dir/sweep"
    "-m sb3_collapse.probe record $work/walker.zip --out $readonly_dir/rollouts.npz --episodes 3"
    "-m sb3_collapse.report $work/fake-sweep --out $readonly_dir/report --no-progress"
  )
  PYTHONPATH=tests/report "$PY" -c "import sys; from fabricated_sweep import write_fake_sweep; write_fake_sweep(sys.argv[1])" \
    "$work/fake-sweep"
else
  echo "(read-only cases skipped: this user cannot mount a read-only file system)"
fi
for case in "${cases[@]}"; do
  # shellcheck disable=SC2086
  "$PY" $case >"$work/out" 2>"$work/err"
  status=$?
  printf '%s\n' "== python $case (exit $status)" >>"$log"; cat "$work/out" "$work/err" >>"$log"
  printf 'exit %s  %s\n      %s\n' "$status" "${case//$work/WORK}" "$(grep -v '^\s*$' "$work/err" | tail -n 1 | cut -c1-200)"
done
echo "Files left in the run, probe and sweep folders: $(ls "$work"/r "$work"/p "$work"/s 2>/dev/null | wc -l)"
tracebacks=$(grep -c Traceback "$log")
echo "Tracebacks: $tracebacks"
((tracebacks == 0))
