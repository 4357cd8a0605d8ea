#!/bin/bash
# One sitting of training steps per model family under four thread settings, interleaved:
#   t1       --threads 1 (the package's old default)
#   default  no --threads (clsplat.threads.default_torch_threads: the idle cores, else 1)
#   t2       --threads 2, OpenMP workers sleep when idle (OMP_WAIT_POLICY=PASSIVE, clsplat's default)
#   t2spin   --threads 2 with CLSPLAT_THREAD_DEFAULTS=0 (libgomp's spinning workers)
# Each run is bench/experiments/step_profile.py around the real `clsplat train` command.
# Usage (from the repository root): sh bench/experiments/thread_sitting.sh OUT.jsonl [ROUNDS]
set -u
OUT=$1; ROUNDS=${2:-2}; RUN=$(mktemp -d)
export POCL_MAX_WORK_GROUP_SIZE=256
SP=".venv/bin/python bench/experiments/step_profile.py"
for r in $(seq "$ROUNDS"); do
 for fam in drivingforward pgt autosplat; do
  case $fam in
   drivingforward) ARGS="train drivingforward --preset small --steps 4 --eval-scenes 0 --no-progress"; SK=1;;
   pgt) ARGS="train pgt --preset small --steps 5"; SK=1;;
   autosplat) ARGS="train autosplat --stop-after 50 --no-progress"; SK=42;;  # steps 43-50: bg_phase2
  esac
  for cfg in t1 default t2 t2spin; do
   case $cfg in
    t1) E="A=1"; T="--threads 1";;
    default) E="A=1"; T="";;
    t2) E="A=1"; T="--threads 2";;
    t2spin) E="CLSPLAT_THREAD_DEFAULTS=0"; T="--threads 2";;
   esac
   rm -rf "$RUN/$fam"
   env $E $SP --skip $SK --json "$OUT" --label "r$r $cfg" -- $ARGS --out "$RUN/$fam" $T > "$RUN/last.log" 2>&1 \
     || echo "FAIL r$r $fam $cfg (see $RUN/last.log)" >&2
  done
 done
done
rm -rf "$RUN"
