"""Every numeric tolerance of the engine, in one place, relative to a stated scale."""

# The domain is a cube around the mesh's bounding box, widened on each side by this fraction of the box's
# largest extent, so the octree holds values a little beyond the surface.
DOMAIN_MARGIN = 0.1

# The domain's centre is snapped to a float32 number (so float32 frames recentre on the device) only where
# that moves it by at most this fraction of the side; else it stays float64 and frames recentre on the host.
CENTRE_SNAP = 2.0**-12

# A frame whose bounding box leaves the domain, or whose largest extent falls below this fraction of the
# domain's side (the octree would be too coarse for it), moves the domain to fit the new frame. A fitted
# frame fills 1/1.2 of the side, so a mesh refits once it shrinks below about half its size, and keeps at
# least about half the resolution a fresh field of it has. At 1/8, spot at 0.15 of its size kept a domain
# 6.7 times its own, and a mean ADF error 22 to 26 times a fresh field's (eleventh outside check, 2026-11-22)
REDOMAIN_MIN_FILL = 0.4

# A frame that moves the domain keeps the cube's side where a fresh fit's side would be at most this much smaller
# (REDOMAIN_KEEP_SIDE), never larger, so a mesh that moves without changing size keeps its local coordinates,
# lattice and planned frame (which is then replayed from a CUDA graph), and the kept cube holds whatever a fresh
# fit's would: a kept side a rounding smaller (the soak's cube, moved back and forth by exactly the margin) moved
# the domain every few frames. A move that grows the side takes REDOMAIN_REFIT_ROOM more than a fresh fit, the
# middle of that window, so a mesh that goes on growing a little between moves keeps it for a while (the bench's
# wobbling armadillo, thrown every frame, grew past a fresh fit's side on each of its last 15 moves, each a new plan
# run eagerly and captured again), and so does a mesh whose new centre only rounds a little further. A mesh that
# shrank below the window gets a fresh fit's side, as fine as a fresh field's. A kept side costs at most 5% of the
# finest cell's resolution against a fresh fit.
REDOMAIN_KEEP_SIDE = 1.05
REDOMAIN_REFIT_ROOM = 1.025

# Surface cells: a triangle is tested against each finest cell grown by this fraction of the cell size,
# so rounding never drops a cell the surface touches (a few extra cells are harmless).
CELL_OVERLAP_SLACK = 1.0e-3

# Closest feature: a barycentric coordinate within this of 0 puts the closest point on the edge or vertex,
# whose pseudonormal then gives the sign.
FEATURE_SNAP = 1.0e-5

# A triangle whose doubled area is below this fraction of its longest edge squared has no face normal (nor a
# share in its vertices' and edges' pseudonormals). float32's cross product of its edges carries rounding of
# about 1e-7 of that square, so below 1e-5 the normal's direction is off by more than about a degree; at the
# 1e-12 used before, three collinear float32 points (a zero-area face closing a split edge) gave a normal of
# pure rounding, 70 degrees off on the surface (outside check, 2026-11-22).
DEGENERATE_AREA = 1.0e-5

# A vertex's or edge's pseudonormal whose weighted sum of unit face normals is shorter than this fraction of
# its weights (angles, or the face count) has cancelled: faces nearly folded onto each other (the rim of a
# flap a millionth of the mesh's size thick). float32 leaves its direction to rounding, which signed points a
# tenth of the mesh's size away wrongly (outside check, 2026-11-22); such a feature lends no normal, and the
# winding number signs the points nearest it.
CANCELLED_PSEUDONORMAL = 1.0e-4

# The BVH's leaf boxes are grown by this much on every side (local units, where the domain's side is 0.7 to
# 1.4; about 16 float32 ulps of the coordinates). A box's rounded distance from a point could otherwise come
# out a few ulps above its triangle's, so a search could prune a triangle nearer than its bound, and its
# answer depended on where it started: with and without coherence, corner values differed in their last bits.
BOX_SLACK = 2.0**-20

# An exact query's normal is the direction from the closest point, except within this fraction of the domain's
# side of the surface: there float32 rounding of the two points (about 6e-8 of the side) would swing that
# direction by more than a few degrees, so the closest feature's normal (pseudonormal, or the face's) is used.
SURFACE_SNAP = 1.0e-6

# Fast winding number: a BVH node is replaced by its dipole when the point is farther from the node's
# area-weighted centre than this many node radii (Barill et al. 2018 use 2), on the radix tree over Morton codes.
# On the SAH-shaped tree 2 radii erred more (at 1,500 corners of a depth-6 octree on six meshes, CPU, 2026-12-01:
# largest errors 0.034 to 0.055 against 0.021 to 0.040 on the radix tree); 2.25 brings them to 0.020 to 0.039.
WINDING_FAR_FIELD = 2.0
WINDING_FAR_FIELD_SAH = 2.25

