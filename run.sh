#!/usr/bin/env bash
# sb3-collapse: set up and run.   bash run.sh demo   |   bash run.sh test   |   bash run.sh setup
#
# setup: headless OpenGL (Debian packages, when missing and apt-get can install them), a virtual
#        environment in .venv (Python 3.11, 3.12 or 3.13: the first of python3.11, python3.12, python3.13, python3
#        that is one; PYTHON=python3.12 chooses), PyTorch (the one already there, else
#        `pip install $TORCH_SPEC`, torch==2.13.0 by default: from PyPI on Linux that is the CUDA build; see
#        docs/install.md#requirements), then this package in editable mode (with its test, zoo, sweep and dev extras
#        for `setup` and `test`).
# demo:  setup, then a short DrQ-v2 run on walker-walk from pixels; writes runs/walker-walk_s0/.
# test:  setup, then the test suite (pytest). Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")"

PYTHON=${PYTHON:-}
VENV=${VENV:-.venv}
TORCH_SPEC=${TORCH_SPEC:-torch==2.13.0}
# The Python versions the test suite passes on (pyproject.toml's classifiers name the same).
SUPPORTED=(3.11 3.12 3.13)
EGL_PACKAGES=(libegl1 libgl1-mesa-dri libegl-mesa0)

log() { printf '\n==> %s\n' "$*"; }

