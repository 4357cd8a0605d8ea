#!/bin/sh
# The PGT benchmark: base stage, then EcoSplat's budget stage, on the small preset; the budget
# curve on held-out synthetic streets; seconds per step and per prediction for every preset; the
# matcher comparison (plane sweep vs epipolar attention, MATCH_STEPS steps each; 0 skips it);
# then the figures (bench/figures/pgt_curves.png, pgt_budget.png) and tables for the results page.
# Usage: sh bench/experiments/pgt_run.sh OUT [BASE_STEPS] [BUDGET_STEPS] [SCENES] [MATCH_STEPS]
# Runs niced, one torch thread (the machine is shared; timings are under that load). Every stage
# resumes from its checkpoint, so a rerun after an interruption continues where it stopped.
set -eu
OUT=${1:?usage: sh bench/experiments/pgt_run.sh OUT [BASE_STEPS] [BUDGET_STEPS] [SCENES] [MATCH_STEPS]}
BASE=${2:-700}
BUDGET=${3:-250}
SCENES=${4:-8}
MATCH=${5:-100}
PY=${PY:-.venv/bin/python}
export POCL_MAX_WORK_GROUP_SIZE=256
mkdir -p "$OUT"
set -x
nice -n 10 $PY -c "import sys; from clsplat.models.pgt.cli import train; sys.exit(train(sys.argv[1:]))" \
  --stage base --data synthetic --preset small --steps "$BASE" --threads 1 --checkpoint-every 50 \
  --out "$OUT/base" $( [ -f "$OUT/base/checkpoint.pt" ] && echo --resume )
nice -n 10 $PY -c "import sys; from clsplat.models.pgt.cli import train; sys.exit(train(sys.argv[1:]))" \
  --stage budget --init "$OUT/base/checkpoint.pt" --data synthetic --preset small --steps "$BUDGET" --threads 1 \
  --checkpoint-every 50 --out "$OUT/budget" $( [ -f "$OUT/budget/checkpoint.pt" ] && echo --resume )
nice -n 10 $PY -c "import sys; from clsplat.models.pgt.cli import evaluate; sys.exit(evaluate(sys.argv[1:]))" \
  --checkpoint "$OUT/budget/checkpoint.pt" --data synthetic --budgets 1,0.5,0.2,0.1,0.05 --num-scenes "$SCENES" \
  --threads 1 --out "$OUT/eval"
nice -n 10 $PY bench/experiments/pgt_speed.py --out "$OUT/speed" --presets tiny,small,paper --repeats 3
if [ "$MATCH" -gt 0 ]; then
  nice -n 10 $PY bench/experiments/pgt_matching.py --preset small --steps "$MATCH" --num-scenes 4 --out "$OUT/matching"
fi
$PY bench/experiments/pgt_figures.py "$OUT" --figures bench/figures
