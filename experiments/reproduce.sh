#!/usr/bin/env bash
# Reproduce the paper's experiments: 5 trials (seeds) of paper_volume and of paper_locomotion, then every figure.
#
#   experiments/reproduce.sh                 # train both sweeps (GPU), then draw every figure into figures/
#   SKIP_TRAIN=1 experiments/reproduce.sh    # only (re)draw the figures from existing sweeps
#
# Settings (environment variables): PYTHON (default .venv/bin/python), SEEDS (default 0,1,2,3,4),
# RUNS (default runs/reproduce: the two sweeps go to $RUNS/paper_volume and $RUNS/paper_locomotion), OUT
# (default figures), DEVICE (default cuda). Hydra's launcher runs the seeds one after another; to use several GPUs
# start one sweep per GPU instead, e.g. `CUDA_VISIBLE_DEVICES=1 SEEDS=1 experiments/reproduce.sh` with the same
# RUNS, then SKIP_TRAIN=1 for the figures. A killed sweep continues where its runs' checkpoints left off:
#   $PYTHON -m freeform.train trainer.resume=$RUNS/paper_locomotion/seed=3
# Expect hours: the paper's locomotion trials took ~28 h each on two A100s; volume trials are much shorter.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-.venv/bin/python}
SEEDS=${SEEDS:-0,1,2,3,4}
RUNS=${RUNS:-runs/reproduce}
OUT=${OUT:-figures}
DEVICE=${DEVICE:-cuda}
VOLUME=$RUNS/paper_volume
LOCOMOTION=$RUNS/paper_locomotion

if [[ -z "${SKIP_TRAIN:-}" ]]; then
    "$PYTHON" -m freeform.train -m experiment=paper_volume "seed=$SEEDS" trainer.device="$DEVICE" \
        trainer.progress=false "hydra.sweep.dir='$VOLUME'"
    "$PYTHON" -m freeform.train -m experiment=paper_locomotion "seed=$SEEDS" trainer.device="$DEVICE" \
        trainer.progress=false "hydra.sweep.dir='$LOCOMOTION'"
fi

"$PYTHON" -m experiments.volume "$VOLUME" --out "$OUT/volume"                        # Fig. 2
"$PYTHON" -m experiments.locomotion "$LOCOMOTION" --out "$OUT/locomotion"            # Fig. 4 A-H
"$PYTHON" -m experiments.critic "$LOCOMOTION" --out "$OUT/critic" --device "$DEVICE" # Fig. 5
"$PYTHON" -m experiments.robustness "$LOCOMOTION" --out "$OUT/robustness" --device "$DEVICE"  # Fig. 6
"$PYTHON" -m experiments.hparams "$VOLUME" "$LOCOMOTION" --out "$OUT/hparams"        # Table I
echo "figures in $OUT/"
