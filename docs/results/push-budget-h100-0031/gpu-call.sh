#!/usr/bin/env bash
# stop 54: time 44f88cd (push budget) against 8398fa0; the wider CUDA tests
# (cases: fix = interleave against .ab/pre plus the budget tests; tests1, tests2 = the wider CUDA tests)
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
  tests1)
    timeout 560 python3 -m pytest -q -p no:cacheprovider -k cuda --durations=8 tests/test_winding_budget.py tests/test_engine.py \
      2>&1 | tee "$out/pytest-cuda-1.log" | tail -22 ;;
  tests2)
    timeout 420 python3 -m pytest -q -p no:cacheprovider -k cuda --durations=5 tests/test_stability.py tests/test_rigid.py \
      tests/test_trim.py tests/test_engine_inputs.py 2>&1 | tee "$out/pytest-cuda-2.log" | tail -14 ;;&
  tests2|probes)
    timeout 300 python3 bench/probes/probe_soup_gate.py stanford-bunny --depth 7 --rounds 2 --noise 0.05 0.2 \
      --fractions 0.15 1.0 --fat-areas 0.03 0.3 --out "$out/soup-gate.json" 2>&1 | grep -v '^Module' | tee "$out/soup-gate.log" | grep -v '^{' ;;
  quick)
    timeout 200 python3 -m pytest -q -p no:cacheprovider -k cuda tests/test_winding_budget.py tests/test_bvh_shape.py \
      2>&1 | tee "$out/pytest-cuda-quick.log" | tail -6
    timeout 150 python3 bench/probes/probe_soup_gate.py stanford-bunny --depth 7 --rounds 1 --noise 0.2 \
      --fractions 0.15 1.0 --fat-areas 0.03 0.3 --out "$out/soup-gate.json" 2>&1 | grep -v '^Module' | tee "$out/soup-gate.log" | grep -v '^{'
    timeout 150 python3 -m badf.bench.interleave --variant pre=.ab/pre --variant tree=. --mesh stanford-bunny \
      --rounds 20 --frames 10 --out "$out/interleave-stanford-bunny.json" 2>&1 | grep -v '^Module' | tee "$out/interleave-stanford-bunny.log" | tail -12
    timeout 90 python3 bench/probes/probe_relink.py .gpudata/stanford-bunny.npz --depth 7 --out "$out/relink.json" \
      2>&1 | grep -v '^Module' | tee "$out/relink.log" | grep -v '^{' | tail -10 ;;
  fix)
    timeout 150 python3 -m badf.bench.interleave --variant pre=.ab/pre --variant tree=. --mesh stanford-bunny \
      --rounds 20 --frames 10 --out "$out/interleave-fix.json" 2>&1 | grep -v '^Module' | tee "$out/interleave-fix.log" | tail -6
    timeout 200 python3 -m pytest -q -p no:cacheprovider -k cuda tests/test_winding_budget.py \
      2>&1 | tee "$out/pytest-cuda-fix.log" | tail -4 ;;
  timing)
    timeout 240 python3 -m badf.bench.interleave --variant pre=.ab/pre --variant tree=. --mesh stanford-bunny \
      --rounds 30 --frames 10 --out "$out/interleave-stanford-bunny.json" 2>&1 | grep -v '^Module' | tee "$out/interleave-stanford-bunny.log" | tail -14
    timeout 200 python3 bench/probes/probe_relink.py .gpudata/stanford-bunny.npz --depth 7 --out "$out/relink.json" \
      2>&1 | grep -v '^Module' | tee "$out/relink.log" | grep -v '^{' | tail -12 ;;
esac
date -u
