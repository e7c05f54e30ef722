#!/usr/bin/env bash
# The GPU figures of issue "Speed" in one device-machine call: the PyTorch backend's tests on
# CUDA, the batched fitter and matching pursuit on the GPU against the CPU paths, and the
# batched frame solver (--device cuda) against the default compiled loop on the same frames.
#
#   OUT=/tmp/gpu bash benchmarks/gpu_run.sh [frames]
#
# Needs the package's dependencies and PyTorch with CUDA; runs from the source tree.
set -uo pipefail
FRAMES=${1:-16}
OUT=${OUT:-/tmp/sparseloc_gpu}
mkdir -p "$OUT"
export PYTHONPATH=$PWD/src PYTHONUNBUFFERED=1
nvidia-smi -L
python3 -c "import torch, numpy, numba, platform; print(platform.python_version(), 'torch', torch.__version__, torch.cuda.get_device_name(0), 'numpy', numpy.__version__, 'numba', numba.__version__)"
echo "== tests of the PyTorch paths (CPU and CUDA)"
timeout 80 python3 -m pytest -q -p no:cacheprovider tests/test_batch_fit.py tests/test_fast_mp.py \
    tests/test_frame_batch.py -k torch 2>&1 | tee "$OUT/pytest_torch.txt" | tail -3
echo "== frame solver"
timeout 240 python3 benchmarks/speed_device.py --frames "$FRAMES" --devices none,cuda \
    --out "$OUT/speed_device.json" 2>&1 | tee "$OUT/speed_device.txt"
echo "== batched fit"
timeout 120 python3 benchmarks/speed_fit.py --windows 1000 --out "$OUT/speed_fit.json" 2>&1 | tee "$OUT/speed_fit.txt"
echo "== matching pursuit"
timeout 150 python3 benchmarks/speed_mp.py --windows 1000 --ref-windows 10 --no-dense32 \
    --torch-device cuda --out "$OUT/speed_mp.json" 2>&1 | tee "$OUT/speed_mp.txt"
