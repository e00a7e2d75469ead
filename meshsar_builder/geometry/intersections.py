"""Self-intersection test of a triangle mesh: a uniform-grid broad phase and a signed-volume narrow phase.

Which faces cross another face of the same mesh, by the definition of pymeshlab's
per-face selection (`compute_selection_by_self_intersections_per_face`): two faces
with no shared vertex intersect when they have any point in common; two faces
sharing one vertex intersect when they have more than that vertex in common (a fan
folded over); faces sharing an edge never count (a face turned over its edge is
the flipped-face test's). Unlike pymeshlab, exactly coplanar overlaps and a face
repeated on the same three vertices count too; elsewhere the two agree face for
face (tests/test_intersections.py). The shape model tests thousands of draws a
run, and pymeshlab spends about 24 ms on a 12,000-face draw; this takes about 5.3 (7.2 before
_neighbours_apart answered the neighbouring pairs, in the same run).

Narrow phase. Two triangles meet iff an edge of one meets the other, so the test
is six segment-triangle tests by signed volumes; four points whose signed volume
is within a relative tolerance of zero are coplanar and are tested in their plane.
Two faces sharing a vertex P meet beyond P iff their wedges at P do: off a common
plane, iff the segment joining the midpoints of one face's edges at P crosses the
other face's interior (either way round).
"""

from __future__ import annotations

import numba
import numpy as np

# Signed volumes below this fraction of (longest edge)^3 count as zero (coplanar points, a
# segment through an edge): a few hundred times the rounding of their products, no more, so
# that "touching" means touching within rounding.
_COPLANAR = 1e-13
# Grid cell size as a multiple of the median face box extent (measured: 1-3x is flat).
_CELL = 1.5


