# E3 at 60 iterations, three seeds per setting: resolution x batch size, and the ghost-cell boundary convention.
# Each run wrote out/e3_fact/<name>/e3.h5 and e3_summary.json; they were copied here as <name>.h5 and
# <name>_summary.json. Table: python examples/seed_table.py --runs data/results/e3_factorial/r64_b16_s{0,1,2}.h5 --at 60
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
for s in 0 1 2; do
  for rb in "32 16" "32 128" "64 16"; do
    set -- $rb
    nice -n 10 python examples/reproduce.py --experiment e3 --iterations 60 --methods adam pg \
      --resolution $1 --batch-size $2 --seeds $s --poisson-solver spectral --out out/e3_fact/r$1_b$2_s$s
  done
  nice -n 10 python examples/reproduce.py --experiment e3 --iterations 60 --methods adam pg \
    --resolution 64 --batch-size 16 --seeds $s --poisson-solver spectral --poisson-boundary ghost \
    --out out/e3_fact/r64_b16_ghost_s$s
done
# The paper text's grid, 80x60 (x by y), batch 16 (added later; same settings otherwise):
for s in 0 1 2; do
  nice -n 10 python examples/reproduce.py --experiment e3 --iterations 60 --methods adam pg \
    --resolution 80 60 --batch-size 16 --seeds $s --poisson-solver spectral --out out/e3_fact/r80x60_b16_s$s
done
# Normalisation and loss reduction (added later): x* without the per-sample normalisation, 3 seeds; the batch
# mean instead of the sum, seed 0 (Adam's scale invariance makes it equal to round-off; tests/inverse/test_reproduce.py).
for s in 0 1 2; do
  nice -n 10 python examples/reproduce.py --experiment e3 --iterations 60 --methods adam pg \
    --resolution 64 --batch-size 16 --seeds $s --poisson-solver spectral --no-normalize --out out/e3_fact/r64_b16_raw_s$s
done
nice -n 10 python examples/reproduce.py --experiment e3 --iterations 60 --methods adam pg \
  --resolution 64 --batch-size 16 --seeds 0 --poisson-solver spectral --reduction mean --out out/e3_fact/r64_b16_mean_s0
