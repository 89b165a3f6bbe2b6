"""Probe, not part of the product (python3 bench/probes/probe_accuracy_updates.py [accuracy bench arguments]): why
does `badf bench accuracy` read a slower update than `badf bench engine`? Runs the accuracy bench itself with every
DistanceField.update logged: its wall time (device synchronised before and after), the engine's device time and
counters, and the object it ran on, so the bench's median can be read frame by frame."""
import sys
import time

import warp as wp

from badf.server.adf import DistanceField

_update = DistanceField.update


def logged_update(self, vertices, *args, **kwargs):
    wp.synchronize_device(self.device)
    start = time.perf_counter()
    result = _update(self, vertices, *args, **kwargs)
    wp.synchronize_device(self.device)
    wall = (time.perf_counter() - start) * 1e3
    s = self.stats()
    print(f"[update] object {id(self) % 100000:05d} frame {s['frame']:3d} wall {wall:7.3f} ms "
          f"device {s['times_ms'].get('total', 0.0):7.3f} ms captures {s['graph_captures']} replans {s['replans']} "
          f"measured {s['measured_frames']} moves {s['domain_moves']}", file=sys.stderr, flush=True)
    return result


DistanceField.update = logged_update

if __name__ == "__main__":
    from badf.bench.accuracy import main

    sys.exit(main())
