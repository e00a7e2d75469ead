"""Registration of demo-resolution phantom hearts: accepted fits that keep structure labels."""

from __future__ import annotations

import numpy as np
import pytest

from meshsar_builder.bench.suite import DEMO, demo_subject
from meshsar_builder.geometry.meshing import transfer_labels
from meshsar_builder.geometry.registration import accept, register
from meshsar_builder.geometry.remesh import remesh, simplify
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
