#!/bin/bash
# One sitting of training steps per model family under thread settings, interleaved:
#   t1       --threads 1 (the package's old default)
#   default  no --threads (clsplat.threads.default_torch_threads: the idle cores, else 1)
#   t2       --threads 2, OpenMP workers sleep when idle (OMP_WAIT_POLICY=PASSIVE, clsplat's default)
#   t2spin   --threads 2 with CLSPLAT_THREAD_DEFAULTS=0 (libgomp's spinning workers)
#   t2sN     --threads 2, idle OpenMP workers spin N iterations before they sleep (GOMP_SPINCOUNT=N;
#            libgomp: ~1e5 iterations per ms; its default is 3e5, PASSIVE is 0)
# Each run is bench/experiments/step_profile.py around the real `clsplat train` command.
# Usage (from the repository root): sh bench/experiments/thread_sitting.sh OUT.jsonl [ROUNDS]
# Environment:
#   FAMILIES="drivingforward pgt autosplat"   CONFIGS="t1 default t2 t2spin"
#   QUIET_LOAD=0.45  before each `default` run, wait until the 1-minute load average is below
#                    this (the default reads the load: the sitting's own previous run must not
#                    decide it); unset: no wait
#   COMPETE=1        run one CPU-bound busy loop beside the whole sitting (the "loaded" case)
#   BEFORE_PY=PATH   config "before": the same command with this python (a venv importing an older
#                    tree, e.g. the commit an issue started from) and that tree's own defaults;
#                    BEFORE_FAMILIES (default "drivingforward pgt") says for which families
set -u
OUT=$1; ROUNDS=${2:-2}; RUN=$(mktemp -d)
FAMILIES=${FAMILIES:-drivingforward pgt autosplat}
CONFIGS=${CONFIGS:-t1 default t2 t2spin}
export POCL_MAX_WORK_GROUP_SIZE=256
HOG=
if [ "${COMPETE:-0}" = 1 ]; then
 python3 -c "while True: pass" & HOG=$!
 trap 'kill $HOG 2>/dev/null' EXIT
 sleep 60   # let the load average see it
fi
wait_quiet() {
 [ -n "${QUIET_LOAD:-}" ] || return 0
 while awk -v q="$QUIET_LOAD" '{exit !($1 >= q)}' /proc/loadavg; do sleep 5; done
}
for r in $(seq "$ROUNDS"); do
 for fam in $FAMILIES; do
  case $fam in
   drivingforward) ARGS="train drivingforward --preset small --steps 4 --eval-scenes 0 --no-progress"; SK=1;;
   pgt) ARGS="train pgt --preset small --steps 5"; SK=1;;
   autosplat) ARGS="train autosplat --stop-after 50 --no-progress"; SK=42;;  # steps 43-50: bg_phase2
  esac
  for cfg in $CONFIGS; do
   case $cfg in
    t1) E="A=1"; T="--threads 1";;
    default) E="A=1"; T=""; wait_quiet;;
    t2) E="A=1"; T="--threads 2";;
    t2spin) E="CLSPLAT_THREAD_DEFAULTS=0"; T="--threads 2";;
    before) case " ${BEFORE_FAMILIES:-drivingforward pgt} " in *" $fam "*) ;; *) continue;; esac
            E="A=1"; T="";;
    t2s*) E="CLSPLAT_THREAD_DEFAULTS=0 GOMP_SPINCOUNT=${cfg#t2s}"; T="--threads 2";;  # e.g. t2s10000
   esac
   rm -rf "$RUN/$fam"
   PYB=.venv/bin/python; [ "$cfg" = before ] && PYB=$BEFORE_PY
   env $E $PYB bench/experiments/step_profile.py --skip $SK --json "$OUT" --label "r$r $cfg${HOG:+ loaded}" -- $ARGS --out "$RUN/$fam" $T > "$RUN/last.log" 2>&1 \
     || echo "FAIL r$r $fam $cfg (see $RUN/last.log)" >&2
  done
 done
done
rm -rf "$RUN"
