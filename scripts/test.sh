#!/usr/bin/env bash
# Lint, then run the whole test suite (logic, CLI, GUI under a virtual display when one is needed).
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/ruff check .
if [ -z "${DISPLAY:-}" ] && command -v xvfb-run >/dev/null 2>&1; then
  exec xvfb-run -a -s "-screen 0 1600x1000x24" .venv/bin/python -m pytest -q --durations=15 "$@"
fi
exec .venv/bin/python -m pytest -q --durations=15 "$@"
