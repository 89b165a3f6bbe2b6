#!/usr/bin/env bash
# stop 52's GPU call: CUDA tests of the winding budget, the bunny's update against 5037f13, the soup gate and relink probes
set -uo pipefail
out="${OUT:-$PWD/bench-out}"; mkdir -p "$out"
export BADF_SHARED_DATA="$PWD/.gpudata"
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . >/dev/null 2>&1 || echo "pip install -e . failed"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee "$out/gpu.txt"
date -u | tee -a "$out/gpu.txt"
case "${1:-all}" in
  tests|all)
    timeout 240 python3 -m pytest -q -p no:cacheprovider -k "cuda" tests/test_winding_budget.py 2>&1 | tee "$out/pytest-cuda.log" | tail -8
    timeout 200 python3 -m badf.bench.interleave --variant main=.ab/main --variant tree=. --mesh stanford-bunny \
      --rounds 30 --frames 10 --out "$out/interleave-stanford-bunny.json" 2>&1 | grep -v '^Module' | tee "$out/interleave-stanford-bunny.log" | tail -14 ;;&
  probes|all)
    timeout 300 python3 bench/probes/probe_soup_gate.py stanford-bunny --depth 7 --rounds 2 --out "$out/soup-gate.json" \
      2>&1 | grep -v '^Module' | tee "$out/soup-gate.log" | grep -v '^{'
    timeout 200 python3 bench/probes/probe_relink.py .gpudata/stanford-bunny.npz --depth 7 --out "$out/relink.json" \
      2>&1 | grep -v '^Module' | tee "$out/relink.log" | grep -v '^{' | tail -12 ;;
esac
date -u
