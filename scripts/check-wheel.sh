#!/usr/bin/env bash
# The wheel works on its own: build it, install it with its dependencies (from PyPI) into a fresh virtual
# environment in a temporary folder, and run `carmreg demo` there, outside the checkout and without its cache.
# Fails when a package or resource is missing from the wheel. Used by .ci/run; takes a few minutes (downloads).
set -euo pipefail
cd "$(dirname "$0")/.."
REPO=$PWD
PY=${PYTHON:-python3}
WORK=$(mktemp -d "${TMPDIR:-/tmp}/carmreg-wheel.XXXXXX")
trap 'rm -rf "$WORK"' EXIT

"$PY" -m venv "$WORK/venv"
"$WORK/venv/bin/python" -m pip install -q --upgrade pip
"$WORK/venv/bin/python" -m pip wheel -q --no-deps -w "$WORK/dist" "$REPO"
rm -rf "$REPO/build"  # setuptools' build folder from `pip wheel`
WHEEL=$(ls "$WORK"/dist/carmreg-*.whl)
echo "check-wheel: built $(basename "$WHEEL")"
"$WORK/venv/bin/python" -m pip install -q "$WHEEL"

cd "$WORK"
export CARMREG_CACHE="$WORK/cache"
"$WORK/venv/bin/python" - "$REPO" <<'PY'
import sys
from pathlib import Path
import carmreg, carmreg.logic, carmreg.resources
repo = Path(sys.argv[1]).resolve()
for module in (carmreg, carmreg.logic, carmreg.resources):
    where = Path(module.__file__).resolve()
    assert repo not in where.parents, f"{module.__name__} imported from the checkout ({where}), not the wheel"
print(f"check-wheel: carmreg imported from {Path(carmreg.__file__).parent}")
PY
"$WORK/venv/bin/carmreg" demo --out "$WORK/demo-out"
for f in result.json overlay.png drr.nrrd carm.tfm slicer/CarmReg.mrml; do
  test -s "$WORK/demo-out/$f" || { echo "check-wheel: carmreg demo did not write $f" >&2; exit 1; }
done
echo "check-wheel: OK (wheel installed in a fresh environment, carmreg demo ran outside the checkout)"
