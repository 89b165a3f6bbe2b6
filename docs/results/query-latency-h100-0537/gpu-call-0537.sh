#!/usr/bin/env bash
# stop 56: where a 65,536-point query's time goes (probe), then the searches' register cap swept (interleave)
set -uo pipefail
out="${OUT:-$PWD/bench-out}"; mkdir -p "$out"
export BADF_SHARED_DATA="$PWD/.gpudata"
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . >/dev/null 2>&1 || echo "pip install -e . failed"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee "$out/gpu.txt"
date -u | tee -a "$out/gpu.txt"
case "${1:-}" in
  probe)
    timeout 200 python3 bench/probes/probe_query_latency.py .gpudata/stanford-bunny.npz cuda:0 --repeat 30 \
      --out "$out/query-latency-bunny.json" 2>&1 | grep -v '^Module' | tee "$out/query-latency-bunny.log"
    date -u
    timeout 330 python3 -m badf.bench.interleave --variant tree=. --variant s56=.ab/s56 --variant s72=.ab/s72 \
      --variant s80=.ab/s80 --mesh stanford-bunny --rounds 16 --frames 10 --out "$out/interleave-search-cap.json" \
      2>&1 | grep -v '^Module' | tee "$out/interleave-search-cap.log" | tail -8
   ;;
  again)
    timeout 560 python3 -m badf.bench.interleave --variant tree=. --variant "${2}=.ab/${2}" \
      --mesh stanford-bunny --rounds 24 --frames 10 --out "$out/interleave-again.json" \
      2>&1 | grep -v '^Module' | tee "$out/interleave-again.log" | tail -8
   ;;
esac
date -u
