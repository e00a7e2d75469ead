import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from meshsar_builder.geometry.ssm import (
    ShapeModel,
    SSMParams,
    build_model,
    compactness,
    generalisation,
    load_model,
    procrustes_align,
    rigid_fit,
    quality_report,
    sample,
    sample_valid,
    save_model,
    specificity_draws,
)
from meshsar_builder.pipeline.errors import MeshError

from .conftest import MANIFESTS

TRUE_VARIANCES = np.array([16.0, 4.0, 1.0])  # mm^2
N_SHAPES = 30


def base_mesh():
    sphere = trimesh.creation.icosphere(subdivisions=2)
    return sphere.vertices * (30.0, 22.0, 18.0), sphere.faces


def true_modes(base: np.ndarray) -> np.ndarray:
    """Three smooth orthonormal modes (3, n, 3), orthogonal to translations and rotations of base."""
    x, y, z = (base / 30.0).T
    zeros = np.zeros_like(x)
    fields = [np.c_[zeros, zeros, x**2], np.c_[y * z, zeros, zeros], np.c_[zeros, np.sin(3 * x), zeros]]
    centred = base - base.mean(axis=0)
    rigid = [np.tile(np.eye(3)[i], (len(base), 1)) for i in range(3)]
    rigid += [np.cross(np.eye(3)[i], centred) for i in range(3)]
    basis, _ = np.linalg.qr(np.stack([f.ravel() for f in rigid + fields], axis=1))
    return basis[:, 6:].T.reshape(3, len(base), 3)


@pytest.fixture(scope="module")
def training():
    """Shapes with exactly the true mode variances, each then moved rigidly (shape 0 stays put)."""
    base, faces = base_mesh()
    modes = true_modes(base)
    rng = np.random.default_rng(3)
    coeffs = rng.standard_normal((N_SHAPES, 3))
    coeffs -= coeffs.mean(axis=0)
    orthonormal, _ = np.linalg.qr(coeffs)
    coeffs = orthonormal * np.sqrt((N_SHAPES - 1) * TRUE_VARIANCES)
    shapes = base + np.tensordot(coeffs, modes, axes=1)
    rotations = Rotation.random(N_SHAPES, random_state=4).as_matrix()
    rotations[0] = np.eye(3)
    shifts = rng.normal(0.0, 20.0, (N_SHAPES, 3))
    shifts[0] = 0.0
    moved = np.einsum("sij,snj->sni", rotations, shapes) + shifts[:, None, :]
    return moved, faces, modes


@pytest.fixture(scope="module")
def model(training):
    shapes, faces, _ = training
    # Shape 0 is the unrotated one: as the reference (the template's role), it puts the model
    # in the frame of the true modes.
    return build_model(shapes, faces, variance=0.98, reference=shapes[0])


def test_known_modes_and_variances_are_recovered(model, training):
    _, _, modes = training
    assert len(model.variances) == 3
    np.testing.assert_allclose(model.variances, TRUE_VARIANCES, rtol=0.05)
    for found, truth in zip(model.modes, modes):
        assert abs(np.dot(found.ravel(), truth.ravel())) > 0.99
    assert compactness(model)[-1] == pytest.approx(1.0, abs=1e-3)
    assert np.all(np.diff(compactness(model)) > 0)


def test_variance_fraction_chooses_the_mode_count(training):
    shapes, faces, _ = training
    fractions = np.cumsum(TRUE_VARIANCES) / TRUE_VARIANCES.sum()  # 0.76, 0.95, 1.0
    assert len(build_model(shapes, faces, variance=fractions[0] - 0.01).variances) == 1
    assert len(build_model(shapes, faces, variance=fractions[1] - 0.01).variances) == 2


def test_model_round_trips_through_npz_without_pickles(model, tmp_path):
    path = tmp_path / "model.npz"
    save_model(path, model)
    with np.load(path, allow_pickle=False) as data:
        assert set(data.files) == {"mean", "modes", "variances", "faces", "total_variance", "labels"}
    loaded = load_model(path)
    for name in ("mean", "modes", "variances", "faces", "labels"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(model, name))
    assert loaded.total_variance == model.total_variance
    assert list(tmp_path.iterdir()) == [path]


