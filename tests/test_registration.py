import os
import subprocess
import sys

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from meshsar_builder.geometry.landmarks import face_labels, label_agreement, label_landmarks, structure_name
from meshsar_builder.geometry.meshing import MeshingParams, labels_to_surface, transfer_labels
from meshsar_builder.geometry.registration import (
    RegistrationParams,
    accept,
    choose_template,
    flipped_faces,
    register,
    surface_distances,
)
from meshsar_builder.geometry.remesh import RemeshParams, remesh, simplify
from meshsar_builder.geometry.structures import STRUCTURES
from meshsar_builder.pipeline.errors import MeshError

PARAMS = RegistrationParams(distance_samples=5000)


def unit_sphere():
    return trimesh.creation.icosphere(subdivisions=5)


def blob(points: np.ndarray) -> np.ndarray:
    """A smooth asymmetric closed surface (no rotational symmetry, so a fit has one answer)."""
    return points * (30.0, 22.0, 18.0) + np.c_[
        3 * np.sin(2 * points[:, 1]), 2 * np.cos(3 * points[:, 2]), 4 * np.sin(2 * points[:, 0] + 1)
    ]


@pytest.fixture(scope="module")
def template():
    sphere = unit_sphere()
    return remesh(blob(sphere.vertices), sphere.faces, RemeshParams(edge_mm=2.5))


def test_similarity_moved_retessellated_template_is_registered_back(template):
    verts, faces = template
    rotation = Rotation.from_euler("xyz", [40, -25, 70], degrees=True).as_matrix()
    scale, shift = 1.2, np.array([10.0, -5.0, 3.0])
    moved = scale * verts @ rotation.T + shift
    subject_verts, subject_faces = remesh(moved, faces, RemeshParams(edge_mm=2.0))
    assert len(subject_verts) != len(verts)

    # Labels: the side of a plane through the template, carried along by the known motion.
    template_labels = (verts[:, 0] > 5.0).astype(np.uint8)
    subject_labels = (((subject_verts - shift) @ rotation / scale)[:, 0] > 5.0).astype(np.uint8)
    fitted, report = register(
        verts, faces, subject_verts, subject_faces, PARAMS, np.random.default_rng(0), template_labels, subject_labels
    )
    assert fitted.shape == verts.shape
    assert np.linalg.norm(fitted - moved, axis=1).mean() < 0.5
    assert report["prealign_scale"] == pytest.approx(scale, rel=0.01)
    assert report["label_agreement"] > 0.97
    accept(report, PARAMS)


def test_smoothly_deformed_ellipsoid_is_fitted_closely_without_flips():
    sphere = unit_sphere()
    ellipsoid = sphere.vertices * (30.0, 22.0, 18.0)

    def field(p):
        return p + np.c_[3 * np.sin(p[:, 1] / 12), 2 * np.cos(p[:, 2] / 9), 2.5 * np.sin(p[:, 0] / 10)]

    template_verts, template_faces = remesh(ellipsoid, sphere.faces, RemeshParams(edge_mm=2.5))
    subject_verts, subject_faces = remesh(field(ellipsoid), sphere.faces, RemeshParams(edge_mm=2.0))
    fitted, report = register(
        template_verts, template_faces, subject_verts, subject_faces, PARAMS, np.random.default_rng(1)
    )
    assert report["mean_mm"] < 0.2
    assert report["flipped_faces"] == 0
    assert report["self_intersections"] == 0
    assert "label_agreement" not in report
    # The report's distance agrees with an independent measurement of the same fit.
    to_subject, to_fit = surface_distances(
        fitted, template_faces, subject_verts, subject_faces, 20000, np.random.default_rng(9)
    )
    assert 0.5 * (to_subject.mean() + to_fit.mean()) == pytest.approx(report["mean_mm"], abs=0.02)


def test_torus_subject_is_refused_for_its_topology(template):
    torus = trimesh.creation.torus(30.0, 10.0)
    with pytest.raises(MeshError, match="registration subject: Euler characteristic 0"):
        register(*template, torus.vertices, torus.faces, PARAMS, np.random.default_rng(0))


