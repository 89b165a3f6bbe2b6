#!/usr/bin/env bash
# One call on a GPU machine (the device tool): set up, check on CUDA, then time.
#   bash bench/gpu_session.sh [tests] [engine] [scratch] [rim] [rimprobe] [random] [signs] [split] [far] [kernels] [service] [viewer] [scaleout] [accuracy] [soak] [shapes] [binned] [slabs] [capped] ...
# Expects warp-lang and the wheels unpacked by ../shared/gpu/setup.sh (sourced before), the shared meshes
# copied into $BADF_SHARED_DATA (default .gpudata/), and writes logs and JSON under $OUT.
# The SAH shape's builder runs on Warp's CPU back-end, whose compiler ../shared/gpu/pack.sh leaves out: carry it as
# .gpu/clang.tar.xz, made here with
#   tar cf - -C .venv/lib/python3.11/site-packages warp/bin/warp-clang.so | xz -6 -T0 > .gpu/clang.tar.xz
# (about 20 MB, so in a call of its own beside the two of warp-lang); it is unpacked into /tmp/site below.
set -uo pipefail
if [ -f .gpu/clang.tar.xz ] && [ ! -f /tmp/site/warp/bin/warp-clang.so ]; then
  tar xJf .gpu/clang.tar.xz -C /tmp/site || echo "unpacking Warp's CPU compiler failed"
