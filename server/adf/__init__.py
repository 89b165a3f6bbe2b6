"""The ADF engine: a triangle mesh and its adaptive distance field on one device, usable in-process.

    from badf.server.adf import DistanceField
    field = DistanceField(vertices, faces, depth=7, sign="auto")
    field.update(new_vertices)
    result = field.query(points, mode="adf", outputs=("distance", "normal"))
"""

from badf.server.adf._buffers import DeviceMemoryError
from badf.server.adf._field import DistanceField, FieldUnavailableError, QueryResult
from badf.server.adf._inputs import BVH_SHAPES, QUERY_MODES, QUERY_OUTPUTS, InvalidInputError
from badf.server.adf._sign import SIGN_METHODS
from badf.server.adf._slice import Slice
from badf.server.adf._warm_up import warm_up

__all__ = [
    "DistanceField", "QueryResult", "Slice", "InvalidInputError", "DeviceMemoryError", "FieldUnavailableError",
    "BVH_SHAPES", "QUERY_MODES", "QUERY_OUTPUTS", "SIGN_METHODS", "warm_up",
]
