"""The topological defects of real whole-heart label maps, put into a phantom's label map.

Real CT label maps (MM-WHS) are not genus 0: their voxel unions had 9-15 handles at about 1 mm.
They come from (label_repair has the repair for each):
- great vessels touching each other or lying across an atrium along a contact of several mm;
- joined chambers whose blood pools meet only through patches of an unlabelled wall (a valve
  plane labelled in parts);
- tunnels through single labels (a myocardium with a hole), detached islands, an LV label in
  several components.
`add_defects` makes each of them where real ones are, on a canonical label map, and says where.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from meshsar_builder.geometry.label_repair import genus
from meshsar_builder.geometry.structures import STRUCTURES

DEFECTS = ("vessel_contact", "vessel_on_atrium", "valve_patches", "tunnels", "islands")


def _dist(mask: np.ndarray, voxel_mm: np.ndarray) -> np.ndarray:
    return ndimage.distance_transform_edt(~mask, sampling=voxel_mm) if mask.any() else np.full(mask.shape, np.inf)


def _world(affine: np.ndarray, index: np.ndarray) -> np.ndarray:
    return np.asarray(index, float) @ affine[:3, :3].T + affine[:3, 3]


def _bridge(labels, voxel_mm, a: str, b: str, grow: str, rng, length_mm: float) -> np.ndarray:
    """A contact between a and b, about length_mm long, labelled `grow`: the background between
    them where they come closest (da + db within 4 mm of its least), around one random spot of
    that approach, away (10 mm) from the ventricles, where vessels leave from and already touch
    the atria."""
    da, db = _dist(labels == STRUCTURES[a], voxel_mm), _dist(labels == STRUCTURES[b], voxel_mm)
    roots = _dist(np.isin(labels, (STRUCTURES["lv"], STRUCTURES["rv"], STRUCTURES["myo"])), voxel_mm) > 10.0
    between = np.where(labels == 0, da + db, np.inf)
    least = np.where(roots, between, np.inf).min()
    if not np.isfinite(least):
        return np.zeros(labels.shape, bool)
    spots = np.argwhere(roots & (between <= least + voxel_mm.max()))
    centre = spots[rng.integers(len(spots))]
    near = np.zeros(labels.shape, bool)
    near[tuple(centre)] = True
    near = _dist(near, voxel_mm) <= length_mm / 2 + least / 2
    bridge = (between <= least + 4.0) & near
    # the piece that touches both
    pieces, _ = ndimage.label(bridge | (labels == STRUCTURES[a]) | (labels == STRUCTURES[b]), structure=np.ones((3, 3, 3)))
    touching = np.intersect1d(pieces[labels == STRUCTURES[a]], pieces[labels == STRUCTURES[b]])
    bridge &= np.isin(pieces, touching[touching > 0])
    labels[bridge] = STRUCTURES[grow]
    return bridge


def add_defects(labels: np.ndarray, affine: np.ndarray, rng: np.random.Generator,
                defects: tuple[str, ...] = DEFECTS, tunnels: int = 6) -> tuple[np.ndarray, list[dict]]:
    """A copy of a canonical whole-heart label map with real label maps' defects, and where.

    labels : (X, Y, Z) uint8 canonical ids (all seven structures), affine : (4, 4) voxel -> RAS mm,
    defects : which of DEFECTS to add, tunnels : how many through-tunnels under the surface.
    Returns the labels and one {"defect", "structures", "position_mm", "voxels"} per change.
    """
    labels = labels.copy()
    voxel_mm = np.linalg.norm(affine[:3, :3], axis=0)
    made = []

    def note(kind, structures, mask):
        if mask.any():
            made.append({"defect": kind, "structures": list(structures),
                         "position_mm": [round(float(c), 1) for c in _world(affine, np.argwhere(mask).mean(axis=0))],
                         "voxels": int(mask.sum())})

    if "vessel_contact" in defects:  # aorta and pulmonary artery touching along several mm
        note("vessel_contact", ("aorta", "pa"), _bridge(labels, voxel_mm, "aorta", "pa", "pa", rng, 12.0))
    if "vessel_on_atrium" in defects:  # the aorta lying across an atrium
        for atrium in ("la", "ra"):
            note("vessel_on_atrium", ("aorta", atrium), _bridge(labels, voxel_mm, "aorta", atrium, "aorta", rng, 10.0))
    if "valve_patches" in defects:
        # An unlabelled 3 mm wall between joined pools, open in three patches only.
        for atrium, ventricle in (("la", "lv"), ("ra", "rv")):
            wall = (labels == STRUCTURES[atrium]) & (_dist(labels == STRUCTURES[ventricle], voxel_mm) <= 3.0)
            spots = np.argwhere(wall)
            if not len(spots):
                continue
            keep = np.zeros(len(spots), bool)
            for centre in spots[rng.choice(len(spots), size=min(3, len(spots)), replace=False)]:
                keep |= np.linalg.norm((spots - centre) * voxel_mm, axis=1) <= 4.0
            cleared = np.zeros_like(wall)
            cleared[tuple(spots[~keep].T)] = True
            labels[cleared] = 0
            note("valve_patches", (atrium, ventricle), cleared)
    if "tunnels" in defects:
        made += _tunnels(labels, affine, voxel_mm, rng, tunnels)
    if "islands" in defects:
        union = labels > 0
        outside = _dist(union, voxel_mm)
        myo = labels == STRUCTURES["myo"]
        # a detached myocardium island 4 mm off the epicardium
        spots = np.argwhere((outside > 4.0) & (outside <= 5.0) & (_dist(myo, voxel_mm) <= 5.0))
        if len(spots):
            blob = _ball(labels.shape, spots[rng.integers(len(spots))], 2.5, voxel_mm)
            labels[blob & (labels == 0)] = STRUCTURES["myo"]
            note("island", ("myo",), blob)
        # two more LV components: one inside the wall, one on the epicardium
        deep = np.argwhere(myo & (_dist(~myo, voxel_mm) >= 3.0))
        surface = np.argwhere(myo & (_dist(~union, voxel_mm) <= 1.0) & (_dist(labels == STRUCTURES["lv"], voxel_mm) > 6.0))
        for spots, radius in ((deep, 1.5), (surface, 1.5)):
            if len(spots):
                blob = _ball(labels.shape, spots[rng.integers(len(spots))], radius, voxel_mm) & myo
                labels[blob] = STRUCTURES["lv"]
                note("lv_component", ("lv", "myo"), blob)
    return labels, made


def _ball(shape, centre, radius_mm: float, voxel_mm: np.ndarray) -> np.ndarray:
    grids = np.ogrid[tuple(slice(0, n) for n in shape)]
    return sum(((g - c) * v) ** 2 for g, c, v in zip(grids, centre, voxel_mm)) <= radius_mm**2


def _tunnels(labels, affine, voxel_mm, rng, count: int) -> list[dict]:
    """Straight tunnels (radius 1.5-2.5 mm) just under the union's surface, tangent to it, that
    enter and leave through it: each a hole through a label, each a handle of the union."""
    made = []
    union = labels > 0
    sdf = _dist(union, voxel_mm) - _dist(~union, voxel_mm)
    grad = np.stack(np.gradient(sdf, *voxel_mm))
    boundary = np.argwhere(union & (sdf >= -voxel_mm.max()))
    handles, parts, _ = genus(union, six=False)
    tries = 0
    while len(made) < count and tries < 20 * count:
        tries += 1
        p = boundary[rng.integers(len(boundary))]
        n = grad[(slice(None), *p)]
        if not np.linalg.norm(n):
            continue
        n = n / np.linalg.norm(n)
        t = np.cross(n, rng.normal(size=3))
        t /= np.linalg.norm(t)
        radius = rng.uniform(1.5, 2.5)
        centre = p * voxel_mm - n * (radius + 1.5)  # voxel-index frame scaled to mm
        lo = np.maximum(((centre - 25) / voxel_mm).astype(int), 0)
        hi = np.minimum(((centre + 25) / voxel_mm).astype(int) + 1, labels.shape)
        grid = np.stack(np.meshgrid(*[np.arange(a, b) * v for a, b, v in zip(lo, hi, voxel_mm)], indexing="ij"), -1)
        rel = grid - centre
        along = rel @ t
        off = np.linalg.norm(rel - along[..., None] * t, axis=-1)
        tube = (off <= radius) & (np.abs(along) <= 25)
        box = tuple(slice(a, b) for a, b in zip(lo, hi))
        carved = tube & union[box]
        trial = labels.copy()
        trial[box][carved] = 0
        new, components, _ = genus(trial > 0, six=False)
        if new == handles + 1 and components == parts:  # exactly one new handle, nothing cut off
            hit = labels[box][carved]
            names = [k for k, v in STRUCTURES.items() if v in set(hit.tolist())]
            labels[:] = trial
            union = labels > 0
            handles = new
            mask = np.zeros(labels.shape, bool)
            mask[box] = carved
            made.append({"defect": "tunnel", "structures": names,
                         "position_mm": [round(float(c), 1) for c in _world(affine, np.argwhere(mask).mean(axis=0))],
                         "voxels": int(carved.sum())})
    return made
