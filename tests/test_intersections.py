"""The self-intersection test against pymeshlab's (the independent reference) and analytic cases."""

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from meshsar_builder.geometry.intersections import pymeshlab_self_intersecting_faces as pymeshlab_faces
from meshsar_builder.geometry.intersections import self_intersecting_faces


def closed_shape(kind: int) -> trimesh.Trimesh:
    """Closed surfaces of other shapes than a heart's: a sphere, a torus (genus 1), a capsule and a
    subdivided box (flat sides: coplanar faces everywhere)."""
    return [
        lambda: trimesh.creation.icosphere(subdivisions=3, radius=30.0),
        lambda: trimesh.creation.torus(30.0, 10.0),
        lambda: trimesh.creation.capsule(height=40.0, radius=15.0),
        lambda: trimesh.creation.box(extents=(40.0, 30.0, 20.0)).subdivide().subdivide(),
    ][kind]()


@settings(max_examples=25, deadline=None)
@given(kind=st.integers(0, 3), amplitude=st.sampled_from([0.0, 0.1, 0.3, 0.6, 1.0, 2.0]), seed=st.integers(0, 2**31))
def test_agrees_with_pymeshlab_face_for_face_on_crumpled_surfaces(kind, amplitude, seed):
    """Random vertex noise, in edge lengths, folds fans over and pushes faces through each
    other (no exact coplanarity left, where the two definitions differ)."""
    mesh = closed_shape(kind)
    noise = np.random.default_rng(seed).normal(size=mesh.vertices.shape)
    verts = mesh.vertices + amplitude * mesh.edges_unique_length.mean() * noise
    np.testing.assert_array_equal(self_intersecting_faces(verts, mesh.faces), pymeshlab_faces(verts, mesh.faces))


