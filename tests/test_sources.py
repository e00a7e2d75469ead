"""Loaders: fixed label tables, canonical RAS, folder layouts, and named errors for bad files."""

from __future__ import annotations

import gzip

import numpy as np
import pytest

from meshsar_builder.dataset.sources import (
    ACDC_TABLE,
    MMWHS_TABLE,
    InputWarning,
    index_acdc,
    index_mmwhs,
    index_nifti,
    read_label_map,
)
from meshsar_builder.geometry.structures import STRUCTURES
from meshsar_builder.pipeline.errors import InputError

from .conftest import save_nifti, save_nifti_with_sform
from .data.make_bad import huge_header

MMWHS_CODES = {205: "myo", 420: "la", 421: "la", 500: "lv", 550: "ra", 600: "rv", 820: "aorta", 850: "pa"}


def lps_affine(shape, voxel=(1.0, 1.0, 1.0)):
    """An LPS-stored volume, as CT often is: first two voxel axes run to patient left and posterior."""
    a = np.diag([-voxel[0], -voxel[1], voxel[2], 1.0])
    a[:3, 3] = [100.0, 50.0, -20.0]
    return a


def test_mmwhs_codes_including_421_map_to_canonical(tmp_path):
    codes = list(MMWHS_CODES) + [999]  # 999: a label outside the table is background
    data = np.zeros((len(codes), 3, 2), np.int16)
    for i, c in enumerate(codes):
        data[i] = c
    affine = lps_affine(data.shape)
    path = save_nifti(tmp_path / "ct_train_1001_label.nii.gz", data, affine)
    with pytest.warns(InputWarning, match=r"label values with no mapping, read as background: 999 \(6 voxels\)"):
        labels, ras = read_label_map(path, MMWHS_TABLE)
    assert ras[0, 0] > 0 and ras[1, 1] > 0 and ras[2, 2] > 0  # reoriented to RAS
    inv = np.linalg.inv(ras)
    for i, c in enumerate(codes):
        world = affine @ np.array([i, 1, 0, 1.0])  # where code c sits in the world
        j = np.round(inv @ world).astype(int)[:3]
        expect = STRUCTURES[MMWHS_CODES[c]] if c in MMWHS_CODES else 0
        assert labels[tuple(j)] == expect, c


def test_table_is_fixed_not_sorted_order(tmp_path):
    """A file holding only 500 and 850 still maps 500 to lv and 850 to pa."""
    data = np.zeros((4, 4, 4), np.int16)
    data[:2] = 500
    data[2:] = 850
    labels, _ = read_label_map(save_nifti(tmp_path / "x_label.nii.gz", data), MMWHS_TABLE)
    assert set(np.unique(labels[:2])) == {STRUCTURES["lv"]} and set(np.unique(labels[2:])) == {STRUCTURES["pa"]}


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda p: p.write_bytes(gzip.compress(b"\x5c\x01\x00\x00" + b"\x00" * 100)[:60]), "not a readable NIfTI"),
        (lambda p: p.write_bytes(b"not a nifti at all"), "not a readable NIfTI"),
        (lambda p: save_nifti(p, np.zeros((5, 5), np.int16)), "must be 3-D"),
        (lambda p: save_nifti(p, np.zeros((3, 3, 3, 2, 2), np.int16)), "must be 3-D"),
        (lambda p: save_nifti(p, np.full((3, 3, 3), 0.5, np.float32)), "non-integer"),
        (lambda p: save_nifti(p, np.full((3, 3, 3), np.nan, np.float32)), "NaN"),
        (lambda p: save_nifti(p, np.zeros((3, 3, 3), np.int16)), "none of the labels"),
        (lambda p: save_nifti_with_sform(p, np.full((3, 3, 3), 500, np.int16), np.zeros((4, 4))), "singular"),
        (lambda p: save_nifti_with_sform(p, np.full((3, 3, 3), 500, np.int16), np.full((4, 4), np.nan)), "non-finite"),
    ],
)
def test_bad_files_are_named(tmp_path, make, message):
    path = tmp_path / "bad_label.nii"
    make(path)
    with pytest.raises(InputError, match=message) as err:
        read_label_map(path, MMWHS_TABLE)
    assert str(path) in str(err.value)


