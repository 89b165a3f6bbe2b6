"""The float64 oracle the tests compare against; it lives in badf.bench._oracle so that the installed
benchmarks measure against the same truth (one implementation)."""

from badf.bench._oracle import (  # noqa: F401
    Nearest,
    bbox_diagonal,
    closest_points_on_triangles,
    nearest,
    signed_distance,
    winding_number,
)
