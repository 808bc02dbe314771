#!/usr/bin/env bash
# Set up (idempotent) and run splat_slam_ros.
#   ./run.sh demo   set up .venv, then run the main job on the embedded default sequence
#   ./run.sh test   set up .venv, then run the test suite (what CI runs)
#   ./run.sh setup  only set up .venv
#   ./run.sh check-system  print the missing Debian packages (empty line: none), install nothing
# Set-up installs the apt packages it needs (when run as root and missing), creates .venv/
# in the repository root, installs torch==2.13.0, the ROS 2 Jazzy wheels, builds the
# tf2_msgs + splat_slam_msgs interface packages into the venv and installs this project editable.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
cd "$ROOT"
VENV="$ROOT/.venv"
# OpenMP threads sleep instead of spinning while idle: on a busy 2-core machine spinning
# made the rasterizer up to 50x slower (measured).
export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"
PY="$VENV/bin/python"

log() { printf '\033[1m[run.sh]\033[0m %s\n' "$*" >&2; }

# missing_packages: the Debian packages set-up needs that this machine lacks, one line, space-
# separated (empty when nothing is missing). Every probe is a plain test or captures its whole
# output before matching it: under `set -o pipefail` a `cmd | grep -q` pipeline fails at random
# when grep exits at the first match and cmd then dies of SIGPIPE.
missing_packages() {
  local need=() libs
  command -v cmake >/dev/null 2>&1 || need+=(cmake)
  command -v g++ >/dev/null 2>&1 || need+=(g++)
  command -v make >/dev/null 2>&1 || need+=(make)
  python3 -c 'import ensurepip, venv' >/dev/null 2>&1 || need+=(python3-venv)
  [ -e /usr/lib/x86_64-linux-gnu/libjemalloc.so.2 ] || [ -e /usr/lib/aarch64-linux-gnu/libjemalloc.so.2 ] || need+=(libjemalloc2)
  libs="$(/sbin/ldconfig -p 2>/dev/null || true)"
  case "$libs" in *"libusb-1.0.so.0 "*) ;; *) need+=(libusb-1.0-0) ;; esac   # open3d
  echo "${need[*]}"
}

ensure_apt() {
  local need=()
  read -r -a need <<< "$(missing_packages)"
  if [ ${#need[@]} -gt 0 ]; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
      log "installing apt packages: ${need[*]}"
      DEBIAN_FRONTEND=noninteractive apt-get update -qq
      DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need[@]}" >/dev/null
    else
      log "missing system packages: ${need[*]} (install them with apt as root, then re-run)"
      case " ${need[*]} " in *" libjemalloc2 "*) [ ${#need[@]} -eq 1 ] || exit 1;; *) exit 1;; esac
    fi
  fi
}

stamp_of() { cat "$@" 2>/dev/null | sha256sum | cut -c1-16; }

ensure_venv() {
  ensure_apt
  if [ ! -x "$PY" ]; then
    log "creating $VENV"
    python3 -m venv "$VENV"
  fi
  local want have
  want=$(stamp_of requirements.txt setup.cfg setup.py)
  have=$(cat "$VENV/.splat_deps_stamp" 2>/dev/null || true)
  if [ "$want" != "$have" ]; then
    log "installing Python packages into .venv (first time: a few minutes)"
    "$PY" -m pip install -q --disable-pip-version-check torch==2.13.0
    "$PY" -m pip install -q --disable-pip-version-check -r requirements.txt
    "$PY" -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation -e .
    echo "$want" > "$VENV/.splat_deps_stamp"
  fi
  want=$(stamp_of msg_defs/CMakeLists.txt msg_defs/package.xml msg_defs/msg/*.msg msg_defs/srv/*.srv msg_defs/build.sh \
    msg_defs/cmake/*.cmake msg_defs/tf2_msgs/CMakeLists.txt msg_defs/tf2_msgs/package.xml msg_defs/tf2_msgs/*/*.*)
  have=$(cat "$VENV/.splat_msgs_stamp" 2>/dev/null || true)
  if [ "$want" != "$have" ]; then
    log "building the tf2_msgs and splat_slam_msgs interface packages into .venv"
    VIRTUAL_ENV="$VENV" PATH="$VENV/bin:$PATH" bash msg_defs/build.sh
    echo "$want" > "$VENV/.splat_msgs_stamp"
  fi
}

cmd="${1:-demo}"
shift || true
case "$cmd" in
  setup) ensure_venv ;;
  check-system) missing_packages ;;
  demo)  ensure_venv; exec "$PY" -m splat_slam_ros.demo "$@" ;;
  test)  ensure_venv; exec "$PY" -m pytest -n "${SPLAT_TEST_WORKERS:-2}" --dist loadfile "$@" ;;
  *) echo "usage: ./run.sh demo|test|setup|check-system [args...]" >&2; exit 2 ;;
esac
