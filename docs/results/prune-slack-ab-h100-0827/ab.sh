#!/usr/bin/env bash
# A/B/C of the searches' prune slack: orig (pruning at best^2), new (prune limit after every leaf test),
# lazy (prune limit worked out again only when the best improves). Alternating, two rounds, two meshes.
set -uo pipefail
out="${OUT:-$PWD/ab-out}"; mkdir -p "$out"; work=$(mktemp -d)
data="$BADF_SHARED_DATA"
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . >/dev/null 2>&1 || echo "pip install -e . failed"
summ() { python3 - "$1" "$2" <<'PY' | tee -a "$out/ab-summary.txt"
import json, sys
d = json.load(open(sys.argv[1])); c = d["configurations"][0]; st = c["update_stages_ms"]
print(f"{sys.argv[2]}: update gpu {c['update_gpu_ms']} wall {c['update_wall_ms']} build {c['build_gpu_ms']} "
      f"distances {st.get('distances')} corners {c['counts'].get('corners')}")
PY
}
for round in 1 2; do
  for v in orig new inflate; do
    cp variants/_bvh_$v.py server/adf/_bvh.py
    for mesh in armadillo-86k stanford-bunny; do
      python3 -m badf.bench.engine --mesh "$data/$mesh.npz" --quick --repeat 20 --out "$work/$mesh-$v-$round.json" > "$work/$mesh-$v-$round.log" 2>&1
      summ "$work/$mesh-$v-$round.json" "$mesh $v $round"
    done
  done
done
cp variants/_bvh_new.py server/adf/_bvh.py
tar czf "$out/ab-runs.tgz" -C "$work" .