def test_wildly_different_shape_is_rejected_with_reasons():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=30.0)
    template_verts, template_faces = remesh(sphere.vertices, sphere.faces, RemeshParams(edge_mm=4.0))
    # A long thin bar: genus 0, but a sphere cannot follow it under the stiffness schedule.
    bar = trimesh.creation.capsule(height=150.0, radius=6.0, count=[32, 32])
    subject_verts, subject_faces = remesh(bar.vertices, bar.faces, RemeshParams(edge_mm=4.0))
    params = RegistrationParams(distance_samples=2000, step_iterations=3)
    _, report = register(
        template_verts, template_faces, subject_verts, subject_faces, params, np.random.default_rng(0)
    )
    with pytest.raises(MeshError, match="registration rejected: two-sided mean surface distance .* mm > 0.5 mm"):
        accept(report, params)


@pytest.mark.parametrize(
    "change, reason",
    [
        ({"mean_mm": 0.8}, "two-sided mean surface distance 0.800 mm > 0.5 mm"),
        ({"p95_mm": 2.0}, "95th-percentile surface distance 2.000 mm > 1.5 mm"),
        ({"flipped_faces": 3}, "3 flipped faces"),
        ({"self_intersections": 4}, "4 self-intersecting faces"),
    ],
)
def test_accept_names_each_broken_threshold(change, reason):
    report = {"mean_mm": 0.1, "p95_mm": 0.3, "flipped_faces": 0, "self_intersections": 0}
    accept(report, PARAMS)
    with pytest.raises(MeshError, match=reason):
        accept({**report, **change}, PARAMS)


