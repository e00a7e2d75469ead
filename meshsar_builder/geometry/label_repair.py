"""Topology repair of multi-label heart maps by anatomy, before their union is meshed.

DESIGN section 6. Real label maps are not genus 0: structures touch where anatomy does not join
them (great vessels against each other and the atria), joined structures are kept apart by an
unlabelled wall (a valve plane) except in patches, and single labels have holes and islands.
Each of those makes a handle in the union's surface. The repair, in order:

1. `clean_labels`: each label's enclosed holes are filled and its small islands dropped (an
   island enclosed by other labels takes their label, so the union does not change).
2. `fill_junction_walls`: between structures that anatomy joins (`JUNCTIONS`), the unlabelled
   voxels within `wall_mm` of both become the nearer one: the joined pools meet over one patch.
3. `separate_contacts`: where structures touch (or come within the gap) without a junction,
   the one lower in `KEEP_ORDER` gives up its voxels within `gap_mm` of the other, so a gap wide
   enough to survive the meshing's smoothing separates them along the contact only.

Whatever handle is left is cut or filled on the meshing grid (`correct_handles`), whichever
changes fewer voxels. Every step returns what it changed, for the sidecar.

On the meshed surface of a biventricular map, `lv_gaps_to_myo` relabels the LV's patches other
than its basal cut (gaps in the myocardium's labels) as myocardium. Before any of it, `check_border`
refuses a map whose field of view cuts a chamber off.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from skimage.measure import euler_number

from meshsar_builder.geometry.digital_topology import ball_core, filled_solid
from meshsar_builder.geometry.measures import vertex_areas
from meshsar_builder.geometry.structures import STRUCTURES
from meshsar_builder.pipeline.errors import MeshError

# Pairs of structures that anatomy joins: their contact is kept and the unlabelled wall between
# them filled. Valve planes (mitral, aortic, tricuspid, pulmonary), the septa, the myocardium
# where it meets the atria and the aortic root, and LV-RV blood touching through a gap in the
# septum's label. Any other contact (vessel-vessel, vessel-atrium, LV-RA, RV-LA, ...) is cut.
JUNCTIONS: frozenset[frozenset[str]] = frozenset(frozenset(pair) for pair in (
    ("lv", "myo"),  # the LV wall
    ("lv", "la"),  # mitral valve
    ("lv", "aorta"),  # aortic valve
    ("myo", "aorta"),  # aortic root in the LV outflow
    ("rv", "ra"),  # tricuspid valve
    ("rv", "pa"),  # pulmonary valve
    ("myo", "rv"),  # interventricular septum
    ("lv", "rv"),  # blood pools meeting through an unlabelled piece of the septum
    ("la", "ra"),  # interatrial septum
    ("myo", "la"),  # LV base against the LA
    ("myo", "ra"),  # LV base against the RA
))

# Where two structures touch without a junction, the later one in this order gives up the
# voxels of the gap: vessels before atria before ventricles, so chambers keep their volume.
KEEP_ORDER: tuple[str, ...] = ("lv", "myo", "rv", "la", "ra", "aorta", "pa")
# Structures whose volume the repair must keep within the bound; vessels are only reported
# (their length in a label map depends on the field of view and the annotator anyway).
CHAMBERS: tuple[str, ...] = ("lv", "myo", "rv", "la", "ra")

_NAMES = {v: k for k, v in STRUCTURES.items()}


def _near(mask: np.ndarray, voxel_mm: np.ndarray, reach_mm: float) -> tuple[tuple[slice, ...], np.ndarray] | None:
    """The box of `mask` widened by reach_mm, and the distance (mm) to `mask` in it; None if empty.

    Every voxel within reach_mm of the mask lies in the box, and the mask lies wholly inside
    it, so the distances there are exact. One structure's box is a fraction of a CT's heart
    crop: the repair's distance maps were most of its time.
    """
    found = ndimage.find_objects(mask.view(np.uint8))
    if not found:
        return None
    pad = np.ceil(reach_mm / voxel_mm).astype(int) + 1
    box = tuple(slice(max(s.start - p, 0), min(s.stop + p, n)) for s, p, n in zip(found[0], pad, mask.shape))
    return box, ndimage.distance_transform_edt(~mask[box], sampling=voxel_mm)


def _within(near: tuple[tuple[slice, ...], np.ndarray], box: tuple[slice, ...]) -> np.ndarray:
    """A `_near` distance map read over `box` (which lies inside its own box)."""
    own, dist = near
    return dist[tuple(slice(b.start - o.start, b.stop - o.start) for b, o in zip(box, own))]


def _overlap(a: tuple[slice, ...], b: tuple[slice, ...]) -> tuple[slice, ...] | None:
    box = tuple(slice(max(x.start, y.start), min(x.stop, y.stop)) for x, y in zip(a, b))
    return box if all(s.start < s.stop for s in box) else None


def _present(labels: np.ndarray) -> list[str]:
    ids = np.flatnonzero(np.bincount(labels.ravel(), minlength=max(STRUCTURES.values()) + 1))
    return [_NAMES[i] for i in ids if i in _NAMES]


def clean_labels(labels: np.ndarray, island_fraction: float) -> tuple[np.ndarray, dict]:
    """Fill each label's enclosed holes and drop its islands smaller than `island_fraction` of it.

    labels : (X, Y, Z) uint8 canonical ids. Returns the cleaned labels and {structure:
    {"holes_filled", "islands_dropped", "island_voxels"}} for structures changed. A hole is
    background enclosed by the label alone; an island is a 26-connected component other than
    the largest. A dropped island enclosed by other labels takes the label that surrounds it
    most, else it becomes background.
    """
    out = labels.copy()
    record = {}
    full = np.ones((3, 3, 3), bool)
    for name in _present(labels):
        sid = STRUCTURES[name]
        holes = ndimage.binary_fill_holes(out == sid) & (out == 0)
        out[holes] = sid
        comp, _ = ndimage.label(out == sid, structure=full)
        sizes = np.bincount(comp.ravel())[1:]
        boxes = ndimage.find_objects(comp)
        dropped = voxels = 0
        for c in np.flatnonzero(sizes < island_fraction * sizes.sum()) + 1:
            if c == sizes.argmax() + 1:
                continue
            # Work in the island's box, one voxel wider: real maps have hundreds of islands.
            box = tuple(slice(max(b.start - 1, 0), b.stop + 1) for b in boxes[c - 1])
            island = comp[box] == c
            sub = out[box]
            ring = ndimage.binary_dilation(island, structure=full) & ~island
            around = np.bincount(sub[ring], minlength=max(STRUCTURES.values()) + 1)
            around[sid] = 0
            sub[island] = around.argmax() if around[0] == 0 else 0  # enclosed: no background around it
            dropped, voxels = dropped + 1, voxels + int(sizes[c - 1])
        if holes.any() or dropped:
            record[name] = {"holes_filled": int(holes.sum()), "islands_dropped": dropped, "island_voxels": voxels}
    return out, record


def fill_junction_walls(labels: np.ndarray, voxel_mm: np.ndarray, wall_mm: float) -> tuple[np.ndarray, list[dict], np.ndarray]:
    """Fill the unlabelled wall between structures that anatomy joins, where both are near.

    labels : (X, Y, Z) uint8, voxel_mm : (3,), wall_mm : a background voxel within this distance
    of both structures of a junction takes the nearer one's label. Returns the labels, one
    {"structures", "voxels"} per junction filled, and the (X, Y, Z) bool mask of the wall voxels
    filled (wall tissue, not chamber volume: the volume bounds leave it out).
    """
    out = labels.copy()
    near = {name: _near(labels == STRUCTURES[name], voxel_mm, wall_mm) for name in _present(labels)}
    record = []
    walls = np.zeros(labels.shape, bool)
    for a, b in sorted(sorted(p) for p in JUNCTIONS):
        if near.get(a) is None or near.get(b) is None or (box := _overlap(near[a][0], near[b][0])) is None:
            continue
        da, db = _within(near[a], box), _within(near[b], box)
        wall = (out[box] == 0) & (da <= wall_mm) & (db <= wall_mm)
        if wall.any():
            out[box][wall] = np.where(da[wall] <= db[wall], STRUCTURES[a], STRUCTURES[b])
            walls[box] |= wall
            record.append({"structures": [a, b], "voxels": int(wall.sum())})
    return out, record, walls


def separate_contacts(labels: np.ndarray, voxel_mm: np.ndarray, gap_mm: float) -> tuple[np.ndarray, list[dict], np.ndarray]:
    """Open a gap where two structures touch, or come within `gap_mm`, without a junction.

    labels : (X, Y, Z) uint8, voxel_mm : (3,). The structure later in KEEP_ORDER loses its voxels
    within gap_mm of the other. Returns the labels, one {"structures", "voxels", "position_mm"
    (voxel index centroid; the caller maps it to mm)} per contact cut, and the (X, Y, Z) bool
    mask of the voxels removed (the new gap walls lie along it).
    """
    out = labels.copy()
    present = [n for n in KEEP_ORDER if n in _present(labels)]
    removed = np.zeros(labels.shape, bool)
    record = []
    for i, keep in enumerate(present):
        kept = _near(out == STRUCTURES[keep], voxel_mm, gap_mm)
        if kept is None:
            continue
        box, dist = kept
        for give in present[i + 1:]:
            if frozenset((keep, give)) in JUNCTIONS:
                continue
            cut = (dist <= gap_mm) & (out[box] == STRUCTURES[give])
            if cut.any():
                out[box][cut] = 0
                removed[box] |= cut
                record.append({"structures": [keep, give], "voxels": int(cut.sum()),
                               "position_index": (np.argwhere(cut).mean(axis=0) + [b.start for b in box]).tolist()})
    return out, record, removed


def genus(solid: np.ndarray, six: bool) -> tuple[int, int, int]:
    """(handles, components, cavities) of a voxel solid with adjacency 6 (complement 26) or 26.

    solid : (X, Y, Z) bool. From the Euler characteristic χ = components − handles + cavities.
    """
    fg = ndimage.generate_binary_structure(3, 1 if six else 3)
    bg = ndimage.generate_binary_structure(3, 3 if six else 1)
    components = ndimage.label(solid, structure=fg)[1]
    cavities = ndimage.label(np.pad(~solid, 1, constant_values=True), structure=bg)[1] - 1
    return components + cavities - euler_number(solid, connectivity=1 if six else 3), components, cavities


def correct_handles(solid: np.ndarray, depth: np.ndarray, six: bool = True, max_passes: int = 4) -> tuple[np.ndarray, list[dict]]:
    """Cut or fill each handle of a solid, whichever changes fewer voxels.

    solid : (X, Y, Z) bool, one component without cavities; depth : (X, Y, Z) float, larger =
    deeper inside (minus the signed distance); six : the solid's adjacency (see `genus`).
    Returns the solid without handles, or with those no cut or fill removed, and one
    {"kind": "cut" | "fill", "voxels", "index" (centroid, voxel units)} per change.

    The candidates are the connected pieces of the two topology-preserving growths
    (`ball_core`: cuts through each handle at its thinnest; `filled_solid`: a patch across each
    tunnel at its narrowest), each thickened by one voxel. Cheapest first, a candidate is kept
    when it removes a handle and leaves one component without cavities. χ is a sum over 2×2×2
    blocks, so a candidate that cannot raise it is dismissed in its own box; the others are
    checked on the whole solid.
    """
    connectivity = 1 if six else 3
    solid = solid.copy()
    handles, _, _ = genus(solid, six)
    changes: list[dict] = []
    for _ in range(max_passes):
        if handles == 0:
            break
        cuts = solid & ~ball_core(solid, depth, six)
        fills = filled_solid(solid, depth, six) & ~solid
        progress = False
        for kind, box, piece in sorted(_pieces(cuts, fills, solid), key=lambda c: c[2].sum()):
            before = solid[box]
            after = before & ~piece if kind == "cut" else before | piece
            if euler_number(after, connectivity) <= euler_number(before, connectivity):
                continue  # removes no handle: skip the whole-solid check
            trial = solid.copy()
            trial[box] = after
            h, components, cavities = genus(trial, six)
            if h < handles and components == 1 and cavities == 0:
                solid, handles, progress = trial, h, True
                changes.append({"kind": kind, "voxels": int(piece.sum()),
                                "index": (np.argwhere(piece).mean(axis=0) + [b.start for b in box]).tolist()})
                if handles == 0:
                    break
        if not progress:
            break
    return solid, changes


def _pieces(cuts: np.ndarray, fills: np.ndarray, solid: np.ndarray):
    """(kind, box, (box) bool) for each 26-connected piece of the cuts and of the fills, one voxel
    thicker on its own side (marching cubes may join voxels across a one-voxel cut diagonally),
    in its box two voxels wider."""
    full = np.ones((3, 3, 3), bool)
    for kind, mask, side in (("cut", cuts, solid), ("fill", fills, ~solid)):
        comp, _ = ndimage.label(mask, structure=full)
        for c, b in enumerate(ndimage.find_objects(comp), start=1):
            box = tuple(slice(max(s.start - 2, 0), min(s.stop + 2, n)) for s, n in zip(b, mask.shape))
            piece = ndimage.binary_dilation(comp[box] == c, structure=full) & side[box]
            yield kind, box, piece


def lv_gaps_to_myo(verts: np.ndarray, faces: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, list[dict]]:
    """A biventricular union surface's LV-labelled patches but its largest, relabelled myo.

    verts : (n, 3) mm, faces : (m, 3), labels : (n,) uint8 -> labels (n,) uint8 and, per patch
    relabelled, its vertex count and area (mm^2). Only where the labels are lv, myo and rv: there
    the LV's blood pool reaches the outer surface only where the stack cuts the base (the largest
    patch). Another LV patch is a gap in the myocardium's labels: on all 8 real M&Ms ED maps,
    44-523 mm^2, mostly the most apical slice labelled blood pool only (on one map also two
    patches at mid-ventricle). Left as LV, it made one label mean two anatomies from subject to
    subject: label-aware registration paired an apical patch with nothing, and the LV centroid
    landmark moved by up to 14 mm. Whole hearts (atria, vessels) are left as they are.
    """
    lv, myo = STRUCTURES["lv"], STRUCTURES["myo"]
    present = set(np.unique(labels).tolist())
    if lv not in present or not present <= {lv, myo, STRUCTURES["rv"]}:
        return labels, []
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    inside = (labels[edges] == lv).all(axis=1)
    n = len(verts)
    graph = coo_matrix((np.ones(inside.sum()), (edges[inside, 0], edges[inside, 1])), shape=(n, n))
    _, component = connected_components(graph, directed=False)
    vertex_area = vertex_areas(verts, faces)
    patches = np.unique(component[labels == lv])
    areas = {int(c): float(vertex_area[(component == c) & (labels == lv)].sum()) for c in patches}
    keep = max(areas, key=areas.get)
    out, relabelled = labels.copy(), []
    for c, area in areas.items():
        if c != keep:
            members = (component == c) & (labels == lv)
            out[members] = myo
            relabelled.append({"vertices": int(members.sum()), "area_mm2": round(area, 1)})
    return out, relabelled


def border_sections(chosen: np.ndarray, voxel_mm: np.ndarray,
                    skip_axis: int | None = None) -> dict[str, dict[str, float]]:
    """{structure: {face: mm^2}}: how much of each chamber (CHAMBERS) lies on each face of the label map's box.

    chosen : (X, Y, Z) uint8 canonical ids, voxel_mm : (3,). Faces are named by voxel axis and end ("axis 2
    first", "axis 0 last"); skip_axis: an axis whose ends are not looked at (a thick-slice stack's slice axis,
    whose ends cut the shape by design)."""
    out: dict[str, dict[str, float]] = {}
    for axis in range(3):
        if axis == skip_axis:
            continue
        pixel_mm2 = float(np.prod(np.delete(voxel_mm, axis)))
        for end, index in (("first", 0), ("last", chosen.shape[axis] - 1)):
            face = np.take(chosen, index, axis=axis)
            for name in CHAMBERS:
                count = int((face == STRUCTURES[name]).sum())
                if count:
                    out.setdefault(name, {})[f"axis {axis} {end}"] = round(count * pixel_mm2, 1)
    return out


def check_border(chosen: np.ndarray, voxel_mm: np.ndarray, skip_axis: int | None, limit_mm2: float, name: str) -> None:
    """MeshError where the label map's border cuts a chamber over more than limit_mm2 (border_sections): the
    surface would close flat on the border, a heart with a part missing that every later stage would accept."""
    cut = {s: faces for s, faces in border_sections(chosen, voxel_mm, skip_axis).items()
           if max(faces.values()) > limit_mm2}
    if cut:
        raise MeshError(f"{name}: the label map's border cuts the heart: {cut} (mm^2 of each structure on each face "
                        f"of the voxel box; limit {limit_mm2:g}): its field of view leaves a part out, and the surface "
                        f"would close flat there. Use a map that holds the whole heart, or set [meshing] "
                        f"max_border_mm2 to accept it")


def repair_summary(record: dict) -> str:
    """Every step the repair took, for a failure's message (a failed item writes no sidecar to read it in)."""
    labels = [f"{s} {c['holes_filled']} hole vox filled, {c['islands_dropped']} islands "
              f"({c['island_voxels']} vox) dropped" for s, c in record.get("labels", {}).items()]
    walls = [f"{'-'.join(w['structures'])} {w['voxels']} vox" for w in record.get("walls_filled", [])]
    contacts = [f"{'-'.join(c['structures'])} {c['voxels']} vox" for c in record.get("contacts_cut", [])]
    handles = [f"{h['kind']} {h['voxels']} vox at {h['position_mm']} ({'/'.join(h['structures'])})"
               for h in record.get("handles", [])]
    return (f"Euler characteristic before {record.get('euler_before', '?')}; labels cleaned: {labels or 'none'}; "
            f"walls filled: {walls or 'none'}; contacts cut: {contacts or 'none'}; handles: {handles or 'none'}")
