set -x
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
cd /work/main
for s in 0 1 2; do
  for rb in "32 16" "32 128" "64 16"; do
    set -- $rb
    nice -n 10 .venv/bin/python examples/reproduce.py --experiment e3 --iterations 60 --methods adam pg \
      --resolution $1 --batch-size $2 --seeds $s --poisson-solver spectral --out out/e3_fact/r$1_b$2_s$s
  done
done
