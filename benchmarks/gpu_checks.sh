#!/usr/bin/env bash
# The GPU checks in one run, for a machine with an NVIDIA GPU, torch and jax (no network needed):
#
#   OUT=/some/folder bash benchmarks/gpu_checks.sh [PART ...]    # default: every part; logs and results to $OUT
#
# Parts (each with its own time limit, so that one part's failure leaves the others):
#   tests     the CUDA tests (tests/phisim/test_cuda.py and every test marked for CUDA), 8 workers
#   jaxcfd    the periodic fluid step against jax-cfd, both sides on the GPU (benchmarks/bench_jaxcfd.py)
#   compiled  phisim.compile (inductor, CUDA graphs) against jax-cfd: one step, batches, rollouts, gradients
#   etdrk     the ETDRK steppers against exponax, both sides on the GPU (benchmarks/bench_etdrk.py)
#   bodies    flows past bodies: sharp against blended bodies, PCG against the direct pressure solve; the DFG
#             cylinder step's kernel launches, host reads and GPU time (bench_bodies.py --cylinder)
#   stepcost  the fixed cost of one smoke step on small grids (benchmarks/bench_simulate.py --step-cost)
#
# Wheels in .whl/ (pyfftw, jax-cfd, tree-math, exponax for the running Python) are installed to /tmp/site first
# where the machine lacks them.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-/tmp/gpu-checks}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1
PY=${PYTHON:-python3}
PEER=$(command -v "$PY")
PARTS=${*:-tests jaxcfd compiled etdrk bodies stepcost}
if compgen -G ".whl/*.whl" >/dev/null; then
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD
fi
{
  nvidia-smi -L
  "$PY" -c "import sys, torch, jax, scipy; from phisim.spectral import pocket
print('python', sys.version.split()[0], 'torch', torch.__version__, 'cuda', torch.version.cuda,
      torch.cuda.get_device_name(0), 'jax', jax.__version__, jax.devices(), 'scipy', scipy.__version__,
      'real-to-real transforms', getattr(pocket._pocket, '__name__', None))"
} 2>&1 | tee "$OUT/machine.txt"

part() { [[ " $PARTS " == *" $1 "* ]]; }

if part tests; then
  echo "== CUDA tests"
  timeout 180 "$PY" -m pytest -q -p no:cacheprovider -p no:logging -n 8 --tb=short -m "not slow" \
    tests/phisim/test_cuda.py tests/phisim/test_compiled_code.py tests/test_scripts_device.py \
    tests/inverse/test_hig.py tests/phisim/solvers/test_linalg.py tests/phisim/pde/test_stepper_api.py \
    tests/phisim/spectral/test_fft.py \
    > "$OUT/tests.log" 2>&1
  echo "tests rc=$?"; grep -E "^(FAILED|ERROR)|passed|failed" "$OUT/tests.log" | tail -25
fi
if part jaxcfd; then
  echo "== periodic fluid step against jax-cfd, both on the GPU"
  timeout 120 "$PY" benchmarks/bench_jaxcfd.py --device cuda --peer-python "$PEER" --rounds 3 --write \
    > "$OUT/jaxcfd.log" 2>&1
  echo "jaxcfd rc=$?"; tail -30 "$OUT/jaxcfd.log"; cp benchmarks/results/jaxcfd_cuda.* "$OUT/" 2>/dev/null
fi
if part compiled; then
  echo "== compiled steps (phisim.compile: inductor, CUDA graphs) against jax-cfd"
  timeout 130 "$PY" benchmarks/bench_jaxcfd.py --device cuda --peer-python "$PEER" --rounds 3 --quick \
    --variants fused compiled > "$OUT/compiled.log" 2>&1
  echo "compiled rc=$?"; tail -16 "$OUT/compiled.log"
fi
if part etdrk; then
  echo "== ETDRK steppers against exponax, both on the GPU"
  timeout 100 "$PY" benchmarks/bench_etdrk.py --device cuda --peer-python "$PEER" --quick --rounds 2 \
    --out "$OUT/etdrk_cuda.json" > "$OUT/etdrk.log" 2>&1
  echo "etdrk rc=$?"; tail -36 "$OUT/etdrk.log"
fi
if part bodies; then
  echo "== flows past bodies on the GPU"
  timeout 100 "$PY" benchmarks/bench_bodies.py --device cuda --wake --sizes 128 256 512 > "$OUT/bodies.log" 2>&1
  echo "bodies rc=$?"; tail -30 "$OUT/bodies.log"
  timeout 120 "$PY" benchmarks/bench_bodies.py --device cuda --cylinder 82 164 --json "$OUT/cylinder_step.json" \
    > "$OUT/cylinder_step.log" 2>&1
  echo "cylinder step rc=$?"; cat "$OUT/cylinder_step.log"
fi
if part stepcost; then
  echo "== the fixed cost of one smoke step"
  timeout 60 "$PY" benchmarks/bench_simulate.py --step-cost --device cuda --markdown > "$OUT/stepcost.log" 2>&1
  echo "stepcost rc=$?"; tail -20 "$OUT/stepcost.log"
fi
