#!/usr/bin/env bash
# On-demand check for tests that depend on the machine: the default suite (./run.sh test)
# three times in a row, (1) as CI runs it, (2) with a CPU-busy process on one core beside it,
# (3) with OMP_NUM_THREADS=1 (other reduction orders and SIMD paths in torch / OpenMP).
# A test that passes in (1) and fails in (2) or (3) asserts on timing or on float reduction
# order; fix the test (docs/development.md "Stress runs"). Extra arguments pass to pytest in every run, e.g.
#   tests/run_stress.sh tests/test_graph_e2e.py
# Prints one line per run (result, wall seconds, load average) and exits non-zero when any
# run failed. Takes about three times as long as ./run.sh test.
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
LOGDIR="${SPLAT_STRESS_LOGS:-$ROOT/out/stress}"
mkdir -p "$LOGDIR"
./run.sh setup

summary() {   # the pytest closing line of a log
  local line=""
  while IFS= read -r ln; do
    case "$ln" in *" passed"*|*" failed"*|*" error"*) line="$ln" ;; esac
  done < "$1"
  echo "$line"
}

results=()
fail=0
run_one() {   # name, then a command prefix
  local name="$1"; shift
  local log="$LOGDIR/$name.log" t0 rc
  t0=$(date +%s)
  echo "[stress] $name: running (log: $log)" >&2
  "$@" ./run.sh test "${ARGS[@]}" >"$log" 2>&1
  rc=$?
  results+=("$name: rc=$rc, $(( $(date +%s) - t0 )) s, load $(cut -d' ' -f1-3 /proc/loadavg): $(summary "$log")")
  [ "$rc" = 0 ] || fail=1
}

ARGS=("$@")
run_one plain env
# one core kept busy for the whole run by a plain shell loop
( while :; do :; done ) &
BUSY=$!
trap 'kill "$BUSY" 2>/dev/null' EXIT
run_one cpu-busy env
kill "$BUSY" 2>/dev/null
wait "$BUSY" 2>/dev/null
trap - EXIT
run_one omp-1-thread env OMP_NUM_THREADS=1

for r in "${results[@]}"; do echo "[stress] $r"; done
exit "$fail"
