#!/bin/sh
# The three model families' tiny presets trained end to end (a few steps, evaluation, metrics.json)
# with the engine on an NVIDIA GPU's OpenCL driver, then on the same machine's PoCL CPU device,
# timed: the models' first run on a GPU (device machine; nothing depends on it). Here, first:
#     .venv/bin/python -m pip wheel -q --no-deps --no-build-isolation -w .whl/clsplat .
# (the package's entry points register the families' `clsplat train` commands), then there, with
# .whl carried:  sh bench/experiments/gpu_models.sh   [STEPS=10]
set -u
. bench/experiments/gpu_env.sh
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
  .whl/clsplat/*.whl || exit 1
cd /tmp  # the installed package, not the checkout
for dev in gpu pocl; do
  for f in drivingforward pgt autosplat; do
    t0=$(date +%s.%N)
    CLSPLAT_DEVICE=$dev timeout 60 python3 /tmp/site/bin/clsplat train $f --data synthetic --preset tiny \
      --steps ${STEPS:-10} --out /tmp/run_${f}_$dev --no-progress > /tmp/run_${f}_$dev.log 2>&1
    rc=$?
    echo "$f on $dev: rc $rc, $(python3 -c "import time; print(f'{time.time() - $t0:.1f}')") s wall" | tee -a $OUT/summary.txt
    grep -m1 -o "renderer .*" /tmp/run_${f}_$dev.log | tee -a $OUT/summary.txt   # the OpenCL device the run used
    tail -n 3 /tmp/run_${f}_$dev.log | tee -a $OUT/summary.txt
    [ -f /tmp/run_${f}_$dev/metrics.json ] && cp /tmp/run_${f}_$dev/metrics.json $OUT/${f}_$dev.json
  done
done
