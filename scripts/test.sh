#!/usr/bin/env bash
# Lint, then run the test suite (logic, CLI, GUI under a virtual display when one is needed).
#
#   ./scripts/test.sh                     the suite: every test but the benchmark cases' (about 5 min on 2 cores)
#   ./scripts/test.sh --benchmark-cases   only the benchmark cases' tests (pytest marker ``benchmark_case``: each
#                                         registers a case of the appearance benchmark, drawn by its independent
#                                         simulator, to pin a behaviour found on it; 15-60 s each, about 5 min)
#   ./scripts/test.sh --all               both (CI runs the suite, then the benchmark cases)
# Further arguments go to pytest (a -m of your own replaces the tier's).
#
# The tests run on one pytest-xdist worker per core, each worker on one numba thread: most of the suite's time is
# registrations whose DRR kernel is parallel over image rows, and two processes on one thread each keep two cores
# busier than one process on two (stop 43, this 2-core machine: 7 min 51 s against 9 min 19 s - 9 min 52 s).
# Up to four workers (each holds its own CTs and cases); CARMREG_TEST_WORKERS=0 runs everything in this process
# (numba on every core), =N on N workers.
set -euo pipefail
cd "$(dirname "$0")/.."
tier=(-m "not benchmark_case")
case "${1:-}" in
  --benchmark-cases) tier=(-m benchmark_case); shift ;;
  --all) tier=(); shift ;;
esac
.venv/bin/ruff check .
cores=$(nproc 2>/dev/null || echo 2)
workers=${CARMREG_TEST_WORKERS:-$(( cores < 4 ? cores : 4 ))}
args=(-q --durations=15 "${tier[@]}")
if [ "$workers" != "0" ]; then
  export NUMBA_NUM_THREADS=1
  args+=(-n "$workers" --dist loadfile)
fi
if [ -z "${DISPLAY:-}" ] && command -v xvfb-run >/dev/null 2>&1; then
  exec xvfb-run -a -s "-screen 0 1600x1000x24" .venv/bin/python -m pytest "${args[@]}" "$@"
fi
exec .venv/bin/python -m pytest "${args[@]}" "$@"
