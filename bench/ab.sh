#!/usr/bin/env bash
# Times engine revisions against each other on one GPU machine, alternating, so that every comparison is within
# one machine (H100s differ by up to 30%, and a call may get an H200 instead).
#
#   Here:   bash bench/ab.sh prepare NAME=REV ...
#           archives each revision's packages under .ab/NAME (ignored by git; carry ".ab" to the machine)
#   There:  . .gpu/setup.sh && bash bench/ab.sh run [--seconds S] [--repeat R] [--variants "A B"] CONFIG ...
#           CONFIG is MESH[:DEPTH], MESH a .npz under $BADF_SHARED_DATA (default .gpudata). Each config runs each
#           variant (default: every one under .ab/, then "tree", the working tree) as `badf bench engine --quick`.
#           No run starts after S seconds (default 420), so that the call ends inside the device tool's 10 minutes
#           with what it timed: $OUT/ab.log and $OUT/ab-json.tgz are written again after every run, and a table of
#           the runs is printed last.
set -uo pipefail

prepare() {
  mkdir -p .ab
  grep -qx '/.ab/' .git/info/exclude 2>/dev/null || echo '/.ab/' >> .git/info/exclude
  for pair in "$@"; do
    name=${pair%%=*}; rev=${pair#*=}
    [ "$name" = tree ] && { echo "ab.sh: 'tree' is the working tree's name; pick another" >&2; exit 2; }
    rm -rf ".ab/$name" && mkdir -p ".ab/$name"
    git archive "$rev" server protocol client cli bench web_viewer | tar -x -C ".ab/$name" || exit 1
    echo "$(git rev-parse --short "$rev")" > ".ab/$name/REVISION"
    echo ".ab/$name: $(cat ".ab/$name/REVISION")"
  done
}

run() {
  seconds=420; repeat=20; variants=""
  while [ $# -gt 0 ]; do
    case "$1" in
      --seconds) seconds=$2; shift 2 ;;
      --repeat) repeat=$2; shift 2 ;;
      --variants) variants=$2; shift 2 ;;
      *) break ;;
    esac
  done
  [ $# -gt 0 ] || { echo "ab.sh run: name at least one MESH[:DEPTH]" >&2; exit 2; }
  out="${OUT:-$PWD/ab-out}"; data="${BADF_SHARED_DATA:-$PWD/.gpudata}"
  if [ -z "$variants" ]; then
    for dir in .ab/*/; do [ -d "$dir" ] && variants="$variants$(basename "$dir") "; done
    variants="${variants}tree"
  fi
  mkdir -p "$out" /tmp/ab-json
  for v in $variants; do  # each variant's packages as badf.*, on its own PYTHONPATH
    src=$PWD; [ "$v" != tree ] && src=$PWD/.ab/$v
    [ -d "$src/server" ] || { echo "ab.sh: no variant $v (.ab/$v)" >&2; exit 2; }
    mkdir -p "/tmp/ab/$v/badf"
    for m in protocol client server web_viewer cli bench; do ln -sfn "$src/$m" "/tmp/ab/$v/badf/$m"; done
  done
  command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | tee -a "$out/ab.log"
  start=$SECONDS
  for config in "$@"; do
    mesh=${config%%:*}; depth=7; [ "$mesh" != "$config" ] && depth=${config#*:}
    for v in $variants; do
      if [ $((SECONDS - start)) -ge "$seconds" ]; then
        echo "ab.sh: $seconds s spent; $v on $mesh at depth $depth and what follows not run" | tee -a "$out/ab.log"
        break 2
      fi
      json="/tmp/ab-json/engine-$mesh-d$depth-$v-$(date -u +%H%M%S).json"
      echo "=== $v, $mesh, depth $depth, $(date -u +%T)" >> "$out/ab.log"
      PYTHONPATH="/tmp/ab/$v${PYTHONPATH:+:$PYTHONPATH}" python3 -m badf.bench.engine --mesh "$data/$mesh.npz" \
        --depth "$depth" --quick --repeat "$repeat" --out "$json" 2>&1 | grep -v '^Module' >> "$out/ab.log"
      tar czf "$out/ab-json.tgz" -C /tmp/ab-json .
    done
  done
  python3 - /tmp/ab-json <<'EOF'
import json, pathlib, sys
# "after up." is the update's device time less its upload stage, whose events bracket host work (the write into
# pinned memory, launches) more than the device's; "wall" is the update's wall time
print(f"{'run':<44} {'update':>7} {'after up.':>9} {'wall':>6} {'dist':>6} {'build':>6} {'moved':>6} {'exact q':>8} "
      f"{'MiB':>6}")
for path in sorted(pathlib.Path(sys.argv[1]).glob("*.json"), key=lambda p: p.stat().st_mtime):
    c = json.loads(path.read_text())["configurations"][0]
    mib = sum(c["memory_bytes"].values()) / 2**20
    stages = c["update_stages_ms"]
    after_upload = c["update_gpu_ms"] - stages.get("upload", 0.0)
    print(f"{path.stem[7:]:<44} {c['update_gpu_ms']:>7} {after_upload:>9.4f} {c['update_wall_ms']:>6.3f} "
          f"{stages['distances']:>6} {c['build_gpu_ms']:>6} {c['moving_update_gpu_ms']:>6} {c['query_exact_ms']:>8} "
          f"{mib:>6.2f}")
EOF
}

case "${1:-}" in
  prepare) shift; prepare "$@" ;;
  run) shift; run "$@" ;;
  *) echo "usage: bash bench/ab.sh prepare NAME=REV ... | run [--seconds S] [--repeat R] [--variants \"A B\"] MESH[:DEPTH] ..." >&2
     exit 2 ;;
esac
