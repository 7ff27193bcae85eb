#!/usr/bin/env bash
# Prepare, on a machine with network access, what benchmarks/gpu.sh needs on a GPU machine that has none (this project's
# lent GPU machines: Python 3.12 with a CUDA build of torch and the packages of benchmarks/rehearsal/
# gpu_machine_packages.txt; no network).
#
#   bash benchmarks/gpu_prepare.sh      # writes .whl/ (wheels for Python 3.12, x86_64) and .gl/ (EGL's Debian packages)
#
# Both folders are git-ignored; carry them to the GPU machine (64 MiB in all), where gpu.sh installs them; .whl/COMMIT
# names the commit they were made at (the copy there has no .git). benchmarks/gpu.md gives the sequence. dm_control is
# carried without its locomotion package and the dog's assets (the suite's other tasks need neither), to fit.
# WHEELS (default .whl) and PY_VERSION (default 3.12) choose the folder and the Python version of the wheels; --no-gl
# leaves .gl/ out. `gpu.sh --rehearse` uses them to make the same wheels for this machine's Python.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
WHEELS=${WHEELS:-.whl}
PY_VERSION=${PY_VERSION:-3.12}
PLATFORMS=(--platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_24_x86_64
           --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64)
# What the GPU machine lacks (benchmarks/rehearsal/gpu_machine_packages.txt), and nothing else: one version of each.
PINNED=(dm_control==1.0.50 mujoco==3.17.0 stable_baselines3==2.9.2 gymnasium==1.4.0 shimmy==2.0.1 labmaze==1.0.6
        dm-env==1.6 dm-tree==0.1.10 glfw==2.11.0 PyOpenGL==3.1.10 Farama-Notifications==0.0.6)

rm -rf "$WHEELS" && mkdir -p "$WHEELS"
"$PYTHON" -m pip download -q --no-deps --only-binary=:all: --python-version "$PY_VERSION" --implementation cp \
    "${PLATFORMS[@]}" -d "$WHEELS" "${PINNED[@]}" 2> >(grep -v "is ignored: it is neither a file nor a directory" >&2)
# dm_control, trimmed: unpacked by gpu.sh (a plain folder on PYTHONPATH), not installed by pip.
work=$(mktemp -d)
"$PYTHON" -m zipfile -e "$WHEELS"/dm_control-*.whl "$work"
rm -rf "$work"/dm_control/locomotion "$work"/dm_control/suite/dog_assets "$WHEELS"/dm_control-*.whl
(cd "$work" && "$PYTHON" -m zipfile -c dm_control.zip dm_control)
mv "$work/dm_control.zip" "$WHEELS/dm_control.zip"
rm -rf "$work"
# The commit the carried copy is of (it travels without .git): gpu.sh writes it into machine.txt.
if git rev-parse --short HEAD >/dev/null 2>&1; then
    echo "$(git rev-parse --short HEAD)$([[ -n $(git status --porcelain --untracked-files=no) ]] && echo \
        ', dirty: uncommitted changes when gpu_prepare.sh ran')" >"$WHEELS/COMMIT"
fi

if [[ ${1:-} != --no-gl ]] && command -v apt-get >/dev/null; then
    mkdir -p .gl /tmp/amd64/partial
    options=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64)
    apt-get "${options[@]}" update -qq
    (cd .gl && apt-get "${options[@]}" download -qq libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
fi
du -sh "$WHEELS" .gl 2>/dev/null || true
