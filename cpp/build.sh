#!/usr/bin/env bash
# Build the C++ library and examples into cpp/build (or $DACR_CPP_BUILD) against the libtorch inside the installed
# torch wheel; incremental: a second run only rebuilds what changed. Used by `make cpp` and tests/test_cpp.py.
#   PYTHON=.venv/bin/python cpp/build.sh
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
build="${DACR_CPP_BUILD:-$here/build}"
python="${PYTHON:-python3}"
missing() { echo "make cpp: $1 is missing ($2)" >&2; exit 1; }
command -v cmake > /dev/null || missing cmake "install it, e.g. apt-get install cmake"
command -v "${CXX:-c++}" > /dev/null || missing "a C++ compiler (${CXX:-c++})" "install g++ or set CXX"
prefix="$("$python" -c 'import torch; print(torch.utils.cmake_prefix_path)' 2> /dev/null)" \
  || missing "torch in $python" "run make .venv, or set PYTHON to the Python that has torch"
generator=("-G" "Unix Makefiles")
command -v ninja > /dev/null && generator=("-G" "Ninja")
if [ ! -f "$build/CMakeCache.txt" ]; then
  mkdir -p "$build"                        # its log inside the build folder, not beside it in the source tree
  cmake -S "$here" -B "$build" "${generator[@]}" -DCMAKE_BUILD_TYPE=Release -DCMAKE_PREFIX_PATH="$prefix" \
    -Wno-dev > "$build/configure.log" 2>&1 || { cat "$build/configure.log" >&2; exit 1; }
fi
cmake --build "$build" -j "$(nproc)"
