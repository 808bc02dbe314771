#!/usr/bin/env bash
# Build the splat_slam_msgs interface package and install it into the venv $VIRTUAL_ENV
# using only pip-installed ROS 2 Jazzy tools (see msg_defs/README.md).
#   VIRTUAL_ENV=/path/to/.venv bash msg_defs/build.sh        (run.sh does this)
# Defaults to <repo>/.venv when VIRTUAL_ENV is unset. Idempotent: a re-run with nothing
# changed only checks the build (~1 s). Build tree: <repo>/build/msgs (git-ignored).
set -euo pipefail
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
ROOT="$(cd "$HERE/.." && pwd)"
VENV="${VIRTUAL_ENV:-$ROOT/.venv}"
PY="$VENV/bin/python"
BUILD="${SPLAT_MSGS_BUILD_DIR:-$ROOT/build/msgs}"

err() { echo "msg_defs/build.sh: error: $*" >&2; exit 2; }
[ -x "$PY" ] || err "no Python venv at $VENV (set VIRTUAL_ENV)"
command -v cmake >/dev/null 2>&1 || err "cmake not found (apt-get install cmake)"
command -v c++ >/dev/null 2>&1 || command -v g++ >/dev/null 2>&1 || err "no C++ compiler (apt-get install g++)"
[ -f "$VENV/share/rosidl_default_generators/cmake/rosidl_default_generatorsConfig.cmake" ] \
  || err "ROS msg build tools missing in $VENV (pip install -r requirements.txt)"

# rosidl finds its type-support generators through the ament index of these prefixes.
export AMENT_PREFIX_PATH="$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export CMAKE_PREFIX_PATH="$VENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
export PATH="$VENV/bin:$PATH"
export LD_LIBRARY_PATH="$VENV/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"

GEN=()
if [ ! -f "$BUILD/CMakeCache.txt" ]; then
  if command -v ninja >/dev/null 2>&1; then GEN=(-G Ninja); fi
fi
# A build tree configured for another venv is stale: start over.
if [ -f "$BUILD/CMakeCache.txt" ] && ! grep -q "^CMAKE_INSTALL_PREFIX:PATH=$VENV\$" "$BUILD/CMakeCache.txt"; then
  rm -rf "$BUILD"
  if command -v ninja >/dev/null 2>&1; then GEN=(-G Ninja); fi
fi

mkdir -p "$BUILD"
cmake -S "$HERE" -B "$BUILD" "${GEN[@]}" -Wno-dev \
  -DCMAKE_BUILD_TYPE=Release \
  -DCMAKE_INSTALL_PREFIX="$VENV" \
  -DPython3_EXECUTABLE="$PY" -DPython3_FIND_VIRTUALENV=ONLY \
  -DBUILD_TESTING=OFF >"$BUILD/configure.log" 2>&1 \
  || { tail -n 40 "$BUILD/configure.log" >&2; err "cmake configure failed (log: $BUILD/configure.log)"; }
cmake --build "$BUILD" -j "$(nproc 2>/dev/null || echo 2)" >"$BUILD/build.log" 2>&1 \
  || { tail -n 40 "$BUILD/build.log" >&2; err "build failed (log: $BUILD/build.log)"; }
cmake --install "$BUILD" >"$BUILD/install.log" 2>&1 \
  || { tail -n 40 "$BUILD/install.log" >&2; err "install failed (log: $BUILD/install.log)"; }

# Check: the generated Python classes import through the venv's interpreter.
"$PY" -c "from splat_slam_msgs.msg import Keyframe, PoseGraphUpdate, ProxyDepth, MapperStatus, FrameAck; from splat_slam_msgs.srv import SaveMap, RenderPose" \
  || err "splat_slam_msgs was installed into $VENV but does not import"
echo "splat_slam_msgs installed into $VENV"