def test_samples_are_seeded_and_truncated_at_three_sigma(model):
    coeffs_a, verts_a = sample(model, np.random.default_rng(11))
    coeffs_b, verts_b = sample(model, np.random.default_rng(11))
    assert coeffs_a.tobytes() == coeffs_b.tobytes() and verts_a.tobytes() == verts_b.tobytes()
    assert sample(model, np.random.default_rng(12))[0].tobytes() != coeffs_a.tobytes()
    rng = np.random.default_rng(5)
    standardised = np.stack([sample(model, rng)[0] for _ in range(2000)]) / np.sqrt(model.variances)
    assert np.abs(standardised).max() <= 3.0
    # The standard deviation of N(0, 1) truncated at +-3 is 0.9866.
    np.testing.assert_allclose(standardised.std(axis=0), 0.9866, rtol=0.05)
    np.testing.assert_allclose(verts_a, model.mean + np.tensordot(coeffs_a, model.modes, axes=1))


def test_sample_valid_accepts_clean_shapes_and_gives_up_on_broken_ones(model):
    params = SSMParams(max_redraws=2)
    coeffs, verts, redraws = sample_valid(model, np.random.default_rng(0), params)
    assert redraws == 0 and verts.shape == model.mean.shape
    pierced = model.mean.copy()
    pierced[np.argmax(pierced[:, 2])] = (0.0, 0.0, -25.0)
    broken = ShapeModel(pierced, model.modes * 1e-3, model.variances, model.faces, model.total_variance)
    with pytest.raises(MeshError, match="all 3 draws self-intersect"):
        sample_valid(broken, np.random.default_rng(0), params)


@settings(deadline=None, max_examples=10)
@given(seed=st.integers(0, 2**32 - 1), shift=st.tuples(*[st.floats(-100, 100)] * 3))
def test_procrustes_removes_rotation_and_translation_and_keeps_scale(seed, shift):
    base, _ = base_mesh()
    rotation = Rotation.random(random_state=seed).as_matrix()
    moved = base @ rotation.T + np.array(shift)
    aligned, mean = procrustes_align(np.stack([base, moved]), reference=base)
    centred = base - base.mean(axis=0)
    np.testing.assert_allclose(aligned[1], aligned[0], atol=1e-8)
    np.testing.assert_allclose(mean, centred, atol=1e-8)
    assert np.linalg.norm(aligned[1]) == pytest.approx(np.linalg.norm(centred), rel=1e-12)


def test_procrustes_keeps_size_differences():
    base, _ = base_mesh()
    aligned, _ = procrustes_align(np.stack([base, 1.5 * base @ Rotation.from_euler("z", 30, degrees=True).as_matrix().T]))
    sizes = np.linalg.norm(aligned - aligned.mean(axis=1, keepdims=True), axis=(1, 2))
    assert sizes[1] / sizes[0] == pytest.approx(1.5, rel=1e-9)


def _assert_same_model(a, b, atol=1e-6):
    np.testing.assert_allclose(a.mean, b.mean, atol=atol)
    np.testing.assert_allclose(a.variances, b.variances, rtol=atol)
    # Signs are fixed by convention, so the modes agree outright (the looser reading, up to
    # sign, would follow from it).
    np.testing.assert_allclose(a.modes, b.modes, atol=atol)
    assert a.total_variance == pytest.approx(b.total_variance, rel=atol)


@settings(deadline=None, max_examples=8)
@given(order=st.permutations(list(range(12))), with_reference=st.booleans())
def test_permuting_the_subjects_gives_the_same_model(training, order, with_reference):
    """Issue 12: mean, modes and variances do not depend on which subject comes first."""
    shapes, faces, _ = training
    shapes = shapes[:12]
    reference = shapes[5] if with_reference else None
    one = build_model(shapes, faces, variance=1.0, reference=reference)
    other = build_model(shapes[list(order)], faces, variance=1.0, reference=reference)
    _assert_same_model(one, other)


