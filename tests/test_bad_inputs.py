"""The bad-input corpus (tests/data/bad/, written by tests/data/make_bad.py): each file fails by name."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from meshsar_builder.dataset.sources import MMWHS_TABLE, read_label_map
from meshsar_builder.geometry.meshfile import read_ply
from meshsar_builder.pipeline import recipe as R
from meshsar_builder.pipeline.errors import InputError, RecipeError
from meshsar_builder.pipeline.runner import build

from .conftest import ball_volume, save_nifti

BAD = Path(__file__).parent / "data" / "bad"

NIFTI = {
    "truncated_label.nii.gz": "not a readable NIfTI",
    "nan_affine_label.nii": "affine is missing, non-finite or singular",
    "singular_affine_label.nii": "affine is missing, non-finite or singular",
    "image_2d_label.nii.gz": "must be 3-D",
    "image_5d_label.nii.gz": "must be 3-D",
    "float_labels_label.nii.gz": "non-integer values",
    "labels_absent_label.nii.gz": r"none of the labels \[205, 420",
    "huge_declared_size_label.nii": "implausible image size",
}
RECIPES = {
    "recipe_wrong_types.toml": "seed: expected an integer, got 'zero'",
    "recipe_unknown_key.toml": r"\[meshing\]: unknown key 'colour'",
    "recipe_negative_spacing.toml": r"\[meshing\] spacing_mm: must be > 0",
    "recipe_zero_samples.toml": r"\[ssm\] samples: must be >= 1",
    "recipe_unknown_view.toml": r"\[radar\] views: unknown view 'dorsal'",
}


def test_corpus_is_complete_and_reproducible(tmp_path, monkeypatch):
    from .data import make_bad

    assert {p.name for p in BAD.iterdir()} == {*NIFTI, *RECIPES, "nan_vertices.ply"}
    monkeypatch.setattr(make_bad, "BAD", tmp_path)
    make_bad.main()
    for p in BAD.iterdir():
        assert (tmp_path / p.name).read_bytes() == p.read_bytes(), p.name


@pytest.mark.parametrize("name", sorted(NIFTI))
def test_bad_nifti_is_named(name):
    with pytest.raises(InputError, match=NIFTI[name]) as err:
        read_label_map(BAD / name, MMWHS_TABLE)
    assert str(err.value).startswith(str(BAD / name))


def test_nan_vertices_are_named():
    with pytest.raises(InputError, match="nan_vertices.ply: mesh has NaN or infinite vertex coordinates"):
        read_ply(BAD / "nan_vertices.ply")


@pytest.mark.parametrize("name", sorted(RECIPES))
def test_bad_recipe_is_named(name):
    with pytest.raises(RecipeError, match=RECIPES[name]) as err:
        R.load(BAD / name)
    assert str(err.value).startswith(str(BAD / name))


def test_a_build_over_the_corpus_reports_each_file_and_meshes_the_rest(tmp_path, tmp_recipe):
    data = tmp_path / "data"
    data.mkdir()
    for name in NIFTI:
        shutil.copy(BAD / name, data / name)
    mask, affine = ball_volume((30, 30, 30), (1, 1, 1), 9)
    save_nifti(data / "good_label.nii.gz", mask.astype(np.int16) * 500, affine)
    recipe = tmp_recipe(f'name = "corpus"\n[[sources]]\nkind = "nifti"\npath = "{data}"\nlabels = {{ lv = 500 }}\n')
    results = build(R.load(recipe), tmp_path / "out", until="meshes")
    failed = {f["item"]: f["message"] for f in json.loads((tmp_path / "out" / "failures.json").read_text())}
    assert len(failed) == len(NIFTI) == len(results.failures)
    for name in NIFTI:
        (message,) = [m for m in failed.values() if m.startswith(str(data / name) + ":")]
        assert message
    assert [p.name for p in (tmp_path / "out" / "meshes").glob("*.ply")] == ["nifti-good_label.ply"]
