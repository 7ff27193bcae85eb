#!/usr/bin/env bash
# Everything sb3-collapse needs a CUDA GPU to check, in about 9 minutes on one GPU. Run it whenever a GPU is at hand.
#
#   bash benchmarks/gpu.sh                 # on a GPU machine (a checkout set up with a CUDA build of torch)
#   bash benchmarks/gpu.sh --rehearse      # the same steps on the CPU at tiny sizes, importing only what the GPU
#                                          # machine has (benchmarks/rehearsal/) plus the carried wheels
#   bash benchmarks/gpu.sh --rehearse --install-only   # its install-and-import part alone (tests/test_gpu_rehearsal.py)
#
# On a GPU machine without network (this project's lent machines): run `bash benchmarks/gpu_prepare.sh` where there is
# network, then carry .whl/ and .gl/ along; this script installs them. Steps, each under its own time limit, each
# writing its results as they come, each skipped with its reason when the preflight found that what it needs failed:
#   0. preflight: versions, imports, one rendered frame (EGL), torch.compile (Triton)   machine.txt, ~20 s
#   1. the CUDA tests (pytest -m cuda; without rendering, those marked dmc are left out)   cuda_tests.log, <= 150 s
#   2. update speed against the reference, batch 512 and 256 (compiled at 512 only)   update_speed.txt, <= 110 s
#   3. compiled update replayed against the eager one; a --deterministic run stopped and resumed   checks.txt, <= 100 s
#   4. training frames/s at the paper's configuration, 1 and 4 envs, eager and compiled   throughput.{txt,csv}, <= 130 s
#   5. runs per GPU: 1 and 3 runs at once (sum of their frames/s, runs the memory holds)   concurrent.csv, the rest
# Everything is also in gpu.log; the script ends by about 540 s with at most 8 files in $OUT (default
# benchmarks/gpu-results/, or benchmarks/gpu-results/rehearsal/). docs/throughput.md#on-a-gpu says what to expect.
set -uo pipefail
cd "$(dirname "$0")/.."
REHEARSE=0 INSTALL_ONLY=0
for arg in "$@"; do
    case $arg in
        --rehearse) REHEARSE=1 ;;
        --install-only) INSTALL_ONLY=1 ;;
        *) echo "usage: bash benchmarks/gpu.sh [--rehearse] [--install-only]" >&2; exit 2 ;;
    esac
done
START=$(date +%s)
BUDGET=${GPU_SH_BUDGET:-540}
PY=${PYTHON:-python3}
[[ -x .venv/bin/python ]] && [[ -z ${PYTHON:-} ]] && PY=.venv/bin/python
if ((REHEARSE)); then
    OUT=${OUT:-benchmarks/gpu-results/rehearsal}
    DEVICE=cpu
    WHEELS=${REHEARSAL_WHEELS:-/tmp/sb3-collapse-rehearsal/wheels-$("$PY" -c 'import sys; print("cp%d%d" % sys.version_info[:2])')}
    SITE=${REHEARSAL_SITE:-/tmp/sb3-collapse-rehearsal/site}
    export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} MKL_NUM_THREADS=${MKL_NUM_THREADS:-1}
else
    OUT=${OUT:-benchmarks/gpu-results}
    DEVICE=cuda
    WHEELS=.whl
    SITE=/tmp/site
fi
mkdir -p "$OUT"
rm -f "$OUT"/{machine.txt,gpu.log,cuda_tests.log,update_speed.txt,checks.txt,throughput.txt,throughput.csv,concurrent.csv}
exec > >(tee -a "$OUT/gpu.log") 2>&1
elapsed() { echo $(($(date +%s) - START)); }
step() { echo; echo "==> $1 ($(elapsed) s so far)"; }
# limit SECONDS: the step's limit, cut to what is left of the budget (less 10 s to write up)
limit() { local left=$((BUDGET - 10 - $(elapsed))); echo $(($1 < left ? $1 : left)); }
skip() { echo "SKIPPED: $1"; }

