"""Registration that holds on real anatomy (issue 26): landmarks with a confidence, a robust
landmark check, acceptance that judges the landmark residual, a divergence monitor that stops
a runaway fit, and a groupwise template checked against the fits it averages."""

import dataclasses

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from meshsar_builder.geometry.groupwise import mean_template
from meshsar_builder.geometry.landmarks import label_landmarks
from meshsar_builder.geometry.nricp import nricp
from meshsar_builder.geometry.registration import _procrustes_many, accept, register, robust_landmarks
from meshsar_builder.geometry.registration_params import RegistrationParams
from meshsar_builder.geometry.structures import STRUCTURES
from meshsar_builder.pipeline.errors import MeshError

PARAMS = RegistrationParams(distance_samples=2000, template_vertices=500)
LV, MYO, RV = STRUCTURES["lv"], STRUCTURES["myo"], STRUCTURES["rv"]


def labelled(axes, cut_rv=0.3, cut_lv=0.6, subdivisions=4):
    """An ellipsoid: rv on one side (x > cut_rv * a), an lv cap on top (z > cut_lv * c), myo elsewhere."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    verts = sphere.vertices * axes
    labels = np.full(len(verts), MYO, np.uint8)
    labels[verts[:, 0] > cut_rv * axes[0]] = RV
    labels[verts[:, 2] > cut_lv * axes[2]] = LV
    return verts, np.asarray(sphere.faces), labels


def test_apex_is_kept_on_an_elongated_ventricle_along_its_axis_and_dropped_on_a_round_one():
    # Long along z, base (rv) on top: the farthest ventricle point is the bottom tip, on the long axis.
    verts, faces, _ = labelled((20.0, 20.0, 45.0))
    labels = np.where(verts[:, 2] > 25.0, RV, MYO).astype(np.uint8)
    marks = label_landmarks(verts, faces, labels)
    assert "apex" in marks.keys and marks.confidence[marks.keys.index("apex")] >= 1
    np.testing.assert_allclose(marks.points(verts)[marks.keys.index("apex")], [0, 0, -45], atol=2.0)  # the mean of a 2 mm band
    # A round ventricle with the "base" beside it (an atrium): no apex, and why.
    verts, faces, labels = labelled((30.0, 30.0, 30.0))
    labels[labels == RV] = STRUCTURES["la"]
    marks = label_landmarks(verts, faces, labels)
    assert "apex" not in marks.keys
    assert dict(marks.dropped)["apex"].startswith("ill-defined: ventricle elongation 1.")


@pytest.mark.parametrize("turn", [(0, 0, 0), (40, -25, 70)])
def test_a_short_axis_maps_apex_lies_along_its_basal_lv_disc(turn):
    """Biventricular (lv, myo, rv only): the lv shows as its basal cut, whose inward normal is the
    long axis, whatever the RV beside it; the apex is the far end along it."""
    verts, faces, labels = labelled((25.0, 25.0, 50.0), cut_rv=0.4, cut_lv=0.8)
    rotation = Rotation.from_euler("xyz", turn, degrees=True).as_matrix()
    marks = label_landmarks(verts @ rotation.T, faces, labels)
    assert "apex" in marks.keys and marks.confidence[marks.keys.index("apex")] >= 1
    np.testing.assert_allclose(marks.points(verts @ rotation.T)[marks.keys.index("apex")],
                               rotation @ [0, 0, -50], atol=2.0)
    # A flat ventricle below its disc (0.58 disc radii long): no apex, and why.
    verts, faces, labels = labelled((40.0, 40.0, 14.0), cut_rv=0.5, cut_lv=0.2)
    marks = label_landmarks(verts, faces, labels)
    assert "apex" not in marks.keys
    assert "ventricle length over disc radius" in dict(marks.dropped)["apex"]


def test_a_short_junction_gives_no_ring_and_says_so():
    verts, faces, labels = labelled((30.0, 30.0, 30.0), cut_rv=0.996, subdivisions=5)  # a ~17 mm junction
    marks = label_landmarks(verts, faces, labels, min_vertices=3)
    dropped = dict(marks.dropped)
    assert "ring:myo-rv" not in marks.keys
    assert "ring:myo-rv" in dropped and "mm long < 20.0 mm" in dropped["ring:myo-rv"]
    assert "ring:lv-myo" in marks.keys  # long enough (~ 2 pi 24 mm)


def test_robust_similarity_outvotes_a_disagreeing_landmark():
    rng = np.random.default_rng(3)
    moving = rng.normal(0.0, 30.0, (8, 3))
    rotation = Rotation.from_euler("xyz", [35, -20, 50], degrees=True).as_matrix()
    fixed = 1.15 * moving @ rotation.T + (5.0, -3.0, 8.0) + rng.normal(0.0, 0.3, (8, 3))
    fixed[5] += (40.0, -10.0, 25.0)  # an "apex" found at the wrong end
    inliers, residual = robust_landmarks(moving, fixed, True, 5.0)
    assert inliers.tolist() == [True] * 5 + [False] + [True] * 2
    assert residual[5] > 40 and residual[inliers].max() < 1.5
    # Fewer than 4: nothing to outvote.
    assert robust_landmarks(moving[:3], fixed[:3], True, 5.0)[0].all()


@pytest.mark.parametrize("similarity", [True, False])
def test_batched_procrustes_matches_trimesh_set_by_set(similarity):
    """The LMedS's batched fits against trimesh's procrustes one set at a time (its formula), a set whose
    points coincide included (with a scale there is no fit: NaN, where trimesh divides by zero)."""
    rng = np.random.default_rng(11)
    moving = rng.normal(0.0, 25.0, (40, 3, 3))
    fixed = np.stack([1.1 * m @ Rotation.random(random_state=i).as_matrix().T + rng.normal(0.0, 9.0, 3)
                      + rng.normal(0.0, 2.0, (3, 3)) for i, m in enumerate(moving)])
    moving[7] = moving[7, :1]  # three coincident points
    matrices = _procrustes_many(moving, fixed, similarity)
    for i, (m, f) in enumerate(zip(moving, fixed)):
        if i == 7 and similarity:
            assert np.isnan(matrices[i]).all()
            continue
        expected = trimesh.registration.procrustes(m, f, reflection=False, scale=similarity, return_cost=False)
        np.testing.assert_allclose(matrices[i], expected, rtol=0, atol=1e-12)
        assert np.linalg.det(matrices[i][:3, :3]) > 0  # a rotation, never a reflection


def test_accept_names_a_divergence_twice_and_the_landmarks_a_fit_moved_away():
    ok = {"mean_mm": 0.1, "p95_mm": 0.3, "flipped_faces": 0, "self_intersections": 0}
    went = {"reason": "surface distance grew", "step": 1, "iteration": 3, "mean_mm": 12.0, "least_mm": 1.0,
            "flipped_faces": 40}
    nricp_summary = {"diverged": went, "first_attempt": {"diverged": {**went, "reason": "faces flipped in numbers"}}}
    with pytest.raises(MeshError, match="diverged twice: faces flipped in numbers at stiffness step 2, iteration 4 "
                                        r"\(mean distance 12.00 mm, least 1.00 mm, 40 faces flipped\); then surface"):
        accept({**ok, "nricp": nricp_summary}, PARAMS)
    # Faces flipped in numbers before the fit's first measure: no least distance yet (JSON holds no infinity).
    first = {"diverged": {**went, "reason": "faces flipped in numbers", "step": 0, "iteration": 0, "least_mm": None}}
    with pytest.raises(MeshError, match=r"iteration 1 \(mean distance 12.00 mm, least none yet, 40 faces flipped\)"):
        accept({**ok, "nricp": {"diverged": went, "first_attempt": first}}, PARAMS)
    moved = {**ok, "landmark_error_mm": 6.0, "landmark_start_error_mm": 2.0, "landmark_offenders": ["apex"],
             "landmark_retry": {"landmark_offenders": ["apex", "centroid:lv"]}}
    with pytest.raises(MeshError, match=r"landmark error 6.00 mm > the robust start's 2.00 mm \+ 2.0 mm "
                                        r"\(landmark_tolerance_mm\), after a retry without apex, centroid:lv; "
                                        "moved away: apex"):
        accept(moved, PARAMS)


def test_a_runaway_start_is_stopped_at_once_and_the_fit_retried_from_the_similarity_start():
    verts, faces, labels = labelled((30.0, 24.0, 20.0), subdivisions=3)
    subject = verts * (1.05, 0.97, 1.02)
    # A start thrown 300 mm away and scrambled, as a spline through coplanar landmarks did.
    wild = verts + np.random.default_rng(0).normal(0.0, 1.0, verts.shape) * 300.0
    fitted, summary = nricp(verts, faces, subject, faces, PARAMS, (labels, labels), None, wild)
    assert summary["diverged"]["step"] == 0 and summary["diverged"]["iteration"] == 0
    assert summary["steps_kept"] == 0
    np.testing.assert_allclose(fitted, verts, atol=1e-9)  # the last fold-free state: the pre-aligned template
    # A start that grows the distance partway (too soft a schedule would) is stopped too.
    growth = dataclasses.replace(PARAMS, divergence_growth=1.0001, divergence_flipped=1.0)
    _, summary = nricp(verts, faces, subject + 0.0, faces, growth, (labels, labels), None, verts + (0.0, 0.0, 9.0))
    assert "diverged" not in summary or summary["diverged"]["reason"] == "surface distance grew"


def test_register_reports_landmarks_and_refuses_a_wild_spline_start():
    verts, faces, labels = labelled((30.0, 24.0, 20.0), subdivisions=3)
    rotation = Rotation.from_euler("z", 40, degrees=True).as_matrix()
    subject = (verts * (1.1, 0.9, 1.0)) @ rotation.T + (4.0, 0.0, -2.0)
    fitted, report = register(verts, faces, subject, faces, PARAMS, np.random.default_rng(0), labels, labels)
    accept(report, PARAMS)
    assert "apex" in report["landmarks"]  # along the axis of its lv cap, the basal disc
    assert report["landmark_error_mm"] <= report["landmark_start_error_mm"] + PARAMS.landmark_tolerance_mm
    assert set(report["landmark_confidence"]) == set(report["landmarks"])


def test_the_groupwise_template_leaves_out_a_fit_far_from_the_others():
    sphere = trimesh.creation.icosphere(subdivisions=3)
    base, faces = sphere.vertices * (30.0, 22.0, 18.0), np.asarray(sphere.faces)
    rng = np.random.default_rng(0)
    fits = [base * (1 + rng.normal(0, 0.03, 3)) for _ in range(5)]
    runaway = base.copy()
    runaway[: len(base) // 2] *= 4.0  # a diverged fit: half of it blown out
    shapes = np.stack([*fits, runaway])
    _, plain = mean_template(shapes, faces, base, 10)
    assert plain["movement_mm"] > 5.0  # the runaway drags the plain mean
    verts, report = mean_template(shapes, faces, base, 10, max_distance_mm=10.0)
    assert report["left_out"] == [5] and report["movement_mm"] < 2.0
    assert max(report["distance_to_fits_mm"][:5]) < 2.0 and report["distance_to_fits_mm"][5] > 10.0
    with pytest.raises(MeshError, match="6 of 6 fits lie farther than 0.01 mm"):
        mean_template(shapes, faces, base, 10, max_distance_mm=0.01)


@pytest.mark.parametrize("field, value", [("divergence_growth", 1.0), ("divergence_flipped", 0.0),
                                          ("retry_stiffening", 0.5), ("groupwise_max_distance_mm", 0.0),
                                          ("landmark_outlier_mm", 0.0), ("landmark_tolerance_mm", -1.0),
                                          ("frame_steps", 0), ("frame_steps", 6), ("ring_points", -1),
                                          ("frame_ring_points", -1), ("frame_min_label_agreement", 1.5)])
def test_new_params_reject_bad_values_naming_the_field(field, value):
    with pytest.raises(ValueError, match=f"^{field}: "):
        RegistrationParams(**{field: value})


def test_a_fit_the_fold_guard_stopped_early_is_retried_stiffer_and_the_better_kept(monkeypatch):
    import meshsar_builder.geometry.registration as registration

    verts, faces, labels = labelled((30.0, 24.0, 20.0), subdivisions=3)
    calls = []

    def fake_nricp(aligned, faces_, subject_verts, subject_faces, params, labels_=None, landmarks=None, start=None):
        calls.append((params.stiffness, landmarks is None and start is None))
        steps = len(params.stiffness)
        kept = 1 if len(calls) == 1 else steps  # the first attempt stops at step 1, the retry runs through
        return aligned, {"steps_kept": kept, "steps": steps, "fold_repeats": 7, "stiffened_vertices": 9}

    monkeypatch.setattr(registration, "nricp", fake_nricp)
    _, report = register(verts, faces, verts * 1.02, faces, PARAMS, np.random.default_rng(0), labels, labels)
    assert len(calls) == 2 and calls[1][1]  # the retry: no spline start, no landmark term
    assert calls[1][0] == tuple(4 * a for a in PARAMS.stiffness) + PARAMS.stiffness[-1:]
    assert report["nricp"]["steps_kept"] == 6 and report["nricp"]["first_attempt"]["steps_kept"] == 1
    # A retry that fares worse than a first attempt that did not diverge is not kept.
    calls.clear()

    def worse_retry(aligned, faces_, subject_verts, subject_faces, params, labels_=None, landmarks=None, start=None):
        calls.append(1)
        return aligned, {"steps_kept": 2 if len(calls) == 1 else 0, "steps": len(params.stiffness), "fold_repeats": 7,
                         "stiffened_vertices": 9}

    monkeypatch.setattr(registration, "nricp", worse_retry)
    _, report = register(verts, faces, verts * 1.02, faces, PARAMS, np.random.default_rng(0), labels, labels)
    assert report["nricp"]["steps_kept"] == 2 and report["nricp"]["retry_attempt"]["steps_kept"] == 0
    # Both stopped early by the fold guard: the one closer to the subject is kept (a real ACDC
    # ventricle: first attempt 0.74 mm, its retry 0.25 mm).
    for retry_closer in (True, False):
        calls.clear()

        def both_stopped(aligned, faces_, subject_verts, subject_faces, params, labels_=None, landmarks=None,
                         start=None):
            calls.append(1)
            off = (len(calls) == 1) == retry_closer  # this attempt ends 3 mm out
            fit = aligned + 3.0 * (aligned - aligned.mean(axis=0)) / np.linalg.norm(aligned - aligned.mean(axis=0),
                                                                                     axis=1, keepdims=True) * off
            return fit, {"steps_kept": 3 if len(calls) == 1 else 4, "steps": len(params.stiffness), "fold_repeats": 7,
                         "stiffened_vertices": 9}

        monkeypatch.setattr(registration, "nricp", both_stopped)
        _, report = register(verts, faces, verts * 1.02, faces, PARAMS, np.random.default_rng(0), labels, labels)
        assert report["mean_mm"] < 1.0
        if retry_closer:
            assert report["nricp"]["steps_kept"] == 4 and report["nricp"]["first_attempt"]["steps_kept"] == 3
        else:
            assert report["nricp"]["steps_kept"] == 3 and report["nricp"]["retry_attempt"]["steps_kept"] == 4


def test_a_step_that_folds_keeps_its_longest_fold_free_part():
    """_fold_free_part halves a folding step until no face turns over or crosses another: one
    vertex of a sphere (radius 10 mm) pushed 100 mm down pierces the far side; an eighth of
    the way (12.5 mm, a dimple) does not, a quarter (25 mm) does."""
    from meshsar_builder.geometry.nricp import _AmbergSystem, _bad_faces, _fold_free_part

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=10.0)
    verts, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    system = _AmbergSystem(verts, faces, gamma=1.0)
    x = system.identity()
    x_step = x.copy()
    top = int(np.argmax(verts[:, 2]))
    x_step.reshape(system.n, 4, 3)[top, 3] = (0.0, 0.0, -100.0)
    assert _bad_faces(verts, system.apply(x_step), faces).any()
    blend, t = _fold_free_part(system, verts, faces, x, x_step)
    assert t == 0.125
    assert not _bad_faces(verts, system.apply(blend), faces).any()
    np.testing.assert_allclose(system.apply(blend)[top], verts[top] + (0.0, 0.0, -12.5), atol=1e-9)
    assert _bad_faces(verts, system.apply(x + 0.25 * (x_step - x)), faces).any()
    # A step that folds at every halving is kept not at all.
    x_step.reshape(system.n, 4, 3)[top, 3] = (0.0, 0.0, -1e4)
    blend, t = _fold_free_part(system, verts, faces, x, x_step)
    assert t == 0 and np.array_equal(blend, x)


def test_a_fit_whose_steps_fold_keeps_their_fold_free_parts_and_goes_on(monkeypatch):
    """nricp keeps the fold-free part of each step that folds past its repeats and runs on.
    A stand-in fold, any face with a vertex moved more than a tenth of the radius (4 mm), makes
    every step toward a sphere 10 mm larger fold: the fit still moves out, never past 4 mm, and
    reports the parts it kept. Ending the fit at the first folding step left it where it began."""
    import meshsar_builder.geometry.nricp as N

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=40.0)
    verts, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    real = N._bad_faces

    def moved_far(aligned, fit, faces_):  # in nricp's own units: scale-free, as a radius fraction
        radius = np.linalg.norm(aligned - aligned.mean(axis=0), axis=1)
        return real(aligned, fit, faces_) | (np.linalg.norm(fit - aligned, axis=1) > 0.1 * radius)[faces_].any(axis=1)

    monkeypatch.setattr(N, "_bad_faces", moved_far)
    params = RegistrationParams(coarse_steps=0, fold_retries=1)
    fitted, summary = N.nricp(verts, faces, verts * 1.25, faces, params)
    moved = np.linalg.norm(fitted - verts, axis=1)
    assert moved.max() <= 4.0 + 1e-9 and moved.mean() > 2.0
    assert summary["partial_steps"] and summary["partial_steps"][0] > 0
