"""Sound accordions of fat panels (stop 53): are their walks cut as a soup's? Prints the frame's sphere areas and
the walks cut, with FAT_AREA as the engine has it and with every node counting."""
import numpy as np

from badf.bench._common import start_warp
from badf.server.adf import DistanceField, _bvh

dev = start_warp("cpu")


def accordion(layers, strips, along):
    """An open sheet folded into `layers` layers across the unit square, each cut into `strips` x `along` panels."""
    lift = 1.0 / (layers - 1)
    profile = [(0.0, 0.0)]
    for k in range(layers):
        y0, y1 = (0.0, 1.0) if k % 2 == 0 else (1.0, 0.0)
        for t in np.linspace(0, 1, along + 1)[1:]:
            profile.append((y0 + (y1 - y0) * t, k * lift))
        if k + 1 < layers:
            profile.append((y1, (k + 1) * lift))
    xs = np.linspace(0, 1, strips + 1)
    v = np.array([(x, y, z) for y, z in profile for x in xs], np.float32)
    row = strips + 1
    i, j = np.meshgrid(np.arange(strips), np.arange(len(profile) - 1))
    a = (j * row + i).ravel()
    f = np.concatenate([np.stack([a, a + 1, a + row], 1), np.stack([a + 1, a + row + 1, a + row], 1)]).astype(np.int32)
    return v, f


for fat in (_bvh.FAT_AREA, 0.0):
    _bvh.FAT_AREA = fat
    for layers, strips, along in [(110, 5, 5), (110, 4, 4), (110, 2, 2)]:
        v, f = accordion(layers, strips, along)
        field = DistanceField(v, f, depth=5, sign="winding", device=dev, rigid="off")
        m = field._bvh.node_moments.numpy()
        areas = m[1][3] / (4 * np.pi * m[0][3] ** 2)
        print(f"FAT_AREA {fat:g}: {layers} layers of {strips} x {along} panels, {len(f)} faces, {areas:.2f} sphere areas, "
              f"walks cut {field.stats()['winding_walks_cut']}", flush=True)
