#!/usr/bin/env bash
# Every CUDA test of the suite on a GPU machine (the device tool), within one call's time.
#   bash bench/cuda_tests.sh [seconds 540] [workers 14]      (from bench/gpu_session.sh tests, or alone)
# Expects warp-lang on PYTHONPATH (../shared/gpu/setup.sh sourced), the shared meshes in $BADF_SHARED_DATA, and
# writes its logs under $OUT. The engine's modules are compiled once, by one process (16 threads, then the kernels
# made on demand: 160 s on an H200, 2026-12-07), into a kernel cache the test processes share; the tests then run
# over pytest-xdist where the machine has it. Run again on the same warm machine, it runs only the tests that have
# not passed or been skipped yet (their ids kept in /tmp/badf-cuda-done.txt), so a second call finishes the first's.
# Warp's CPU compiler (.gpu/clang.tar.xz, see gpu_session.sh) must be there for the SAH tree's cases.
set -uo pipefail
start=$SECONDS
budget="${1:-540}"
workers="${2:-14}"
out="${OUT:-$PWD/bench-out}"; mkdir -p "$out"
export WARP_CACHE_PATH="${WARP_CACHE_PATH:-/tmp/badf-warp-cache}"
done_list=/tmp/badf-cuda-done.txt
if [ ! -f /tmp/badf-cuda-warmed ]; then
  python3 - <<'PY' 2>&1 | grep -v "^Warp" | tail -4 | tee -a "$out/cuda-tests.txt"
import time
import warp as wp
wp.config.log_level = wp.LOG_ERROR
wp.init()
import badf.server.adf  # noqa: F401 - registers the engine's modules
from badf.server.adf._warm_up import warm_up
t = time.time()
for block_dim in (None, 64):  # the modules as loaded by default, and the searches' and signs' blocks of 64
    try:
        wp.force_load(device="cuda:0", block_dim=block_dim, max_workers=16)
    except Exception as error:  # noqa: BLE001 - warm_up below compiles whatever this left
        print("force_load failed:", type(error).__name__, error)
print("modules loaded in %.1f s" % (time.time() - t))
print("warm_up on cuda:0 %.1f s" % warm_up("cuda:0"))
PY
  touch /tmp/badf-cuda-warmed
fi
python3 -m pytest --collect-only -q -p no:cacheprovider -k cuda tests 2>/dev/null | grep '::' | sed 's/ *$//' | sort > /tmp/badf-cuda-ids.txt
touch "$done_list"
mapfile -t ids < <(comm -23 /tmp/badf-cuda-ids.txt <(sort -u "$done_list"))
echo "$(wc -l < /tmp/badf-cuda-ids.txt) CUDA tests, ${#ids[@]} to run" | tee -a "$out/cuda-tests.txt"
parallel=()
python3 -c "import xdist" 2>/dev/null && parallel=(-n "$workers")
log="$out/cuda-tests-$(date -u +%H%M%S).log"
left=$(( budget - (SECONDS - start) ))
[ "${#ids[@]}" -gt 0 ] && timeout -s INT -k 20 "$left" python3 -m pytest "${parallel[@]}" -v -p no:cacheprovider "${ids[@]}" > "$log" 2>&1
# a verbose line names the outcome before the id under xdist, after it without
grep -oE '(PASSED|SKIPPED|XFAIL) tests/.*|^tests/.* (PASSED|SKIPPED|XFAIL)' "$log" \
  | sed -E 's/^(PASSED|SKIPPED|XFAIL) //; s/ (PASSED|SKIPPED|XFAIL).*$//; s/ *$//' >> "$done_list"
sort -u "$done_list" -o "$done_list"
echo "this run: $(grep -cE 'PASSED tests/|^tests/.* PASSED' "$log") passed, $(grep -cE 'FAILED tests/|^tests/.* FAILED' "$log") failed;" \
  "$(comm -12 /tmp/badf-cuda-ids.txt "$done_list" | wc -l) of $(wc -l < /tmp/badf-cuda-ids.txt) passed or skipped so far" | tee -a "$out/cuda-tests.txt"
grep -E '^(FAILED|ERROR) ' "$log" | sort -u | head -40
tail -1 "$log"
