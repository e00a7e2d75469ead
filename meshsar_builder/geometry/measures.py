"""Measures of a triangle mesh that several geometry modules share."""

from __future__ import annotations

import numpy as np


def vertex_areas(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """verts : (n, 3) float, faces : (m, 3) int -> (n,) a third of the area of the faces around each vertex."""
    corners = verts[faces]
    face_areas = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    return np.bincount(faces.ravel(), np.repeat(face_areas / 3.0, 3), minlength=len(verts))