fi
out="${OUT:-$PWD/bench-out}"
mkdir -p "$out"
export BADF_SHARED_DATA="${BADF_SHARED_DATA:-$PWD/.gpudata}"
export WARP_CACHE_PATH="${WARP_CACHE_PATH:-/tmp/badf-warp-cache}"  # one kernel cache for every step and call
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . >/dev/null 2>&1 || echo "pip install -e . failed"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee "$out/gpu.txt"
for step in "$@"; do
  echo "=== $step"
  case "$step" in
    tests)
      # every CUDA test of the suite (312 on 2026-12-07), spread over pytest-xdist after one compile of the engine;
      # run again on the same machine, it finishes what the last call left
      OUT="$out" bash bench/cuda_tests.sh "${BADF_TESTS_SECONDS:-540}" ;;
    engine)
      python3 -m badf.bench.engine --mesh "$BADF_SHARED_DATA/stanford-bunny.npz" --out "$out/engine-bunny.json" \
        2>&1 | tee "$out/engine-bunny.log" ;;
    signs)
      # each sign method on a closed mesh: what auto's per-frame check for parts running into each other costs
      python3 -m badf.bench.engine --mesh "$BADF_SHARED_DATA/armadillo-86k.npz" --repeat 15 --sign-sweep \
        --out "$out/signs-armadillo.json" 2>&1 | tee "$out/signs-armadillo.log" | grep -v '^Module' ;;
    split)
      # the corner stage with long searches shared out over BVH subtrees or not, at depths 5 to 8
      python3 -m badf.bench.engine --mesh "$BADF_SHARED_DATA/stanford-bunny.npz" --repeat 15 --split-sweep 5 6 7 8 \
        --out "$out/split-sweep-bunny.json" 2>&1 | tee "$out/split-sweep-bunny.log" ;;
    far)
      # far corners searched by subtree beside the others (12 cells by default where no winding numbers run
      # beside the searches) against off, on a closed and an open mesh at depths 7 and 8
      for mesh in armadillo-86k stanford-bunny; do
        python3 -m badf.bench.engine --mesh "$BADF_SHARED_DATA/$mesh.npz" --repeat 10 --far-sweep 7 8 \
          --out "$out/far-$mesh.json" 2>&1 | tee "$out/far-$mesh.log" | grep -v '^Module'
      done ;;
    kernels)
      # one default update, kernel by kernel: device busy time against the update's span
      python3 -m badf.bench.engine --mesh "$BADF_SHARED_DATA/stanford-bunny.npz" --repeat 10 --kernels --block-sweep --register-sweep \
        --out "$out/kernels-bunny.json" 2>&1 | tee "$out/kernels-bunny.log" ;;
    service)
      python3 -m badf.bench.service --mesh "$BADF_SHARED_DATA/stanford-bunny.npz" --out "$out/service-bunny.json" \
        2>&1 | tee "$out/service-bunny.log" ;;
    viewer)
      # the bunny's 256x256 slices as the viewer asks for them, its drawing, and following a 60 fps stream;
      # about 2 minutes (most of it the worker's first kernel build). The viewer's own rows need viser on the
      # machine: ../shared/gpu/pack.sh viser msgspec websockets zstandard (without it they are skipped, said so)
      python3 -m badf.bench.viewer --mesh "$BADF_SHARED_DATA/stanford-bunny.npz" --out "$out/viewer-bunny.json" \
        2>&1 | tee "$out/viewer-bunny.log" ;;
    scaleout)
      # one worker per visible GPU against one worker, 8 and 16 client processes, and the one-GPU control;
      # about 3-4 minutes on 2 GPUs (less when the engine's kernels are already in Warp's cache)
      python3 -m badf.bench.scaleout --mesh "$BADF_SHARED_DATA/stanford-bunny.npz" --device cuda \
        --out "$out/scaleout-bunny.json" 2>&1 | tee "$out/scaleout-bunny.log" | grep -v ' badf INFO ' ;;
    accuracy)
      # error against run time on every mesh (depths 5-9, dense grid to depth 9) and the stability table;
      # writes accuracy-<gpu>.md, two PNGs and results/accuracy-<gpu>.json under $OUT
      python3 -m badf.bench.accuracy --out-dir "$out" --workers "$(nproc)" 2>&1 | tee "$out/accuracy.log" | tail -45 ;;
    soak)
      # 8 client processes x 4 objects on one worker on cuda:0 for 60 s; answers, counters, RSS and GPU memory
      python3 -m badf.bench.soak --device cuda:0 --seconds 60 --out "$out/soak-gpu.json" 2>&1 \
        | tee "$out/soak.log" | grep -v ' badf INFO ' ;;
    binned)
      # the corners near the surface answered from bins of triangles, against the engine's walks (a probe)
      for mesh in stanford-bunny armadillo-86k rocker-arm; do
        python3 bench/probes/probe_binned_near.py "$BADF_SHARED_DATA/$mesh.npz" cuda:0 --out "$out/binned-$mesh.json" \
          2>&1 | grep -v '^Module' | tee "$out/binned-$mesh.log" | tail -9
      done ;;
    slabs)
      # the corner walks with a slab beside each 4-wide node's box, against boxes alone (a probe)
      for mesh in stanford-bunny armadillo-86k rocker-arm; do
        python3 bench/probes/probe_slabs.py "$BADF_SHARED_DATA/$mesh.npz" cuda:0 --out "$out/slabs-$mesh.json" \
          2>&1 | grep -v '^Module' | tee "$out/slabs-$mesh.log" | tail -6
      done ;;
    capped)
      # an open mesh's corner sides from its holes' caps (pseudonormals of the capped mesh less the caps' solid
      # angles) against the engine's winding walk: times on the device, sides against the float64 oracle (a probe)
      python3 bench/probes/probe_capped_winding.py "$BADF_SHARED_DATA"/{stanford-bunny,sumner_horse_gallop}.npz \
        --device cuda:0 --out "$out/capped-winding.json" 2>&1 | grep -v '^Module' | tee "$out/capped-winding.log" | tail -4 ;;
    shapes)
      # the SAH shape's host time (one thread and all), its CUDA tests, then the engine on either shape, alternated:
      # the bunny's engine bench on each, and objects on either alternated (about 5 minutes from a cold start)
      python3 bench/probes/probe_shape_builder.py "$BADF_SHARED_DATA"/{stanford-bunny,armadillo-86k,spot}.npz 2>&1 \
        | grep -v '^Module' | tee "$out/shape-builder.log"
      python3 -m pytest -q -p no:cacheprovider -k cuda tests/test_bvh_shape.py \
        "tests/test_engine.py::test_fast_winding_numbers_match_the_oracle_at_the_corners" \
        "tests/test_engine.py::test_the_winding_walk_sums_its_expansions_to_float32_rounding" 2>&1 | tail -3 \
        | tee "$out/pytest-shape.log"
      for bvh in morton sah; do
        python3 -m badf.bench.engine --mesh "$BADF_SHARED_DATA/stanford-bunny.npz" --quick --bvh "$bvh" \
          --out "$out/engine-stanford-bunny-$bvh.json" 2>&1 | grep -v '^Module' | tee -a "$out/shapes.log"
      done
      python3 bench/probes/probe_bvh_shapes.py "$BADF_SHARED_DATA"/{stanford-bunny,armadillo-86k}.npz --device cuda:0 \
        --depths 7 --rounds 4 --frames 20 --points 65536 --out "$out/shapes-cuda.json" 2>&1 | grep depth \
        | tee "$out/shapes-cuda.log" ;;
    rim)
      # ADF queries beside openings answered exactly, as the engine grew: before either rule (d41a4d4), with the
      # corners' diagonal rule (a583058), and with leaves the rim crosses too (the working tree). Here:
      # bench/ab.sh prepare before=d41a4d4 head=a583058, carry .ab. The bunny's frames and 65,536-point ADF batches
      # near its surface and in its box, the three engines alternated
      python3 -m badf.bench.interleave --variant before=.ab/before --variant diagonal=.ab/head --variant rim=. \
        --mesh "$BADF_SHARED_DATA/stanford-bunny.npz" --depth 7 --rounds "${BADF_RIM_ROUNDS:-12}" --frames 10 \
        --queries 10 --out "$out/rim-interleave.json" 2>&1 | grep -v '^Module' | tee "$out/rim-interleave.log" ;;
    scratch)
      # the octree's smaller scratch (2026-12-08: no child links, 32-bit corner table and node sort, in-place scan,
      # slice buffers by what a plane crosses) against the engine before it, alternated; the bunny at depths 7 and
      # 8. Here: bash bench/ab.sh prepare scratchbase=13e2db7, carry .ab
      for depth in 7 8; do
        python3 -m badf.bench.interleave --variant before=.ab/scratchbase --variant scratch=. \
          --mesh "$BADF_SHARED_DATA/stanford-bunny.npz" --depth $depth --rounds "${BADF_SCRATCH_ROUNDS:-8}" --frames 10 \
          --out "$out/scratch-interleave-d$depth.json" 2>&1 | grep -v '^Module' | tee "$out/scratch-interleave-d$depth.log"
      done ;;
    rimprobe)
      # the rim rules' accuracy on CUDA (a bowl's rim at depths 4 to 6, the bunny's surface at 6 and 7; about two
      # minutes, most of it the host's oracle), as docs/results/rim-leaves-h100-0051 has it on the CPU
      python3 bench/probes/probe_rim_jumps.py --device cuda:0 --bunny "$BADF_SHARED_DATA/stanford-bunny.npz" 2>&1 \
        | grep -v '^Module' | tee "$out/rim-probe-cuda.jsonl" ;;
    random)
      # the random check on CUDA at depths 7 to 10, for $BADF_RANDOM_SECONDS (120)
      python3 -m badf.bench.random_check --device cuda:0 --depths 7 10 --seed 9000000 \
        --seconds "${BADF_RANDOM_SECONDS:-120}" --out "$out/random-cuda.json" 2>&1 | grep -v '^Module' \
        | tee "$out/random-cuda.log" | tail -12 ;;
    *)
      echo "unknown step $step" ;;
  esac
done
