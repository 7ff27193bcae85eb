#!/usr/bin/env bash
# sb3-collapse: set up and run.   bash run.sh demo   |   bash run.sh test   |   bash run.sh setup
#
# setup: headless OpenGL (Debian packages, when missing and apt-get can install them), a virtual
#        environment in .venv (Python >= 3.11; PYTHON=python3.12 picks one), PyTorch (the one already there, else
#        `pip install $TORCH_SPEC`, torch==2.13.0 by default: from PyPI on Linux that is the CUDA build; see
#        README.md#requirements), then this package in editable mode (with its test, zoo, sweep and dev extras
#        for `setup` and `test`).
# demo:  setup, then a short DrQ-v2 run on walker-walk from pixels; writes runs/walker-walk_s0/.
# test:  setup, then the test suite (pytest). Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")"

PYTHON=${PYTHON:-}
VENV=${VENV:-.venv}
TORCH_SPEC=${TORCH_SPEC:-torch==2.13.0}
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

find_python() {
    local candidate
    for candidate in ${PYTHON:-python3.11 python3.12 python3}; do
        if "$candidate" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
            echo "$candidate"; return
        fi
    done
    echo "Python >= 3.11 is required; ${PYTHON:-python3.11, python3.12, python3}: none here (set PYTHON=...)." >&2
    exit 1
}

check_venv_python() {
    # A venv made by another Python is kept only when PYTHON does not ask for a different version.
    [[ -n $PYTHON ]] || return 0
    local wanted have
    wanted=$("$(find_python)" -c 'import sys; print("%d.%d" % sys.version_info[:2])')
    have=$("$VENV/bin/python" -c 'import sys; print("%d.%d" % sys.version_info[:2])')
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
        log "Creating the virtual environment $VENV"
        "$(find_python)" -m venv "$VENV"
    fi
    check_venv_python
    if ! "$VENV/bin/python" -c 'import torch' 2>/dev/null; then
        log "Installing PyTorch ($TORCH_SPEC)"
        # shellcheck disable=SC2086  # TORCH_SPEC's words: a requirement and pip's options (--index-url ...)
        pip_install $TORCH_SPEC
    fi
    log "Installing sb3-collapse and its dependencies"
    pip_install -e ".${extras:+[$extras]}"
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
        "$VENV/bin/python" -m pytest "$@"
        ;;
    *)
        echo "usage: bash run.sh demo|test|setup [extra arguments]" >&2
        exit 2
        ;;
esac
