#!/usr/bin/env bash
# Create benchmarks/.phiflow-venv with PhiFlow 3.4.0 (and phiml) on torch, for the peer benchmarks.
#
#   bash benchmarks/setup_phiflow.sh     # install (idempotent; a second run only checks)
#
# torch is installed first from a local CPU wheel when the machine has one
# (pip install --no-deps --no-index torch==2.13.0), which avoids downloading a multi-GB CUDA build.
#
# The patch: when phiml compresses the sparse matrix of a jit-compiled linear function
# (SparseCoordinateTensor.compress in phiml/math/_sparse.py) it ravels (row, column) pairs into
# one linear index of the indices' dtype, int32, which overflows once rows*columns exceeds 2**31
# (grids above ~215x215 cells). The patch casts both index arrays to int64 before ravelling.
# The installed phiml stays untouched; a patched copy of the package is written to
# .phiflow-venv/phiml-patched/phiml, and the benchmark puts that directory first on PYTHONPATH
# only for the cases that need it (those report "patched": true).
set -euo pipefail
cd "$(dirname "$0")"
VENV=.phiflow-venv
PY=${PYTHON:-python3}
start=$(date +%s)

if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
fi
VPY="$VENV/bin/python"

if ! "$VPY" -c "import torch, phi" 2>/dev/null; then
  "$VPY" -m pip install -q --upgrade pip setuptools wheel >/dev/null
  if ! "$VPY" -c "import torch" 2>/dev/null; then
    if "$VPY" -m pip install -q --no-deps --no-index "torch==2.13.0" 2>/dev/null; then
      "$VPY" -m pip install -q "torch==2.13.0"
    else
      "$VPY" -m pip install -q "torch>=2.1"
    fi
  fi
  "$VPY" -m pip install -q "phiflow==3.4.0"
fi
"$VPY" -c "import phi, phiml, torch; print('phiflow', phi.__version__, 'phiml', phiml.__version__, 'torch', torch.__version__)"

"$VPY" - "$VENV/phiml-patched" <<'PYEOF'
import os, shutil, sys, phiml
dest = os.path.abspath(sys.argv[1])
src = os.path.dirname(phiml.__file__)
target = os.path.join(dest, "phiml", "math", "_sparse.py")
old = "lin_idx = bi.ravel_multi_index(bi.stack([c_idx_packed, u_idx_packed], -1)[0], (c_dims.volume, u_dims.volume))"
new = "lin_idx = bi.ravel_multi_index(bi.stack([bi.to_int64(c_idx_packed), bi.to_int64(u_idx_packed)], -1)[0], (c_dims.volume, u_dims.volume))  # phisim-benchmark int64 patch"
if os.path.exists(target) and "phisim-benchmark int64 patch" in open(target).read():
    print("phiml patch: present in", dest)
    sys.exit(0)
if os.path.exists(dest):
    shutil.rmtree(dest)
shutil.copytree(src, os.path.join(dest, "phiml"), ignore=shutil.ignore_patterns("__pycache__"))
text = open(target).read()
if text.count(old) != 1:
    sys.exit("phiml patch: expected line not found exactly once in %s (phiml version changed?)" % target)
open(target, "w").write(text.replace(old, new))
print("phiml patch: patched copy written to", dest)
PYEOF
echo "setup_phiflow: done in $(( $(date +%s) - start )) s"
