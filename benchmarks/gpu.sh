#!/usr/bin/env bash
# Everything sb3-collapse needs a CUDA GPU to check, in about 9 minutes on one GPU. Run it whenever a GPU is at hand;
# benchmarks/gpu.md gives the sequence on a lent machine without network (what to prepare and carry, the one call).
#
#   bash benchmarks/gpu.sh                 # on a GPU machine (a checkout set up with a CUDA build of torch)
#   bash benchmarks/gpu.sh --rehearse      # the same steps on the CPU at tiny sizes, with the GPU machine's Python,
#                                          # torch and numpy (benchmarks/rehearsal/venv.sh), importing only what the
#                                          # GPU machine has (benchmarks/rehearsal/) plus the carried wheels
#   bash benchmarks/gpu.sh --rehearse --install-only   # its install-and-import part alone (tests/test_gpu_rehearsal.py)
#
# Steps, in the order of the value of what they return, each under its own time limit (cut to what is left of the
# budget, and skipped with a line when too little is left), each writing its results as they come, each skipped with
# its reason when the preflight found that what it needs failed:
#   0. preflight: versions; the package's imports, a rendered frame then a DrQv2 trained in the same process,
#      torch.compile of a Linear forward and backward (each in a subprocess)             machine.txt, <= 90 s
#   1. update speed against the reference, batch 512 and 256 (compiled at 512 only)    update_speed.txt, <= 110 s
#   2. training frames/s at the paper's configuration, 1 and 4 envs, eager and compiled throughput.{txt,csv}, <= 130 s
#   3. compiled update replayed against the eager one; a --deterministic run stopped and resumed   checks.txt, <= 90 s
#   4. the CUDA tests (pytest -m cuda; without rendering, those marked dmc are left out)   cuda_tests.log, <= 100 s
#   5. runs per GPU: 3 runs at once, 1 env each (one run: step 2's)                    concurrent.csv, the rest
# Everything is also in gpu.log; the script ends by about 540 s (GPU_SH_BUDGET; the rehearsal: twice every limit, see
# SCALE) with at most 8 files in $OUT (default benchmarks/gpu-results/, or benchmarks/gpu-results/rehearsal/).
# benchmarks/gpu.md says where each figure goes.
set -uo pipefail

