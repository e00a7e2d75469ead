"""The bad-input corpus (tests/data/bad/, written by tests/data/make_bad.py): each file fails by name."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from meshsar_builder.dataset.label_maps import InputWarning, read_label_map
from meshsar_builder.dataset.sources import MMWHS_TABLE, index_acdc, index_nifti
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
# Usable files the loader warns about (message naming the file), and what it then reads.
WARNED = {
    "no_affine_label.nii": "neither sform nor qform is set",
    "unmapped_values_label.nii.gz": r"label values with no mapping, read as background: 7 \(32 voxels\)",
}
OTHER = {"nan_vertices.ply", "float_noise_label.nii.gz", "ct_image.nii.gz", "Info_no_NbFrame.cfg"}
RECIPES = {
    "recipe_wrong_types.toml": "seed: expected an integer, got 'zero'",
    "recipe_unknown_key.toml": r"\[meshing\]: unknown key 'colour'",
    "recipe_negative_spacing.toml": r"\[meshing\] spacing_mm: must be > 0",
    "recipe_zero_samples.toml": r"\[ssm\] samples: must be >= 1",
    "recipe_unknown_view.toml": r"\[radar\] views: unknown view 'dorsal'",
}


def test_corpus_is_complete_and_reproducible(tmp_path, monkeypatch):
    from .data import make_bad

    assert {p.name for p in BAD.iterdir()} == {*NIFTI, *RECIPES, *WARNED, *OTHER}
    monkeypatch.setattr(make_bad, "BAD", tmp_path)
    make_bad.main()
    for p in BAD.iterdir():
        assert (tmp_path / p.name).read_bytes() == p.read_bytes(), p.name


@pytest.mark.parametrize("name", sorted(NIFTI))
def test_bad_nifti_is_named(name):
    with pytest.raises(InputError, match=NIFTI[name]) as err:
        read_label_map(BAD / name, MMWHS_TABLE)
    assert str(err.value).startswith(str(BAD / name))


@pytest.mark.parametrize("name", sorted(WARNED))
def test_usable_file_warns_by_name(name):
    with pytest.warns(InputWarning, match=WARNED[name]) as caught:
        labels, _ = read_label_map(BAD / name, MMWHS_TABLE)
    assert all(str(w.message).startswith(str(BAD / name)) for w in caught)
    # 500 -> lv everywhere it was written; 7 (unmapped) -> background
    assert (labels > 0).sum() == (32 if "unmapped" in name else 64)


def test_missing_affine_is_an_error_when_required():
    with pytest.raises(InputError, match=r"no_affine_label.nii: neither sform nor qform .*require_affine = true"):
        read_label_map(BAD / "no_affine_label.nii", MMWHS_TABLE, require_affine=True)


def test_float_labels_within_tolerance_are_rounded():
    noisy, affine = read_label_map(BAD / "float_noise_label.nii.gz", MMWHS_TABLE)
    exact = np.zeros((8, 8, 8), np.uint8)
    exact[2:6, 2:6, 2:6] = noisy[3, 3, 3]
    assert noisy[3, 3, 3] > 0 and np.array_equal(noisy, exact)


def test_index_skips_an_intensity_image_by_content_or_by_pattern(tmp_path):
    shutil.copy(BAD / "ct_image.nii.gz", tmp_path / "ct_image.nii.gz")
    shutil.copy(BAD / "unmapped_values_label.nii.gz", tmp_path / "case_label.nii.gz")
    with pytest.warns(InputWarning, match=r"skipped 1 file\(s\) that are not label maps: ct_image.nii.gz \(512 distinct values"):
        (item,) = index_nifti(tmp_path, "own", {"lv": 500})
    assert item.subject == "case_label"
    with pytest.warns(InputWarning, match=r"ct_image.nii.gz \(name does not match '\*_label.nii.gz'\)"):
        (item,) = index_nifti(tmp_path, "own", {"lv": 500}, pattern="*_label.nii.gz")
    assert item.subject == "case_label"
    (tmp_path / "case_label.nii.gz").unlink()
    with pytest.warns(InputWarning), pytest.raises(InputError, match=r"none of the 1 \*.nii / \*.nii.gz files is a label map"):
        index_nifti(tmp_path, "own", {"lv": 500})


def test_acdc_without_nbframe_leaves_only_cycle_fraction_unknown(tmp_path):
    pdir = tmp_path / "patient001"
    pdir.mkdir()
    shutil.copy(BAD / "Info_no_NbFrame.cfg", pdir / "Info.cfg")
    for f in (1, 5):
        shutil.copy(BAD / "unmapped_values_label.nii.gz", pdir / f"patient001_frame{f:02d}_gt.nii.gz")
    with pytest.warns(InputWarning, match=r"patient001/Info.cfg: no 'NbFrame' in Info.cfg; cycle_fraction left unknown"):
        items = index_acdc(tmp_path, "acdc")
    assert [(i.frame, i.phase, i.cycle_fraction) for i in items] == [(1, "ED", None), (5, "ES", None)]


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
    save_nifti(data / "extra_label.nii.gz", np.where(mask, 500, 9).astype(np.int16), affine)
    shutil.copy(BAD / "ct_image.nii.gz", data / "ct_image.nii.gz")
    recipe = tmp_recipe(f'name = "corpus"\n[[sources]]\nkind = "nifti"\npath = "{data}"\nlabels = {{ lv = 500 }}\n')
    results = build(R.load(recipe), tmp_path / "out", until="meshes")
    failed = {f["item"]: f["message"] for f in json.loads((tmp_path / "out" / "failures.json").read_text())}
    assert len(failed) == len(NIFTI) == len(results.failures)
    for name in NIFTI:
        (message,) = [m for m in failed.values() if m.startswith(str(data / name) + ":")]
        assert message
    assert sorted(p.name for p in (tmp_path / "out" / "meshes").glob("*.ply")) == ["nifti-extra_label.ply", "nifti-good_label.ply"]
    # the warnings land in the sidecars: the image skipped at indexing, the unmapped label 9 at meshing
    (skip,) = json.loads((tmp_path / "out" / "sources" / "nifti.json").read_text())["warnings"]
    assert "ct_image.nii.gz (512 distinct values" in skip
    (unmapped,) = json.loads((tmp_path / "out" / "meshes" / "nifti-extra_label.json").read_text())["warnings"]
    assert unmapped.startswith(str(data / "extra_label.nii.gz")) and f"9 ({(~mask).sum()} voxels)" in unmapped
