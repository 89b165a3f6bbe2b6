#!/usr/bin/env bash
# stop 55: the corners' whole walk (2812d87, the working tree) against 163884b (flags) and 8398fa0 (pre)
# cases: timing = interleave of the three, then the budget's CUDA tests; queries = ab.sh's engine bench of each
set -uo pipefail
out="${OUT:-$PWD/bench-out}"; mkdir -p "$out"
export BADF_SHARED_DATA="$PWD/.gpudata"
if [ -f .ab/clang.tar.xz ] && [ ! -f /tmp/site/warp/bin/warp-clang.so ]; then
  tar xJf .ab/clang.tar.xz -C /tmp/site && echo "Warp's CPU compiler unpacked" || echo "unpacking Warp's CPU compiler failed"
fi
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . >/dev/null 2>&1 || echo "pip install -e . failed"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee "$out/gpu.txt"
date -u | tee -a "$out/gpu.txt"; git log -1 --format=%h 2>/dev/null | tee -a "$out/gpu.txt"
case "${1:-}" in
  timing)
    timeout 230 python3 -m badf.bench.interleave --variant pre=.ab/pre --variant tree=. \
      --mesh stanford-bunny --rounds 20 --frames 10 --out "$out/interleave-confirm.json" 2>&1 | grep -v '^Module' \
      | tee "$out/interleave-confirm.log" | tail -6
    date -u
    timeout 100 python3 -m pytest -q -p no:cacheprovider -k cuda tests/test_winding_budget.py \
      2>&1 | tee "$out/pytest-cuda-budget.log" | tail -3
   ;;
  queries)
    OUT="$out" timeout 560 bash bench/ab.sh run --seconds 420 --repeat 20 --variants "pre flags tree" stanford-bunny:7 \
      2>&1 | tail -8 ;;
esac
date -u
