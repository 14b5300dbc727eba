#!/usr/bin/env bash
# The GPU check in one command (issue 28), for the first GPU machine at hand:
#   bash tools/gpu_check.sh [--size 1944x2592x64] [--iters 5] [--no-tests] [--out docs/gpu_check.md]
# Registers NVIDIA's OpenCL driver when the machine has no ICD file for it (libnvidia-opencl.so.1 found,
# /etc/OpenCL/vendors writable), shows the devices, then runs tools/gpu_check.py: every kernel built, the
# kernel-against-twin tests, and seconds per iteration at the paper's full frame with each FFT backend,
# written into docs/gpu_check.md. CM2CL_DEVICE picks the device (default: cm2cl's choice, a GPU first).
# Needs a Python with cm2cl importable (pip install -e ".[test,vkfft]", or PYTHONPATH=. and a pyopencl wheel).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

vendors=/etc/OpenCL/vendors
if ! ls "$vendors"/*nvidia*.icd >/dev/null 2>&1; then
  lib=$(ldconfig -p 2>/dev/null | awk '/libnvidia-opencl\.so\.1/ {print $NF; exit}')
  [ -n "$lib" ] || lib=$(find / -name 'libnvidia-opencl.so.1' -not -path '*/proc/*' 2>/dev/null | head -1 || true)
  if [ -n "$lib" ] && mkdir -p "$vendors" 2>/dev/null && [ -w "$vendors" ]; then
    echo "$lib" > "$vendors/nvidia.icd"
    echo "gpu_check: registered NVIDIA's OpenCL driver ($lib) in $vendors/nvidia.icd"
  fi
fi

"$PY" -m cm2cl devices
exec "$PY" tools/gpu_check.py "$@"