elapsed() { echo $(($(date +%s) - START)); }
step() { echo; echo "==> $1 ($(elapsed) s so far)"; }
# limit SECONDS [AT_LEAST]: the step's time limit, SECONDS (times SCALE) cut to what is left of BUDGET (less 10 s to
# write up); prints nothing and fails when that is under AT_LEAST seconds (default 10), so that a step never gets a
# timeout of 0 or less: the caller skips it with a line (too_late).
limit() {
    local left=$((BUDGET - 10 - $(elapsed))) least=${2:-10} asked=$(($1 * ${SCALE:-1}))
    local seconds=$((asked < left ? asked : left))
    ((seconds >= least)) || return 1
    echo "$seconds"
}
too_late() { echo "SKIPPED: $((BUDGET - 10 - $(elapsed))) s left of the ${BUDGET} s budget, under the ${1} s this step needs"; }
skip() { echo "SKIPPED: $1"; }
# bounded SECONDS KILL_AFTER COMMAND...: COMMAND under timeout (SIGINT at SECONDS, so that it prints what it has;
# SIGKILL KILL_AFTER later), then SIGKILL to whatever it left running in timeout's process group (a worker that
# outlived its parent would hold the step's pipe open, and its tee with it, and take the next step's CPU or GPU);
# then the empty libraries that a compilation killed mid-way leaves in torch's inductor cache are removed (a later
# step that compiles the same code would load one and fail: "file too short").
bounded() {
    local seconds=$1 kill_after=$2 group status
    shift 2
    group=$(mktemp)
    # bash -c prints its pid, then becomes timeout (same pid), which makes its own process group of that number.
    bash -c 'echo $$ >"$0"; exec "$@"' "$group" timeout --signal=INT --kill-after="$kill_after" "$seconds" "$@"
    status=$?
    kill -KILL -- "-$(cat "$group")" 2>/dev/null
    rm -f "$group"
    [[ -d ${TORCHINDUCTOR_CACHE_DIR:-} ]] && find "$TORCHINDUCTOR_CACHE_DIR" -name "*.so" -empty -delete
    return $status
}
# read_preflight FILE: the preflight's verdicts, each with a default for the ones it did not write (it was killed or
# timed out before them), then whatever FILE holds.
read_preflight() {
    local why="the preflight ended before this check (timed out or killed: see machine.txt)"
    DEVICE_OK=0 CORE_OK=0 RENDER_OK=0 COMPILE_OK=0 DEVICE_WHY=$why CORE_WHY=$why RENDER_WHY=$why COMPILE_WHY=$why
    RENDER_EXPORT=""
    # shellcheck disable=SC1090
    [[ -f $1 ]] && source "$1"
    return 0
}
# egl_vendor NVIDIA_FILE FOLDER...: the NVIDIA driver's EGL vendor file when it exists, no vendor file is in the
# FOLDERs (glvnd's defaults), and __EGL_VENDOR_LIBRARY_FILENAMES is unset; else nothing. glvnd finds no vendor
# otherwise where the driver is mounted apart (/usr/local/nvidia) and MuJoCo's EGL fails or falls back to Mesa.
egl_vendor() {
    local file=$1 folder
    shift
    [[ -z ${__EGL_VENDOR_LIBRARY_FILENAMES:-} && -f $file ]] || return 0
    for folder in "$@"; do compgen -G "$folder/*.json" >/dev/null && return 0; done
    echo "$file"
}
# commit WHEELS: the commit that the results are of: SB3_COLLAPSE_COMMIT, else git's, else WHEELS/COMMIT (written by
# gpu_prepare.sh: the copy on a lent GPU machine has no .git), else unknown.
commit() {
    if [[ -n ${SB3_COLLAPSE_COMMIT:-} ]]; then
        echo "$SB3_COLLAPSE_COMMIT (SB3_COLLAPSE_COMMIT)"
    elif git rev-parse --short HEAD >/dev/null 2>&1; then
        echo "$(git rev-parse --short HEAD)$([[ -n $(git status --porcelain --untracked-files=no) ]] && echo ', dirty')"
    elif [[ -f $1/COMMIT ]]; then
        echo "$(cat "$1/COMMIT") ($1/COMMIT, from gpu_prepare.sh)"
    else
        echo "unknown (no .git, no SB3_COLLAPSE_COMMIT, no $1/COMMIT)"
    fi
}
[[ ${BASH_SOURCE[0]} == "$0" ]] || return 0  # sourced (tests/test_gpu_preflight.py): the functions alone

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
# The rehearsal's time limits are the GPU's times SCALE (GPU_SH_SCALE, default 2): on a busy 2-core machine, what
# the GPU machine's 16 cores start in seconds (torch imported by several processes at once, compilations on the CPU)
# takes minutes.
SCALE=${GPU_SH_SCALE:-$( ((REHEARSE)) && echo 2 || echo 1)}
BUDGET=${GPU_SH_BUDGET:-$((540 * SCALE))}
if ((REHEARSE)); then
    OUT=${OUT:-benchmarks/gpu-results/rehearsal}
    mkdir -p "$OUT"
    # The GPU machine's interpreter: Python 3.12, torch 2.11, numpy 2.5 (made once; PYTHON chooses another).
    PY=${PYTHON:-$(bash benchmarks/rehearsal/venv.sh)} || { echo "error: could not make the rehearsal's venv"; exit 3; }
    DEVICE=cpu
    WHEELS=${REHEARSAL_WHEELS:-/tmp/sb3-collapse-rehearsal/wheels-$("$PY" -c 'import sys; print("cp%d%d" % sys.version_info[:2])')}
    SITE=${REHEARSAL_SITE:-/tmp/sb3-collapse-rehearsal/site-$("$PY" -c 'import sys; print("cp%d%d" % sys.version_info[:2])')}
    export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} MKL_NUM_THREADS=${MKL_NUM_THREADS:-1}
    # Its own inductor cache, kept between rehearsals (others' compilations on this machine stay out of it).
    export TORCHINDUCTOR_CACHE_DIR=${TORCHINDUCTOR_CACHE_DIR:-/tmp/sb3-collapse-rehearsal/inductor}
else
    OUT=${OUT:-benchmarks/gpu-results}
    PY=${PYTHON:-python3}
    [[ -x .venv/bin/python ]] && [[ -z ${PYTHON:-} ]] && PY=.venv/bin/python
    DEVICE=cuda
    WHEELS=.whl
    SITE=/tmp/site
    export TORCHINDUCTOR_CACHE_DIR=${TORCHINDUCTOR_CACHE_DIR:-/tmp/torchinductor_$(id -un)}  # torch's default, named
fi
mkdir -p "$OUT"
rm -f "$OUT"/{machine.txt,gpu.log,cuda_tests.log,update_speed.txt,checks.txt,throughput.txt,throughput.csv,concurrent.csv}
exec > >(tee -a "$OUT/gpu.log") 2>&1

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
vendor=$(egl_vendor /usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json /usr/share/glvnd/egl_vendor.d \
    /etc/glvnd/egl_vendor.d)
[[ -n $vendor ]] && export __EGL_VENDOR_LIBRARY_FILENAMES=$vendor && echo "__EGL_VENDOR_LIBRARY_FILENAMES=$vendor"
export MUJOCO_GL=${MUJOCO_GL:-egl} PYTHONUNBUFFERED=1 PYTHONPATH=${PYTHONPATH:+$PYTHONPATH:}$PWD
if ((INSTALL_ONLY)); then
    step "Imports"
    "$PY" -c "import shimmy; from dm_control import suite; import sb3_collapse.train, sb3_collapse.report
import stable_baselines3, gymnasium, mujoco, numpy, torch, sys
print('python', sys.version.split()[0], 'torch', torch.__version__, 'numpy', numpy.__version__)
print('imports: ok; stable_baselines3', stable_baselines3.__version__, 'from', stable_baselines3.__file__)"
    exit $?
fi

