"""Mesh metrics on analytic cases (DESIGN section 11)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

pytest.importorskip("torch")

from meshsar_builder.geometry.closest import closest_among, point_to_surface  # noqa: E402
from meshsar_builder.trainer import metrics as M  # noqa: E402


@pytest.fixture(scope="module")
def spheres():
    return trimesh.creation.icosphere(5, radius=30.0), trimesh.creation.icosphere(5, radius=33.0)


def test_concentric_spheres(spheres):
    inner, outer = spheres
    got = M.mesh_metrics(outer.vertices, outer.faces, inner.vertices, inner.faces, samples=5000)
    # Facets sag below the sphere by at most r (1 - cos(edge / 2r)) ~ 0.02 mm at this level.
    for key in ("assd_mm", "hd_mm", "hd95_mm"):
        assert got[key] == pytest.approx(3.0, abs=0.06), key
    diagonal = np.linalg.norm(np.ptp(inner.vertices, axis=0))
    assert got["assd_norm"] == pytest.approx(got["assd_mm"] / diagonal)
    assert got["dice"] == pytest.approx(2 * 30**3 / (30**3 + 33**3), abs=0.005)
    assert got["jaccard"] == pytest.approx(30**3 / 33**3, abs=0.005)
    # Radial offset only: normals agree to the facet curvature, Laplacians scale by 33/30.
    assert got["ane_rad"] < 0.02
    assert got["si_pct"] == 0


def test_identical_meshes_score_perfectly_on_every_metric(spheres):
    inner, _ = spheres
    mesh = trimesh.creation.icosphere(3, radius=30.0)
    verts = mesh.vertices * [1.0, 1.4, 0.8]  # an ellipsoid: vertex normals differ from face normals
    got = M.mesh_metrics(verts, mesh.faces, verts, mesh.faces, samples=5000)
    assert set(got) == set(M.COLUMNS)
    assert got["dice"] == 1 and got["jaccard"] == 1
    for key in ("assd_mm", "assd_norm", "hd_mm", "hd_norm", "hd95_mm", "hd95_norm", "anld"):
        assert got[key] == pytest.approx(0, abs=1e-9), key
    assert got["ane_rad"] == pytest.approx(0, abs=1e-6)
    assert got["si_pct"] == 0


def test_ane_of_reversed_normals_is_pi():
    mesh = trimesh.creation.icosphere(2, radius=30.0)
    verts = mesh.vertices * [1.0, 1.4, 0.8]
    got = M.mesh_metrics(verts, mesh.faces[:, ::-1], verts, mesh.faces, samples=1000)
    assert got["ane_rad"] == pytest.approx(np.pi, abs=1e-6)


def test_interpolated_normals_are_radial_on_a_sphere():
    mesh = trimesh.creation.icosphere(4, radius=30.0)
    rng = np.random.default_rng(1)
    points = rng.normal(size=(500, 3))
    points *= rng.uniform(20, 40, (500, 1)) / np.linalg.norm(points, axis=1, keepdims=True)
    normals = M.interpolated_normals(points, mesh.vertices, mesh.faces)
    radial = points / np.linalg.norm(points, axis=1, keepdims=True)
    # Facets of a level-4 sphere turn by ~0.03 rad; interpolation stays within that of the radius.
    assert M.angles(normals, radial).max() < 0.02
    # At a vertex it is exactly the vertex normal.
    np.testing.assert_allclose(M.interpolated_normals(mesh.vertices[:20], mesh.vertices, mesh.faces),
                               M.vertex_normals(mesh.vertices, mesh.faces)[:20], atol=1e-12)


def test_closest_barycentric_rebuilds_points_on_the_surface_and_projects_points_off_it():
    from meshsar_builder.geometry.surface_map import closest_barycentric, interpolation_matrix

    mesh = trimesh.creation.icosphere(3, radius=20.0)
    rng = np.random.default_rng(2)
    weights = rng.dirichlet(np.ones(3), len(mesh.faces))
    points = np.einsum("nk,nkc->nc", weights, mesh.vertices[mesh.faces])
    face, found = closest_barycentric(points, mesh.vertices, mesh.faces)
    np.testing.assert_array_equal(face, np.arange(len(mesh.faces)))
    np.testing.assert_allclose(found, weights, atol=1e-9)
    # Off the surface: the weights give the closest surface point, as trimesh finds it.
    off = points * rng.uniform(0.8, 1.2, (len(points), 1))
    closest, _, _ = trimesh.proximity.closest_point(mesh, off)
    np.testing.assert_allclose(interpolation_matrix(off, mesh.vertices, mesh.faces) @ mesh.vertices, closest, atol=1e-9)


def test_pushed_through_vertex_self_intersects():
    mesh = trimesh.creation.icosphere(2, radius=30.0)
    verts = mesh.vertices.copy()
    verts[0] *= -1.3  # through the centre and out of the far side: its fan crosses the far side's faces
    got = M.mesh_metrics(verts, mesh.faces, mesh.vertices, mesh.faces, samples=2000)
    assert got["si_pct"] > 0


def test_point_to_surface_matches_brute_force():
    """libigl's tree against every face tried (this project's own point-triangle kernel), on a
    bumpy ellipsoid, points inside and out, and points on its corners and edges (ties)."""
    mesh = trimesh.creation.icosphere(2, radius=20.0)
    rng = np.random.default_rng(3)
    verts = mesh.vertices * [1.0, 1.5, 0.7] + rng.normal(scale=0.5, size=mesh.vertices.shape)
    points = np.concatenate([rng.normal(scale=25.0, size=(300, 3)), verts[:20],
                             (verts[mesh.edges[:20, 0]] + verts[mesh.edges[:20, 1]]) / 2])
    dist, face = point_to_surface(points, verts, mesh.faces)
    every = np.broadcast_to(np.arange(len(mesh.faces)), (len(points), len(mesh.faces)))
    _, _, d2 = closest_among(points, verts, mesh.faces, every)
    np.testing.assert_allclose(dist, np.sqrt(d2), rtol=1e-12, atol=1e-12)
    _, _, at_face = closest_among(points, verts, mesh.faces, face[:, None])  # the named face holds the distance
    np.testing.assert_allclose(np.sqrt(at_face), dist, rtol=1e-12, atol=1e-12)
    assert np.all(dist[300:] < 1e-9)


def test_closest_point_regions_of_one_triangle():
    verts = np.array([[0.0, 0, 0], [2, 0, 0], [0, 2, 0]])
    points = np.array([[-1.0, -1, 1], [3, -1, 0], [1, -1, 0], [0.5, 0.5, 2], [2, 2, 0]])
    expected = np.array([[0.0, 0, 0], [2, 0, 0], [1, 0, 0], [0.5, 0.5, 0], [1, 1, 0]])
    closest, _, _ = closest_among(points, verts, np.array([[0, 1, 2]]), np.zeros((5, 1), dtype=np.int64))
    np.testing.assert_allclose(closest, expected, atol=1e-12)


def test_inside_matches_a_sphere_away_from_its_facets():
    mesh = trimesh.creation.icosphere(4, radius=30.0)
    points = np.random.default_rng(4).uniform(-40, 40, (4000, 3))
    radius = np.linalg.norm(points, axis=1)
    clear = np.abs(radius - 30) > 0.1  # facets sag by < 0.03 mm at this level
    np.testing.assert_array_equal(M.inside(points, mesh.vertices, mesh.faces)[clear], radius[clear] < 30)


def test_voxelised_box_volume():
    box = trimesh.creation.box(extents=(10.0, 6.0, 4.0))
    lo = np.array([-6.0, -4.0, -3.0])
    inside = M.voxelise(box.vertices, box.faces, lo, (24, 16, 12), 0.5)
    assert inside.sum() * 0.125 == pytest.approx(240.0)
