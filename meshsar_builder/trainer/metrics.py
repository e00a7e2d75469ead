"""Mesh comparison metrics (DESIGN section 11) for any two triangle meshes given as numpy arrays.

Both meshes in mm in one frame. Dice and Jaccard from voxelisation (ray parity
along z, Embree), ASSD / HD / HD95 from area-weighted surface samples and exact
point-to-triangle distances, ANE and ANLD per predicted vertex, SI from
pymeshlab's per-face self-intersection test.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from meshsar_builder.geometry.intersections import self_intersecting_faces
from meshsar_builder.geometry.closest import point_to_surface
from meshsar_builder.geometry.surface_map import closest_barycentric
from meshsar_builder.radar.visibility import embree_intersector
from meshsar_builder.trainer.losses import mesh_edges, sample_surface, uniform_laplacian

# Paper column order; *_norm are divided by the ground truth's bounding-box diagonal.
COLUMNS = ("dice", "jaccard", "assd_mm", "assd_norm", "hd_mm", "hd_norm", "hd95_mm", "hd95_norm",
           "ane_rad", "anld", "si_pct")


def voxelise(verts: np.ndarray, faces: np.ndarray, lo: np.ndarray, shape: tuple[int, int, int],
             voxel_mm: float) -> np.ndarray:
    """Inside mask (X, Y, Z) bool of a closed mesh on the grid with voxel centres lo + (i + 0.5) voxel_mm.

    Ray parity: one ray per (x, y) column along +z from below the grid, every hit found
    by Embree; a voxel centre is inside when an odd number of hits lie below it.
    """
    nx, ny, nz = shape
    xs, ys = lo[0] + (np.arange(nx) + 0.5) * voxel_mm, lo[1] + (np.arange(ny) + 0.5) * voxel_mm
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    # A fixed sub-micron offset keeps columns off mesh edges and vertices laid on the voxel lattice.
    origins = np.stack([gx.ravel() + 1.3e-5, gy.ravel() + 2.9e-5, np.full(gx.size, lo[2] - voxel_mm)], axis=1)
    directions = np.tile([0.0, 0.0, 1.0], (len(origins), 1))
    hits, ray, _ = embree_intersector(verts, faces).intersects_location(origins, directions, multiple_hits=True)
    first = lo[2] + 0.5 * voxel_mm
    # Hit at z toggles every voxel centre above it: index of the first such centre.
    start = np.clip(np.ceil((hits[:, 2] - first) / voxel_mm), 0, nz).astype(np.int64)
    toggles = np.zeros((len(origins), nz + 1), dtype=np.int64)
    np.add.at(toggles, (ray, start), 1)
    return (np.cumsum(toggles[:, :nz], axis=1) % 2 == 1).reshape(nx, ny, nz)


def inside(points: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N,) bool: which of points (N, 3) lie inside a closed mesh (verts (n, 3), faces (m, 3)), by the
    parity of the Embree hits of a ray from each point along a fixed oblique direction."""
    # Oblique, so rays from points on a lattice do not run along mesh edges.
    direction = np.array([0.2719, 0.3821, 0.8831])
    points = np.asarray(points, dtype=np.float64)
    _, ray, _ = embree_intersector(verts, faces).intersects_location(
        points, np.tile(direction / np.linalg.norm(direction), (len(points), 1)), multiple_hits=True)
    return np.bincount(ray, minlength=len(points)) % 2 == 1


