#!/usr/bin/env bash
# Stop 59: every CUDA test of the suite, spread over parallel pytest processes that share one Warp kernel cache.
# Run again on the same warm machine, it runs only the tests that have no result yet (/tmp/done.txt).
set -uo pipefail
start=$SECONDS
budget="${1:-540}"
procs="${2:-12}"
out="${OUT:-$PWD/out59}"; mkdir -p "$out"
[ -f .gpu/clang.tar.xz ] && [ ! -f /tmp/site/warp/bin/warp-clang.so ] && tar xJf .gpu/clang.tar.xz -C /tmp/site
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . >/dev/null 2>&1 || echo "pip -e failed"
mkdir -p /tmp/data && cp -n .gpudata/*.npz /tmp/data/ 2>/dev/null; cp -n .ab/*.npz /tmp/data/ 2>/dev/null
export BADF_SHARED_DATA=/tmp/data WARP_CACHE_PATH=/tmp/wcache
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | tee -a "$out/gpu.txt"; date -u | tee -a "$out/gpu.txt"
ls /tmp/data | tr '\n' ' '; echo
if [ ! -d /tmp/wcache ] && [ -f .gpudata/wcache.tgz ]; then tar xzf .gpudata/wcache.tgz -C /tmp && echo "kernel cache carried: $(du -sh /tmp/wcache | cut -f1)"; fi
if [ ! -f /tmp/warmed ]; then
  t0=$SECONDS
  python3 - <<'PY' 2>&1 | grep -v "^Warp" | tail -5 | tee -a "$out/gpu.txt"
import time
import warp as wp
wp.config.log_level = wp.LOG_ERROR
wp.init()
import badf.server.adf
from badf.server.adf._warm_up import warm_up
t = time.time()
for block_dim in (None, 64):  # the modules as loaded by default, and the searches' and signs' blocks of 64
    try:
        wp.force_load(device="cuda:0", block_dim=block_dim, max_workers=16)
    except Exception as error:  # noqa: BLE001 - the warm-up below compiles what this left
        print("force_load failed:", type(error).__name__, error)
print("parallel load %.1f s" % (time.time() - t))
print("warm_up on cuda:0 %.1f s" % warm_up("cuda:0"))
PY
  echo "warm-up wall $((SECONDS - t0)) s" | tee -a "$out/gpu.txt"; touch /tmp/warmed
  tar czf "$out/wcache.tgz" -C /tmp wcache
fi
python3 -m pytest --collect-only -q -p no:cacheprovider -k cuda tests 2>/dev/null | grep '::' | sort > /tmp/ids.txt
touch /tmp/done.txt; sort -u /tmp/done.txt -o /tmp/done.txt
comm -23 /tmp/ids.txt /tmp/done.txt > /tmp/todo.txt
echo "collected $(wc -l < /tmp/ids.txt), done before $(wc -l < /tmp/done.txt), to run $(wc -l < /tmp/todo.txt)"
left=$(( budget - (SECONDS - start) ))
echo "running with xdist -n $procs for at most $left s"
run=$(date +%H%M%S)
mapfile -t ids < /tmp/todo.txt
timeout -s INT -k 20 "$left" python3 -m pytest -n "$procs" -v -p no:cacheprovider "${ids[@]}" > "$out/$run-c.log" 2>&1
cat "$out"/$run-c.log | grep -oE '(PASSED|SKIPPED|XFAIL) tests/[^ ]*.*$' | sed -E 's/^(PASSED|SKIPPED|XFAIL) //' >> /tmp/done.txt
sort -u /tmp/done.txt -o /tmp/done.txt
cp /tmp/done.txt "$out/done.txt"
echo "results: $(cat "$out"/$run-c.log | grep -cE 'PASSED tests/') passed, $(cat "$out"/$run-c.log | grep -cE 'FAILED tests/') failed, $(cat "$out"/$run-c.log | grep -cE 'SKIPPED tests/') skipped, $(cat "$out"/$run-c.log | grep -cE 'ERROR tests/') errors; done $(wc -l < /tmp/done.txt) of $(wc -l < /tmp/ids.txt)"
cat "$out"/$run-c.log | grep -E '(FAILED|ERROR) tests/' | head -40
cat "$out"/$run-c.log | grep -E '^(FAILED|ERROR) ' | head -30
du -sh /tmp/wcache 2>/dev/null; date -u; echo "wall $((SECONDS - start)) s"
