"""Loaders: fixed label tables, canonical RAS, folder layouts, and named errors for bad files."""

from __future__ import annotations

import gzip
import json
import warnings
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest

from meshsar_builder.dataset.label_maps import InputWarning, read_label_map
from meshsar_builder.dataset.shape_models import load_shape_model, read_surface
from meshsar_builder.dataset.shards import Shard
from meshsar_builder.dataset.sources import ACDC_TABLE, MMWHS_TABLE, index_acdc, index_mmwhs, index_nifti
from meshsar_builder.dataset.verify import verify
from meshsar_builder.geometry.meshfile import read_ply, write_ply
from meshsar_builder.geometry.structures import STRUCTURES
from meshsar_builder.pipeline import recipe as R
from meshsar_builder.pipeline.errors import InputError
from meshsar_builder.pipeline.io import sha256_file
from meshsar_builder.pipeline.runner import build

from .conftest import MANIFESTS, save_nifti, save_nifti_with_sform
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


def test_pixdim_gives_the_spacing_where_the_sform_disagrees(tmp_path):
    """Real ACDC files: an sform of unit voxels, diag(-1, -1, 1), beside pixdim 1.37 x 1.37 x 10 mm.
    Read as ITK reads them: pixdim's spacing, the sform's orientation and origin, with a warning."""
    data = np.zeros((6, 5, 4), np.uint8)
    data[2, 3, 1] = 3
    img = nib.Nifti1Image(data, np.diag([-1.0, -1.0, 1.0, 1.0]))
    img.header.set_zooms((1.5, 1.5, 10.0))
    path = tmp_path / "patient001_frame01_gt.nii.gz"
    nib.save(img, str(path))
    assert np.allclose(nib.load(str(path)).affine[:3, :3], np.diag([-1.0, -1.0, 1.0]))  # the file is as ACDC's
    with pytest.warns(InputWarning, match=r"patient001_frame01_gt.nii.gz: the affine's voxel size \[1.0, 1.0, 1.0\] mm "
                                          r"disagrees with the header's pixdim \[1.5, 1.5, 10.0\] mm"):
        labels, ras = read_label_map(path, ACDC_TABLE)
    np.testing.assert_allclose(np.abs(np.diag(ras)[:3]), [1.5, 1.5, 10.0])
    (i, j, k), = np.argwhere(labels == STRUCTURES["lv"])
    np.testing.assert_allclose(ras @ [i, j, k, 1.0], [-3.0, -4.5, 10.0, 1.0])  # voxel (2, 3, 1) in the file's world
    consistent = save_nifti(tmp_path / "b.nii.gz", data, np.diag([-1.5, -1.5, 10.0, 1.0]))
    with warnings.catch_warnings():
        warnings.simplefilter("error", InputWarning)
        _, same = read_label_map(consistent, ACDC_TABLE)
    np.testing.assert_allclose(same, ras)


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
    [failed] = index_acdc(tmp_path, "acdc")  # a failed item: the meshes stage raises its error
    assert failed.extra["index_error"].endswith("patient003/Info.cfg: missing 'ES' in Info.cfg")


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


# --- external shape models ----------------------------------------------------------------------

ATLAS = Path(__file__).parent / "data" / "shape_model"
ATLAS_FILES = {"mean": ATLAS / "mean.vtk", "modes": ATLAS / "modes.csv.gz", "variances": ATLAS / "variances.csv",
               "vertex_labels": ATLAS / "labels.csv"}


def test_synthetic_atlas_files_are_reproducible(tmp_path, monkeypatch):
    from .data import make_shape_model

    monkeypatch.setattr(make_shape_model, "FOLDER", tmp_path)
    make_shape_model.main()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in ATLAS.iterdir())
    for p in ATLAS.iterdir():
        assert (tmp_path / p.name).read_bytes() == p.read_bytes(), p.name


def test_shape_model_reads_the_atlas_layout():
    model = load_shape_model(ATLAS_FILES, labels={"lv": 10, "rv": 20})
    # read independently: the components' rows are x1, y1, z1, x2, ...
    columns = np.loadtxt(gzip.open(ATLAS_FILES["modes"], "rt"), delimiter=",")
    assert model.mean.shape == (162, 3) and model.modes.shape == (3, 162, 3) and model.faces.shape == (320, 3)
    np.testing.assert_allclose(model.modes[1][7], columns[21:24, 1])
    # the first mode is the uniform scaling: each vertex moves along its own position
    np.testing.assert_allclose(model.modes[0], model.mean / np.linalg.norm(model.mean), atol=1e-6)
    np.testing.assert_allclose(model.variances, np.loadtxt(ATLAS_FILES["variances"]))
    superior = model.mean[:, 2] >= 0
    assert np.all(model.labels[superior] == STRUCTURES["lv"]) and np.all(model.labels[~superior] == STRUCTURES["rv"])
    assert np.isclose(model.total_variance, model.variances.sum())
    two = load_shape_model({k: v for k, v in ATLAS_FILES.items() if k != "vertex_labels"}, n_modes=2, structure="myo")
    assert two.modes.shape == (2, 162, 3) and set(two.labels) == {STRUCTURES["myo"]}
    assert two.total_variance == pytest.approx(model.total_variance)


