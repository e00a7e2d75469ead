"""Digital topology of voxel sets: simple points and topology-preserving growth.

A voxel is *simple* for a set X when adding it to X (or removing it) changes neither the number
of components, of tunnels (handles) nor of cavities. Bertrand's local test decides it from the
3×3×3 neighbourhood: with (a, b) the adjacencies of X and of its complement, (26, 6) or (6, 26),
x is simple iff X ∩ N*(x) has exactly one a-component (for a = 6: counted in N18, 6-adjacent to
x) and the complement has exactly one b-component likewise.

Growing a region from a ball by simple points only, in a chosen order, gives a set with the
topology of a ball that covers all of a domain except thin cuts through its handles: the
classic step of topology correction (Han, Xu & Prince 2002; Ségonne 2008). Grown from the deep
inside outward, it cuts each handle where it is thinnest; grown in the complement from the
outside inward, it fills each tunnel where it is narrowest.
"""

from __future__ import annotations

import heapq

import numba
import numpy as np

# Offsets of the 27 positions of a 3×3×3 neighbourhood, index = 9·i + 3·j + k, centre 13.
_OFFSETS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)], dtype=np.int64)
_CENTRE = 13
_L1 = np.abs(_OFFSETS).sum(axis=1)  # 1: face neighbour, 2: edge, 3: corner


def _adjacency(max_l1: int) -> np.ndarray:
    """(27, 27) bool: positions p, q adjacent (differ by one step of L1 norm ≤ max_l1, L∞ = 1)."""
    d = _OFFSETS[:, None, :] - _OFFSETS[None, :, :]
    linf, l1 = np.abs(d).max(axis=2), np.abs(d).sum(axis=2)
    return (linf == 1) & (l1 <= max_l1)


_ADJ6 = _adjacency(1)
_ADJ26 = _adjacency(3)
_N18 = _L1 <= 2
_N26 = np.ones(27, dtype=bool)
_N18[_CENTRE] = _N26[_CENTRE] = False
_FACE = _L1 == 1


@numba.njit(cache=True)
def _components(member, allowed, adj, need_face):
    """Components of {p : member[p] & allowed[p]} under `adj`; with need_face, only those that
    contain a face neighbour of the centre are counted."""
    seen = np.zeros(27, dtype=np.bool_)
    stack = np.empty(27, dtype=np.int64)
    count = 0
    for start in range(27):
        if seen[start] or not (member[start] and allowed[start]):
            continue
        top = 0
        stack[0] = start
        seen[start] = True
        touches = False
        while top >= 0:
            p = stack[top]
            top -= 1
            if _FACE[p]:
                touches = True
            for q in range(27):
                if adj[p, q] and not seen[q] and member[q] and allowed[q]:
                    seen[q] = True
                    top += 1
                    stack[top] = q
        if touches or not need_face:
            count += 1
    return count


@numba.njit(cache=True)
def _is_simple(region, x, y, z, six_region):
    """Whether voxel (x, y, z) is simple for `region` (uint8 volume, 1 = in) with the region's
    adjacency 6 (six_region) or 26, its complement's the other."""
    member = np.empty(27, dtype=np.bool_)
    other = np.empty(27, dtype=np.bool_)
    for p in range(27):
        v = region[x + _OFFSETS[p, 0], y + _OFFSETS[p, 1], z + _OFFSETS[p, 2]] != 0
        member[p] = v
        other[p] = not v
    member[13] = False
    other[13] = False
    if six_region:
        return (_components(member, _N18, _ADJ6, True) == 1
                and _components(other, _N26, _ADJ26, False) == 1)
    return (_components(member, _N26, _ADJ26, False) == 1
            and _components(other, _N18, _ADJ6, True) == 1)


@numba.njit(cache=True)
def _grow(region, domain, priority, six_region):
    """Add voxels of `domain` to `region` in order of increasing priority, simple points only.

    region, domain : (X, Y, Z) uint8 (modified: region in place), priority : (X, Y, Z) float64.
    Both must be zero on the outer layer of the volume. A voxel that is not simple when it comes
    up is tried again whenever one of its neighbours joins the region.
    """
    nx, ny, nz = region.shape
    queued = np.zeros(region.shape, dtype=np.bool_)
    heap = [(0.0, np.int64(0))]
    heap.pop()
    for x in range(1, nx - 1):
        for y in range(1, ny - 1):
            for z in range(1, nz - 1):
                if region[x, y, z] or not domain[x, y, z]:
                    continue
                for p in range(27):
                    if region[x + _OFFSETS[p, 0], y + _OFFSETS[p, 1], z + _OFFSETS[p, 2]]:
                        heap.append((priority[x, y, z], np.int64((x * ny + y) * nz + z)))
                        queued[x, y, z] = True
                        break
    heapq.heapify(heap)
    while len(heap):
        _, flat = heapq.heappop(heap)
        x, rest = divmod(flat, ny * nz)
        y, z = divmod(rest, nz)
        queued[x, y, z] = False
        if region[x, y, z] or not _is_simple(region, x, y, z, six_region):
            continue
        region[x, y, z] = 1
        for p in range(27):
            a, b, c = x + _OFFSETS[p, 0], y + _OFFSETS[p, 1], z + _OFFSETS[p, 2]
            if domain[a, b, c] and not region[a, b, c] and not queued[a, b, c]:
                queued[a, b, c] = True
                heapq.heappush(heap, (priority[a, b, c], np.int64((a * ny + b) * nz + c)))
    return region


def ball_core(solid: np.ndarray, depth: np.ndarray, six: bool = True) -> np.ndarray:
    """The largest subset of a solid with the topology of a ball, grown deepest first.

    solid : (X, Y, Z) bool, one component; depth : (X, Y, Z) float, larger = deeper inside
    (e.g. minus the signed distance); six : the solid's adjacency is 6 (its complement's 26),
    else 26 (complement 6). Returns (X, Y, Z) bool ⊆ solid; solid minus it are the cuts through
    its handles (and nothing else when the solid has no cavity).
    """
    pad = np.pad(solid, 2).astype(np.uint8)
    prio = -np.pad(np.asarray(depth, np.float64), 2)
    region = np.zeros_like(pad)
    seed = np.unravel_index(np.argmin(np.where(pad > 0, prio, np.inf)), pad.shape)
    region[seed] = 1
    _grow(region, pad, prio, six)
    return region[2:-2, 2:-2, 2:-2].astype(bool)


def filled_solid(solid: np.ndarray, depth: np.ndarray, six: bool = True) -> np.ndarray:
    """The smallest superset of a solid with the topology of a ball, its tunnels filled where
    the outside, grown from the volume's border farthest first, cannot pass.

    solid : (X, Y, Z) bool, depth : (X, Y, Z) float (larger = deeper inside), six : the solid's
    adjacency as in `ball_core`. Returns (X, Y, Z) bool ⊇ solid.
    """
    outside = np.pad(~solid, 2).astype(np.uint8)
    prio = np.pad(np.asarray(depth, np.float64), 2)
    region = np.zeros_like(outside)
    region[[0, 1, -2, -1], :, :] = 1
    region[:, [0, 1, -2, -1], :] = 1
    region[:, :, [0, 1, -2, -1]] = 1
    domain = outside.copy()
    domain[[0, -1], :, :] = domain[:, [0, -1], :] = domain[:, :, [0, -1]] = 0
    _grow(region, domain, prio, not six)
    return ~region[2:-2, 2:-2, 2:-2].astype(bool)