# A winding-number walk opens at most this many internal nodes; the nodes still waiting then take their expansion where
# the point lies beyond their radius and are left out where it lies within (`BvhView.winding_budget`), and the walk is
# counted (`stats()["winding_walks_cut"]`). Near a sound surface a walk opens a few nodes a level: the shared meshes at
# depths 5 to 9, one subdivided to 1.4 million faces and one with doubled faces needed fewer than 1,024 at every corner
# (CPU, 2026-12-06; docs/engine.md, "Fast winding numbers"). In a soup of large triangles no node is far from any point,
# and without a budget a frame cost the corners times the faces: the bunny's violent frame took 1.92 s on an H100 at
# depth 7, 0.27 s with this budget.
WINDING_BUDGET = 2048
# The budget binds only a soup: a frame whose surface area passes this many times the area of the sphere its BVH's
# root bounds (a closed convex surface inside a sphere has at most the sphere's area); or a tree that misfits the frame
# (RERUN_SPREAD below), whose frame runs again. A sound surface's walks may open more nodes than the budget, where its
# triangles are long and thin (a closed cylinder of 2,000 sections, 8,000 faces: every node is near every point beside
# it; cut, its walks signed 34,495 of its 140,195 corners at depth 7 wrongly, H100), and run whole, for 21 ms more a
# frame there. Measured at the root (CPU, 2026-12-06): the shared meshes 0.18 to 0.32 sphere areas, that cylinder 0.42,
# a sheet folded into 40 layers 4.1; the shared meshes' vertices thrown a fifth of their extent 10 (spot) to 138 (the
# armadillo), a twentieth 1.2 to 14.5.
SOUP_AREA = 8.0
# Where it binds, the budget counts only the fat nodes a walk opens: of more than this many times the area of the disc
# of their radius. A soup's nodes pile large triangles; a node of long thin triangles has little area for its radius,
# whatever the frame's area: an open sheet of strips folded into 110 layers (11.8 sphere areas, so a soup by the bar)
# had 5,168 walks cut and 691 of its 4,913 corners on the other side when every node counted, none cut with this; the
# bunny's whole throw took 1.63 to 1.67 s either way (CPU, depth 4, two rounds, 2026-12-06; not measured on a GPU).
# Swept on the CPU (docs/results/fat-area-cpu-2226): at 0.03 the sheet's strip nodes count and its walks are cut as if
# every node counted; at 0.3 the bunny's whole throw takes 15 to 20% longer, and no sound surface tried is cut at 0.1.
FAT_AREA = 0.1

# A BVH linked on Morton codes is refitted while the domain holds the frames. Consecutive leaves then hold neighbouring
# triangles, so their centroids lie less than a triangle's box apart (the leaf spread, Bvh.measure_spread: 0.6 to 0.8 on
# the shared meshes). A tree linked on a frame unlike the later ones (a violent frame's soup) keeps that frame's order:
# refitted to the calm mesh again, the bunny's spread was 9.6 and every walk ran long. Once the spread passes
# RELINK_SPREAD times the one at the last link (or the floor, for a tree linked on triangles of no size), the next frame
# links the tree again. Sixty frames of a dancer and of a galloping horse stayed within 8% of their first frame's.
RELINK_SPREAD = 2.0
RELINK_SPREAD_FLOOR = 0.25
# A frame whose winding walks met their budget on a tree due to be linked again runs again at once on a tree of its own
# where its spread passes this: the calm mesh on a soup's tree measured 3.3 (spot) to 12.5 (the armadillo), a soup on
# another soup's tree 0.52, whose walks meet the budget on any tree (CPU and H100, 2026-12-06).
RERUN_SPREAD = 1.0

# An open mesh's winding numbers in queries are corrected by its rim (`_sign.rim_fans`: fans C that close the faces'
# boundary chain, so w_S + w_C is a whole number off the surface). Where a walk's |w| lies within RIM_DOUBT of 1/2 (its
# expansions erred by up to 0.06 on the shared meshes, and 0.09 on frames that run through themselves), w becomes
# round(w + w_C) - w_C with w_C summed exactly, which is the oracle's w wherever the walk erred by less than
# RIM_TRUST; where w + w_C lies farther than that from a whole number the walk's w stays. A rim of more fan
# triangles than RIM_LIMIT (each point in doubt sums all of them) is left out, and such meshes keep the walk's w:
# at 4,000 fans, exact queries of 40,000 points beside an open ribbon (37% of them in doubt) took 2.19 s against
# 0.68 with the rim left out (CPU, outside re-check of 2026-12-02); 1,024 holds a scanned mesh's few holes (the
# bunny's 213 fans) and bounds that cost to about a quarter.
RIM_DOUBT = 0.2
RIM_TRUST = 0.25
RIM_LIMIT = 1024

