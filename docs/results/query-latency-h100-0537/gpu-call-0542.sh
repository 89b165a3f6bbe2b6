#!/usr/bin/env bash
# stop 56, second machine: staged query copies + flat far-point check + searches at 80 registers (tree)
# against f6fad79's engine (.ab/main). cases: probe = query latency, alternated, then CUDA query tests;
# update = interleaved updates, bunny then armadillo
set -uo pipefail
out="${OUT:-$PWD/bench-out}"; mkdir -p "$out"
export BADF_SHARED_DATA="$PWD/.gpudata"
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . >/dev/null 2>&1 || echo "pip install -e . failed"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee "$out/gpu.txt"
date -u | tee -a "$out/gpu.txt"
mkdir -p /tmp/v/main/badf
for p in protocol client server web_viewer cli bench; do ln -sfn "$PWD/.ab/main/$p" "/tmp/v/main/badf/$p"; done
case "${1:-}" in
  probe)
    for round in 1 2; do
      for v in main tree; do
        if [ $v = main ]; then pp=/tmp/v/main:$PYTHONPATH; else pp=$PYTHONPATH; fi
        extra=""; [ $v = tree ] && [ $round = 2 ] && extra="--profile"
        echo "== $v, round $round"
        PYTHONPATH=$pp timeout 150 python3 bench/probes/probe_query_latency.py .gpudata/stanford-bunny.npz cuda:0 \
          --repeat 30 $extra --out "$out/query-latency-$v-$round.json" 2>&1 | grep -v '^Module' \
          | grep -v "^Warp\|CUDA Toolkit\|Devices:\|\"cpu\"\|\"cuda:0\"\|Kernel cache\|/root/.cache" | tee "$out/query-latency-$v-$round.log"
      done
    done
    date -u
    timeout 170 python3 -m pytest -q -p no:cacheprovider -x tests/test_engine.py -k "cuda and (staged or exact_queries_match or band or adf_error)" \
      2>&1 | tee "$out/pytest-cuda-queries.log" | tail -3
   ;;
  update)
    timeout 280 python3 -m badf.bench.interleave --variant tree=. --variant s80=.ab/s80 \
      --mesh stanford-bunny --rounds 24 --frames 10 --out "$out/interleave-bunny.json" \
      2>&1 | grep -v '^Module' | tee "$out/interleave-bunny.log" | tail -6
    date -u
    timeout 280 python3 -m badf.bench.interleave --variant tree=. --variant s80=.ab/s80 \
      --mesh armadillo-86k --rounds 16 --frames 10 --out "$out/interleave-armadillo.json" \
      2>&1 | grep -v '^Module' | tee "$out/interleave-armadillo.log" | tail -6
    date -u
    for v in main tree; do
      if [ $v = main ]; then pp=/tmp/v/main:$PYTHONPATH; else pp=$PYTHONPATH; fi
      echo "== $v, round 3"
      PYTHONPATH=$pp timeout 100 python3 bench/probes/probe_query_latency.py .gpudata/stanford-bunny.npz cuda:0 \
        --repeat 30 --out "$out/query-latency-$v-3.json" 2>&1 | grep -v '^Module' \
        | grep -v "^Warp\|CUDA Toolkit\|Devices:\|\"cpu\"\|\"cuda:0\"\|Kernel cache\|/root/.cache" | tee "$out/query-latency-$v-3.log"
    done
   ;;
esac
date -u