def test_shape_model_reads_ply_and_npy_alike(tmp_path):
    model = load_shape_model(ATLAS_FILES, labels={"lv": 10, "rv": 20})
    write_ply(tmp_path / "mean.ply", model.mean, model.faces)
    np.save(tmp_path / "modes.npy", model.modes.reshape(3, -1).T)
    np.save(tmp_path / "variances.npy", model.variances)
    again = load_shape_model({"mean": tmp_path / "mean.ply", "modes": tmp_path / "modes.npy",
                              "variances": tmp_path / "variances.npy"}, structure="lv")
    for a, b in ((again.mean, model.mean), (again.modes, model.modes), (again.faces, model.faces)):
        np.testing.assert_allclose(a, b)


def _atlas_variant(tmp_path, name, text):
    files = dict(ATLAS_FILES)
    files[name] = tmp_path / ATLAS_FILES[name].name.replace(".gz", "")
    files[name].write_text(text)
    return files


@pytest.mark.parametrize(
    "name, text, message",
    [
        ("modes", "\n".join(",".join(["0.1"] * 486) for _ in range(3)), r"modes.csv: 3 rows, expected 3 x 162 vertices of mean.vtk \(it has 3n columns"),
        ("variances", "4\n1\n", r"variances.csv: 2 variances for 3 modes"),
        ("variances", "1\n4\n9\n", r"variances.csv: variances must be >= 0 and in descending order"),
        ("vertex_labels", "10\n" * 161, r"labels.csv: 161 labels for 162 vertices"),
        ("vertex_labels", "10\n" * 161 + "30\n", r"labels.csv: values \[30\] not in the label table"),
        ("mean", "# vtk DataFile Version 3.0\nx\nASCII\nDATASET POLYDATA\nPOINTS 1 float\n0 0 0\n", r"mean.vtk: surface has no polygons"),
    ],
)
def test_shape_model_bad_files_are_named(tmp_path, name, text, message):
    files = _atlas_variant(tmp_path, name, text)
    with pytest.raises(InputError, match=message):
        load_shape_model(files, labels={"lv": 10, "rv": 20})


def test_shape_model_components_scaled_by_sigma_are_refused(tmp_path):
    model = load_shape_model(ATLAS_FILES, labels={"lv": 10, "rv": 20})
    np.save(tmp_path / "scaled.npy", model.modes.reshape(3, -1).T * np.sqrt(model.variances))
    with pytest.raises(InputError, match=r"scaled.npy: columns are not orthonormal .* divide them out"):
        load_shape_model({**ATLAS_FILES, "modes": tmp_path / "scaled.npy"}, labels={"lv": 10, "rv": 20})


SHAPE_RECIPE = """\
name = "atlas"
seed = 3
[[sources]]
kind = "shape_model"
path = "{path}"
mean = "mean.vtk"
modes = "{modes}"
variances = "{variances}"
structures = ["lv"]
samples = {samples}
"""


def test_shape_model_samples_are_seeded_truncated_and_clean(tmp_path, tmp_recipe):
    from meshsar_builder.geometry.intersections import self_intersecting_faces

    recipe = tmp_recipe(SHAPE_RECIPE.format(path=ATLAS, modes="modes.csv.gz", variances="variances.csv", samples=5))
    results = build(R.load(recipe), tmp_path / "out", until="sources")
    rec = results.of("sources")["shape_model"]
    model = load_shape_model({k: v for k, v in ATLAS_FILES.items() if k != "vertex_labels"}, structure="lv")
    assert rec["shape_model"]["files"]["modes"] == "modes.csv.gz" and rec["shape_model"]["n_modes"] == 3
    for sid, s in rec["shape_samples"].items():
        verts, faces, labels = read_ply(tmp_path / "out" / "sources" / "shape_model" / f"{sid}.ply")
        coeffs = np.array(s["coeffs"])
        assert np.all(np.abs(coeffs) <= 3 * np.sqrt(model.variances))
        expected = model.mean + np.einsum("k,knd->nd", coeffs, model.modes)
        np.testing.assert_allclose(verts, expected, atol=1e-4)
        assert np.array_equal(faces, model.faces) and set(labels) == {STRUCTURES["lv"]}
        assert not self_intersecting_faces(verts, faces).any()
    more = tmp_recipe(SHAPE_RECIPE.format(path=ATLAS, modes="modes.csv.gz", variances="variances.csv", samples=7), "more.toml")
    again = build(R.load(more), tmp_path / "more", until="sources").of("sources")["shape_model"]["shape_samples"]
    assert all(again[sid] == s for sid, s in rec["shape_samples"].items()), "a sample does not change with the count"