# The carried wheels (gpu_prepare.sh), installed the way the device's documentation installs them: pip --target, no
# index, no dependencies; dm_control, trimmed, unpacked beside them. The rehearsal makes its own for this Python.
if ((REHEARSE)) && [[ ! -f $WHEELS/dm_control.zip ]]; then
    step "Rehearsal: the carried wheels for this Python, into $WHEELS (gpu_prepare.sh)"
    WHEELS=$WHEELS PY_VERSION=$("$PY" -c 'import sys; print("%d.%d" % sys.version_info[:2])') PYTHON=$PY \
        bash benchmarks/gpu_prepare.sh --no-gl || { echo "error: could not download the wheels (no network?)"; exit 3; }
fi
if [[ -d $WHEELS ]] && { ((REHEARSE)) || ! "$PY" -c "import stable_baselines3, dm_control" 2>/dev/null; }; then
    step "Installing the carried wheels ($WHEELS) into $SITE"
    rm -rf "$SITE"
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" "$WHEELS"/*.whl \
        || exit 2
    "$PY" -m zipfile -e "$WHEELS"/dm_control.zip "$SITE" || exit 2
    export PYTHONPATH=$SITE${PYTHONPATH:+:$PYTHONPATH}
fi
if ((REHEARSE)); then  # the import guard: nothing the GPU machine lacks
    export PYTHONPATH=$PWD/benchmarks/rehearsal:$PYTHONPATH SB3_COLLAPSE_REHEARSAL_SITE=$SITE
