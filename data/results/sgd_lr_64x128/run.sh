#!/bin/bash
# SGD learning-rate probe at the published size (64², batch 128), 40 iterations, seed 0.
# The 32²/16 rates diverge here (E3: lr 1e-9 at iteration 2), so pick the rate for the 300-iteration runs.
cd "$(dirname "$0")/../../.."
export OMP_NUM_THREADS=1
for lr in 1e-10 1e-11 3e-12; do
  python examples/reproduce.py --experiment e3 --resolution 64 --batch-size 128 --methods sgd --sgd-lr $lr \
    --iterations 40 --seeds 0 --out data/results/sgd_lr_64x128/e3_lr$lr
done
for lr in 1e-5 3e-6 1e-6; do
  python examples/reproduce.py --experiment e4 --resolution 64 --batch-size 128 --methods sgd --sgd-lr $lr \
    --iterations 40 --seeds 0 --out data/results/sgd_lr_64x128/e4_lr$lr
done
