#!/usr/bin/env bash
# The rehearsal's interpreter: a Python 3.12 virtual environment with the GPU machine's versions (torch 2.11, numpy
# 2.5, triton 3.6; benchmarks/rehearsal/gpu_machine_packages.txt lists the image's distributions) and the ones of its
# packages that sb3-collapse and its tests import. Nothing of sb3-collapse's own dependencies that the GPU machine
# lacks (SB3, gymnasium, dm_control, mujoco, shimmy): those come as the carried wheels (gpu_prepare.sh), as there.
#
#   bash benchmarks/rehearsal/venv.sh      # prints the interpreter's path; made once, reused while its versions hold
#
# REHEARSAL_VENV (default /tmp/sb3-collapse-rehearsal/venv312) chooses the folder, PYTHON312 the interpreter that
# makes it (default: pyenv's 3.12, else python3.12 on the PATH); a venv already there gets what the lists below add.
# torch comes from PyPI, its CUDA build, as on the GPU machine, with its NVIDIA libraries and triton (5 GB in all,
# about 5 minutes once): it runs on the CPU here. Exit status 3: no network.
set -euo pipefail
VENV=${REHEARSAL_VENV:-/tmp/sb3-collapse-rehearsal/venv312}
# The GPU machine's versions (the device tool's KINDS.md: Python 3.12.3, torch 2.11.0+cu130, numpy 2.5.2, triton
# 3.6.0), then what sb3-collapse and its tests import from the image, at the versions pip picks.
PINS=(torch==2.11.0 numpy==2.5.2 triton==3.6.0)
# dm_control's, SB3's and mujoco's needs that the image has (the carried wheels are installed without dependencies).
OTHERS=(matplotlib tensorboard tqdm rich pyyaml pillow psutil pytest pytest-timeout hypothesis scikit-learn
        lxml scipy requests pandas etils attrs wrapt cloudpickle setuptools protobuf pyparsing typing-extensions imageio)
READY=$VENV/.rehearsal-ready
if [[ -f $READY && $(cat "$READY") == "${PINS[*]} ${OTHERS[*]}" ]] && "$VENV/bin/python" -c "import torch" 2>/dev/null
then
    echo "$VENV/bin/python"
    exit 0
fi
if [[ -n ${PYTHON312:-} ]]; then
    maker=("$PYTHON312")
elif command -v pyenv >/dev/null && pyenv versions --bare | grep -q '^3\.12'; then
    maker=(env "PYENV_VERSION=$(pyenv versions --bare | grep '^3\.12' | tail -1)" python3.12)
else
    maker=(python3.12)
fi
if ! "$VENV/bin/python" -c "import sys; assert sys.version_info[:2] == (3, 12)" 2>/dev/null; then
    rm -rf "$VENV"
    "${maker[@]}" -m venv "$VENV" >&2
    "$VENV/bin/python" -m pip install -q --upgrade pip >&2 || { echo "error: no network to PyPI?" >&2; exit 3; }
fi
"$VENV/bin/python" -m pip install -q "${PINS[@]}" "${OTHERS[@]}" >&2 || { echo "error: pip install failed" >&2; exit 3; }
echo "${PINS[*]} ${OTHERS[*]}" >"$READY"
echo "$VENV/bin/python"
