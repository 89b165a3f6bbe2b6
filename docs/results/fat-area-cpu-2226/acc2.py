"""Sound accordions of fat panels (stop 53): are their walks cut as a soup's? Prints the frame's sphere areas and
the walks cut, with FAT_AREA as the engine has it and with every node counting."""
import numpy as np

from badf.bench._cases import folded_sheet
from badf.bench._common import start_warp
from badf.server.adf import DistanceField, _bvh

dev = start_warp("cpu")

for fat in (_bvh.FAT_AREA, 0.0):
    _bvh.FAT_AREA = fat
    for layers, strips, along in [(110, 5, 5), (110, 4, 4), (110, 2, 2)]:
        v, f = folded_sheet(layers, strips, panels=along)
        field = DistanceField(v, f, depth=5, sign="winding", device=dev, rigid="off")
        m = field._bvh.node_moments.numpy()
        areas = m[1][3] / (4 * np.pi * m[0][3] ** 2)
        print(f"FAT_AREA {fat:g}: {layers} layers of {strips} x {along} panels, {len(f)} faces, {areas:.2f} sphere areas, "
              f"walks cut {field.stats()['winding_walks_cut']}", flush=True)