fi
if ((!REHEARSE)) && [[ -d .gl ]] && ! ldconfig -p | grep -q libEGL.so.1; then
    for f in .gl/*.deb; do dpkg -x "$f" /; done
    ldconfig
fi
export MUJOCO_GL=${MUJOCO_GL:-egl} PYTHONUNBUFFERED=1 PYTHONPATH=${PYTHONPATH:+$PYTHONPATH:}$PWD
if ((INSTALL_ONLY)); then
    step "Imports"
    "$PY" -c "import shimmy; from dm_control import suite; import sb3_collapse.train, sb3_collapse.report
import stable_baselines3, gymnasium, mujoco, torch
print('imports: ok; stable_baselines3', stable_baselines3.__version__, 'from', stable_baselines3.__file__)"
    exit $?
fi

step "0. Preflight"
{
    date -u +"%Y-%m-%d %H:%M UTC"
    echo "commit $(git rev-parse --short HEAD 2>/dev/null || echo unknown)$( ((REHEARSE)) && echo '; REHEARSAL on the CPU')"
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null
    echo "NVIDIA_DRIVER_CAPABILITIES=${NVIDIA_DRIVER_CAPABILITIES:-(unset)}"
} >"$OUT/machine.txt"
cat "$OUT/machine.txt"
status=$(mktemp)
DEVICE_OK=0 CORE_OK=0 RENDER_OK=0 COMPILE_OK=0 DEVICE_WHY="preflight failed" CORE_WHY="preflight failed"
RENDER_WHY="preflight failed" COMPILE_WHY="preflight failed" RENDER_EXPORT=""
timeout --kill-after=10 "$(limit 200)" "$PY" benchmarks/gpu_preflight.py --device "$DEVICE" --out "$OUT/machine.txt" \
    --status "$status"
# shellcheck disable=SC1090
source "$status"
[[ -n $RENDER_EXPORT ]] && export "${RENDER_EXPORT?}"
RUNS=$((DEVICE_OK && CORE_OK))  # every step needs the device and the package
RUNS_WHY="${DEVICE_WHY:-$CORE_WHY}"

# Sizes: the paper's on the GPU; tiny ones on the CPU, where the rehearsal checks the plumbing, not the speed.
if ((REHEARSE)); then
    SPEED=(--size 32 --hidden-dim 32 --batch-sizes 16 8 --compiled-batch-sizes 16 --rounds 2 --updates 2
           --buffer-size 100)
    CHECKS=(--size 32 --hidden-dim 32 --batch-size 16 --updates 4 --resume-batch-size 16 --frames 800 --seed-frames 400)
    TRAIN=(--size 32 --hidden-dim 32 --batch-size 16 --seed-frames 100 --frames 32 --buffer-size 1000)
    ENVS=(1 2) CONCURRENT=(2)
else
    SPEED=(--batch-sizes 512 256 --compiled-batch-sizes 512 --rounds 3 --updates 20)
    CHECKS=()
    TRAIN=(--seed-frames 2000 --frames 2000)
    ENVS=(1 4) CONCURRENT=(1 3)
fi

step "1. CUDA tests (pytest -m cuda)"
if ((!CORE_OK)); then skip "$CORE_WHY"; else
    marks="cuda"
    ((RENDER_OK)) || { marks="cuda and not dmc"; echo "without the tests that render (dm_control): $RENDER_WHY"; }
    mapfile -t cuda_tests < <(grep -rl "mark.cuda" tests --include="test_*.py" | sort)  # not the others' imports (Ray)
    timeout --signal=INT --kill-after=20 "$(limit 150)" "$PY" -m pytest -m "$marks" -q -p no:cacheprovider \
        --durations=15 "${cuda_tests[@]}" 2>&1 | tee "$OUT/cuda_tests.log"
fi

step "2. Update speed against the reference, on the same device"
impls=(reference ours ours-ieee ours-no-prefetch)
((COMPILE_OK)) && impls+=(ours-compiled) || echo "without ours-compiled: $COMPILE_WHY"
if ((!RUNS)); then skip "$RUNS_WHY"; else
    timeout --signal=INT --kill-after=10 "$(limit 110)" "$PY" benchmarks/update_speed.py --device "$DEVICE" \
        --impls "${impls[@]}" --ready-timeout 80 "${SPEED[@]}" 2>&1 | tee "$OUT/update_speed.txt"
fi

step "3. Exactness: the compiled update replayed against the eager one; a --deterministic run stopped and resumed"
checks=()
((COMPILE_OK)) && checks+=(replay) || echo "without replay: $COMPILE_WHY"
((RENDER_OK)) && checks+=(resume) || echo "without resume: $RENDER_WHY"
if ((!RUNS)); then skip "$RUNS_WHY"; elif ((${#checks[@]} == 0)); then skip "nothing left to check"; else
    timeout --signal=INT --kill-after=10 "$(limit 100)" "$PY" benchmarks/gpu_checks.py --device "$DEVICE" \
        --checks "${checks[@]}" "${CHECKS[@]}" 2>&1 | tee "$OUT/checks.txt"
fi

step "4. Training frames/s, walker-walk at the paper's configuration: ${ENVS[*]} envs, eager and compiled"
compile=(off)
((COMPILE_OK)) && compile+=(on)
if ((!RUNS)); then skip "$RUNS_WHY"; elif ((!RENDER_OK)); then skip "$RENDER_WHY"; else
    timeout --signal=INT --kill-after=20 "$(limit 130)" "$PY" benchmarks/train_throughput.py --device "$DEVICE" \
        --envs "${ENVS[@]}" --compile "${compile[@]}" "${TRAIN[@]}" --csv "$OUT/throughput.csv" 2>&1 \
        | tee "$OUT/throughput.txt"
fi

step "5. Runs per device: ${CONCURRENT[*]} runs at once (2 envs each, eager)"
if ((!RUNS)); then skip "$RUNS_WHY"; elif ((!RENDER_OK)); then skip "$RENDER_WHY"; elif (($(limit 600) < 30)); then
    skip "less than 30 s left"
else
    timeout --signal=INT --kill-after=20 "$(limit 600)" "$PY" benchmarks/train_throughput.py --device "$DEVICE" \
        --envs 2 --compile off --concurrent "${CONCURRENT[@]}" "${TRAIN[@]}" --csv "$OUT/concurrent.csv" 2>&1 \
        | tee -a "$OUT/throughput.txt"
fi
rm -f "$status"
step "done: $(ls "$OUT" | tr '\n' ' ')"
