"""Every acceptance tolerance of the tests, in one place, each in the unit it is stated in."""

# Exact queries and stored corner values: absolute distance error, in bounding-box diagonals.
EXACT_DISTANCE = 1e-5
# Signs must agree with the winding-number oracle farther than this from a closed surface, in diagonals.
SIGN_MARGIN = 1e-3
# ADF interpolation near the surface (within two finest cells): error below this many finest cells.
ADF_NEAR_SURFACE = 1.0