install_rendering_packages() {
    local missing=()
    for package in "${EGL_PACKAGES[@]}"; do
        dpkg -s "$package" >/dev/null 2>&1 || missing+=("$package")
    done
    if ((${#missing[@]} == 0)); then
        return
    fi
    local sudo=""
    if [[ $(id -u) != 0 ]]; then
        if command -v sudo >/dev/null && sudo -n true 2>/dev/null; then sudo="sudo"; else
            echo "Headless rendering needs: ${missing[*]} libosmesa6. Install them (apt-get install ...) and rerun." >&2
            return
        fi
    fi
    log "Installing headless OpenGL packages: ${missing[*]} libosmesa6"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" libosmesa6 >/dev/null
}

python_version() { "$1" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null; }

find_python() {
    # PYTHON chooses (a version outside SUPPORTED with a warning); else the first candidate of a supported version.
    local candidate version supported
    supported=$(printf '%s, ' "${SUPPORTED[@]}")
    if [[ -n $PYTHON ]]; then
        version=$(python_version "$PYTHON") || { echo "PYTHON=$PYTHON does not run here." >&2; exit 1; }
        [[ " ${SUPPORTED[*]} " == *" $version "* ]] ||
            echo "Warning: $PYTHON is Python $version; the test suite passes on ${supported%, }." >&2
        echo "$PYTHON"; return
    fi
    local skipped=()
    for candidate in python3.11 python3.12 python3.13 python3; do
        version=$(python_version "$candidate") || { skipped+=("$candidate: not found"); continue; }
        if [[ " ${SUPPORTED[*]} " == *" $version "* ]]; then
            # Say why it is not the first choice (stderr: the caller reads the name from stdout).
            ((${#skipped[@]} == 0)) ||
                echo "Took $candidate (Python $version) because $(IFS=';'; echo "${skipped[*]}" | sed 's/;/; /g')." >&2
            echo "$candidate"; return
        fi
        skipped+=("$candidate is Python $version")
    done
    echo "None of python3.11, python3.12, python3.13, python3 is Python ${supported%, } here:" \
        "set PYTHON=... to one." >&2
    exit 1
}

check_venv_python() {
    # A venv made by another Python is kept only when PYTHON does not ask for a different version.
    [[ -n $PYTHON ]] || return 0
    local wanted have
    wanted=$(python_version "$(find_python)")
    have=$(python_version "$VENV/bin/python")
    if [[ $wanted != "$have" ]]; then
        echo "$VENV holds Python $have, not $PYTHON's $wanted: set VENV=.venv-$wanted (or remove $VENV) and rerun." >&2
        exit 1
    fi
}

setup() {
    local extras=${1:-}
    if command -v dpkg >/dev/null && command -v apt-get >/dev/null; then
        install_rendering_packages
    fi
    if [[ ! -x $VENV/bin/python ]]; then
        local python
        python=$(find_python)
        log "Creating the virtual environment $VENV with $python (Python $(python_version "$python"))"
        "$python" -m venv "$VENV"
    fi
    check_venv_python
    log "Using $VENV: Python $("$VENV/bin/python" -c 'import platform; print(platform.python_version())')"
    if ! "$VENV/bin/python" -c 'import torch' 2>/dev/null; then
        log "Installing PyTorch ($TORCH_SPEC)"
        # shellcheck disable=SC2086  # TORCH_SPEC's words: a requirement and pip's options (--index-url ...)
        pip_install $TORCH_SPEC
    fi
    install_package ".${extras:+[$extras]}"
}

install_package() {
    # $1: this package with its extras, installed in editable mode with its dependencies.
    if "$VENV/bin/python" -c 'import sys; sys.exit(sys.version_info < (3, 13))'; then
        log "Installing sb3-collapse and its dependencies but labmaze, which has no wheel for Python 3.13 and" \
            "builds only with Bazel: dm_control.locomotion, which needs it and which this package does not use," \
            "will not import"
        # pip resolves as usual (labmaze's metadata comes from its source) and installs nothing; then each package it
        # chose, labmaze aside, is installed at the chosen version without its dependencies (pip chose them all).
        local report
        report=$(mktemp -d)
        pip_install --dry-run --report "$report/report.json" -e "$1"
        "$VENV/bin/python" -c '
import json, sys
for item in json.load(open(sys.argv[1]))["install"]:
    if item["metadata"]["name"].lower() not in ("labmaze", "sb3-collapse"):
        print(item["metadata"]["name"] + "==" + item["metadata"]["version"])
' "$report/report.json" >"$report/requirements.txt"
        if [[ -s $report/requirements.txt ]]; then
            pip_install --no-deps -r "$report/requirements.txt"
        fi
        pip_install --no-deps -e "$1"
        rm -rf "$report"
    else
        log "Installing sb3-collapse and its dependencies"
        pip_install -e "$1"
    fi
}

pip_install() {
    # The filter drops pip's warnings about unreadable local index folders that some machines configure.
    "$VENV/bin/python" -m pip --disable-pip-version-check -q install "$@" \
        2> >(grep -v "is ignored: it is neither a file nor a directory" >&2)
}

command=${1:-}
shift || true
case $command in
    setup)
        setup test,zoo,sweep,dev
        ;;
    demo)
        setup
        log "Training DrQ-v2 on walker-walk from pixels at its DrQ-v2 preset but for 6,000 frames (preset: 1.1M), 2,000 seed frames (4,000), batch 32 (512), an evaluation of 1 episode (10) every 3,000 frames (10,000); minutes on a CPU: benchmarks/README.md#demo"
        "$VENV/bin/python" -m sb3_collapse.train --env walker-walk --frames 6000 --seed 0 --logdir runs \
            --seed-frames 2000 --batch-size 32 --eval-every-frames 3000 --eval-episodes 1 "$@"
        echo "See the curves with: $VENV/bin/tensorboard --logdir runs"
        ;;
    test)
        setup test,zoo,sweep,dev
        log "Running the test suite"
        # Two workers (pytest-xdist): on two cores the suite takes about 0.6x as long as in one process
        # (benchmarks/README.md#test-suite); tests/conftest.py shares the longest run between the workers. -n 0 runs it in one.
        "$VENV/bin/python" -m pytest -n auto --maxprocesses 2 --dist loadfile --no-loadscope-reorder "$@"
        ;;
    *)
        echo "usage: bash run.sh demo|test|setup [extra arguments]" >&2
        exit 2
        ;;
esac