def self_intersecting_faces(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Which faces intersect another face of the mesh (see the module's definition).

    verts : (n, 3) float, faces : (m, 3) int  ->  (m,) bool
    """
    # Writeable C arrays, whatever comes in (the ssm stage's shared model is read-only): numba compiles a
    # kernel once per array type, and a second specialisation can swap machine code in the cache (radar/jit.py).
    verts = np.require(verts, dtype=np.float64, requirements=["C", "W"])
    faces = np.require(faces, dtype=np.int64, requirements=["C", "W"])
    if len(faces) < 2:
        return np.zeros(len(faces), dtype=bool)
    if not np.isfinite(verts).all():
        raise ValueError(f"verts: {int((~np.isfinite(verts)).any(axis=1).sum())} vertices are not finite")
    if faces.min() < 0 or faces.max() >= len(verts):
        raise ValueError(f"faces: indices must lie in [0, {len(verts)}), got {faces.min()}..{faces.max()}")
    return _self_intersections(verts, faces, _CELL)


def compile_kernels() -> None:
    """Compile the check's kernels, or load them from numba's on-disk cache, on a tetrahedron (a build's
    warm-up: Stage.warm): the same array types as every mesh, so the same compiled code."""
    corners = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    self_intersecting_faces(corners, np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))


# The narrow phase works on the rows of an (8, 3) scratch array P (the pair's six corners and
# two segment ends), named by row: views and temporaries in the pair loop cost more than the tests.
# Explicit signatures: numba would otherwise compile a version for every literal row number
# passed (29 of _cross2): 19 s of compilation on a cold cache instead of 8.
_SIGNATURES = {
    "_orient": "float64(float64[:, ::1], int64, int64, int64, int64)",
    "_drop_axis": "int64(float64[:, ::1], int64, int64, int64)",
    "_cross2": "float64(float64[:, ::1], int64, int64, int64, int64, int64)",
    "_on_segment_2d": "boolean(float64[:, ::1], int64, int64, int64, int64, int64)",
    "_segments_meet_2d": "boolean(float64[:, ::1], int64, int64, int64, int64, int64, int64, float64)",
    "_inside_2d": "boolean(float64[:, ::1], int64, int64, int64, int64, int64, int64, float64)",
    "_segment_meets_triangle": "boolean(float64[:, ::1], int64, int64, int64, int64, int64, float64, float64, boolean)",
    "_same_ray_2d": "boolean(float64[:, ::1], int64, int64, int64, int64, int64, float64)",
    "_strictly_between_2d": "boolean(float64[:, ::1], int64, int64, int64, int64, int64, int64, float64, int64)",
    "_wedges_overlap_2d": "boolean(float64[:, ::1], int64, int64, int64, int64, int64, int64, int64, float64)",
}


def pymeshlab_self_intersecting_faces(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """pymeshlab's per-face self-intersection selection, the reference the tests and
    `meshsar bench geometry` compare self_intersecting_faces with.

    verts : (n, 3) float, faces : (m, 3) int  ->  (m,) bool
    """
    import pymeshlab  # here: the trainer's metrics use only the test above, so training needs no pymeshlab

    meshset = pymeshlab.MeshSet()
    meshset.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(verts, dtype=np.float64),
                                    face_matrix=np.ascontiguousarray(faces, dtype=np.int32)))
    meshset.compute_selection_by_self_intersections_per_face()
    return np.array(meshset.current_mesh().face_selection_array(), dtype=bool)


@numba.njit(_SIGNATURES["_orient"], cache=True)
def _orient(P, p, q, r, s):
    """Six times the signed volume of the tetrahedron of rows p, q, r, s."""
    ax, ay, az = P[q, 0] - P[p, 0], P[q, 1] - P[p, 1], P[q, 2] - P[p, 2]
    bx, by, bz = P[r, 0] - P[p, 0], P[r, 1] - P[p, 1], P[r, 2] - P[p, 2]
    cx, cy, cz = P[s, 0] - P[p, 0], P[s, 1] - P[p, 1], P[s, 2] - P[p, 2]
    return ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)


@numba.njit(cache=True, inline="always")
def _sign(x, tol):
    if x > tol:
        return 1
    if x < -tol:
        return -1
    return 0


@numba.njit(_SIGNATURES["_drop_axis"], cache=True)
def _drop_axis(P, p, q, r):
    """The axis along which the plane of rows p, q, r is steepest: dropping it keeps the plane's shape."""
    ux, uy, uz = P[q, 0] - P[p, 0], P[q, 1] - P[p, 1], P[q, 2] - P[p, 2]
    vx, vy, vz = P[r, 0] - P[p, 0], P[r, 1] - P[p, 1], P[r, 2] - P[p, 2]
    nx, ny, nz = abs(uy * vz - uz * vy), abs(uz * vx - ux * vz), abs(ux * vy - uy * vx)
    if nx >= ny and nx >= nz:
        return 0
    return 1 if ny >= nz else 2


@numba.njit(_SIGNATURES["_cross2"], cache=True)
def _cross2(P, a, b, c, i, j):
    """z of (b - a) x (c - a) in the (i, j) plane."""
    return (P[b, i] - P[a, i]) * (P[c, j] - P[a, j]) - (P[b, j] - P[a, j]) * (P[c, i] - P[a, i])


@numba.njit(_SIGNATURES["_on_segment_2d"], cache=True)
def _on_segment_2d(P, p, q, r, i, j):
    """Row r, collinear with segment [p, q], lies within its box."""
    return (min(P[p, i], P[q, i]) <= P[r, i] <= max(P[p, i], P[q, i])
            and min(P[p, j], P[q, j]) <= P[r, j] <= max(P[p, j], P[q, j]))


@numba.njit(_SIGNATURES["_segments_meet_2d"], cache=True)
def _segments_meet_2d(P, a, b, c, d, i, j, tol):
    """Closed segments [a, b] and [c, d] share a point, in the (i, j) plane."""
    d1, d2 = _sign(_cross2(P, c, d, a, i, j), tol), _sign(_cross2(P, c, d, b, i, j), tol)
    d3, d4 = _sign(_cross2(P, a, b, c, i, j), tol), _sign(_cross2(P, a, b, d, i, j), tol)
    if d1 * d2 < 0 and d3 * d4 < 0:
        return True
    return ((d1 == 0 and _on_segment_2d(P, c, d, a, i, j)) or (d2 == 0 and _on_segment_2d(P, c, d, b, i, j))
            or (d3 == 0 and _on_segment_2d(P, a, b, c, i, j)) or (d4 == 0 and _on_segment_2d(P, a, b, d, i, j)))


@numba.njit(_SIGNATURES["_inside_2d"], cache=True)
def _inside_2d(P, x, p, q, r, i, j, tol):
    """Row x lies in the closed triangle of rows p, q, r, in the (i, j) plane."""
    s1 = _sign(_cross2(P, p, q, x, i, j), tol)
    s2 = _sign(_cross2(P, q, r, x, i, j), tol)
    s3 = _sign(_cross2(P, r, p, x, i, j), tol)
    return (s1 >= 0 and s2 >= 0 and s3 >= 0) or (s1 <= 0 and s2 <= 0 and s3 <= 0)


@numba.njit(_SIGNATURES["_segment_meets_triangle"], cache=True)
def _segment_meets_triangle(P, a, b, p, q, r, tol, tol2, strict):
    """Segment [a, b] meets triangle (p, q, r) (rows of P); strict: crosses its interior (a
    coplanar segment never does). tol, tol2: the zero of signed volumes and of signed areas."""
    oa, ob = _sign(_orient(P, p, q, r, a), tol), _sign(_orient(P, p, q, r, b), tol)
    if oa * ob > 0:
        return False
    if oa == 0 and ob == 0:
        if strict:
            return False
        k = _drop_axis(P, p, q, r)
        i, j = (k + 1) % 3, (k + 2) % 3
        return (_inside_2d(P, a, p, q, r, i, j, tol2) or _segments_meet_2d(P, a, b, p, q, i, j, tol2)
                or _segments_meet_2d(P, a, b, q, r, i, j, tol2) or _segments_meet_2d(P, a, b, r, p, i, j, tol2))
    s1 = _sign(_orient(P, a, b, p, q), tol)
    s2 = _sign(_orient(P, a, b, q, r), tol)
    s3 = _sign(_orient(P, a, b, r, p), tol)
    if strict:
        return oa * ob < 0 and ((s1 > 0 and s2 > 0 and s3 > 0) or (s1 < 0 and s2 < 0 and s3 < 0))
    return (s1 >= 0 and s2 >= 0 and s3 >= 0) or (s1 <= 0 and s2 <= 0 and s3 <= 0)


@numba.njit(_SIGNATURES["_same_ray_2d"], cache=True)
def _same_ray_2d(P, p, a, x, i, j, tol):
    """Rows a and x lie on one ray from row p, in the (i, j) plane."""
    along = (P[a, i] - P[p, i]) * (P[x, i] - P[p, i]) + (P[a, j] - P[p, j]) * (P[x, j] - P[p, j])
    return _sign(_cross2(P, p, a, x, i, j), tol) == 0 and along > 0


@numba.njit(_SIGNATURES["_strictly_between_2d"], cache=True)
def _strictly_between_2d(P, p, a, x, b, i, j, tol, turn):
    """Row x lies strictly inside the wedge (p; a, b) whose turn from a to b has sign turn."""
    return _sign(_cross2(P, p, a, x, i, j), tol) == turn and _sign(_cross2(P, p, x, b, i, j), tol) == turn


@numba.njit(_SIGNATURES["_wedges_overlap_2d"], cache=True)
def _wedges_overlap_2d(P, p, a, b, c, d, i, j, tol):
    """Coplanar wedges (p; a, b) and (p; c, d), each under 180 deg, share more than their apex."""
    ab = _sign(_cross2(P, p, a, b, i, j), tol)
    cd = _sign(_cross2(P, p, c, d, i, j), tol)
    if ab == 0 or cd == 0:
        return False
    for x in (c, d):  # an edge of one strictly inside the other wedge
        if _strictly_between_2d(P, p, a, x, b, i, j, tol, ab):
            return True
    for x in (a, b):
        if _strictly_between_2d(P, p, c, x, d, i, j, tol, cd):
            return True
    # No edge inside the other wedge: they overlap only if they are the same wedge.
    return ((_same_ray_2d(P, p, a, c, i, j, tol) and _same_ray_2d(P, p, b, d, i, j, tol))
            or (_same_ray_2d(P, p, a, d, i, j, tol) and _same_ray_2d(P, p, b, c, i, j, tol)))


@numba.njit(cache=True, inline="always")
def _plane_side(verts, v, normal, offset, f, tol):
    """Which side of face f's plane vertex v lies on (0: on it, within tol)."""
    return _sign(normal[f, 0] * verts[v, 0] + normal[f, 1] * verts[v, 1] + normal[f, 2] * verts[v, 2] - offset[f], tol)


@numba.njit(cache=True, inline="always")
def _faces_intersect(verts, faces, normal, offset, f, g, length_tol, P):
    """Faces f and g intersect, by the module's definition, for a pair that _neighbours_apart left open (so
    no shared edge, and a shared corner only where the planes cross). normal, offset: faces' unit normals
    and plane offsets; P: (8, 3) scratch, so the pair loop allocates nothing."""
    shared, k0, k1 = 0, 0, 0
    for k in range(3):
        for j in range(3):
            if faces[f, k] == faces[g, j]:
                shared += 1
                k0, k1 = k, j
    if shared == 3:
        return True
    if shared == 0:  # Möller's rejection: one face strictly on one side of the other's plane
        for side in range(2):
            this, other = (f, g) if side == 0 else (g, f)
            s0 = _plane_side(verts, faces[other, 0], normal, offset, this, length_tol)
            s1 = _plane_side(verts, faces[other, 1], normal, offset, this, length_tol)
            s2 = _plane_side(verts, faces[other, 2], normal, offset, this, length_tol)
            if s0 == s1 == s2 != 0:
                return False
    # Rows 0-2: face f, rows 3-5: face g, each rotated so that a shared vertex comes first.
    longest = 0.0
    for k in range(3):
        for axis in range(3):
            P[k, axis] = verts[faces[f, (k0 + k) % 3], axis]
            P[3 + k, axis] = verts[faces[g, (k1 + k) % 3], axis]
    for t in (0, 3):
        for k in range(3):
            e0, e1, e2 = (P[t + (k + 1) % 3, 0] - P[t + k, 0], P[t + (k + 1) % 3, 1] - P[t + k, 1],
                          P[t + (k + 1) % 3, 2] - P[t + k, 2])
            longest = max(longest, e0 * e0 + e1 * e1 + e2 * e2)
    tol, tol2 = _COPLANAR * longest * np.sqrt(longest), _COPLANAR * longest
    if shared == 0:
        for k in range(3):
            if _segment_meets_triangle(P, k, (k + 1) % 3, 3, 4, 5, tol, tol2, False):
                return True
            if _segment_meets_triangle(P, 3 + k, 3 + (k + 1) % 3, 0, 1, 2, tol, tol2, False):
                return True
        return False
    # One shared vertex, row 0 (= row 3): faces (0; 1, 2) and (0; 4, 5).
    dc, dd = _orient(P, 0, 1, 2, 4), _orient(P, 0, 1, 2, 5)
    sc, sd = _sign(dc, tol), _sign(dd, tol)
    if sc * sd > 0:  # the other face leaves this one's plane at once: only the apex is shared
        return False
    if sc == 0 and sd == 0:
        k = _drop_axis(P, 0, 1, 2)
        return _wedges_overlap_2d(P, 0, 1, 2, 4, 5, (k + 1) % 3, (k + 2) % 3, tol2)
    ea, eb = _orient(P, 0, 4, 5, 1), _orient(P, 0, 4, 5, 2)
    if sc * sd < 0 and _sign(ea, tol) * _sign(eb, tol) < 0:
        # Each face crosses the other's plane: g meets the planes' common line in [apex, X], f in [apex, Y],
        # X - apex = x / (dc - dd), Y - apex = y / (ea - eb) (x, y below). They share more than the apex iff X
        # and Y lie on one side of it. x and y are parallel, so the sign of x.y is sure unless one is ~0
        # (then the midpoint test below decides). The check went from 7.5 to 6.4 ms a 12,000-face draw, with the
        # same answers on 1.95 M faces of shape-model samples, crumpled ones and folded spheres.
        dot, xx, yy = 0.0, 0.0, 0.0
        for axis in range(3):
            x = dc * (P[5, axis] - P[0, axis]) - dd * (P[4, axis] - P[0, axis])
            y = ea * (P[2, axis] - P[0, axis]) - eb * (P[1, axis] - P[0, axis])
            dot += x * y
            xx += x * x
            yy += y * y
        if dot != 0.0 and dot * dot >= 0.25 * xx * yy:
            return (dot > 0) == ((dc - dd > 0) == (ea - eb > 0))
    for half in range(2):  # the midpoints of one face's edges at the apex, against the other face
        first, other = (1, 4) if half == 0 else (4, 1)
        second = first + 1
        for axis in range(3):
            P[6, axis] = 0.5 * (P[first, axis] + P[0, axis])
            P[7, axis] = 0.5 * (P[second, axis] + P[0, axis])
        if _segment_meets_triangle(P, 6, 7, 0, other, other + 1, tol, tol2, True):
            return True
    return False


@numba.njit(cache=True, inline="always")
def _free_corners_one_side(verts, normal, offset, f, g0, g1, g2, f0, f1, f2, tol):
    """Face g's two corners that are not face f's lie strictly on one side of f's plane (g shares one
    corner with f: g0, g1, g2 and f0, f1, f2 are their vertex indices)."""
    a, b = -1, -1
    for x in (g0, g1, g2):
        if x != f0 and x != f1 and x != f2:
            if a < 0:
                a = x
            else:
                b = x
    return _plane_side(verts, a, normal, offset, f, tol) * _plane_side(verts, b, normal, offset, f, tol) > 0


@numba.njit(cache=True, inline="always")
def _neighbours_apart(verts, faces, normal, offset, f, g, tol):
    """Faces f and g surely do not intersect because they are neighbours: they share an edge, or they share a
    corner and one's free corners lie strictly on one side of the other's plane. Three quarters of a mesh's
    candidate pairs are answered here, in a few plain loads, before _faces_intersect, whose set-up alone cost
    50 ns a pair when it gave these answers itself."""
    f0, f1, f2, g0, g1, g2 = faces[f, 0], faces[f, 1], faces[f, 2], faces[g, 0], faces[g, 1], faces[g, 2]
    shared = ((f0 == g0) + (f0 == g1) + (f0 == g2) + (f1 == g0) + (f1 == g1) + (f1 == g2)
              + (f2 == g0) + (f2 == g1) + (f2 == g2))
    if shared == 2:
        return True
    if shared != 1:
        return False
    return (_free_corners_one_side(verts, normal, offset, f, g0, g1, g2, f0, f1, f2, tol)
            or _free_corners_one_side(verts, normal, offset, g, f0, f1, f2, g0, g1, g2, tol))


@numba.njit(cache=True)
def _self_intersections(verts, faces, cell_factor):
    """(m,) bool: the broad phase (faces' boxes in a uniform grid of cell_factor times the
    median box extent, each box in every cell it overlaps) and the narrow phase per pair."""
    m = len(faces)
    lo = np.empty((m, 3))
    hi = np.empty((m, 3))
    normal = np.empty((m, 3))
    offset = np.empty(m)
    extent = np.empty(m)
    extent_sum = 0.0
    for f in range(m):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        for k in range(3):
            lo[f, k] = min(verts[a, k], verts[b, k], verts[c, k])
            hi[f, k] = max(verts[a, k], verts[b, k], verts[c, k])
        extent[f] = max(hi[f, 0] - lo[f, 0], hi[f, 1] - lo[f, 1], hi[f, 2] - lo[f, 2])
        ux, uy, uz = verts[b, 0] - verts[a, 0], verts[b, 1] - verts[a, 1], verts[b, 2] - verts[a, 2]
        vx, vy, vz = verts[c, 0] - verts[a, 0], verts[c, 1] - verts[a, 1], verts[c, 2] - verts[a, 2]
        nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
        norm = np.sqrt(nx * nx + ny * ny + nz * nz)
        if norm > 0:
            nx, ny, nz = nx / norm, ny / norm, nz / norm
        normal[f, 0], normal[f, 1], normal[f, 2] = nx, ny, nz
        offset[f] = nx * verts[a, 0] + ny * verts[a, 1] + nz * verts[a, 2]
        extent_sum += extent[f]
    length_tol = _COPLANAR * extent_sum / m  # plane distances this small are 0
    origin = np.empty(3)
    span = np.empty(3)
    for k in range(3):
        origin[k] = lo[:, k].min()
        span[k] = hi[:, k].max() - origin[k]
    cell = max(cell_factor * np.median(extent), 1e-9 * max(span[0], span[1], span[2]), 1e-300)
    # Bound the grid to a few cells a face (a mesh of a few huge faces among tiny ones).
    while (span[0] / cell + 1) * (span[1] / cell + 1) * (span[2] / cell + 1) > 64.0 * m + 1024:
        cell *= 1.5
    dims = np.empty(3, dtype=np.int64)
    for k in range(3):
        dims[k] = int(span[k] / cell) + 1
    cells_lo = np.empty((m, 3), dtype=np.int64)
    cells_hi = np.empty((m, 3), dtype=np.int64)
    count = np.zeros(dims[0] * dims[1] * dims[2] + 1, dtype=np.int64)
    for f in range(m):
        for k in range(3):
            cells_lo[f, k] = min(int((lo[f, k] - origin[k]) / cell), dims[k] - 1)
            cells_hi[f, k] = min(int((hi[f, k] - origin[k]) / cell), dims[k] - 1)
        for x in range(cells_lo[f, 0], cells_hi[f, 0] + 1):
            for y in range(cells_lo[f, 1], cells_hi[f, 1] + 1):
                for z in range(cells_lo[f, 2], cells_hi[f, 2] + 1):
                    count[(x * dims[1] + y) * dims[2] + z + 1] += 1
    start = np.cumsum(count)
    fill = start.copy()
    members = np.empty(start[-1], dtype=np.int64)
    for f in range(m):
        for x in range(cells_lo[f, 0], cells_hi[f, 0] + 1):
            for y in range(cells_lo[f, 1], cells_hi[f, 1] + 1):
                for z in range(cells_lo[f, 2], cells_hi[f, 2] + 1):
                    key = (x * dims[1] + y) * dims[2] + z
                    members[fill[key]] = f
                    fill[key] += 1
    hit = np.zeros(m, dtype=np.bool_)
    scratch = np.empty((8, 3))
    for key in range(len(start) - 1):
        first, last = start[key], start[key + 1]
        z = key % dims[2]
        y = (key // dims[2]) % dims[1]
        x = key // (dims[1] * dims[2])
        for s in range(first, last):
            f = members[s]
            flo0, flo1, flo2, fhi0, fhi1, fhi2 = lo[f, 0], lo[f, 1], lo[f, 2], hi[f, 0], hi[f, 1], hi[f, 2]
            fc0, fc1, fc2 = cells_lo[f, 0], cells_lo[f, 1], cells_lo[f, 2]
            for r in range(s + 1, last):
                g = members[r]
                if (flo0 > hi[g, 0] or lo[g, 0] > fhi0 or flo1 > hi[g, 1] or lo[g, 1] > fhi1
                        or flo2 > hi[g, 2] or lo[g, 2] > fhi2):
                    continue
                # Each pair once: in the cell holding the lower corner of the boxes' overlap.
                if max(fc0, cells_lo[g, 0]) != x or max(fc1, cells_lo[g, 1]) != y or max(fc2, cells_lo[g, 2]) != z:
                    continue
                if hit[f] and hit[g]:
                    continue
                if _neighbours_apart(verts, faces, normal, offset, f, g, length_tol):
                    continue
                if _faces_intersect(verts, faces, normal, offset, f, g, length_tol, scratch):
                    hit[f] = True
                    hit[g] = True
    return hit
