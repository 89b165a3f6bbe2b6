"""Every acceptance tolerance of the tests and benchmarks, in one place, each in the unit it is stated in.

The tests read it through tests/tolerances.py; the installed benchmarks (`badf bench accuracy`, whose
stability table states the same bounds) read it here.
"""

# Exact queries and stored corner values: absolute distance error, in bounding-box diagonals.
EXACT_DISTANCE = 1e-5
# Signs must agree with the winding-number oracle farther than this from a closed surface, in diagonals.
SIGN_MARGIN = 1e-3
# ADF interpolation near the surface (within one finest cell, where halo=1 guarantees a finest leaf):
# error below this many finest cells.
ADF_NEAR_SURFACE = 1.0

# Float32 distances: relative error of a distance that is large against the mesh (points far away).
FLOAT32_RELATIVE = 1e-6
# ADF anywhere in the domain: trilinear interpolation of exact corner values of a 1-Lipschitz function is
# within the distance from the point to its farthest corner, so within this many diagonals of its leaf cell.
ADF_LEAF_DIAGONALS = 1.0
# An open mesh's winding number is trusted for the sign only this far from 1/2.
WINDING_CONFIDENCE = 0.1
# The engine's fast winding number (exact near the point, expansions of far BVH nodes) off the surface:
# absolute error, half the confidence margin, so no sign the tests trust rests on the approximation.
FAST_WINDING = 0.05
# Float32 input coordinates are rounded by half a unit in the last place: 2**-24 of their magnitude per
# axis; a distance moves by at most sqrt(3) times that for the point and again for the surface.
FLOAT32_INPUT_ROUNDING = 2.0**-24
