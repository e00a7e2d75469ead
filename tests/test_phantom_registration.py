"""Registration of demo-resolution phantom hearts: accepted fits that keep structure labels."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from meshsar_builder.bench.suite import DEMO, demo_subject
from meshsar_builder.geometry.meshing import transfer_labels
from meshsar_builder.geometry.registration import accept, register
from meshsar_builder.geometry.remesh import remesh, simplify
from meshsar_builder.pipeline.errors import MeshError
from meshsar_builder.pipeline.recipe import load

pytestmark = pytest.mark.slow


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
        fitted, report = register(tv, tf, v, f, recipe.registration, np.random.default_rng(i), tl, labels)
        accept(report, recipe.registration)  # mean <= 0.5 mm, p95 <= 1.5 mm, no flips or self-intersections
        assert report["label_agreement"] >= 0.95, report["label_agreement"]


def test_every_phantom_full_whole_heart_subject_is_accepted(tmp_path):
    """Issue 16: all 20 whole-heart subjects of manifests/phantom_full.toml register (the stage's
    seeding and median template), at the smoke recipe's coarse resolution to stay quick."""
    from pathlib import Path

    from meshsar_builder.geometry.meshing import labels_to_surface
    from meshsar_builder.dataset.sources import MMWHS_TABLE, read_label_map
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
    rejected = {}
    for subject, (v, f, labels) in surfaces.items():
        _, report = register(tv, tf, v, f, params, item_rng(full.seed, "register", subject), tl, labels)
        try:
            accept(report, params)
        except MeshError as error:  # collect every rejection, then fail naming them all
            rejected[subject] = str(error)
    assert rejected == {}
