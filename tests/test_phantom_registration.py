"""Registration of demo-resolution phantom hearts: accepted fits that keep structure labels."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from meshsar_builder.bench.suite import DEMO, demo_subject
from meshsar_builder.geometry.meshing import transfer_labels
from meshsar_builder.geometry.registration import accept, register
from meshsar_builder.geometry.remesh import remesh, simplify
from meshsar_builder.pipeline.recipe import load

pytestmark = pytest.mark.slow
# Measured 0.20 mm between the final templates of seeds 0 and 2 (their seed templates: 3.4 mm).
# The rounds stop once a template moves < 0.5 mm, so two runs may keep up to about that much
# of their seed; twice the measurement, still below the convergence tolerance.
SEED_TOLERANCE_MM = 0.4


def test_phantom_subjects_register_and_keep_structure_labels():
    recipe = load(DEMO)
    surfaces = []
    for i in range(3):
        s = demo_subject(i)
        v, f = remesh(s.verts, s.faces, recipe.remesh)
        surfaces.append((v, f, transfer_labels(s.verts, s.labels, v)))
    tv, tf = simplify(surfaces[0][0], surfaces[0][1], recipe.registration.template_vertices)
    tl = transfer_labels(surfaces[0][0], surfaces[0][2], tv)
    for i, (v, f, labels) in enumerate(surfaces[1:], start=1):
        _, report = register(tv, tf, v, f, recipe.registration, np.random.default_rng(i), tl, labels)
        # mean <= 0.5 mm, p95 <= 1.5 mm, no flips or self-intersections; to one reference subject
        # (a first groupwise round) the structures may still sit a little apart, measured >= 0.964.
        accept(report, recipe.registration, correspondence=False)
        assert min(report["label_agreement_by_structure"].values()) >= 0.95, report["label_agreement_by_structure"]


def test_every_phantom_full_whole_heart_subject_is_accepted(tmp_path):
    """Issue 16: all 20 whole-heart subjects of manifests/phantom_full.toml are accepted through
    the stage's groupwise rounds from its median template, at the smoke recipe's coarse
    resolution to stay quick."""
    from pathlib import Path

    from meshsar_builder.dataset.label_maps import read_label_map
    from meshsar_builder.dataset.sources import MMWHS_TABLE
    from meshsar_builder.geometry.groupwise import register_groupwise
    from meshsar_builder.geometry.meshing import labels_to_surface
    from meshsar_builder.geometry.phantom_heart import write_mmwhs_subject
    from meshsar_builder.geometry.registration import choose_template
    from meshsar_builder.pipeline.seeding import item_rng

    manifests = Path(__file__).resolve().parents[1] / "manifests"
    full, smoke = load(manifests / "phantom_full.toml"), load(manifests / "smoke.toml")
    spec = full.sources[0]
    assert spec.anatomy == "whole_heart" and spec.use == "ssm"
    surfaces = {}
    for n in range(spec.subjects):
        subject = f"{spec.name}-ct_train_{1001 + n}"
        path = write_mmwhs_subject(tmp_path, f"ct_train_{1001 + n}", item_rng(full.seed, "sources", subject),
                                   voxel_mm=smoke.sources[0].voxel_mm)
        labels, affine = read_label_map(path, MMWHS_TABLE)
        s = labels_to_surface(labels, affine, list(spec.structures), smoke.meshing)
        v, f = remesh(s.verts, s.faces, smoke.remesh)
        surfaces[subject] = (v, f, transfer_labels(s.verts, s.labels, v))
    volumes = {k: trimesh.Trimesh(v, f, process=False).volume for k, (v, f, _) in surfaces.items()}
    chosen = choose_template(volumes, full.registration.template)
    params = smoke.registration
    tv, tf = simplify(*surfaces[chosen][:2], params.template_vertices)
    tl = transfer_labels(surfaces[chosen][0], surfaces[chosen][2], tv)
    names = list(surfaces)
    # The stage's rounds; any rejection (label agreement judged in the last round) raises naming the subject.
    _, _, rounds = register_groupwise((tv, tf, tl), list(surfaces.values()), params,
                                      lambda r, i: item_rng(full.seed, "register", f"round{r}/{names[i]}"))
    assert len(rounds[-1]["fits"]) == spec.subjects


@pytest.fixture(scope="module")
def labelled_heart(tmp_path_factory):
    """A phantom whole heart (1.5 mm voxels, smoke meshing, 2.5 mm edges) with its long-axis warps."""
    from pathlib import Path

    from meshsar_builder.dataset.label_maps import read_label_map
    from meshsar_builder.dataset.sources import MMWHS_TABLE
    from meshsar_builder.geometry.landmarks import label_landmarks
    from meshsar_builder.geometry.meshing import labels_to_surface
    from meshsar_builder.geometry.phantom_heart import write_mmwhs_subject
    from meshsar_builder.geometry.remesh import RemeshParams
    from meshsar_builder.geometry.structures import STRUCTURES
    from meshsar_builder.pipeline.seeding import item_rng
    from tests.test_registration import long_axis_warps

    smoke = load(Path(__file__).resolve().parents[1] / "manifests" / "smoke.toml")
    path = write_mmwhs_subject(tmp_path_factory.mktemp("heart"), "ct_train_1001",
                               item_rng(0, "sources", "phantom_wh-ct_train_1001"), voxel_mm=(1.5, 1.5, 1.5))
    s = labels_to_surface(*read_label_map(path, MMWHS_TABLE), ["lv", "myo", "rv", "la", "ra", "aorta", "pa"],
                          smoke.meshing)
    verts, faces = remesh(s.verts, s.faces, RemeshParams(edge_mm=2.5))
    labels = transfer_labels(s.verts, s.labels, verts)
    marks = label_landmarks(verts, faces, labels)
    apex = marks.points(verts)[marks.keys.index("apex")]
    base = verts[labels > STRUCTURES["myo"]].mean(axis=0)  # rv, atria and vessels: the base side
    return verts, faces, labels, long_axis_warps(verts, apex, base)


@pytest.mark.parametrize("warp", ["twist", "shear", "bulge"])
def test_phantom_heart_known_warp_is_recovered_vertex_by_vertex(labelled_heart, warp):
    from tests.test_registration import assert_warp_recovered, recover_warp

    verts, faces, labels, warps = labelled_heart
    error, report = recover_warp(verts, faces, labels, 2000, warps[warp], 3.0)
    assert_warp_recovered(error, report)


def test_coarse_start_keeps_the_known_twist_correspondence_of_a_full_resolution_fit(labelled_heart):
    """Issue 32: the stiffest step on a coarse template (here 700 of 2,000 vertices) starts the
    rest; the twist is recovered as well as by the fit that runs every step at full resolution
    (measured 0.641 / 0.643 mm; the first two steps coarse: up to 0.09 mm worse at 6,000)."""
    import dataclasses

    from tests.test_registration import PARAMS, assert_warp_recovered, recover_warp

    verts, faces, labels, warps = labelled_heart
    full, full_report = recover_warp(verts, faces, labels, 2000, warps["twist"], 3.0,
                                     dataclasses.replace(PARAMS, coarse_steps=0))
    coarse, report = recover_warp(verts, faces, labels, 2000, warps["twist"], 3.0,
                                  dataclasses.replace(PARAMS, coarse_steps=1, coarse_vertices=700))
    assert "coarse" not in full_report["nricp"]
    assert report["nricp"]["coarse"]["used"] and report["nricp"]["steps_kept"] == len(PARAMS.stiffness)
    assert report["nricp"]["coarse"]["vertices"] <= 710
    assert_warp_recovered(coarse, report)
    assert coarse.mean() <= full.mean() + 0.03, (coarse.mean(), full.mean())


@pytest.fixture(scope="module")
def smoke_phantoms(tmp_path_factory):
    """The smoke recipe's 3 whole-heart subjects, remeshed as its stages do, and their volumes."""
    from pathlib import Path

    from meshsar_builder.dataset.label_maps import read_label_map
    from meshsar_builder.dataset.sources import MMWHS_TABLE
    from meshsar_builder.geometry.meshing import labels_to_surface
    from meshsar_builder.geometry.phantom_heart import write_mmwhs_subject
    from meshsar_builder.pipeline.seeding import item_rng

    smoke = load(Path(__file__).resolve().parents[1] / "manifests" / "smoke.toml")
    spec, surfaces = smoke.sources[0], []
    for n in range(spec.subjects):
        subject = f"ct_train_{1001 + n}"
        path = write_mmwhs_subject(tmp_path_factory.mktemp("smoke"), subject,
                                   item_rng(smoke.seed, "sources", f"{spec.name}-{subject}"), voxel_mm=spec.voxel_mm)
        s = labels_to_surface(*read_label_map(path, MMWHS_TABLE), list(spec.structures), smoke.meshing)
        v, f = remesh(s.verts, s.faces, smoke.remesh)
        surfaces.append((v, f, transfer_labels(s.verts, s.labels, v)))
    return smoke, surfaces


