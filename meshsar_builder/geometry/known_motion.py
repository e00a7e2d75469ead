"""Known cardiac motion: an ED mesh moved by a smooth time-varying map, to judge frame tracking (issue 27.3).

The map combines radial contraction toward the long axis, descent of the base toward a still
apex, and twist about the long axis (apex and base turning opposite ways), each peaking at
end-systole. Every frame is the moved mesh re-tessellated (as a real frame is meshed on its
own) with labels carried over. A tracker fits the ED mesh to every frame; its error is each
fitted vertex's distance from where the map sends it, with the twist (circumferential)
component apart: on a surface of revolution only the labels' junctions can show it.
tests/test_tracking.py and `meshsar bench tracking` use it.
"""

from __future__ import annotations

import numpy as np

from meshsar_builder.geometry.meshing import transfer_labels
from meshsar_builder.geometry.remesh import RemeshParams, remesh
from meshsar_builder.geometry.structures import STRUCTURES as S

CONTRACTION = 0.08  # radial, at end-systole
DESCENT_MM = 12.0  # of the base toward the apex
TWIST_DEG = 10.0  # apex against base (+-5 deg each)


def long_axis(verts: np.ndarray, labels: np.ndarray, faces: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(centre, unit axis pointing to the apex, apex and base positions along it) of a ventricle-
    like shape. With faces, where the LV shows on the surface as a basal disc (short-axis data:
    its area-weighted normals agree, coherence >= 0.5), the axis is the disc's inward normal:
    the anatomical long axis (within 1-5 deg of the slice normal on the real M&Ms maps), where
    the principal axis of a biventricular union runs 46-84 deg off it, toward the RV. Otherwise
    the principal axis, turned toward the end farther from the basal (non-lv/myo) labels.

    verts : (n, 3) float mm, labels : (n,) int, faces : (m, 3) int or None."""
    centre = verts.mean(axis=0)
    axis = np.linalg.eigh(np.cov((verts - centre).T))[1][:, 2]
    basal = ~np.isin(labels, (S["lv"], S["myo"]))
    if basal.any() and ((verts[basal] - centre) @ axis).mean() > 0:
        axis = -axis
    if faces is not None:
        disc = (labels[faces] == S["lv"]).all(axis=1)
        corners = verts[faces[disc]]
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # 2 x area
        total = normals.sum(axis=0)
        if disc.any() and np.linalg.norm(total) >= 0.5 * np.linalg.norm(normals, axis=1).sum():
            axis = -total / np.linalg.norm(total)
    along = (verts - centre) @ axis
    return centre, axis, float(along.max()), float(along.min())


def cycle_map(verts: np.ndarray, frame: tuple, t: float) -> np.ndarray:
    """Where the known motion sends verts (n, 3) at cycle time t in [0, 1); `frame` = long_axis(...)."""
    centre, axis, apex, base = frame
    c = np.sin(np.pi * t) ** 2  # 0 at ED, 1 at end-systole
    p = verts - centre
    along = p @ axis
    radial = p - along[:, None] * axis
    s = np.clip((apex - along) / (apex - base), 0.0, 1.0)  # 0 at the apex, 1 at the base
    radial = radial * (1 - CONTRACTION * c)
    angle = np.radians(TWIST_DEG) * c * (0.5 - s)
    radial = np.cos(angle)[:, None] * radial + np.sin(angle)[:, None] * np.cross(axis, radial)
    return centre + (along + DESCENT_MM * c * s)[:, None] * axis + radial


def cine(verts: np.ndarray, faces: np.ndarray, labels: np.ndarray, n_frames: int, edge: RemeshParams):
    """The known-motion frames of an ED mesh, each remeshed at `edge` with labels carried over:
    (frames [(verts, faces, labels)] with the ED mesh first, the truth per frame [(n, 3)], long_axis)."""
    frame = long_axis(verts, labels, faces)
    frames, truth = [(verts, faces, labels)], [verts]
    for t in np.arange(1, n_frames) / n_frames:
        moved = cycle_map(verts, frame, t)
        fv, ff = remesh(moved, faces, edge)
        frames.append((fv, ff, transfer_labels(moved, labels, fv)))
        truth.append(moved)
    return frames, truth, frame


def errors(fits: list, truth: list, frame: tuple) -> np.ndarray:
    """(frames - 1, 3): per tracked frame the mean vertex error, its twist (circumferential) part and the rest (mm)."""
    centre, axis = frame[:2]
    rows = []
    for fit, true in zip(fits[1:], truth[1:]):
        d = fit - true
        radial = (true - centre) - ((true - centre) @ axis)[:, None] * axis
        circ = np.cross(axis, radial)
        circ /= np.maximum(np.linalg.norm(circ, axis=1, keepdims=True), 1e-9)
        twist = np.abs(np.sum(d * circ, axis=1))
        total = np.linalg.norm(d, axis=1)
        rows.append((total.mean(), twist.mean(), np.sqrt(np.maximum(total**2 - twist**2, 0)).mean()))
    return np.array(rows)