def test_without_a_reference_the_frame_is_the_population_pose_not_the_first_shape():
    """Subjects lie in one scanner frame but turned by up to ~10 degrees; the first one by 25.
    The model must sit in their common pose (the identity here), not the first subject's."""
    base, faces = base_mesh()
    rng = np.random.default_rng(7)
    turns = Rotation.from_rotvec(rng.normal(0.0, 0.08, (16, 3)))
    turns = Rotation.concatenate([Rotation.from_euler("z", 25, degrees=True), turns])
    stretch = 1.0 + rng.normal(0.0, 0.05, (len(turns), 3))  # shape changes along the base's own axes
    shapes = np.stack([t.apply(base * k) + rng.normal(0, 30, 3) for t, k in zip(turns, stretch)])
    mean = build_model(shapes, faces, variance=1.0).mean
    turned = np.degrees(Rotation.align_vectors(mean - mean.mean(0), base - base.mean(0))[0].magnitude())
    average = np.degrees(Rotation.concatenate(turns).mean().magnitude())
    assert turned == pytest.approx(average, abs=0.5) and turned < 5.0


def test_generalisation_drops_to_zero_with_the_true_mode_count(training):
    shapes, _, _ = training
    errors = generalisation(shapes[:12], max_modes=4)
    assert errors.shape == (4,)
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.02 and errors[3] == pytest.approx(errors[2], abs=1e-6)


def test_specificity_of_model_samples_is_small_and_reported(model, training):
    shapes, _, _ = training
    params = SSMParams(specificity_samples=20)
    distances, redraws = specificity_draws(model, shapes, np.random.default_rng(0), params, 20)
    mean_mm, std_mm = distances.mean(axis=1), distances.std(axis=1)
    # Samples lie in the training span; the nearest of 30 training shapes is a few mm off at most.
    assert mean_mm.shape == std_mm.shape == (3,)
    assert np.all((0.0 < mean_mm) & (mean_mm < 3.0)) and np.all(std_mm >= 0.0) and redraws >= 0
    report = quality_report(model, shapes[:10], np.random.default_rng(0), params)
    assert report["modes"] == 3 and len(report["generalisation_mm"]) == 3 and len(report["compactness"]) == 3
    assert len(report["specificity_curve_mm"]) == 3 and report["specificity_mm"] == report["specificity_curve_mm"][-1]
    assert report["specificity_draws"] == 20


def test_specificity_is_the_naive_nearest_training_distance_of_the_samplers_draws(model, training):
    """Reference: the same draws through sample_valid (same seed), nearest shape by a plain loop."""
    shapes, _, _ = training
    shapes = shapes[:6]
    params = SSMParams(specificity_samples=5)
    mean_mm = specificity_draws(model, shapes, np.random.default_rng(3), params, 5)[0].mean(axis=1)
    rng = np.random.default_rng(3)
    fitted = [rigid_fit(s, model.mean) for s in shapes]
    for j in range(1, len(model.variances) + 1):
        cut = ShapeModel(model.mean, model.modes[:j], model.variances[:j], model.faces, model.total_variance)
        scores = []
        for _ in range(params.specificity_samples):
            verts = sample_valid(cut, rng, params)[1]
            scores.append(min(float(np.mean([np.linalg.norm(v - t) for v, t in zip(verts, f)])) for f in fitted))
        assert mean_mm[j - 1] == pytest.approx(np.mean(scores), rel=1e-9)


@pytest.mark.parametrize(
    "field, value",
    [
        ("samples", 0),
        ("variance", 0.0),
        ("variance", 1.5),
        ("truncate_sigma", 0.0),
        ("max_redraws", -1),
        ("procrustes_iterations", 0),
        ("specificity_samples", 0),
        ("specificity_items", 0),
        ("samples_per_item", 0),
    ],
)
def test_params_reject_bad_values_naming_the_field(field, value):
    with pytest.raises(ValueError, match=f"^{field}: .*got {value}"):
        SSMParams(**{field: value})


def test_nearest_mean_distance_is_numpys_least_mean_norm():
    """The specificity's distance (one numba pass that stops a shape's sum once it passes the least so far)
    against numpy's mean vertex norm per shape and its minimum: the nearest shape first, last, and tied."""
    from meshsar_builder.geometry.ssm import nearest_mean_distance

    rng = np.random.default_rng(5)
    verts = rng.normal(0.0, 20.0, (500, 3))
    shapes = verts + rng.normal(0.0, 1.0, (6, 1, 1)) * rng.normal(0.0, 3.0, (6, 500, 3))
    for order in (np.arange(6), np.arange(6)[::-1], np.r_[0, 0, np.arange(1, 6)]):
        stack = np.ascontiguousarray(shapes[order])
        expected = np.linalg.norm(stack - verts, axis=2).mean(axis=1).min()
        assert nearest_mean_distance(stack, verts) == pytest.approx(expected, rel=1e-12)


