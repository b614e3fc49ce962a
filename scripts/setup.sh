#!/usr/bin/env bash
# Create .venv and install CarmReg (editable) with its GUI and test extras.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".[gui,test]"
# An editable install leaves CarmReg's own modules uncompiled: where Python may not write bytecode itself
# (PYTHONDONTWRITEBYTECODE set, as on this project's machines) every command would compile them again. A wheel
# install compiles them; so does this (a stale .pyc is ignored: Python checks each against its source).
.venv/bin/python -m compileall -q CarmRegModule Logic CarmReg.py > /dev/null
