#!/usr/bin/env bash
# A/B of the triangle test's narrow path on the bunny's default update, variants alternated.
# variants/dist.py is server/adf/_geometry.py as committed after it; old.patch and new.patch turn it into the others.
set -u
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . >/dev/null 2>&1
for round in 1 2 3; do
  for v in new dist old; do
    cp variants/$v.py server/adf/_geometry.py
    echo "== round $round variant $v $(date -u +%H:%M:%S)"
    python3 -m badf.bench.engine --mesh "$BADF_SHARED_DATA/stanford-bunny.npz" --quick --repeat 30 2>&1 \
      | grep -E "^ +depth=7 |stages of the first configuration, update"
  done
done
cp variants/new.py server/adf/_geometry.py