def test_a_worker_builds_the_stage_model_once_for_the_same_inputs(training, tmp_path, monkeypatch):
    """stages/ssm.py: the items of one worker share the model of identical inputs (built once, read-only, equal
    to a fresh build); a changed input file is a new model."""
    import stages.ssm as stage
    from meshsar_builder.geometry import ssm as ssm_module
    from meshsar_builder.geometry.meshfile import write_ply

    shapes, faces, _ = training
    paths = []
    for k, verts in enumerate([shapes[0], *shapes[:8]]):
        paths.append(str(tmp_path / f"{k}.ply"))
        write_ply(paths[-1], verts, faces, np.zeros(len(verts), np.uint8))
    builds = []
    monkeypatch.setattr(stage, "build_model", lambda *a, **k: builds.append(1) or ssm_module.build_model(*a, **k))
    stage._built_model.cache_clear()
    inputs = tuple((p, stage.sha256_file(p)) for p in paths)
    first, again = stage._built_model(inputs, 0.98, 20), stage._built_model(inputs, 0.98, 20)
    assert again is first and len(builds) == 1
    model, kept = first
    assert not model.mean.flags.writeable and not model.modes.flags.writeable and not kept.flags.writeable
    fresh = ssm_module.build_model(shapes[:8], faces, 0.98, 20, labels=np.zeros(len(shapes[0]), np.uint8),
                                   reference=shapes[0])
    np.testing.assert_allclose(model.modes, fresh.modes, atol=1e-9)
    write_ply(paths[3], shapes[9], faces, np.zeros(len(shapes[9]), np.uint8))
    changed = tuple((p, stage.sha256_file(p)) for p in paths)
    assert stage._built_model(changed, 0.98, 20) is not first and len(builds) == 2
    stage._built_model.cache_clear()


def test_the_stage_lists_its_longest_items_first(tmp_path):
    """stages/ssm.py's plan: the specificity parts (most of the stage's time) before the model and the short
    sample parts, so that the sample parts even out two workers' ends."""
    import stages.ssm as stage
    from meshsar_builder.pipeline import recipe as R
    from meshsar_builder.pipeline.runner import Context, Results

    recipe = R.override(R.load(MANIFESTS / "smoke.toml"), "ssm", "samples_per_item", 2, "test")
    fits = {f"s{i}": {"fit": {}, "final": True, "subject": f"s{i}", "source": "x"} for i in range(3)}
    results = Results(done={"register": fits})
    ids = [item.id for item in stage.plan(Context(out=tmp_path, recipe=recipe), results)]
    parts = [f"specificity/{c}" for c in range(recipe.ssm.specificity_items)]
    assert ids == [*parts, "model", "samples/0", "samples/1"]


def test_a_registration_that_kept_fewer_than_two_fits_fails_the_model_saying_why(tmp_path):
    """The rounds stop when fewer than 2 fits are left, before a template, and a model needs 3: the ssm stage plans
    one item that fails naming the fits kept, not every item on a missing template file or the model's own check."""
    from types import SimpleNamespace

    from meshsar_builder.geometry.ssm import SSMParams
    from meshsar_builder.pipeline.runner import Context, Results
    from stages import ssm

    ctx = Context(out=tmp_path, recipe=SimpleNamespace(ssm=SSMParams(), seed=0))
    kept = {"round0/ct_1001": {"final": False, "fit": {}, "subject": "ct_1001", "source": "mmwhs"}}
    [item] = ssm.plan(ctx, Results(done={"register": kept}))
    with pytest.raises(MeshError, match=r"at least 3 registered subjects, and registration kept 1 \(round0/ct_1001\)"):
        ssm.run(ctx, item)
    final = {f"ct_{n}": {"final": True, "fit": {}, "subject": f"ct_{n}", "source": "mmwhs"} for n in (1001, 1002, 1003)}
    assert len(ssm.plan(ctx, Results(done={"register": final}))) > 1
    two = dict(list(final.items())[:2])  # the last round's fits, but too few for a model (_built_model's own test)
    [item] = ssm.plan(ctx, Results(done={"register": two}))
    with pytest.raises(MeshError, match=r"at least 3 registered subjects, and registration kept 2 \(ct_1001, ct_10"):
        ssm.run(ctx, item)
