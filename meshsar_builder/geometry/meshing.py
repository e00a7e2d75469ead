"""Label maps to closed surface meshes: signed distance, isotropic resampling, marching cubes.

DESIGN section 6. The signed distance of the union mask (EDT on both sides, in
mm) is resampled linearly to isotropic spacing and smoothed lightly before
marching cubes: the distance to voxel centres is jagged, and thick ACDC slices
would stair-step without the resampling.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree
from skimage import measure
from skimage.graph import MCP_Geometric
from skimage.morphology import ball

from meshsar_builder.geometry.structures import STRUCTURES
from meshsar_builder.pipeline.errors import InputError, MeshError

# Each great vessel and the chamber(s) whose valve it leaves from.
VALVE_CHAMBERS: dict[str, tuple[str, ...]] = {"aorta": ("lv",), "pa": ("rv",)}
# Step between the slabs of equal distance from the valve whose centroids trace the centreline.
_SLAB_MM = 2.0
# The cut's normal: the centreline's direction over this arclength either side of the cut.
_TANGENT_MM = 4.0


@dataclass(frozen=True)
class MeshingParams:
    spacing_mm: float = 1.0  # isotropic resampling step of the signed distance
    sigma_mm: float = 1.0  # Gaussian smoothing of the resampled signed distance
    max_closing_voxels: int = 3  # largest closing radius tried to remove handles
    # Great vessels cut at this length (mm) from their valve along their centreline, e.g.
    # {aorta = 30, pa = 25}: label maps' vessel lengths depend on the field of view and the annotator.
    vessel_length_mm: dict[str, float] = field(default_factory=dict)

    def __post_init__(self):
        if not self.spacing_mm > 0:
            raise ValueError(f"spacing_mm: must be > 0, got {self.spacing_mm}")
        if not self.sigma_mm >= 0:
            raise ValueError(f"sigma_mm: must be >= 0, got {self.sigma_mm}")
        if not 0 <= self.max_closing_voxels <= 10:
            raise ValueError(f"max_closing_voxels: must be in 0..10, got {self.max_closing_voxels}")
        unknown = sorted(set(self.vessel_length_mm) - set(VALVE_CHAMBERS))
        if unknown:
            raise ValueError(f"vessel_length_mm: unknown vessel {unknown[0]!r}; vessels: {sorted(VALVE_CHAMBERS)}")
        for vessel, length in self.vessel_length_mm.items():
            if not 0 < length < 1000:
                raise ValueError(f"vessel_length_mm: {vessel} must be in (0, 1000) mm, got {length}")


class Surface(NamedTuple):
    verts: np.ndarray  # (n, 3) float64, RAS mm
    faces: np.ndarray  # (m, 3) int64, outward-oriented
    labels: np.ndarray  # (n,) uint8, canonical structure id of the nearest labelled voxel
    closing_voxels: int  # closing radius that made it genus 0 (0: none needed)


def signed_distance(mask: np.ndarray, voxel_mm: np.ndarray) -> np.ndarray:
    """Signed distance to the mask boundary, mm: negative inside, zero halfway between voxel centres.

    mask : (X, Y, Z) bool, voxel_mm : (3,) float -> (X, Y, Z) float32
    """
    outside = ndimage.distance_transform_edt(~mask, sampling=voxel_mm)
    inside = ndimage.distance_transform_edt(mask, sampling=voxel_mm)
    return (outside - inside).astype(np.float32)


def mask_surface(mask: np.ndarray, affine: np.ndarray, params: MeshingParams) -> tuple[np.ndarray, np.ndarray]:
    """Largest connected surface of a mask, in world mm.

    mask : (X, Y, Z) bool, affine : (4, 4) voxel -> RAS mm
    Returns verts (n, 3) float64, faces (m, 3) int64 with outward normals.
    """
    voxel_mm = np.linalg.norm(affine[:3, :3], axis=0)
    step = params.spacing_mm / voxel_mm  # new-grid step in voxel units, per axis
    # Crop to the mask with a margin wide enough for the smoothing kernel and the zero level.
    margin_mm = 3 * params.sigma_mm + 2 * params.spacing_mm + 2 * voxel_mm.max()
    pad = np.ceil(margin_mm / voxel_mm).astype(int)
    nz = np.argwhere(mask)
    lo = nz.min(axis=0) - pad
    hi = nz.max(axis=0) + pad + 1
    padded = np.zeros(hi - lo, dtype=bool)
    src_lo = np.maximum(lo, 0)
    src_hi = np.minimum(hi, mask.shape)
    padded[tuple(slice(a - l, b - l) for a, b, l in zip(src_lo, src_hi, lo))] = mask[
        tuple(slice(a, b) for a, b in zip(src_lo, src_hi))
    ]
    sdf = signed_distance(padded, voxel_mm)
    axes = [np.arange(0, n - 1 + 1e-9, s) for n, s in zip(padded.shape, step)]
    coords = np.meshgrid(*axes, indexing="ij")
    iso = ndimage.map_coordinates(sdf, coords, order=1, mode="nearest").astype(np.float32)
    del coords
    if params.sigma_mm > 0:
        iso = ndimage.gaussian_filter(iso, params.sigma_mm / params.spacing_mm, mode="nearest")
    if not (iso.min() < 0 < iso.max()):
        raise MeshError("mask vanished after resampling and smoothing (structure thinner than the smoothing?)")
    verts, faces, _, _ = measure.marching_cubes(iso, level=0.0, spacing=(params.spacing_mm,) * 3)
    vox = lo + verts / voxel_mm  # new-grid mm -> voxel index of the original volume
    world = vox @ affine[:3, :3].T + affine[:3, 3]
    mesh = trimesh.Trimesh(world, faces, process=True)
    parts = mesh.split(only_watertight=False)
    mesh = max(parts, key=lambda m: abs(m.volume)) if len(parts) > 1 else mesh
    if mesh.volume < 0:
        mesh.invert()
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def is_closed_genus0(verts: np.ndarray, faces: np.ndarray) -> tuple[bool, int, bool]:
    """(ok, euler characteristic, watertight) of a surface. verts : (n, 3), faces : (m, 3)."""
    mesh = trimesh.Trimesh(verts, faces, process=False)
    euler = int(mesh.euler_number)
    watertight = bool(mesh.is_watertight)
    return watertight and euler == 2, euler, watertight


def labels_to_surface(
    labels: np.ndarray, affine: np.ndarray, structures: list[str], params: MeshingParams, name: str = "label map"
) -> Surface:
    """Mesh the union of `structures` of a canonical label map; close handles if needed.

    labels : (X, Y, Z) uint8 canonical ids, affine : (4, 4). Raises InputError when
    none of the structures is present, MeshError when no closed genus-0 surface results.
    """
    if params.vessel_length_mm:
        labels = trim_vessels(labels, affine, params.vessel_length_mm, name)
    ids = [STRUCTURES[s] for s in structures]
    mask = np.isin(labels, ids)
    if not mask.any():
        present = sorted(k for k, v in STRUCTURES.items() if (labels == v).any())
        raise InputError(f"{name}: none of the structures {structures} present (found: {present})")
    euler = watertight = None
    for radius in range(params.max_closing_voxels + 1):
        closed = mask if radius == 0 else ndimage.binary_closing(np.pad(mask, radius), ball(radius))[
            (slice(radius, -radius),) * 3
        ]
        closed = ndimage.binary_fill_holes(closed)
        verts, faces = mask_surface(closed, affine, params)
        ok, euler, watertight = is_closed_genus0(verts, faces)
        if ok:
            return Surface(verts, faces, nearest_labels(verts, labels, mask, affine), radius)
    raise MeshError(
        f"{name}: surface is not closed genus 0 (euler={euler}, watertight={watertight}) "
        f"after morphological closing up to radius {params.max_closing_voxels} voxels"
    )


def trim_vessels(labels: np.ndarray, affine: np.ndarray, lengths: dict[str, float], name: str = "label map") -> np.ndarray:
    """Cut each great vessel by a plane `lengths[vessel]` mm from its valve, along its centreline.

    labels : (X, Y, Z) uint8 canonical ids, affine : (4, 4) voxel -> RAS mm,
    lengths : {"aorta" | "pa": mm}. Returns a copy with the cut-off parts set to 0.
    The valve is the vessel's contact with its chamber's blood pool (VALVE_CHAMBERS). The
    centreline is traced by the centroids of slabs of equal geodesic distance from the valve
    inside the vessel (26-connected, mm), starting at the valve's centroid; the cut is where its
    arclength reaches the length, by the plane through that point normal to the centreline there.
    What lies beyond the plane, and any part of the vessel not connected to the valve, is
    removed: the vessel ends in a flat cap and keeps no downstream contact with other structures.
    A vessel shorter than its length loses only its unconnected parts; a map without the vessel
    is left as is.
    MeshError when a vessel touches no chamber of its valve.
    """
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    out = labels.copy()
    for vessel, length in sorted(lengths.items()):
        mask = labels == STRUCTURES[vessel]
        if not mask.any():
            continue
        chamber = np.isin(labels, [STRUCTURES[c] for c in VALVE_CHAMBERS[vessel]])
        valve = mask & ndimage.binary_dilation(chamber)
        if not valve.any():
            raise MeshError(f"{name}: {vessel} touches no {'/'.join(VALVE_CHAMBERS[vessel])}, so it has no valve to measure from")
        # Work in the vessel's bounding box: geodesic distance (mm) from the valve inside the vessel.
        box = ndimage.find_objects(mask.astype(np.uint8))[0]
        sub, valve_sub = mask[box], valve[box]
        offset = np.array([s.start for s in box])
        distance, _ = MCP_Geometric(np.where(sub, 1.0, np.inf), sampling=tuple(spacing)).find_costs(np.argwhere(valve_sub))
        # Parts of the vessel not connected to the valve (infinite distance) are dropped below.
        inside = np.argwhere(sub & np.isfinite(distance))
        d = distance[tuple(inside.T)]
        world = (inside + offset) @ affine[:3, :3].T + affine[:3, 3]
        # Centreline: the valve centroid, then slab centroids every _SLAB_MM of distance.
        levels = np.arange(_SLAB_MM, d.max() + _SLAB_MM, _SLAB_MM)
        which = np.clip(np.round(d / _SLAB_MM).astype(int), 0, len(levels))
        sums = np.zeros((len(levels) + 1, 3))
        np.add.at(sums, which, world)
        counts = np.bincount(which, minlength=len(levels) + 1)
        centreline = np.vstack([world[valve_sub[tuple(inside.T)]].mean(axis=0), (sums[1:] / np.maximum(counts[1:, None], 1))[counts[1:] > 0]])
        level = np.concatenate([[0.0], levels[counts[1:] > 0]])
        arclength = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centreline, axis=0), axis=1))])
        if arclength[-1] < length + _TANGENT_MM:
            out[box][sub & ~np.isfinite(distance)] = 0
            continue  # shorter than the cut length
        point = np.array([np.interp(length, arclength, centreline[:, k]) for k in range(3)])
        ahead, behind = (np.array([np.interp(s, arclength, centreline[:, k]) for k in range(3)])
                         for s in (length + _TANGENT_MM, max(length - _TANGENT_MM, 0.0)))
        normal = (ahead - behind) / np.linalg.norm(ahead - behind)
        # Beyond the plane, and past the first half of the length (a vessel curving back near
        # its root keeps that part): cut. Then keep only what still connects to the valve.
        cut = ((world - point) @ normal > 0) & (d > 0.5 * np.interp(length, arclength, level))
        kept = np.zeros_like(sub)
        kept[tuple(inside[~cut].T)] = True
        components, _ = ndimage.label(kept, structure=np.ones((3, 3, 3)))
        attached = np.unique(components[valve_sub & kept])
        kept &= np.isin(components, attached[attached > 0])
        out[box][sub & ~kept] = 0
    return out


def nearest_labels(verts: np.ndarray, labels: np.ndarray, mask: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """Label of the nearest boundary voxel of `mask` for each vertex.

    verts : (n, 3) RAS mm, labels : (X, Y, Z) uint8, mask : (X, Y, Z) bool -> (n,) uint8
    """
    boundary = mask & ~ndimage.binary_erosion(mask)
    idx = np.argwhere(boundary)
    centres = idx @ affine[:3, :3].T + affine[:3, 3]
    _, nearest = cKDTree(centres).query(verts)
    return labels[tuple(idx[nearest].T)].astype(np.uint8)


def long_axis_landmarks(labels: np.ndarray, affine: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, float]:
    """Apex and base-plane position of the LV of a canonical label map, for motion over a cycle.

    labels : (X, Y, Z) uint8 canonical ids, affine : (4, 4) voxel -> RAS mm, axis : (3,) the long
    axis toward the apex (for a short-axis stack, its slice normal).
    Returns apex (3,) RAS mm, the mean of the myocardial voxels within 1 mm (along the axis) of
    the most apical one, and base (float) mm along the axis, the most basal LV voxel (blood or
    wall). Voxel centres: both are quantised to the voxel size along the axis.
    """
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    myo = np.argwhere(labels == STRUCTURES["myo"]) @ affine[:3, :3].T + affine[:3, 3]
    lv = np.argwhere(np.isin(labels, (STRUCTURES["myo"], STRUCTURES["lv"]))) @ affine[:3, :3].T + affine[:3, 3]
    if not len(myo):
        raise InputError("long-axis landmarks: no LV myocardium in the label map")
    depth = myo @ axis
    return myo[depth >= depth.max() - 1.0].mean(axis=0), float((lv @ axis).min())


def transfer_labels(src_verts: np.ndarray, src_labels: np.ndarray, dst_verts: np.ndarray) -> np.ndarray:
    """Label of the nearest source vertex for each destination vertex.

    src_verts : (n, 3), src_labels : (n,) uint8, dst_verts : (k, 3) -> (k,) uint8
    """
    _, nearest = cKDTree(src_verts).query(dst_verts)
    return np.asarray(src_labels, dtype=np.uint8)[nearest]


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def closest_on_triangles(points: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest point of each triangle to each point, and the squared distance.

    points : (..., 3), tri : (..., 3, 3) corners, broadcast together -> (..., 3), (...,).
    The projection on the plane when it falls inside the triangle, else the nearest of the
    closest points on the three edges (degenerate triangles fall through to the edges).
    """
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    ab, ac, ap = b - a, c - a, points - a
    d00, d01, d11 = _dot(ab, ab), _dot(ab, ac), _dot(ac, ac)
    d20, d21 = _dot(ap, ab), _dot(ap, ac)
    den = d00 * d11 - d01 * d01
    safe = np.where(den > 0, den, 1.0)
    s, t = (d11 * d20 - d01 * d21) / safe, (d00 * d21 - d01 * d20) / safe
    inside = (den > 0) & (s >= 0) & (t >= 0) & (s + t <= 1)
    best = a + s[..., None] * ab + t[..., None] * ac
    best_d2 = np.where(inside, _dot(points - best, points - best), np.inf)
    for start, end in ((a, b), (b, c), (c, a)):
        edge = end - start
        length2 = _dot(edge, edge)
        along = np.clip(_dot(points - start, edge) / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
        on_edge = start + along[..., None] * edge
        d2 = _dot(points - on_edge, points - on_edge)
        closer = d2 < best_d2
        best = np.where(closer[..., None], on_edge, best)
        best_d2 = np.where(closer, d2, best_d2)
    return best, best_d2


def point_to_surface(points: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact distance from each point to a triangle mesh and the nearest face.

    points (N, 3), verts (n, 3), faces (m, 3) -> distances (N,), face ids (N,).
    Candidates are the faces with the k nearest centroids; a point's answer is final
    once it is no farther than (k-th centroid distance - largest centroid-to-vertex
    radius), below which no other face can reach; k doubles for the rest.
    """
    tri = np.asarray(verts, dtype=np.float64)[np.asarray(faces)]
    centroids = tri.mean(1)
    radius = np.linalg.norm(tri - centroids[:, None], axis=2).max()
    tree = cKDTree(centroids)
    points = np.asarray(points, dtype=np.float64)
    best = np.full(len(points), np.inf)
    best_face = np.zeros(len(points), dtype=np.int64)
    todo = np.arange(len(points))
    k = min(16, len(faces))
    while len(todo):
        reach, cand = tree.query(points[todo], k=k)
        reach, cand = reach.reshape(len(todo), -1), cand.reshape(len(todo), -1)
        dist = np.sqrt(closest_on_triangles(points[todo][:, None, :], tri[cand])[1])  # (t, k)
        pick = dist.argmin(1)
        best[todo] = dist[np.arange(len(todo)), pick]
        best_face[todo] = cand[np.arange(len(todo)), pick]
        if k == len(faces):
            break
        todo = todo[best[todo] > reach[:, -1] - radius]
        k = min(2 * k, len(faces))
    return best, best_face