def test_shape_model_draws_that_self_intersect_are_redrawn(tmp_path, tmp_recipe):
    """One mode (sigma 1 m) pushing vertex 0 inward and the pole (0, 0, 45) outward, or the
    reverse: far enough inward either pierces the far side, so most draws must be redrawn."""
    from meshsar_builder.geometry.intersections import self_intersecting_faces

    mean, faces = read_surface(ATLAS_FILES["mean"])
    pole = int(np.argmax(mean[:, 2]))
    dent = np.zeros((len(mean), 3))
    dent[0], dent[pole] = -mean[0] / np.linalg.norm(mean[0]), mean[pole] / np.linalg.norm(mean[pole])
    np.save(tmp_path / "dent.npy", dent.reshape(-1, 1) / np.sqrt(2))
    np.save(tmp_path / "dent_var.npy", np.array([1000.0**2]))
    (tmp_path / "mean.vtk").write_bytes(ATLAS_FILES["mean"].read_bytes())
    body = SHAPE_RECIPE.format(path=tmp_path, modes="dent.npy", variances="dent_var.npy", samples=4)
    rec = build(R.load(tmp_recipe(body + "[ssm]\nmax_redraws = 100\n")), tmp_path / "out", until="sources").of("sources")["shape_model"]
    assert sum(s["redraws"] for s in rec["shape_samples"].values()) > 0
    for sid in rec["shape_samples"]:
        verts, _, _ = read_ply(tmp_path / "out" / "sources" / "shape_model" / f"{sid}.ply")
        assert not self_intersecting_faces(verts, faces).any()


@pytest.mark.slow
def test_shape_model_example_builds_end_to_end(tmp_path, monkeypatch):
    monkeypatch.chdir(MANIFESTS.parent)
    monkeypatch.delenv("MESHSAR_DATA", raising=False)
    out = tmp_path / "out"
    results = build(R.load(MANIFESTS / "shape_model_example.toml"), out)
    assert results.failures == [] and verify(out) == []
    index = json.loads((out / "index.json").read_text())
    assert index["counts"]["source"] == {"synthetic_atlas": 6}
    shard = Shard(out / index["shards"][0]["file"])
    sample = shard[0]
    assert sample.meta["provenance"] == "shape_model" and sample.meta["subset"] == "ssm"
    assert sample.meta["shape_model"]["sha256"]["modes"] == sha256_file(ATLAS_FILES["modes"])
    assert set(np.unique(sample.vert_labels)) == {STRUCTURES["lv"], STRUCTURES["rv"]}


def _eight_bit_image_and_its_labels() -> tuple[np.ndarray, np.ndarray]:
    """An MR-like 8-bit image (a bright pool in a dimmer wall on a dark field, smoothed, with noise) and a label map of
    the same scene with 40 labels (a parcellated wall), each at most 256 values."""
    x, y, z = np.meshgrid(*(np.linspace(-1, 1, 40),) * 3, indexing="ij")
    r = np.sqrt(x**2 + y**2 + z**2)
    rng = np.random.default_rng(0)
    image = np.where(r < 0.4, 200.0, np.where(r < 0.6, 110.0, 15.0)) + rng.normal(0, 12, r.shape)
    image = np.clip(image, 0, 255).astype(np.uint8)
    labels = np.where(r < 0.4, 3, 0).astype(np.uint8)
    wall = (r >= 0.4) & (r < 0.6)
    labels[wall] = 10 + (np.degrees(np.arctan2(y, x))[wall] + 180).astype(int) // 9  # 40 sectors
    return image, labels


def test_an_eight_bit_image_is_told_from_a_label_map_by_its_texture(tmp_path):
    """An 8-bit image has at most 256 values, as a label map may: its voxels vary from neighbour to neighbour where a
    label map's are uniform. Skipped by a folder's scan, refused when named; the parcellated map stays a label map."""
    image, labels = _eight_bit_image_and_its_labels()
    assert 32 < len(np.unique(image)) <= 256 and len(np.unique(labels)) == 42
    save_nifti(tmp_path / "data" / "s1_image.nii.gz", image)
    save_nifti(tmp_path / "data" / "s1_gt.nii.gz", labels)
    with pytest.warns(InputWarning, match=r"skipped 1 file.*s1_image.nii.gz \(\d+ distinct values that vary"):
        items = index_nifti(tmp_path / "data", "own", {"lv": 3})
    assert [Path(i.path).name for i in items] == ["s1_gt.nii.gz"]
    with pytest.raises(InputError, match=r"s1_image.nii.gz: \d+ distinct values that vary .* an image rather than"):
        read_label_map(tmp_path / "data" / "s1_image.nii.gz", {3: "lv"})
    with pytest.warns(InputWarning, match="label values with no mapping"):  # the wall's 40 parcels
        labels_read, _ = read_label_map(tmp_path / "data" / "s1_gt.nii.gz", {3: "lv"})
    assert (labels_read == STRUCTURES["lv"]).sum() == (labels == 3).sum()
