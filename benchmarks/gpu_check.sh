#!/bin/bash
# The checks that need a CUDA GPU, in one call of the device tool (a machine with PyTorch and
# CUDA, no install): the PyTorch path of the atom search on CUDA against NumPy's selections
# (tests and benchmarks/speed_mp.py), then the test suite on that machine's own Python stack.
# Usage: bash benchmarks/gpu_check.sh [OUTDIR]; the log goes to OUTDIR/gpu_check.log, the
# suite's own output to OUTDIR/pytest.log.
set -o pipefail
out=${1:-${OUT:-benchmarks/results}}
mkdir -p "$out"
log="$out/gpu_check.log"
export PYTHONPATH=$PWD/src PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1
{
  echo "== machine"
  nvidia-smi -L
  python3 -c "import sys, torch, numpy, numba, pandas, scipy; print('Python', sys.version.split()[0], '| torch', torch.__version__, '| CUDA', torch.cuda.is_available(), '| numpy', numpy.__version__, '| numba', numba.__version__, '| scipy', scipy.__version__, '| pandas', pandas.__version__)"
  git log -1 --format='commit %h %s' 2>/dev/null || true
  echo "== PyTorch paths of the atom search (CPU and CUDA) against NumPy"
  python3 -m pytest -q -p no:cacheprovider tests/test_fast_mp.py -k torch -rA 2>&1 | grep -E "PASSED|FAILED|SKIPPED|ERROR|passed|failed"
  echo "== matching pursuit over the fine dictionary, PyTorch on CUDA"
  timeout 200 python3 benchmarks/speed_mp.py --windows 1000 --ref-windows 10 --no-dense32 \
    --torch-device cuda --out "$out/speed_mp.json"
  echo "== the test suite on this machine's Python stack (shared data absent here)"
  python3 -m pip list 2>/dev/null | grep -i -E "^(click|typer|rich|pyarrow|h5py|tifffile|matplotlib) "
  timeout 300 python3 -m pytest -q -p no:cacheprovider -n 14 --timeout 240 -rfE --tb=line \
    > "$out/pytest.log" 2>&1
  grep -E "^(FAILED|ERROR)|passed|failed" "$out/pytest.log" | head -60
} 2>&1 | tee "$log"
