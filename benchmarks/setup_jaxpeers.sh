#!/usr/bin/env bash
# Create the virtual environment of the JAX peers of the ETDRK benchmark (exponax 0.2.0, jax-cfd 0.2.1, CPU jax).
#
#   bash benchmarks/setup_jaxpeers.sh [VENV]     # default VENV: benchmarks/.venv-jax (idempotent)
#
# The environment stays apart from phisim's (.venv): the peer runs in a child process
# (benchmarks/peer_exponax.py) with its own interpreter. A '.gitignore' holding '*' is written into
# the environment so that git never lists it.
set -euo pipefail
cd "$(dirname "$0")"
VENV=${1:-.venv-jax}
PY=${PYTHON:-python3}
start=$(date +%s)

if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
fi
printf '*\n' > "$VENV/.gitignore"
VPY="$VENV/bin/python"
if ! "$VPY" -c "import jax, exponax, jax_cfd" 2>/dev/null; then
  "$VPY" -m pip install -q --upgrade pip setuptools wheel >/dev/null
  "$VPY" -m pip install -q "jax[cpu]" "jax-cfd==0.2.1" "exponax==0.2.0"
fi
"$VPY" -c "import jax, exponax, jax_cfd; print('jax', jax.__version__, 'exponax', getattr(exponax, '__version__', '0.2.0'), 'jax_cfd', jax_cfd.__version__)"
echo "setup_jaxpeers: done in $(( $(date +%s) - start )) s"
