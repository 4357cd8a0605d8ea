# Training steps of an older tree against today's, alternating, 2 rounds: the median of each
# run's logged step time (log.jsonl "time_s") after a skip, per family, one torch thread.
#   sh bench/experiments/steps_tree_ab.sh OLD_TREE
# OLD_TREE: a checkout of the old commit with clsplat/kernels, clsplat/models and clsplat/bench
# linked to its kernels/, models/ and bench/ (as run_tree.py needs); run from the repository root.
set -u
OLD=$1   # DF_DATA: DrivingForward's --data (default synthetic; a synthetic-cache:DIR saves generating)
run() { # tree label family args...
  tree=$1; label=$2; fam=$3; shift 3; out=/tmp/stepsab/$label-$fam-$RANDOM; mkdir -p /tmp/stepsab
  if [ $tree = today ]; then pre=""; else pre="bench/experiments/run_tree.py $tree"; fi
  POCL_MAX_WORK_GROUP_SIZE=256 timeout 400 .venv/bin/python $pre bench/experiments/train_any_tree.py $fam "$@" --no-progress --out $out >/dev/null 2>&1
  python3 -c "
import json,statistics,sys
import os
f='$out/log.jsonl' if os.path.exists('$out/log.jsonl') else '$out/.staging/log.jsonl'
rows=[json.loads(l) for l in open(f) if '\"time_s\"' in l]
t=[r['time_s'] for r in rows][$SKIP:]
print('$label $fam', len(t), 'steps, median step ms %.1f' % (1e3*statistics.median(t)))" 2>&1 | tail -1
}
for r in 1 2; do
  for tree in $OLD today; do
    l=$(basename $tree)
    SKIP=2 run $tree $l pgt --preset small --steps 10 --threads 1
    SKIP=40 run $tree $l autosplat --preset demo --stop-after 70 --threads 1
    SKIP=2 run $tree $l drivingforward --preset small --steps 6 --data "${DF_DATA:-synthetic}" --threads 1
  done
done
