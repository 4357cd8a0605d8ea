#!/bin/sh
# The engine on an NVIDIA GPU's OpenCL driver, on the device machine (nothing depends on it):
#   run there from the repository root with the wheels of pyopencl, pytools, platformdirs and
#   siphash24 (and Mako, for pyopencl.scan) for its Python in .whl/ (carried), $OUT the folder that comes back:
#     sh bench/experiments/gpu_check.sh
# 1. installs the wheels (pyopencl's bundles the ICD loader) and points the loader at the driver's
#    libnvidia-opencl where no ICD file names it; 2. lists the OpenCL devices; 3. gpu_check.py's
#    accuracy / determinism / kernel-time table on the default device (the GPU); 4. the engine's
#    own tests on it, the stiff-case catalogue (tests/test_stiff.py) with the GPU's per-tile sort
#    among them (they run on PoCL in CI; what fails here is recorded, not hidden).
#    GPU_IMPLS=1: both backward_impl values and sort_impl=tiles side by side, and their tests;
#    GPU_SORT=1: both sort_impl values at 100k-1M, and the tests on the GPU's default.
set -u
. bench/experiments/gpu_env.sh
if [ -z "$lib" ] && [ -n "${GPU_ONLY:-}" ]; then  # no GPU driver for OpenCL: only what PoCL there still owes
  timeout 120 python3 -m pytest -q -p no:cacheprovider -rf tests/test_order.py tests/test_bin.py 2>&1 | tail -30 | tee $OUT/pytest_pocl.txt
  exit 0
fi
python3 -c "import clsplat; print(clsplat.describe_devices())" 2>&1 | tee $OUT/devices.txt
if [ -n "${GPU_IMPLS:-}" ]; then  # the per-Gaussian backward and the per-tile sort on the GPU, beside the defaults, one run
  for cfg in "backward_impl=pixel" "backward_impl=gaussian" "sort_impl=tiles"; do
    timeout 110 python3 bench/experiments/gpu_check.py --out $OUT/${cfg%%=*}_${cfg##*=} --scenes ${SCENES:-tiny,10k,A,B} --repeats 3 \
      --set $cfg 2>&1 | tail -12
  done
  timeout 150 python3 -m pytest -q -p no:cacheprovider -rf --timeout 60 tests/test_composite_bwd_gaussian.py \
    tests/test_order.py 2>&1 | tail -40 | tee $OUT/pytest_impls_gpu.txt
  exit 0
fi
if [ -n "${GPU_SORT:-}" ]; then  # the two tile-list paths side by side up to 1M, then the tests on the GPU's default
  for cfg in "sort_impl=depth" "sort_impl=tiles"; do
    timeout 200 python3 bench/experiments/gpu_check.py --out $OUT/${cfg%%=*}_${cfg##*=} --scenes 100k,1m,A,B --repeats 3 \
      --torch-max-n 0 --set $cfg 2>&1 | tail -8
  done
  timeout 150 python3 -m pytest -q -p no:cacheprovider -rf --timeout 60 tests/test_order.py tests/test_rasterization.py \
    tests/test_autograd.py tests/test_packed.py tests/test_portability_limits.py 2>&1 | tail -40 | tee $OUT/pytest_sort_gpu.txt
  exit 0
fi
timeout 240 python3 bench/experiments/gpu_check.py --out $OUT --scenes tiny,10k,A,B --repeats 5 2>&1 | tee $OUT/gpu_check.log
timeout 120 python3 -m pytest -q -p no:cacheprovider -rf --timeout 60 tests/test_rasterization.py tests/test_autograd.py \
  tests/test_composite.py tests/test_composite_bwd.py tests/test_project.py tests/test_project_bwd.py tests/test_sh.py \
  tests/test_sh_bwd.py tests/test_order.py tests/test_bin.py tests/test_reduce.py tests/test_packed.py \
  tests/test_gsplat_rendering.py tests/test_composite_bwd_gaussian.py tests/test_portability_limits.py \
  tests/test_stiff.py 2>&1 | tee $OUT/pytest_gpu.txt | tail -60