# A closed mesh whose enclosed volume is below this fraction of (area x extent) encloses nothing
# (a doubled sheet, a flat closed shape); "auto" does not pick pseudonormals for it.
MIN_ENCLOSED_VOLUME = 1.0e-6

# Before "auto" settles on pseudonormals it looks just outside up to this many faces (spread over every
# part), this fraction of the mesh's extent off each, for the solid: parts nested or running into each
# other, which pseudonormals sign wrongly. A wider step would reach across narrow gaps between parts (a
# false alarm costs speed, not accuracy); a narrower one, float32's resolution of the face's position.
SOLID_BESIDE_SAMPLE = 16384
SOLID_BESIDE_REACH = 1.0e-4
# After a first frame without, "auto" looks beside this many points every frame (a window moving on through
# all of them: the faces' centroids, and on a coarse mesh six more points of each face), so a mesh that comes
# to overlap itself as it deforms is signed by winding numbers while it does. An overlap over a fraction q of the faces goes unseen in a frame with probability (1 - q)^sample:
# 1.7% at q = 1e-3. On this project's CPU (2026-11-22, depth 7) it took 0.033 s of the samba dancer's 0.20 s
# update (20K triangles) and 0.042 s of the armadillo's 0.62 s (86K); `sign="pseudonormal"` skips it.
SOLID_WATCH_SAMPLE = 4096

# The smallest band, as a fraction of the domain's side. Bands from here up to what float32 coordinates resolve
# (about 6e-8 of the side) are taken and act as a band of about zero: every corner off the surface reads
# +-band. Far below that, a band's square (the searches compare squared distances) would leave float32's normal
# numbers (a side of about 1 in local units: 2^-80 here, 2^-126 there). Registration refuses a smaller band; a band that
# becomes smaller later (the domain grew) is widened to it.
MIN_BAND = 2.0**-40

# Query points farther than this many domain sides from the domain's centre are moved in along the line to
# it (and the move added to their distance). No square of a length overflows float32 in the kernels then, and
# the searches still tell faces apart: from farther out float32 rounds their distances alike to an ulp or two,
# and every box "ties", so an exact query at 5e8 sides of the bunny took 1.3 ms a point against 0.013 near it
# (2^40 until 2026-12-02; CPU). The move changes a distance by at most r^2 / (2 FAR_POINT) for a mesh within r of
# the centre: 3.6e-7 of the side, a relative 3.4e-13, far below float32's rounding (see _pull_far_points).
FAR_POINT = 2.0**20

# A band wider than this many domain sides is beyond every distance the kernels meet (their points lie
# within FAR_POINT sides), so they take this instead: a wider one could overflow float32 (1e35 on a mesh of
# 1e-6). Far points moved in (FAR_POINT) are still clamped at the band asked for, on the host.
MAX_KERNEL_BAND = 2.0**44

# A frame is rigid (rigid="auto": the field is kept and queries are moved into it, _rigid.py) where one rotation and
# translation carry every used vertex of the last rebuilt frame to within this fraction of its bounding box's
# diagonal of the frame's: a tenth of the 1e-5 that exact queries keep. float32 frames pass it within about 10
# mesh sizes of the origin (their rounding there is about 6e-8 of the coordinates); float64 ones anywhere.
RIGID_TOLERANCE = 1.0e-6
# Vertices the pose is fitted to and checked at first (with each axis's extremes), before every vertex is checked.
RIGID_SAMPLE = 64

# Points are sent to the device in batches of at most this many, so memory stays bounded.
QUERY_CHUNK = 1 << 20

# On CUDA, a batch of at most this many points travels through pinned host buffers, whose copies run at the bus's
# rate (a pageable copy is staged by the driver); larger batches go pageable, so an object pins at most 2.9 MB.
STAGED_POINTS = 1 << 16

# An exact batch of at least this many points, by device kind, is walked in its points' Morton order (a sort on the
# device, PointQuery._order): a warp's (or a CPU thread's) walks then start near each other and share the nodes they
# load, where a caller's order (uniform samples) gives each warp 32 unrelated walks. On an H100 (2026-12-07) ordering
# changed the bunny's and the armadillo's exact queries by +13% to -18% at 65,536 points (the sort, about 0.1 ms,
# against what it saves) and by -16% to -53% at 1,048,576; sizes between were not measured. On this project's 2-core
# CPU it took 10 to 40% off from 2,048 points on (docs/engine.md, "A batch query's time").
ORDERED_POINTS = {"cuda": 1 << 17, "cpu": 1 << 11}

# Size limits checked at the boundary (vertex and face indices stay within int32 arithmetic).
MAX_VERTICES = 1 << 26
MAX_FACES = 1 << 26
MAX_DEPTH = 10
MAX_HALO = 2
