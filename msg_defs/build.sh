#!/usr/bin/env bash
# Build the tf2_msgs and splat_slam_msgs interface packages and install them into the venv $VIRTUAL_ENV
# using only pip-installed ROS 2 Jazzy tools (see msg_defs/README.md).
#   VIRTUAL_ENV=/path/to/.venv bash msg_defs/build.sh        (run.sh does this)
# Defaults to <repo>/.venv when VIRTUAL_ENV is unset. Idempotent: a re-run with nothing
# changed only checks the build (~1 s). Build trees: <repo>/build/msgs{,-tf2_msgs} (git-ignored).
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

# build_pkg SOURCE_DIR BUILD_DIR: configure, build and install one interface package.
build_pkg() {
  local src="$1" bld="$2" gen=()
  # A build tree configured for another venv is stale: start over.
  if [ -f "$bld/CMakeCache.txt" ] && ! grep -q "^CMAKE_INSTALL_PREFIX:PATH=$VENV\$" "$bld/CMakeCache.txt"; then
    rm -rf "$bld"
  fi
  if [ ! -f "$bld/CMakeCache.txt" ] && command -v ninja >/dev/null 2>&1; then gen=(-G Ninja); fi
  mkdir -p "$bld"
  cmake -S "$src" -B "$bld" "${gen[@]}" -Wno-dev \
    -DCMAKE_BUILD_TYPE=Release \
    -DCMAKE_INSTALL_PREFIX="$VENV" \
    -DPython3_EXECUTABLE="$PY" -DPython3_FIND_VIRTUALENV=ONLY \
    -DBUILD_TESTING=OFF >"$bld/configure.log" 2>&1 \
    || { tail -n 40 "$bld/configure.log" >&2; err "cmake configure failed (log: $bld/configure.log)"; }
  cmake --build "$bld" -j "$(nproc 2>/dev/null || echo 2)" >"$bld/build.log" 2>&1 \
    || { tail -n 40 "$bld/build.log" >&2; err "build failed (log: $bld/build.log)"; }
  cmake --install "$bld" >"$bld/install.log" 2>&1 \
    || { tail -n 40 "$bld/install.log" >&2; err "install failed (log: $bld/install.log)"; }
}

# tf2_msgs (the standard interface package, not on PyPI) and splat_slam_msgs
build_pkg "$HERE/tf2_msgs" "$BUILD-tf2_msgs"
build_pkg "$HERE" "$BUILD"

# Check: the generated Python classes import through the venv's interpreter.
"$PY" -c "from tf2_msgs.msg import TFMessage, TF2Error; from tf2_msgs.srv import FrameGraph; from tf2_msgs.action import LookupTransform" \
  || err "tf2_msgs was installed into $VENV but does not import"
"$PY" -c "from splat_slam_msgs.msg import Keyframe, PoseGraphUpdate, ProxyDepth, MapperStatus, FrameAck; from splat_slam_msgs.srv import SaveMap, RenderPose, LoadMap" \
  || err "splat_slam_msgs was installed into $VENV but does not import"
echo "tf2_msgs and splat_slam_msgs installed into $VENV"