def signed_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    """Volume enclosed by a closed mesh, mm^3: positive when its faces wind outward."""
    tri = verts[faces]
    return float(np.einsum("fc,fc->f", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6)


def occupancy_surface(occupancy: np.ndarray, lo: np.ndarray, voxel_mm: float,
                      level: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Closed outward mesh of {occupancy > level} by marching cubes: verts (n, 3) mm, faces (m, 3).

    occupancy (X, Y, Z) sampled at voxel centres lo + (i + 0.5) voxel_mm; padded with zeros so the
    surface closes at the grid's border.
    """
    padded = np.pad(occupancy.astype(np.float32), 1)
    verts, faces, _, _ = marching_cubes(padded, level, spacing=(voxel_mm,) * 3)
    verts = verts + lo + (0.5 - 1) * voxel_mm  # index 0 of the padded grid is one voxel before lo's centre
    faces = faces.astype(np.int64)
    return verts, faces if signed_volume(verts, faces) > 0 else faces[:, ::-1].copy()


def overlap(pred: tuple[np.ndarray, np.ndarray], gt: tuple[np.ndarray, np.ndarray], voxel_mm: float = 0.5) -> dict:
    """Dice and Jaccard of two closed meshes, each (verts (n, 3), faces (m, 3)), voxelised on one grid."""
    both = np.concatenate([pred[0], gt[0]])
    lo = both.min(0) - voxel_mm
    shape = tuple(int(s) for s in np.ceil((both.max(0) + voxel_mm - lo) / voxel_mm))
    a, b = voxelise(*pred, lo, shape, voxel_mm), voxelise(*gt, lo, shape, voxel_mm)
    inter, union, total = np.count_nonzero(a & b), np.count_nonzero(a | b), a.sum() + b.sum()
    return {"dice": float(2 * inter / total) if total else 1.0, "jaccard": float(inter / union) if union else 1.0}


def vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(n, 3) unit area-weighted vertex normals."""
    tri = verts[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length 2 * area: area weighting
    summed = np.zeros_like(verts)
    for corner in range(3):
        np.add.at(summed, faces[:, corner], cross)
    return summed / np.maximum(np.linalg.norm(summed, axis=1, keepdims=True), 1e-300)


def interpolated_normals(points: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals of a mesh at the closest surface point to each of points (N, 3),
    interpolated barycentrically from its vertex normals: smooth across edges, and exactly
    a vertex's normal at that vertex."""
    face, weights = closest_barycentric(points, verts, faces)  # (N,), (N, 3)
    normals = np.einsum("nk,nkc->nc", weights, vertex_normals(verts, faces)[faces[face]])
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)


def angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) angle in radians between the vectors a (N, 3) and b (N, 3); atan2 keeps it exact near 0."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("nc,nc->n", a, b))


def laplacian_coordinates(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(n, 3) uniform Laplacian coordinates x_i - mean of neighbours."""
    edges = torch.from_numpy(mesh_edges(faces))
    return uniform_laplacian(torch.from_numpy(np.asarray(verts, dtype=np.float64)), edges).numpy()


def mesh_metrics(pred_verts: np.ndarray, pred_faces: np.ndarray, gt_verts: np.ndarray, gt_faces: np.ndarray,
                 voxel_mm: float = 0.5, samples: int = 20_000, seed: int = 0) -> dict:
    """Every metric of COLUMNS for a predicted mesh against a ground truth (DESIGN section 11).

    verts (n, 3) float mm, faces (m, 3) int, both closed meshes in one frame.
    ASSD: mean of the two directed mean distances of `samples` area-weighted surface
    points; HD: the larger directed maximum; HD95: the larger directed 95th percentile.
    ANE: mean angle (rad) between each predicted vertex normal and the ground-truth normal
    at its closest surface point, interpolated from the ground truth's vertex normals. ANLD: mean |L_pred(i) - L_gt(nearest gt vertex)|
    over predicted vertices / mean ground-truth edge length. SI: % of predicted faces
    intersecting a non-adjacent face.
    """
    pv, gv = np.ascontiguousarray(pred_verts, dtype=np.float64), np.ascontiguousarray(gt_verts, dtype=np.float64)
    pf, gf = np.ascontiguousarray(pred_faces, dtype=np.int64), np.ascontiguousarray(gt_faces, dtype=np.int64)
    generator = torch.Generator().manual_seed(seed)
    directed = []
    for (av, af), (bv, bf) in (((pv, pf), (gv, gf)), ((gv, gf), (pv, pf))):
        points = sample_surface(torch.from_numpy(av), torch.from_numpy(af), samples, generator).numpy()
        directed.append(point_to_surface(points, bv, bf)[0])
    diagonal = float(np.linalg.norm(gv.max(0) - gv.min(0)))
    assd = float(np.mean([d.mean() for d in directed]))
    hd = float(max(d.max() for d in directed))
    hd95 = float(max(np.percentile(d, 95) for d in directed))

    ane = float(angles(vertex_normals(pv, pf), interpolated_normals(pv, gv, gf)).mean())

    nearest_vertex = cKDTree(gv).query(pv)[1]
    gt_edges = mesh_edges(gf)
    mean_edge = np.linalg.norm(gv[gt_edges[:, 0]] - gv[gt_edges[:, 1]], axis=1).mean()
    lap_diff = laplacian_coordinates(pv, pf) - laplacian_coordinates(gv, gf)[nearest_vertex]
    anld = float(np.linalg.norm(lap_diff, axis=1).mean() / mean_edge)

    return {
        **overlap((pv, pf), (gv, gf), voxel_mm),
        "assd_mm": assd, "assd_norm": assd / diagonal, "hd_mm": hd, "hd_norm": hd / diagonal,
        "hd95_mm": hd95, "hd95_norm": hd95 / diagonal, "ane_rad": ane, "anld": anld,
        "si_pct": float(100 * self_intersecting_faces(pv, pf).mean()),
    }