def test_flipped_faces_are_folds_not_turns():
    """A face turned past 90 degrees along with its neighbourhood is no fold (a real dilated RV's
    fit turned 71 faces so, on the subject's surface); one turned against it is, and so is every
    turned face of a mesh turned inside out."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=30.0)
    verts, faces = sphere.vertices, sphere.faces
    turned = verts @ Rotation.from_euler("x", 150, degrees=True).as_matrix().T
    assert not flipped_faces(verts, turned, faces).any()
    # a twist about z, 150 degrees from bottom to top: smooth, one to one, and the side faces turn past 90
    angle = np.radians(150.0) * (verts[:, 2] + 30.0) / 60.0
    twisted = np.c_[verts[:, 0] * np.cos(angle) - verts[:, 1] * np.sin(angle),
                    verts[:, 0] * np.sin(angle) + verts[:, 1] * np.cos(angle), verts[:, 2]]
    assert (np.einsum("ij,ij->i", sphere.face_normals, trimesh.Trimesh(twisted, faces).face_normals) < 0).sum() > 50
    assert not flipped_faces(verts, twisted, faces).any()
    dragged = verts.copy()
    top = int(np.argmax(verts[:, 2]))
    dragged[top, 0] += 9.0  # past its neighbours (edges 3.8 mm): a face on the far side turns over
    folded = flipped_faces(verts, dragged, faces)
    turned_alone = np.einsum("ij,ij->i", sphere.face_normals, trimesh.Trimesh(dragged, faces).face_normals) < 0
    assert folded.any() and np.array_equal(folded, turned_alone)
    assert set(np.flatnonzero(folded)) <= set(np.flatnonzero((faces == top).any(axis=1)))
    assert flipped_faces(verts, verts * [-1.0, 1.0, 1.0], faces).sum() > len(faces) // 2  # inside out


def test_choose_template_takes_the_median_volume_deterministically():
    assert choose_template({"a": 3.0, "b": 1.0, "c": 2.0}) == "c"
    assert choose_template({"d": 4.0, "c": 3.0, "b": 2.0, "a": 1.0}) == "b"
    assert choose_template({"y": 2.0, "x": 2.0, "z": 1.0}) == "x"
    assert choose_template({"a": 3.0, "b": 1.0}, "a") == "a"
    with pytest.raises(ValueError, match="template: subject 'q' is not among the 2 subjects"):
        choose_template({"a": 3.0, "b": 1.0}, "q")


@pytest.mark.parametrize(
    "field, value",
    [
        ("template", ""),
        ("template_vertices", 10),
        ("max_mean_mm", 0.0),
        ("max_p95_mm", -1.0),
        ("icp_points", 1),
        ("stiffness", ()),
        ("normal_weight", (0.5,)),
        ("step_iterations", 0),
        ("match_distance_mm", 0.0),
        ("distance_samples", 5),
        ("max_normal_deg", 0.0),
        ("gamma", 0.0),
        ("reverse_weight", -1.0),
        ("converge_mm", 0.0),
        ("fold_retries", -1),
        ("fold_stiffening", 1.0),
        ("landmark_weight", -0.1),
        ("landmark_smoothing", -1.0),
        ("frame_landmark_smoothing", -1.0),
        ("min_label_agreement", 1.5),
        ("groupwise_rounds", -1),
        ("groupwise_converge_mm", -0.1),
        ("groupwise_smoothing", -1),
        ("coarse_steps", -1),
        ("round_coarse_steps", -1),
        ("coarse_vertices", 10),
    ],
)
def test_params_reject_bad_values_naming_the_field(field, value):
    with pytest.raises(ValueError, match=f"^{field}: "):
        RegistrationParams(**{field: value})


def chamber_with_vessel(axes, tilt_deg, vessel_radius, arch_radius, sweep_deg, voxel_mm=2.0):
    """Label map of an ellipsoidal chamber (lv) joined to a thin tube (aorta) that leaves its top,
    bends over in an arch and ends in a rounded tip: a thin part with a concave junction."""
    shape = (60, 44, 60)
    affine = np.diag([voxel_mm] * 3 + [1.0])
    affine[:3, 3] = -0.5 * voxel_mm * np.array(shape) + (10.0, 0.0, 20.0)
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).reshape(-1, 3)
    points = grid @ affine[:3, :3].T + affine[:3, 3]
    tilt = Rotation.from_euler("y", tilt_deg, degrees=True).as_matrix()
    local = points @ tilt  # chamber frame
    chamber = np.sum((local / np.asarray(axes)) ** 2, axis=1) <= 1.0
    # Centre line: up the chamber's axis from its centre to its top, then an arch towards +x.
    top = axes[2] - 2.0
    stem = np.c_[np.zeros(40), np.zeros(40), np.linspace(0.0, top, 40)]
    phi = np.radians(np.linspace(0.0, sweep_deg, 200))
    arch = np.c_[arch_radius * (1 - np.cos(phi)), np.zeros_like(phi), top + arch_radius * np.sin(phi)]
    line = np.r_[stem, arch] @ tilt.T
    distance, _ = cKDTree(line).query(points)
    vessel = (distance <= vessel_radius) & ~chamber
    labels = np.zeros(len(points), dtype=np.uint8)
    labels[chamber] = STRUCTURES["lv"]
    labels[vessel] = STRUCTURES["aorta"]
    return labels.reshape(shape), affine


@pytest.fixture(scope="module")
def vessel_shapes():
    params = MeshingParams(spacing_mm=1.5, sigma_mm=1.0)
    shapes = []
    for axes, tilt, radius, arch_radius, sweep in (
        ((30.0, 24.0, 20.0), 0.0, 7.0, 22.0, 120.0),
        ((33.0, 22.0, 22.0), 10.0, 6.0, 26.0, 140.0),
    ):
        labels, affine = chamber_with_vessel(axes, tilt, radius, arch_radius, sweep)
        surface = labels_to_surface(labels, affine, ["lv", "aorta"], params)
        verts, faces = remesh(surface.verts, surface.faces, RemeshParams(edge_mm=3.0))
        shapes.append((verts, faces, transfer_labels(surface.verts, surface.labels, verts)))
    return shapes


def test_chamber_with_thin_curved_vessel_is_registered_without_folds(vessel_shapes):
    (t_verts, t_faces, t_labels), (s_verts, s_faces, s_labels) = vessel_shapes
    t_verts, t_faces_simple = simplify(t_verts, t_faces, 1200)
    t_labels = transfer_labels(vessel_shapes[0][0], vessel_shapes[0][2], t_verts)
    params = RegistrationParams(distance_samples=5000)
    fitted, report = register(
        t_verts, t_faces_simple, s_verts, s_faces, params, np.random.default_rng(3), t_labels, s_labels
    )
    assert report["flipped_faces"] == 0
    assert report["self_intersections"] == 0
    accept(report, params)
    # The template vessel (shorter, thicker, less bent) reaches the subject vessel's tip.
    tip = s_verts[[np.argmax(s_verts[:, 0])]]
    _, tip_distance, _ = trimesh.proximity.closest_point(trimesh.Trimesh(fitted, t_faces_simple, process=False), tip)
    assert tip_distance[0] < 3.0  # trimesh's nricp_amberg with the old schedule: 12.8 mm short, 1 flip
    assert report["label_agreement"] > 0.9


def test_fold_guard_keeps_an_overly_soft_schedule_fold_free(vessel_shapes):
    """Even a schedule ending far too soft for this template leaves no folded or crossing faces."""
    (t_verts, t_faces, _), (s_verts, s_faces, _) = vessel_shapes
    t_verts, t_faces = simplify(t_verts, t_faces, 800)
    params = RegistrationParams(
        distance_samples=2000, stiffness=(0.05, 0.005, 0.0005), normal_weight=(0.5, 0.0, 0.0), step_iterations=6
    )
    fitted, report = register(t_verts, t_faces, s_verts, s_faces, params, np.random.default_rng(4))
    assert report["flipped_faces"] == 0
    assert report["self_intersections"] == 0
    assert report["nricp"]["steps"] == 3


def test_systems_on_one_topology_share_one_fill_reducing_order():
    """The factorisation's order depends on the faces alone: systems on moved vertices of one mesh (every
    subject on one template, every frame of a subject) reuse it, and another mesh gets its own. It keeps each
    vertex's 4 unknowns together and is the minimum degree order of the stiffness's own ring pattern."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    from meshsar_builder.geometry.nricp import _AmbergSystem

    sphere = unit_sphere()
    first = _AmbergSystem(blob(sphere.vertices) / 80.0, sphere.faces, gamma=1.0)
    moved = _AmbergSystem(1.1 * blob(sphere.vertices) / 80.0 + 0.3, sphere.faces, gamma=1.0)
    assert moved.order is first.order  # found once
    other = trimesh.creation.icosphere(subdivisions=2)
    assert _AmbergSystem(np.asarray(other.vertices), np.asarray(other.faces), gamma=1.0).order is not first.order
    n = len(sphere.vertices)
    blocks = first.order.reshape(n, 4)
    assert (blocks == blocks[:, :1] + np.arange(4)).all() and (blocks[:, 0] % 4 == 0).all()
    assert np.array_equal(np.sort(blocks[:, 0] // 4), np.arange(n))
    pattern = sp.csr_matrix((np.ones(len(first.rings[0])), first.rings[:2]), shape=(n, n)) + n * sp.eye(n)
    expected = np.argsort(splu(pattern.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                               options={"SymmetricMode": True}).perm_c)
    np.testing.assert_array_equal(blocks[:, 0] // 4, expected)


def test_the_preconditioner_inverts_a_fit_system_and_factorises_a_singular_one():
    """The preconditioner (CHOLMOD's Cholesky factor, its diagonal shifted by 1e-9 of its largest entry) solves a
    fit's sparse system to the direct solve's vertices, so the conjugate gradients need one or two iterations. The
    stiffness alone is singular (it leaves transforms varying linearly with position free): it still factorises,
    on a larger shift where a zero eigenvalue came out negative; an indefinite matrix is refused, named."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    from meshsar_builder.geometry.nricp import _AmbergSystem
    from meshsar_builder.geometry.nricp_solve import Operator, pcg, preconditioner

    ico = trimesh.creation.icosphere(subdivisions=3)
    system = _AmbergSystem(np.asarray(ico.vertices) * [1.0, 0.8, 0.6], np.asarray(ico.faces), gamma=1.0)
    rng = np.random.default_rng(0)
    targets = 1.05 * system.apply(system.identity()) + 0.01 * rng.standard_normal((system.n, 3))
    stiffness = 0.01 * system.stiffness(1.0 / system.spacing**4, np.zeros(len(system.edges)))
    data, rhs = system.data(rng.uniform(0.5, 1.0, system.n), targets)
    matrix = (stiffness + data).tocsr()
    # The fit's matrix is itself singular up to rounding (transforms that move no vertex), so the vertices the
    # two solutions put are compared.
    exact = spsolve(matrix.tocsc(), rhs)
    solve = preconditioner(matrix, system.order)
    solved = solve(rhs)
    assert np.linalg.norm(matrix @ solved - rhs) <= 1e-6 * np.linalg.norm(rhs)
    np.testing.assert_allclose(system.apply(solved), system.apply(exact), atol=1e-6)
    iterations = []
    pcg(Operator(matrix, None, 0.0), rhs, system.identity(), lambda r: iterations.append(1) or solve(r), rtol=1e-6,
        max_iterations=50)
    assert len(iterations) <= 2

    # The stiffness alone has 16 zero eigenvalues here, and rounding can leave one slightly negative: a larger
    # shift still gives a factor that solves the consistent systems in one or two iterations.
    singular = stiffness.tocsr()
    assert np.linalg.matrix_rank(singular.toarray()) < 4 * system.n
    rhs = singular @ rng.standard_normal((4 * system.n, 3))
    for matrix in (singular, singular - 1e-8 * singular.diagonal().max() * sp.eye(4 * system.n, format="csr")):
        iterations = []
        solve = preconditioner(matrix, system.order)
        solved = pcg(Operator(singular, None, 0.0), rhs, np.zeros_like(rhs), lambda r: iterations.append(1) or
                     solve(r), rtol=1e-8, max_iterations=50)
        assert np.linalg.norm(singular @ solved - rhs) <= 1e-8 * np.linalg.norm(rhs) and len(iterations) <= 2

    with pytest.raises(ArithmeticError, match=f"system \\({4 * system.n} unknowns\\) is not positive definite"):
        preconditioner(-sp.eye(4 * system.n, format="csr"), system.order)


def test_stiffness_leaves_transforms_varying_linearly_with_position_free():
    """The second-order stiffness (nricp.py) costs nothing for affine transforms that vary
    linearly with position, a twist among them, on a curved surface too, and does cost
    for a smooth transform field that varies quadratically. The fold guard's first-order
    edge term, where it is switched on, makes the linear field cost too (and leaves a
    constant transform free)."""
    from meshsar_builder.geometry.nricp import _AmbergSystem

    sphere = unit_sphere()
    verts = blob(sphere.vertices) / 80.0  # curved everywhere, about unit size
    system = _AmbergSystem(verts, sphere.faces, gamma=1.0)
    no_edges = np.zeros(len(system.edges))
    stiffness = system.stiffness(1.0 / system.spacing**4, no_edges)
    coefficients = np.random.default_rng(0).normal(size=(4, 4, 3))
    linear = np.einsum("ij,jkl->ikl", np.c_[np.ones(len(verts)), verts], coefficients).reshape(-1, 3)
    quadratic = (np.sum(verts**2, axis=1)[:, None, None] * coefficients[0]).reshape(-1, 3)
    constant = np.tile(coefficients[0], (len(verts), 1))

    def energy(x, matrix=stiffness):
        return float(np.sum(x * (matrix @ x)))

    assert abs(energy(linear)) < 1e-6 * energy(quadratic)  # rounding only
    guarded = system.stiffness(0 * system.spacing, system.edge_base)
    assert energy(linear, guarded) > 1e3 * abs(energy(constant, guarded))


# ---------------------------------------------------------------------------------------------
# Labels: landmarks, agreement, acceptance, and known warps recovered vertex by vertex


def test_hemisphere_landmarks_match_the_analytic_centroids_and_ring():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=20.0)
    labels = np.where(sphere.vertices[:, 2] > 0, STRUCTURES["la"], STRUCTURES["ra"]).astype(np.uint8)
    marks = label_landmarks(sphere.vertices, sphere.faces, labels)
    assert set(marks.keys) == {"centroid:la", "centroid:ra", "ring:la-ra"}
    points = dict(zip(marks.keys, marks.points(sphere.vertices)))
    # The area centroid of a hemispherical shell of radius r lies r/2 from the centre.
    np.testing.assert_allclose(points["centroid:la"], [0, 0, 10.0], atol=0.3)
    np.testing.assert_allclose(points["centroid:ra"], [0, 0, -10.0], atol=0.3)
    np.testing.assert_allclose(points["ring:la-ra"], [0, 0, 0], atol=0.3)
    np.testing.assert_allclose(np.asarray(marks.weights.sum(axis=1)).ravel(), 1.0)


def test_face_labels_and_label_agreement_match_naive_loops():
    rng = np.random.default_rng(5)
    faces = rng.integers(0, 50, size=(200, 3))
    labels = rng.integers(1, 4, size=50)
    naive = [max(labels[f], key=lambda s: (list(labels[f]).count(s), s == labels[f][0])) for f in faces]
    np.testing.assert_array_equal(face_labels(faces, labels), naive)

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=10.0)
    # Points just off face interiors, as fitted vertices lie: each has one closest face.
    on, held = trimesh.sample.sample_surface(sphere, 60, seed=5)
    fitted = on + sphere.face_normals[held] * rng.uniform(-0.5, 0.5, (60, 1))
    t_labels, s_labels = rng.integers(1, 3, size=60), rng.integers(1, 3, size=len(sphere.vertices))
    _, _, face = trimesh.proximity.closest_point(sphere, fitted)
    agree = np.array([t in s_labels[sphere.faces[f]] for t, f in zip(t_labels, face)])
    points_as_faces = np.repeat(np.arange(60)[:, None], 3, axis=1)  # no boundaries: every structure a region
    overall, per = label_agreement(fitted, points_as_faces, t_labels, sphere.vertices, sphere.faces, s_labels,
                                   min_vertices=1)
    assert overall == pytest.approx(agree.mean())
    for s in (1, 2):
        assert per[structure_name(s)] == pytest.approx(agree[t_labels == s].mean())


def test_a_strip_between_structures_is_not_a_region_judged_or_landmarked():
    """Real whole-heart CT shows the LV as strips of 16-33 vertices (0-2 inside them) where a
    contact was cut; such a strip is neither judged by label agreement nor given a centroid."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=40.0)
    verts, faces = sphere.vertices, sphere.faces
    z = verts[:, 2]
    labels = np.where(z > 0, STRUCTURES["la"], STRUCTURES["ra"]).astype(np.uint8)
    strip = np.abs(z) < 1.5  # one vertex row each side of the equator
    labels[strip] = STRUCTURES["lv"]
    band = (z > 10) & (z < 25) & (verts[:, 0] > 0)  # a patch with an inside: a region
    labels[band] = STRUCTURES["rv"]
    from meshsar_builder.geometry.landmarks import surface_regions

    inner = ~np.isin(np.arange(len(verts)), faces[(labels[faces] != labels[faces][:, :1]).any(axis=1)].ravel())
    assert strip.sum() >= 10 and (inner & strip).sum() == 0
    assert set(surface_regions(faces, labels, 10)) == {STRUCTURES["la"], STRUCTURES["ra"], STRUCTURES["rv"]}
    # the subject: the same surface with the strip's vertices relabelled, so the strip would score 0
    subject_labels = np.where(strip, STRUCTURES["ra"], labels)
    overall, per = label_agreement(verts, faces, labels, verts, faces, subject_labels)
    assert set(per) == {"la", "ra", "rv"} and min(per.values()) == 1.0
    assert overall < 1.0  # the strip's vertices still count in the overall figure
    marks = label_landmarks(verts, faces, labels)
    assert "centroid:lv" not in marks.keys and "centroid:rv" in marks.keys
    assert not any("lv" in key for key in marks.keys)


def test_accept_names_the_structures_below_the_label_agreement():
    report = {"mean_mm": 0.1, "p95_mm": 0.3, "flipped_faces": 0, "self_intersections": 0,
              "label_agreement_by_structure": {"rv": 0.93, "ra": 0.95, "la": 0.99}}
    with pytest.raises(MeshError, match=r"label agreement < 0.97 for rv 0.930, ra 0.950$"):
        accept(report, RegistrationParams(min_label_agreement=0.97))
    accept(report, RegistrationParams(min_label_agreement=0.9))
    accept(report, RegistrationParams(min_label_agreement=0.97), correspondence=False)  # an earlier groupwise round


def long_axis_warps(verts: np.ndarray, apex: np.ndarray, base: np.ndarray) -> dict:
    """The known smooth maps of issue 12, about the long axis apex -> base of `verts` (n, 3).

    twist: 0.3 rad from apex to base; shear: a tangential slide across the axis growing
    from 0 at the apex to 8 mm at the base; bulge: a Gaussian (sigma 12 mm) outward push of
    10 % of the local radius at the point farthest from the axis."""
    axis = (base - apex) / np.linalg.norm(base - apex)
    along = (verts - apex) @ axis
    low, high = along.min(), along.max()
    centre = verts.mean(axis=0)
    across = np.cross(axis, [0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.cross(axis, [1.0, 0.0, 0.0])
    across /= np.linalg.norm(across)

    def height(p):
        return ((p - apex) @ axis - low) / (high - low)

    def twist(p):
        angle = 0.3 * height(p)[:, None]
        r = p - centre
        parallel = (r @ axis)[:, None] * axis
        radial = r - parallel
        return centre + parallel + radial * np.cos(angle) + np.cross(axis, radial) * np.sin(angle)

    def shear(p):
        return p + 8.0 * height(p)[:, None] * across

    radial = verts - centre - ((verts - centre) @ axis)[:, None] * axis
    peak = verts[np.argmax(np.linalg.norm(radial, axis=1))]
    radius = np.linalg.norm(radial, axis=1).max()

    def bulge(p):
        gauss = np.exp(-np.sum((p - peak) ** 2, axis=1) / (2 * 12.0**2))
        out = p - centre - ((p - centre) @ axis)[:, None] * axis
        return p + 0.1 * radius * gauss[:, None] * out / np.linalg.norm(out, axis=1, keepdims=True)

    return {"twist": twist, "shear": shear, "bulge": bulge}


def recover_warp(verts, faces, labels, template_vertices, warp, subject_edge_mm, params=PARAMS):
    """Register a simplified template of a labelled surface onto its warped, re-tessellated copy.

    Returns the vertex-by-vertex error (template size,) mm against the known map and the report."""
    t_verts, t_faces = simplify(verts, faces, template_vertices)
    t_labels = transfer_labels(verts, labels, t_verts)
    s_verts, s_faces = remesh(warp(verts), faces, RemeshParams(edge_mm=subject_edge_mm))
    s_labels = transfer_labels(warp(verts), labels, s_verts)
    fitted, report = register(t_verts, t_faces, s_verts, s_faces, params, np.random.default_rng(0), t_labels, s_labels)
    return np.linalg.norm(fitted - warp(t_verts), axis=1), report


@pytest.fixture(scope="module")
def labelled_blob():
    sphere = unit_sphere()
    verts, faces = remesh(blob(sphere.vertices), sphere.faces, RemeshParams(edge_mm=2.0))
    # Four structures: quadrants about the long (x) axis, split once more along it.
    quadrant = (verts[:, 1] > 0).astype(int) + 2 * (verts[:, 2] > 0)
    labels = np.where(verts[:, 0] > 8.0, quadrant + 2, np.where(quadrant < 2, 6, 7)).astype(np.uint8)
    apex, base = verts[np.argmin(verts[:, 0])], verts[np.argmax(verts[:, 0])]
    return verts, faces, labels, long_axis_warps(verts, apex, base)


def assert_warp_recovered(error: np.ndarray, report: dict) -> None:
    """Issue 12: vertex error (n,) mm within 1.0 mean / 2.5 p95, each structure's label agreement >= 0.98."""
    assert error.mean() <= 1.0
    assert np.percentile(error, 95) <= 2.5
    for structure, agreement in report["label_agreement_by_structure"].items():
        assert agreement >= 0.98, (structure, agreement)


@pytest.mark.parametrize("warp", ["twist", "shear", "bulge"])
def test_labelled_smooth_surface_known_warp_is_recovered_vertex_by_vertex(labelled_blob, warp):
    verts, faces, labels, warps = labelled_blob
    error, report = recover_warp(verts, faces, labels, 1500, warps[warp], 2.5)
    assert_warp_recovered(error, report)
    accept(report, RegistrationParams())


# The coarse start (nricp._coarse_start)


@pytest.fixture(scope="module")
def small_pair():
    """A ~640-vertex ellipsoid and a smoothly bulged, re-tessellated copy: quick fits."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    ellipsoid = sphere.vertices * (30.0, 22.0, 18.0)
    bulged = ellipsoid + np.c_[2 * np.sin(ellipsoid[:, 1] / 10), np.zeros(len(ellipsoid)), np.zeros(len(ellipsoid))]
    subject = remesh(bulged, sphere.faces, RemeshParams(edge_mm=3.0))
    return ellipsoid, sphere.faces, subject


def test_coarse_start_runs_the_stiffest_steps_coarse_and_never_all_of_them(small_pair):
    from meshsar_builder.geometry.nricp import nricp

    verts, faces, (s_verts, s_faces) = small_pair
    coarse = RegistrationParams(coarse_steps=2, coarse_vertices=200)
    fitted, summary = nricp(verts, faces, s_verts, s_faces, coarse)
    assert summary["coarse"]["used"] and summary["coarse"]["steps"] == 2
    assert summary["steps_kept"] == summary["steps"] == len(coarse.stiffness)
    assert len(summary["step_distances_mm"]) == len(coarse.stiffness)  # the coarse steps' first
    assert np.abs(fitted).max() < 100  # a fit of the subject, not a runaway
    # A one-step schedule has nothing left for full resolution: no coarse stage at all.
    one = RegistrationParams(stiffness=(0.001,), normal_weight=(0.0,), frame_steps=1, coarse_steps=3,
                             coarse_vertices=200)
    assert "coarse" not in nricp(verts, faces, s_verts, s_faces, one)[1]
    # Too few vertices to coarsen (fewer than twice coarse_vertices): none either.
    assert "coarse" not in nricp(verts, faces, s_verts, s_faces, RegistrationParams(coarse_vertices=400))[1]


def test_a_coarse_copy_that_cannot_be_made_falls_back_to_the_full_schedule(small_pair, monkeypatch):
    import meshsar_builder.geometry.nricp as N

    verts, faces, (s_verts, s_faces) = small_pair
    params = RegistrationParams(coarse_steps=1, coarse_vertices=200)

    def broken(*args):
        raise MeshError("surface simplified to 200 vertices: 3 self-intersecting faces")

    monkeypatch.setattr(N, "simplify", broken)
    full, summary = N.nricp(verts, faces, s_verts, s_faces, params)
    assert summary["coarse"] == {"used": False, "reason": "surface simplified to 200 vertices: 3 self-intersecting faces"}
    assert summary["steps_kept"] == len(params.stiffness)
    reference, _ = N.nricp(verts, faces, s_verts, s_faces, RegistrationParams(coarse_steps=0))
    np.testing.assert_array_equal(full, reference)  # exactly the full-resolution fit


def test_the_preconditioner_stays_inside_its_buffers(small_pair, tmp_path, monkeypatch):
    """The preconditioner's factorisation of a fit's matrices, repeated in a child process whose Python objects go
    through glibc's malloc too (PYTHONMALLOC=malloc), so that a stray write meets glibc's chunk checks. SuperLU,
    the factorisation before CHOLMOD, with supernodes relaxed to 80 columns in panels of 20 wrote past its buffers
    on these (a 642-vertex ellipsoid's fit and its 200-vertex coarse start): glibc aborted within 5 rounds, and
    test processes crashed at random."""
    import scipy.sparse as sp

    import meshsar_builder.geometry.nricp as N

    verts, faces, (s_verts, s_faces) = small_pair
    factorised = []
    real = N.preconditioner
    monkeypatch.setattr(N, "preconditioner", lambda matrix, order: factorised.append((matrix, order)) or
                        real(matrix, order))
    N.nricp(verts, faces, s_verts, s_faces, RegistrationParams(coarse_steps=4, coarse_vertices=200))
    assert {matrix.shape[0] for matrix, _ in factorised} == {4 * 200, 4 * len(verts)}
    for k, (matrix, order) in enumerate(factorised):
        sp.save_npz(tmp_path / f"matrix{k}.npz", matrix.tocsr())
        np.save(tmp_path / f"order{k}.npy", order)
    script = (
        "import sys, numpy as np, scipy.sparse as sp\n"
        "from meshsar_builder.geometry.nricp_solve import preconditioner\n"
        "rng = np.random.default_rng(0)\n"
        "for _ in range(20):\n"
        f"    for k in range({len(factorised)}):\n"
        "        matrix = sp.load_npz(f'{sys.argv[1]}/matrix{k}.npz')\n"
        "        solve = preconditioner(matrix, np.load(f'{sys.argv[1]}/order{k}.npy'))\n"
        "        assert np.isfinite(solve(rng.standard_normal((matrix.shape[0], 3)))).all()\n"
        "print('ok')\n")
    env = {**os.environ, "PYTHONMALLOC": "malloc"}
    done = subprocess.run([sys.executable, "-c", script, str(tmp_path)], env=env, capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.strip() == "ok", (done.returncode, done.stderr[-2000:])


def test_groupwise_rounds_before_the_last_run_more_steps_coarse(small_pair):
    """A round that only makes the next template runs round_coarse_steps coarse; the last
    round's fits (the model's shapes) keep coarse_steps, and both reach the subject alike."""
    from meshsar_builder.geometry.groupwise import register_groupwise

    verts, faces, (s_verts, s_faces) = small_pair
    params = RegistrationParams(coarse_steps=1, round_coarse_steps=4, coarse_vertices=200, groupwise_rounds=1,
                                groupwise_converge_mm=0.0, landmark_weight=0.0)
    subjects = [(s_verts, s_faces, None), (s_verts * 1.05, s_faces, None)]
    _, _, rounds = register_groupwise((verts, faces, None), subjects, params, lambda r, i: np.random.default_rng(i))
    assert [r["round"] for r in rounds] == [0, 1]
    assert [fit["nricp"]["coarse"]["steps"] for fit in rounds[0]["fits"]] == [4, 4]
    assert [fit["nricp"]["coarse"]["steps"] for fit in rounds[1]["fits"]] == [1, 1]
    for fits in (rounds[0]["fits"], rounds[1]["fits"]):
        assert all(fit["nricp"]["coarse"]["used"] and fit["mean_mm"] < 0.3 for fit in fits), fits


def test_frame_fits_coarsen_only_the_whole_schedule():
    from meshsar_builder.geometry.tracking import frame_params

    params = RegistrationParams(coarse_steps=1)
    assert frame_params(params).coarse_steps == 0  # the soft steps of a warm start
    assert frame_params(params, len(params.stiffness)).coarse_steps == 1
