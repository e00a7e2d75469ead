"""Groupwise template (issue 12): the Procrustes mean of the fits, clean, in a canonical frame."""

import dataclasses

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from meshsar_builder.geometry.groupwise import bbox_centred, final_round, mean_template, movement, taubin
from meshsar_builder.geometry.intersections import self_intersecting_faces
from meshsar_builder.geometry.measures import flipped_faces, unique_edges
from meshsar_builder.geometry.registration_params import RegistrationParams
from meshsar_builder.geometry.ssm import population_pose, rigid_fit
from meshsar_builder.pipeline.errors import MeshError


def ellipsoid():
    sphere = trimesh.creation.icosphere(subdivisions=3)
    return sphere.vertices * (30.0, 22.0, 18.0), np.asarray(sphere.faces)


def subjects(count: int, seed: int, turn_rad: float = 0.1):
    """Smoothly varied ellipsoids (per-axis stretch, a bend), each turned a little and shifted."""
    base, faces = ellipsoid()
    rng = np.random.default_rng(seed)
    shapes = []
    for _ in range(count):
        stretch = 1.0 + rng.normal(0.0, 0.06, 3)
        bend = rng.normal(0.0, 0.004)
        shape = base * stretch + np.c_[np.zeros(len(base)), np.zeros(len(base)), bend * base[:, 0] ** 2]
        turn = Rotation.from_rotvec(rng.normal(0.0, turn_rad, 3))
        shapes.append(turn.apply(shape) + rng.normal(0.0, 25.0, 3))
    return np.stack(shapes), faces, base


def test_the_template_is_the_procrustes_mean_in_the_population_pose_centred_on_its_box():
    shapes, faces, base = subjects(10, seed=1)
    verts, report = mean_template(shapes, faces, shapes[0], max_smoothing=10)
    assert report["smoothing_steps"] == 0 and report["self_intersections"] == report["flipped_faces"] == 0
    np.testing.assert_allclose(verts.min(axis=0) + verts.max(axis=0), 0.0, atol=1e-9)
    # The pose: rotating it any further only moves it away from the subjects as they lie.
    pose = population_pose(shapes)
    assert np.linalg.norm(rigid_fit(verts, pose) - (verts - verts.mean(axis=0) + pose.mean(axis=0))) < 1e-6
    # The shape: each subject's stretch averaged, so the mean is close to the plain base.
    assert movement(base, verts)[0] < 1.0
    assert report["movement_mm"] == pytest.approx(movement(shapes[0], verts)[0])
    assert report["subjects"] == 10


@settings(deadline=None, max_examples=6)
@given(order=st.permutations(list(range(8))), first=st.integers(0, 7))
def test_the_template_does_not_depend_on_the_order_of_the_subjects(order, first):
    shapes, faces, _ = subjects(8, seed=2, turn_rad=0.2)
    one, _ = mean_template(shapes, faces, shapes[0], max_smoothing=10)
    # Another order, and another previous template (only the movement report depends on it).
    other, _ = mean_template(shapes[list(order)], faces, shapes[first], max_smoothing=10)
    np.testing.assert_allclose(one, other, atol=1e-6)


def test_a_folded_mean_is_smoothed_clean_or_the_round_fails_naming_it():
    """Every fit drags one vertex 14 mm sideways, past its neighbours (its faces turn over and
    cut others): the mean has the fold too; Taubin steps undo it, and with none allowed the
    round fails."""
    shapes, faces, _ = subjects(6, seed=3)
    shapes = np.stack([rigid_fit(s, shapes[0]) for s in shapes])
    top = int(np.argmax(shapes[0][:, 2]))
    dented = shapes.copy()
    dented[:, top, 0] += 14.0
    assert flipped_faces(shapes[0], dented[0], faces).any() and self_intersecting_faces(dented[0], faces).any()
    verts, report = mean_template(dented, faces, shapes[0], max_smoothing=10)
    assert report["flipped_faces"] > 0 and report["self_intersections"] > 0 and 1 <= report["smoothing_steps"] <= 10
    assert not flipped_faces(rigid_fit(shapes[0], verts), verts, faces).any()
    assert not self_intersecting_faces(verts, faces).any()
    with pytest.raises(MeshError, match=r"groupwise template: \d+ self-intersecting and \d+ flipped faces remain after 0 Taubin"):
        mean_template(dented, faces, shapes[0], max_smoothing=0)