step "0. Preflight"
{
    date -u +"%Y-%m-%d %H:%M UTC"
    echo "commit $(commit "$WHEELS")$( ((REHEARSE)) && echo '; REHEARSAL on the CPU')"
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null
    echo "NVIDIA_DRIVER_CAPABILITIES=${NVIDIA_DRIVER_CAPABILITIES:-(unset)}"
    echo "__EGL_VENDOR_LIBRARY_FILENAMES=${__EGL_VENDOR_LIBRARY_FILENAMES:-(unset)}"
} >"$OUT/machine.txt"
cat "$OUT/machine.txt"
status=$(mktemp)
if t=$(limit 90 30); then  # each of its subprocess checks gets 15 s less than the whole
    bounded "$t" 10 "$PY" benchmarks/gpu_preflight.py --device "$DEVICE" --out "$OUT/machine.txt" \
        --status "$status" --timeout $((t - 15))
else
    too_late 30
fi
read_preflight "$status"
rm -f "$status"
[[ -n $RENDER_EXPORT ]] && export "${RENDER_EXPORT?}" && echo "from now on: $RENDER_EXPORT"
RUNS=$((DEVICE_OK && CORE_OK))  # every step needs the device and the package
RUNS_WHY=$( ((DEVICE_OK)) && echo "$CORE_WHY" || echo "$DEVICE_WHY")

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
    ENVS=(1 4) CONCURRENT=(3)
fi

step "1. Update speed against the reference, on the same device"
impls=(reference ours ours-ieee ours-no-prefetch)
# The reference with cuDNN's autotuner on, as DrQ-v2's train.py runs it, where update_speed.py offers it.
grep -q '"reference-autotune"' benchmarks/update_speed.py && impls=(reference reference-autotune "${impls[@]:1}")
((COMPILE_OK)) && impls+=(ours-compiled) || echo "without ours-compiled: $COMPILE_WHY"
if ((!RUNS)); then skip "$RUNS_WHY"; elif ! t=$(limit 110 30); then too_late 30; else
    bounded "$t" 10 "$PY" benchmarks/update_speed.py --device "$DEVICE" \
        --impls "${impls[@]}" --ready-timeout $((80 * SCALE)) "${SPEED[@]}" 2>&1 | tee "$OUT/update_speed.txt"
fi

step "2. Training frames/s, walker-walk at the paper's configuration: ${ENVS[*]} envs, eager and compiled"
compile=(off)
((COMPILE_OK)) && compile+=(on)
if ((!RUNS)); then skip "$RUNS_WHY"; elif ((!RENDER_OK)); then skip "$RENDER_WHY"; elif ! t=$(limit 130 40); then
    too_late 40
else
    bounded "$t" 20 "$PY" benchmarks/train_throughput.py --device "$DEVICE" \
        --envs "${ENVS[@]}" --compile "${compile[@]}" "${TRAIN[@]}" --csv "$OUT/throughput.csv" 2>&1 \
        | tee "$OUT/throughput.txt"
fi

step "3. Exactness: the compiled update replayed against the eager one; a --deterministic run stopped and resumed"
checks=()
((COMPILE_OK)) && checks+=(replay) || echo "without replay: $COMPILE_WHY"
((RENDER_OK)) && checks+=(resume) || echo "without resume: $RENDER_WHY"
if ((!RUNS)); then skip "$RUNS_WHY"; elif ((${#checks[@]} == 0)); then skip "nothing left to check"
elif ! t=$(limit 90 30); then too_late 30; else
    bounded "$t" 10 "$PY" benchmarks/gpu_checks.py --device "$DEVICE" \
        --checks "${checks[@]}" "${CHECKS[@]}" 2>&1 | tee "$OUT/checks.txt"
fi

step "4. CUDA tests (pytest -m cuda)"
if ((!CORE_OK)); then skip "$CORE_WHY"; elif ! t=$(limit 100 30); then too_late 30; else
    marks="cuda"
    ((RENDER_OK)) || { marks="cuda and not dmc"; echo "without the tests that render (dm_control): $RENDER_WHY"; }
    mapfile -t cuda_tests < <(grep -rl "mark.cuda" tests --include="test_*.py" | sort)  # not the others' imports (Ray)
    bounded "$t" 20 "$PY" -m pytest -m "$marks" -q -p no:cacheprovider \
        --durations=15 "${cuda_tests[@]}" 2>&1 | tee "$OUT/cuda_tests.log"
fi

step "5. Runs per device: ${CONCURRENT[*]} runs at once (1 env each, eager; one run alone: step 2)"
if ((!RUNS)); then skip "$RUNS_WHY"; elif ((!RENDER_OK)); then skip "$RENDER_WHY"; elif ! t=$(limit 600 40); then
    too_late 40
else
    bounded "$t" 20 "$PY" benchmarks/train_throughput.py --device "$DEVICE" \
        --envs 1 --compile off --concurrent "${CONCURRENT[@]}" "${TRAIN[@]}" --csv "$OUT/concurrent.csv" 2>&1 \
        | tee -a "$OUT/throughput.txt"
fi
step "done: $(ls "$OUT" | tr '\n' ' ')"