def test_groupwise_rounds_wash_out_the_seed_subject_and_the_model_ignores_subject_order(smoke_phantoms):
    """Issue 12: the final template hardly depends on which subject seeded it (surface to
    surface: the seeds' tessellations differ, so vertex to vertex is meaningless), and the
    model of the final fits is the same in any subject order (1e-6)."""
    from meshsar_builder.geometry.groupwise import register_groupwise
    from meshsar_builder.geometry.registration import surface_distances
    from meshsar_builder.geometry.ssm import build_model

    smoke, surfaces = smoke_phantoms
    params = smoke.registration
    finals, seeds = [], []
    for seed in (0, 2):
        v, f, labels = surfaces[seed]
        tv, tf = simplify(v, f, params.template_vertices)
        tl = transfer_labels(v, labels, tv)
        fits, templates, rounds = register_groupwise((tv, tf, tl), surfaces, params,
                                                     lambda r, i: np.random.default_rng(100 * r + i))
        assert len(rounds) == 3 and rounds[-1]["movement_mm"] < 1.0
        finals.append((templates[-1], tf))
        seeds.append((templates[0], tf))
        # The model of the same fits in another order: mean, modes (signs fixed) and variances.
        one = build_model(fits, tf, 1.0, reference=templates[-1])
        other = build_model(fits[[2, 0, 1]], tf, 1.0, reference=templates[-1])
        np.testing.assert_allclose(one.mean, other.mean, atol=1e-6)
        np.testing.assert_allclose(one.modes, other.modes, atol=1e-6)
        np.testing.assert_allclose(one.variances, other.variances, rtol=1e-6)

    def distance(a, b):
        to_b, to_a = surface_distances(*a, *b, 20000, np.random.default_rng(0))
        return 0.5 * (to_b.mean() + to_a.mean())

    # The two final templates, as they are (one canonical frame), against the two seeds (centred).
    final = distance(*finals)
    seed = distance(*[(v - (v.min(0) + v.max(0)) / 2, f) for v, f in seeds])
    assert final < SEED_TOLERANCE_MM and final < 0.2 * seed, (final, seed)