def test_taubin_barely_shrinks_and_keeps_the_box_centred_template_put():
    verts, faces = ellipsoid()
    smoothed = taubin(verts, faces, 10)
    volume = trimesh.Trimesh(verts, faces).volume
    assert trimesh.Trimesh(smoothed, faces).volume == pytest.approx(volume, rel=0.01)
    np.testing.assert_allclose(bbox_centred(verts + 5.0), verts, atol=1e-9)


def test_fewer_than_two_fits_is_refused():
    shapes, faces, _ = subjects(1, seed=4)
    with pytest.raises(MeshError, match="at least 2 subjects, got 1"):
        mean_template(shapes, faces, shapes[0], max_smoothing=10)


@pytest.mark.parametrize(
    "rounds, round_, moved, last",
    [
        (0, 0, None, True),  # groupwise off: the reference subject's fits are the last
        (2, 0, None, False),
        (2, 1, 3.0, False),
        (2, 1, 0.4, True),  # converged: the template moved < 0.5 mm
        (2, 2, 3.0, True),  # the round limit
        (3, 2, 0.6, False),
    ],
)
def test_the_last_round_is_the_limit_or_the_first_converged_one(rounds, round_, moved, last):
    params = dataclasses.replace(RegistrationParams(), groupwise_rounds=rounds)
    assert final_round(round_, moved, params) is last


@settings(max_examples=60, deadline=None)
@given(faces=st.lists(st.lists(st.integers(0, 40), min_size=3, max_size=3), max_size=60),
       dtype=st.sampled_from([np.int32, np.int64]))
def test_unique_edges_are_the_rows_numpy_finds(faces, dtype):
    """The int64-key unique against np.unique over rows: the same edges, order and dtype (an empty mesh too)."""
    faces = np.array(faces, dtype=dtype).reshape(-1, 3)
    rows = np.unique(np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    got = unique_edges(faces)
    assert got.dtype == faces.dtype and got.shape == rows.shape and np.array_equal(got, rows)


def test_a_rounds_fits_are_costed_by_the_same_subjects_fits_in_the_round_before(tmp_path, monkeypatch):
    """The register stage's items carry the subject's fit time of the previous round as their cost (the pool starts
    the costliest first, runner.Item.cost); round 0 has none to go by."""
    from types import SimpleNamespace

    from meshsar_builder.pipeline.runner import Context, Results
    from stages import register

    monkeypatch.setattr(register, "seed_template", lambda *args: "template-0.ply")
    monkeypatch.setattr(register, "groupwise_template", lambda folder, round_, *args: (f"template-{round_}.ply", 2.0))
    ctx = Context(out=tmp_path, recipe=SimpleNamespace(registration=RegistrationParams()))
    subject = {"use": "ssm", "source": "s", "subject": "x", "frame": None, "phase": "", "provenance": "phantom"}
    results = Results(done={"remesh": {name: subject for name in ("a", "b", "c")}})
    assert [it.cost for it in register.plan(ctx, results)] == [0.0, 0.0, 0.0]
    results.done["register"] = {f"round0/{name}": {"item": f"round0/{name}", "seconds": s}
                                for name, s in (("a", 2.5), ("b", 1.25), ("c", 4.0))}
    results.passes["register"] = 1
    items = register.plan(ctx, results)
    assert [(it.id, it.cost) for it in items] == [("round1/a", 2.5), ("round1/b", 1.25), ("round1/c", 4.0)]
