#!/bin/bash
# Per-call cost, two trees side by side: alternating processes of `clsplat bench percall`
# from tree A and tree B (each its own checkout with a .venv that imports it), ROUNDS rounds.
# Usage: sh bench/experiments/percall_ab.sh TREE_A TREE_B OUT.jsonl [ROUNDS] [SCENES] [REPEATS]
set -u
A=$1; B=$2; OUT=$3; ROUNDS=${4:-5}; SCENES=${5:-tiny}; REPEATS=${6:-200}
export POCL_MAX_WORK_GROUP_SIZE=256
for r in $(seq "$ROUNDS"); do
 for t in "$A" "$B"; do
  (cd "$t" && .venv/bin/clsplat bench percall --scenes "$SCENES" --repeats "$REPEATS" 2>/dev/null) \
   | python3 -c "import sys, json
for l in sys.stdin:
    if l.startswith('{'):
        d = json.loads(l); d.update(tree='$t', round=$r, load=open('/proc/loadavg').read().split()[0]); print(json.dumps(d))" >> "$OUT"
 done
done
