#!/usr/bin/env bash
# One entry point that does all set-up on a fresh machine, then runs a job.
#   bash run.sh demo   -> small simulate + train demo; writes HDF5 and PNGs to out/demo/
#   bash run.sh test   -> the test suite (fast tests; set PHISIM_SLOW=1 to include slow ones), in
#                         PHISIM_TEST_WORKERS worker processes (default 2, one torch thread each; 0: one process)
set -euo pipefail
cd "$(dirname "$0")"
VENV=${PHISIM_VENV:-.venv}
PY=${PYTHON:-python3}

setup_env() {
  if [ ! -x "$VENV/bin/python" ]; then
    "$PY" -m venv "$VENV"
  fi
  # shellcheck disable=SC1091
  . "$VENV/bin/activate"
  local stamp="$VENV/.phisim-installed"
  if [ -f "$stamp" ] && [ "$stamp" -nt setup.py ]; then return; fi
  python -m pip install -q --upgrade pip setuptools wheel >/dev/null
  if ! python -c "import torch" 2>/dev/null; then
    # Prefer a local CPU wheel when the machine carries one (no multi-GB CUDA download);
    # elsewhere fall back to the normal index.
    if python -m pip install -q --no-deps --no-index "torch==2.13.0" 2>/dev/null; then
      python -m pip install -q "torch==2.13.0"
    else
      python -m pip install -q "torch>=2.1"
    fi
  fi
  python -m pip install -q -e ".[test]"
  touch "$stamp"
}

cmd=${1:-help}; shift || true
case "$cmd" in
  setup) setup_env ;;
  demo) setup_env; python examples/demo.py "$@" ;;
  test)
    setup_env
    workers=${PHISIM_TEST_WORKERS:-2}
    par=()
    if [ "$workers" != "0" ]; then par=(-n "$workers"); fi
    if [ "${PHISIM_SLOW:-0}" = "1" ]; then python -m pytest -q ${par[@]+"${par[@]}"} "$@"
    else python -m pytest -q -m "not slow" ${par[@]+"${par[@]}"} "$@"; fi ;;
  *) echo "usage: bash run.sh {demo|test|setup} [args...]"; exit 2 ;;
esac
