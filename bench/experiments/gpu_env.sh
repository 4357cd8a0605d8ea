# Sourced by the device-machine scripts (gpu_check.sh, gpu_models.sh), from the repository root:
# installs the carried wheels (.whl/*.whl: pyopencl, which bundles the ICD loader, pytools,
# platformdirs, siphash24, Mako; gpu_models.sh adds its own), lays the source tree out as the
# installed package does (setup.cfg's package_dir), and points the ICD loader at the NVIDIA
# driver's libnvidia-opencl where no ICD file names it. Sets $lib (empty: no driver found).
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
for d in kernels bench models; do [ -e clsplat/$d ] || ln -s ../$d clsplat/$d; done
lib=$(ls /usr/local/nvidia/lib64/libnvidia-opencl.so.1 /usr/lib/x86_64-linux-gnu/libnvidia-opencl.so.1 \
      /usr/lib64/libnvidia-opencl.so.1 2>/dev/null | head -1)
[ -n "$lib" ] || lib=$(find /usr /opt /lib -name 'libnvidia-opencl.so*' 2>/dev/null | head -1)
echo "ICD files: $(ls /etc/OpenCL/vendors 2>/dev/null | tr '\n' ' '); libnvidia-opencl: ${lib:-not found}"
if [ -n "$lib" ]; then  # the vendors already listed, and the NVIDIA driver's
  mkdir -p /tmp/icd && cp /etc/OpenCL/vendors/*.icd /tmp/icd/ 2>/dev/null; echo "$lib" > /tmp/icd/nvidia.icd
  export OCL_ICD_VENDORS=/tmp/icd
fi
nvidia-smi -L
