"""Points of one surface mapped onto another: closest faces and barycentric weights."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import trimesh

from meshsar_builder.geometry.closest import closest_points


def closest_barycentric(points: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each point's closest surface point, as its face and barycentric weights there.

    points : (N, 3), verts : (n, 3), faces : (m, 3) -> face ids (N,), weights (N, 3)
    (in [0, 1], summing to 1; weights @ verts[faces[face]] is the closest point).
    """
    verts, faces = np.asarray(verts, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    _, face, closest = closest_points(points, verts, faces)
    tri = verts[faces[face]]  # (N, 3, 3)
    # The closest point lies in its triangle: only rounding leaves [0, 1] (degenerate triangles).
    weights = np.clip(np.nan_to_num(trimesh.triangles.points_to_barycentric(tri, closest), nan=1 / 3), 0.0, 1.0)
    return face, weights / np.maximum(weights.sum(axis=1, keepdims=True), 1e-300)


def interpolation_matrix(points: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """(N, n) sparse: row i holds the barycentric weights of point i's closest point on the
    surface verts (n, 3), faces (m, 3), so that matrix @ f interpolates a per-vertex field f (n, ...)."""
    face, weights = closest_barycentric(points, verts, faces)
    rows = np.repeat(np.arange(len(face)), 3)
    return sp.csr_matrix((weights.ravel(), (rows, np.asarray(faces)[face].ravel())), shape=(len(face), len(verts)))
