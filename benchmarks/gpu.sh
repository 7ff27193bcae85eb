#!/usr/bin/env bash
# Everything sb3-collapse needs a CUDA GPU to check, in at most 10 minutes on one GPU. Run it whenever a GPU is at hand.
#
#   bash benchmarks/gpu.sh            # in a checkout set up with a CUDA build of torch (bash run.sh setup)
#
# On a GPU machine without network (this project's lent machines): run `bash benchmarks/gpu_prepare.sh` where there is
# network, then carry .whl/ and .gl/ along; this script installs them. Steps, each under its own time limit:
#   1. the CUDA tests (pytest -m cuda: tests/test_cuda.py and the other tests marked cuda)   ~3 min
#   2. benchmarks/update_speed.py at the paper's batch sizes: reference, ours, compiled, TF32 off, no prefetch   ~2 min
#   3. benchmarks/train_throughput.py at the paper's configuration (walker-walk, batch 512)   ~2 min
#   4. a cartpole-balance learning curve at its preset for the time left (benchmarks/learning_curve.py)   ~2-3 min
# Results go to $OUT (default benchmarks/gpu-results/), the figures benchmarks/README.md takes: machine.txt,
# cuda_tests.log, update_speed.txt, train_throughput.csv, learning_curve.png, learning_eval.csv, gpu.log.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-benchmarks/gpu-results}
mkdir -p "$OUT"
PY=${PYTHON:-python3}
[[ -x .venv/bin/python ]] && [[ -z ${PYTHON:-} ]] && PY=.venv/bin/python
START=$(date +%s)
exec > >(tee -a "$OUT/gpu.log") 2>&1

if [[ -d .whl ]] && ! "$PY" -c "import stable_baselines3, dm_control" 2>/dev/null; then
    echo "==> Installing the carried wheels into /tmp/site"
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 2
    "$PY" -m zipfile -e .whl/dm_control.zip /tmp/site || exit 2
    export PYTHONPATH=/tmp/site:$PWD${PYTHONPATH:+:$PYTHONPATH}
fi
if [[ -d .gl ]] && ! ldconfig -p | grep -q libEGL.so.1; then
    for f in .gl/*.deb; do dpkg -x "$f" /; done
    ldconfig
fi
export MUJOCO_GL=${MUJOCO_GL:-egl} PYTHONUNBUFFERED=1 PYTHONPATH=${PYTHONPATH:-$PWD}
if ! "$PY" -c "import torch, sys; sys.exit(not torch.cuda.is_available())"; then
    echo "error: torch sees no CUDA GPU here (torch.cuda.is_available() is False): run this script on a GPU machine." >&2
    exit 2
fi
{
    date -u +"%Y-%m-%d %H:%M UTC"
    echo "commit $(git rev-parse --short HEAD 2>/dev/null || echo unknown)"
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null
    "$PY" -c "import torch, platform; print('torch', torch.__version__, 'CUDA', torch.version.cuda, 'python', platform.python_version())"
} | tee "$OUT/machine.txt"

step() { echo; echo "==> $1 ($(($(date +%s) - START)) s so far)"; }

step "1. CUDA tests"
mapfile -t cuda_tests < <(grep -rl "mark.cuda" tests --include="test_*.py")  # not the others: their imports (Ray...)
timeout 240 "$PY" -m pytest -m cuda -q -p no:cacheprovider "${cuda_tests[@]}" 2>&1 | tee "$OUT/cuda_tests.log"

step "2. Update speed, batch 512 and 256"
timeout 150 "$PY" benchmarks/update_speed.py --device cuda --impls reference ours ours-compiled ours-ieee ours-no-prefetch \
    --batch-sizes 512 256 --rounds 3 --updates 20 2>&1 | tee "$OUT/update_speed.txt"

step "3. Training throughput, walker-walk at the paper's configuration"
timeout 150 "$PY" benchmarks/train_throughput.py --device cuda --envs 1 2 --compile off --seed-frames 2000 \
    --frames 2000 --csv "$OUT/train_throughput.csv"

left=$((570 - ($(date +%s) - START)))
step "4. cartpole-balance learning curve at its preset, for ${left} s (resumable: benchmarks/learning_curve.py)"
if ((left > 30)); then
    curve=(benchmarks/learning_curve.py --env cartpole-balance --frames 60000 --run-dir /tmp/gpu-learning --device cuda
           --out "$OUT/learning_curve.png")
    timeout --signal=INT --kill-after=30 "$left" "$PY" "${curve[@]}"
    "$PY" "${curve[@]}" --plot-only  # what the time allowed, over the published curves
    cp /tmp/gpu-learning/eval.csv "$OUT/learning_eval.csv" 2>/dev/null
fi
step "done"
