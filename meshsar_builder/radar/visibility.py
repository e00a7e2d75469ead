"""Facet geometry and Embree visibility of a mesh's facets from the aperture's probe points (DESIGN section 4)."""

from __future__ import annotations

import itertools

import numpy as np
import trimesh

from meshsar_builder.pipeline.errors import MeshsarError
from meshsar_builder.radar.imaging import invalid
from meshsar_builder.radar.params import FACET_MODELS, RAY_OFFSET_MM

# ---------------------------------------------------------------- facets and visibility


def facet_geometry(verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroids (F, 3), outward unit normals (F, 3) and areas (F,) of a mesh.

    verts : (n, 3) float mm; faces : (F, 3) int, counter-clockwise seen from outside.
    Degenerate facets get a zero normal and area, so they never contribute.
    """
    return triangle_geometry(np.asarray(verts, dtype=np.float64)[np.asarray(faces)])


def triangle_geometry(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroids (F, 3), unit normals (F, 3) and areas (F,) of triangles tri (F, 3, 3), corners counter-clockwise."""
    tri = np.asarray(tri, dtype=np.float64)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    double_area = np.linalg.norm(cross, axis=1)
    normals = np.divide(cross, double_area[:, None], out=np.zeros_like(cross), where=double_area[:, None] > 0)
    return tri.mean(axis=1), normals, double_area / 2


def scatterer_points(verts: np.ndarray, faces: np.ndarray, mode: str, rng: np.random.Generator | None) -> np.ndarray:
    """(F, 3) float: each facet's point scatterer, a seeded uniform point in it for mode "random", else its centroid."""
    tri = np.asarray(verts, dtype=np.float64)[np.asarray(faces)]
    if mode not in FACET_MODELS:
        raise invalid("facet", f"must be one of {', '.join(FACET_MODELS)}", mode)
    if mode != "random":
        return tri.mean(axis=1)
    r = rng.random((len(tri), 2))
    # Folding the unit square's upper triangle onto the lower keeps the density uniform.
    outside = r.sum(axis=1) > 1
    r[outside] = 1 - r[outside]
    return tri[:, 0] + r[:, :1] * (tri[:, 1] - tri[:, 0]) + r[:, 1:] * (tri[:, 2] - tri[:, 0])


def embree_intersector(verts: np.ndarray, faces: np.ndarray):
    """trimesh's Embree ray intersector for a mesh; MeshsarError if embreex is missing.

    Never trimesh's pure-Python backend: 10^4 times slower, and it exhausts memory
    at 10^5 rays.
    """
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector
    except ImportError as exc:
        raise MeshsarError(
            "radar visibility needs the Embree ray backend: install embreex "
            f"(pip install embreex); importing it failed: {exc}"
        ) from exc
    mesh = trimesh.Trimesh(np.asarray(verts, dtype=np.float64), np.asarray(faces), process=False)
    return RayMeshIntersector(mesh)


class EmbreeOccluder:
    """Embree's any-hit (occlusion) query on a mesh: `intersects_any` as trimesh's intersector has it, without the
    closest-hit search that trimesh runs for it (28 % less time on a heart's visibility rays, the same answers).

    verts : (n, 3) float mm, shifted to their bounding box's corner before Embree's float32
    (as trimesh does), so that precision follows the mesh's size, not its position.
    """

    def __init__(self, verts: np.ndarray, faces: np.ndarray):
        try:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh
        except ImportError as exc:
            raise MeshsarError(f"radar visibility needs embreex (pip install embreex); importing it failed: {exc}") \
                from exc
        verts = np.asarray(verts, dtype=np.float64)
        self.origin = verts.min(axis=0)
        self.scene = rtcore_scene.EmbreeScene()
        TriangleMesh(scene=self.scene, vertices=(verts - self.origin).astype(np.float32),
                     indices=np.asarray(faces, dtype=np.int32))

    def intersects_any(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(R,) bool: whether each ray (origins, unit directions (R, 3)) hits the mesh."""
        shifted = (np.asarray(origins, dtype=np.float64) - self.origin).astype(np.float32)
        return self.scene.run(shifted, np.asarray(directions, dtype=np.float32), query="OCCLUDED") != -1


def visibility(verts: np.ndarray, faces: np.ndarray, probes: np.ndarray, intersector=None) -> tuple[np.ndarray, int]:
    """Per facet, the fraction of probes it faces and sees without occlusion.

    verts : (n, 3) float mm; faces : (F, 3) int; probes : (P, 3) float mm.
    intersector : anything with trimesh's intersects_any (embree_intersector(verts, faces),
    or an EmbreeOccluder, the default), to reuse across views. Returns (F,) float in [0, 1]
    and the number of rays cast. A ray starts at the
    centroid lifted by RAY_OFFSET_MM along the normal and counts as blocked if it
    hits any facet (probes lie outside the mesh, so nothing lies beyond them).
    """
    fractions, rays = visibilities(verts, faces, [probes], intersector)
    return fractions[0], rays


def visibilities(verts: np.ndarray, faces: np.ndarray, probe_sets, intersector=None) -> tuple[list[np.ndarray], int]:
    """visibility for several probe sets (P_i, 3) (one per view) in one batch of rays.

    Returns a list of (F,) float, one per set, and the number of rays cast in all: one
    Embree call and one pass of the facets' geometry for every view, as the trainer's masks
    need them.
    """
    if intersector is None:
        intersector = EmbreeOccluder(verts, faces)
    probe_sets = [np.asarray(probes, dtype=np.float64).reshape(-1, 3) for probes in probe_sets]
    centres, normals, _ = facet_geometry(verts, faces)
    to_probe = np.concatenate(probe_sets)[None, :, :] - centres[:, None, :]
    facing = np.einsum("fc,fpc->fp", normals, to_probe) > 0
    facet, probe = np.nonzero(facing)
    directions = to_probe[facet, probe]
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    origins = centres[facet] + RAY_OFFSET_MM * normals[facet]
    blocked = intersector.intersects_any(origins, directions)
    seen = np.zeros(facing.shape)
    seen[facet[~blocked], probe[~blocked]] = 1.0
    bounds = np.cumsum([0] + [len(probes) for probes in probe_sets])
    return [seen[:, a:b].mean(axis=1) for a, b in itertools.pairwise(bounds)], len(facet)