def test_agrees_with_pymeshlab_on_overdrawn_shape_model_samples():
    """A bumpy sphere's shape model drawn far past its range: many pierced and folded faces."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=40.0)
    rng = np.random.default_rng(7)
    direction = sphere.vertex_normals
    # Along random axes: modes along a coordinate axis keep the icosphere's mirror symmetry,
    # whose mirrored faces touch exactly on the mirror plane (the two tests round that apart).
    modes = [np.sin(sphere.vertices @ rng.normal(size=3) / 12.0 + rng.uniform(0, 6)) for _ in range(5)]
    flagged = 0
    for draw in range(12):
        radial = sum(rng.normal(scale=4.0 + 2 * draw) * mode for mode in modes)
        verts = sphere.vertices + radial[:, None] * direction
        ours = self_intersecting_faces(verts, sphere.faces)
        np.testing.assert_array_equal(ours, pymeshlab_faces(verts, sphere.faces))
        flagged += ours.any()
    assert 3 <= flagged < 12  # both kinds of draw were met


TRIANGLE = [[0, 0, 0], [2, 0, 0], [0, 2, 0]]
CASES = {
    # name: (vertices, faces, expected flags)
    "crossing, no shared vertex": (TRIANGLE + [[0.5, 0.5, -1], [0.5, 0.5, 1], [3, 3, 0]], [[0, 1, 2], [3, 4, 5]], True),
    "apart": (TRIANGLE + [[10.5, 0.5, -1], [10.5, 0.5, 1], [13, 3, 0]], [[0, 1, 2], [3, 4, 5]], False),
    "touching at a corner": (TRIANGLE + [[2, 0, 0], [3, 0, 1], [3, 0, -1]], [[0, 1, 2], [3, 4, 5]], True),
    "coplanar overlap": (TRIANGLE + [[0.5, 0.5, 0], [3, 0.5, 0], [0.5, 3, 0]], [[0, 1, 2], [3, 4, 5]], True),
    "coplanar, one inside the other": (TRIANGLE + [[0.2, 0.2, 0], [0.6, 0.2, 0], [0.2, 0.6, 0]],
                                       [[0, 1, 2], [3, 4, 5]], True),
    "coplanar, side by side": (TRIANGLE + [[2.1, 0, 0], [4, 0, 0], [2.1, 2, 0]], [[0, 1, 2], [3, 4, 5]], False),
    "fan folded through": (TRIANGLE + [[1, 1, 1], [1, 1, -1]], [[0, 1, 2], [0, 3, 4]], True),
    "fan folded flat over": (TRIANGLE + [[2, 1, 0], [1, 2, 0]], [[0, 1, 2], [0, 3, 4]], True),
    "fan, flat": ([[0, 0, 0], [2, 0, 0], [1, 2, 0], [-1, 2, 0], [-2, 0, 0]], [[0, 1, 2], [0, 3, 4]], False),
    "fan, bent away": (TRIANGLE + [[-1, 0, 1], [0, -1, 1]], [[0, 1, 2], [0, 3, 4]], False),
    "shared edge, folded flat": (TRIANGLE + [[1, 1.5, 0]], [[0, 1, 2], [0, 1, 3]], False),
    "the same face twice": (TRIANGLE, [[0, 1, 2], [0, 2, 1]], True),
}


@pytest.mark.parametrize("name", list(CASES))
def test_analytic_pairs(name):
    verts, faces, expected = CASES[name]
    verts, faces = np.array(verts, dtype=np.float64), np.array(faces)
    np.testing.assert_array_equal(self_intersecting_faces(verts, faces), [expected, expected])
    # Neither the order of the faces nor a rigid motion changes the verdict.
    rotation = trimesh.transformations.random_rotation_matrix(np.random.default_rng(3).random(3))[:3, :3]
    np.testing.assert_array_equal(self_intersecting_faces(verts @ rotation.T + 5.0, faces[::-1]), [expected, expected])


def test_two_overlapping_spheres_flag_the_faces_across_each_other():
    """Two spheres in one mesh, 25 mm apart (radius 20 mm): the faces that cross the other
    sphere's surface, and no others, meet the other sphere's faces."""
    one = trimesh.creation.icosphere(subdivisions=3, radius=20.0)
    verts = np.vstack([one.vertices, one.vertices + (25.0, 0, 0)])
    faces = np.vstack([one.faces, one.faces + len(one.vertices)])
    other_centre = np.where(np.arange(len(faces))[:, None] < len(one.faces), (25.0, 0, 0), (0.0, 0, 0))
    radius = np.linalg.norm(verts[faces] - other_centre[:, None, :], axis=2)  # (F, 3) from the other centre
    flagged = self_intersecting_faces(verts, faces)
    # Clear of the chordal error (0.1 mm here): across, or wholly to one side.
    across = (radius.min(axis=1) < 19.5) & (radius.max(axis=1) > 20.5)
    beside = (radius.min(axis=1) > 20.5) | (radius.max(axis=1) < 19.5)
    assert across.sum() > 20 and flagged[across].all()
    assert not flagged[beside].any()
    np.testing.assert_array_equal(flagged, pymeshlab_faces(verts, faces))


def test_small_inputs_and_bad_indices():
    assert self_intersecting_faces(np.zeros((3, 3)), np.array([[0, 1, 2]])).tolist() == [False]
    assert self_intersecting_faces(np.zeros((0, 3)), np.zeros((0, 3), int)).shape == (0,)
    with pytest.raises(ValueError, match="faces: indices"):
        self_intersecting_faces(np.zeros((3, 3)), np.array([[0, 1, 3], [0, 1, 2]]))
    with pytest.raises(ValueError, match="1 vertices are not finite"):
        self_intersecting_faces(np.array([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]]), np.array([[0, 1, 2], [0, 2, 1]]))
    # A degenerate mesh (every corner at one point) and far-flung faces do not break the grid.
    assert self_intersecting_faces(np.zeros((4, 3)), np.array([[0, 1, 2], [1, 2, 3]])).tolist() == [False, False]
    far = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1e9, 0, 0], [1e9 + 1, 0, 0], [1e9, 1, 0]])
    assert not self_intersecting_faces(far, np.array([[0, 1, 2], [3, 4, 5]])).any()
