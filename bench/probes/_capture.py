"""What the probes share: a coherent update of a mesh at depth 7 whose corner-search launch is captured,
so a probe can launch its own variant of the search over exactly the engine's inputs."""

import numpy as np
import warp as wp

from badf.server.adf import DistanceField
from badf.server.adf import _distance

# corner_searches' inputs up to its budget; after it come the budget, `seeded` and the seeds
SEEDING_INPUTS = 16


def captured_search(path: str, device: str):
    """(field, the corner search's inputs before its budget (what seeds a search), corner count, the
    engine's distances)."""
    wp.config.log_level = wp.LOG_ERROR
    wp.init()
    data = np.load(path)
    vertices, faces = data["vertices"], data["faces"]
    field = DistanceField(vertices, faces, depth=7, device=device)
    field.use_graphs = False
    field.update(vertices * np.float32(1.001))
    captured = {}
    launch = wp.launch

    def spy(kernel, *args, **kwargs):
        if kernel is _distance.corner_searches:
            captured["inputs"] = list(kwargs["inputs"])
        return launch(kernel, *args, **kwargs)

    wp.launch = spy
    try:
        field.update(vertices * np.float32(1.002))
    finally:
        wp.launch = launch
    inputs = captured["inputs"][:SEEDING_INPUTS]
    count = int(inputs[1].numpy()[0])
    return field, inputs, count, np.abs(field._corners.value.numpy()[:count])