def test_enormous_declared_size_is_refused_before_reading(tmp_path):
    path = tmp_path / "huge_label.nii"
    path.write_bytes(huge_header())  # a header that promises 128 GB, and no data
    with pytest.raises(InputError, match="implausible image size"):
        read_label_map(path, MMWHS_TABLE)


def write_acdc_patient(root, name, frames, ed, es, nb):
    pdir = root / name
    pdir.mkdir(parents=True)
    (pdir / "Info.cfg").write_text(f"ED: {ed}\nES: {es}\nGroup: NOR\nHeight: 170.0\nNbFrame: {nb}\nWeight: 70.0\n")
    for f in frames:
        data = np.zeros((8, 8, 4), np.uint8)
        data[2:6, 2:6, 1:3] = 3
        save_nifti(pdir / f"{name}_frame{f:02d}_gt.nii.gz", data, np.diag([1.5, 1.5, 8.0, 1]))


def test_acdc_phase_and_provenance(tmp_path):
    write_acdc_patient(tmp_path, "patient001", [1, 5, 12], ed=1, es=12, nb=30)
    write_acdc_patient(tmp_path, "patient002", [1, 9], ed=1, es=9, nb=20)
    items = index_acdc(tmp_path, "acdc")
    got = {(i.subject, i.frame): (i.phase, i.provenance) for i in items}
    assert got == {
        ("patient001", 1): ("ED", "annotated"),
        ("patient001", 5): ("", "predicted"),
        ("patient001", 12): ("ES", "annotated"),
        ("patient002", 1): ("ED", "annotated"),
        ("patient002", 9): ("ES", "annotated"),
    }
    assert items[1].item_id == "acdc-patient001-f05" and items[1].cycle_fraction == pytest.approx(4 / 30)
    assert index_acdc(tmp_path, "acdc", limit=1)[-1].subject == "patient001"
    labels, affine = read_label_map(items[0].path, ACDC_TABLE)
    assert np.allclose(np.linalg.norm(affine[:3, :3], axis=0), [1.5, 1.5, 8.0])
    assert (labels == STRUCTURES["lv"]).sum() == 32


def test_acdc_info_cfg_missing_key_is_named(tmp_path):
    write_acdc_patient(tmp_path, "patient003", [1], ed=1, es=5, nb=10)
    (tmp_path / "patient003" / "Info.cfg").write_text("ED: 1\nNbFrame: 10\n")
    with pytest.raises(InputError, match=r"patient003/Info.cfg: missing 'ES'"):
        index_acdc(tmp_path, "acdc")


def test_mmwhs_and_nifti_indexes(tmp_path):
    for s in ("ct_train_1002", "ct_train_1001"):
        save_nifti(tmp_path / "mmwhs" / f"{s}_label.nii.gz", np.full((2, 2, 2), 500, np.int16))
    items = index_mmwhs(tmp_path / "mmwhs", "mmwhs")
    assert [i.subject for i in items] == ["ct_train_1001", "ct_train_1002"]
    assert items[0].item_id == "mmwhs-ct_train_1001"
    save_nifti(tmp_path / "own" / "site A" / "case.1.nii.gz", np.full((2, 2, 2), 7, np.int16))
    (item,) = index_nifti(tmp_path / "own", "own", {"lv": 7})
    assert item.item_id == "own-site_A_case_1" and item.table == {7: "lv"}
    with pytest.raises(InputError, match="does not exist"):
        index_mmwhs(tmp_path / "nowhere", "mmwhs")
    with pytest.raises(InputError, match="no MM-WHS label maps"):
        index_mmwhs(tmp_path / "own", "mmwhs")
