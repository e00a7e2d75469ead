"""Subjects and frames from real cine layouts: regex over file paths, CSV frame tables, 4-D label
maps read one frame per T index, ACDC's predicted 4-D maps, the shipped recipes for these
layouts, and a named error for each kind of bad input."""

from __future__ import annotations

import re
import string
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from meshsar_builder.dataset.frames import direct_meshes, subject_series
from meshsar_builder.dataset.label_maps import InputWarning, LabelItem, n_frames, read_label_map
from meshsar_builder.dataset.sources import ACDC_TABLE, SourceSpec, index_acdc, index_nifti
from meshsar_builder.geometry.structures import STRUCTURES
from meshsar_builder.pipeline import recipe as R
from meshsar_builder.pipeline.errors import InputError, RecipeError
from stages.sources import index_source

from .conftest import MANIFESTS, save_nifti

AFFINE = np.diag([1.5, 1.5, 8.0, 1.0])
AFFINE[:3, 3] = [-10.0, 20.0, 5.0]
LV = 3  # the ACDC / test label value of the LV blood pool


def frame_volume(k: int, shape=(8, 8, 4)) -> np.ndarray:
    """A tiny label map whose LV has k + 1 voxels in its first row: frame k is recognisable."""
    data = np.zeros(shape, np.uint8)
    data[1:7, 1:7, 1:3] = 2  # myocardium
    data.reshape(-1)[: k + 1] = LV
    return data


def save_4d(path: Path, T: int, affine=AFFINE) -> Path:
    return save_nifti(path, np.stack([frame_volume(t) for t in range(T)], axis=-1), affine)


def summary(items: list[LabelItem]) -> list[tuple]:
    return [(i.subject, i.frame, i.phase, i.provenance, i.t) for i in items]


# --- 4-D label maps --------------------------------------------------------------------------------


def test_4d_map_is_one_frame_per_t_index_with_the_file_affine(tmp_path):
    path = save_4d(tmp_path / "cine" / "sub01.nii.gz", 5)
    assert n_frames(path) == 5
    items = index_nifti(tmp_path / "cine", "cine", {"lv": LV, "myo": 2}, phases={"ED": 0, "ES": 3})
    assert summary(items) == [("sub01", t, {0: "ED", 3: "ES"}.get(t, ""), "annotated", t) for t in range(5)]
    assert [i.item_id for i in items] == [f"cine-sub01-f{t:02d}" for t in range(5)]
    assert [i.cycle_fraction for i in items] == [t / 5 for t in range(5)]
    assert items[0].extra == {"n_frames": 5}
    for li in items:  # each item reads its own frame, and every frame the one affine
        labels, affine = read_label_map(li.path, li.table, t=li.t)
        assert (labels == STRUCTURES["lv"]).sum() == li.t + 1
        assert np.allclose(affine, AFFINE)
    # the item survives the sources stage's JSON, t included
    assert LabelItem.from_json(items[2].to_json()) == items[2]


def test_4d_map_without_a_frame_or_out_of_range_is_named(tmp_path):
    path = save_4d(tmp_path / "sub01.nii.gz", 3)
    with pytest.raises(InputError, match=r"sub01.nii.gz: label map must be 3-D, got shape \(8, 8, 4, 3\)"):
        read_label_map(path, {LV: "lv"})
    with pytest.raises(InputError, match=r"sub01.nii.gz: frame index t = 3 out of range .* 3 frames"):
        read_label_map(path, {LV: "lv"}, t=3)
    with pytest.raises(InputError, match=r"phases puts ES at frame 7, out of range .* 3 frames"):
        index_nifti(tmp_path, "n", {"lv": LV}, phases={"ES": 7})
    # a frame's own problem names the frame
    with pytest.raises(InputError, match=r"sub01.nii.gz \[t=1\]: none of the labels \[9\]"):
        read_label_map(path, {9: "lv"}, t=1)


def test_old_sidecars_without_t_still_load():
    d = LabelItem("a-s", "a", "/x.nii.gz", "s", {1: "lv"}).to_json()
    del d["t"]
    assert LabelItem.from_json(d).t is None


# --- regex over relative paths ---------------------------------------------------------------------

SA_REGEX = r"(?P<subject>[^/]+)_sa_(?P<phase>ED|ES)_gt\.nii(\.gz)?$"


def test_regex_gives_subjects_and_phases_and_skips_the_rest(tmp_path):
    for s in ("sub02", "sub01"):
        for ph in ("ED", "ES"):
            save_nifti(tmp_path / "site" / f"{s}_sa_{ph}_gt.nii.gz", frame_volume(0), AFFINE)
    save_nifti(tmp_path / "site" / "sub01_sa.nii.gz", frame_volume(0), AFFINE)  # an image, say
    with pytest.warns(InputWarning, match=r"skipped 1 file.*sub01_sa.nii.gz \(path not matched by regex"):
        items = index_nifti(tmp_path, "sa", {"lv": LV}, regex=SA_REGEX)
    assert summary(items) == [("sub01", None, "ED", "annotated", None), ("sub01", None, "ES", "annotated", None),
                              ("sub02", None, "ED", "annotated", None), ("sub02", None, "ES", "annotated", None)]
    assert [i.item_id for i in items] == ["sa-sub01-ED", "sa-sub01-ES", "sa-sub02-ED", "sa-sub02-ES"]
    # the recipe's phases number frames known by their phase only
    with pytest.warns(InputWarning, match="skipped 1 file"):
        items = index_nifti(tmp_path, "sa", {"lv": LV}, regex=SA_REGEX, phases={"ED": 1, "ES": 12}, limit=1)
    assert summary(items) == [("sub01", 1, "ED", "annotated", None), ("sub01", 12, "ES", "annotated", None)]


def test_regex_with_frame_numbers_and_phases_from_the_recipe(tmp_path):
    for s in ("a", "b"):
        for f in (1, 5, 9):
            save_nifti(tmp_path / s / f"{s}_frame{f:02d}.nii.gz", frame_volume(f), AFFINE)
    items = index_nifti(tmp_path, "x", {"lv": LV}, regex=r"^(?P<subject>\w+)/\w+_frame(?P<frame>\d+)",
                        phases={"ED": 1, "ES": 9}, provenance="predicted")
    assert summary(items) == [(s, f, {1: "ED", 9: "ES"}.get(f, ""), "predicted", None)
                              for s in ("a", "b") for f in (1, 5, 9)]


@pytest.mark.parametrize("files, kwargs, message", [
    ({"a_sa_ED.nii.gz": 3}, {"regex": SA_REGEX}, r"regex: .* matches none of the 1 label map\(s\)"),
    ({"s1_a_ED.nii.gz": 3, "s1_b_ED.nii.gz": 3}, {"regex": r"(?P<subject>s\d)_\w_(?P<phase>ED)"},
     r"s1_a_ED.nii.gz and .*s1_b_ED.nii.gz both claim subject 's1' phase ED"),
    ({"s1_f1_x.nii.gz": 3, "s1_f1_y.nii.gz": 3}, {"regex": r"(?P<subject>s\d)_f(?P<frame>\d)"},
     r"s1_f1_x.nii.gz and .*s1_f1_y.nii.gz both claim subject 's1' frame 1"),
    ({"s1_f1_ED.nii.gz": 3, "s1_f2_ED.nii.gz": 3}, {"regex": r"(?P<subject>s\d)_f(?P<frame>\d)_(?P<phase>ED)"},
     r"both claim subject 's1' phase ED \(frames 1 and 2\)"),
    ({"s1_fx.nii.gz": 3}, {"regex": r"(?P<subject>s\d)_f(?P<frame>\w)"}, r"frame must be a non-negative integer"),
    ({"s1_dia.nii.gz": 3}, {"regex": r"(?P<subject>s\d)_(?P<phase>\w+)\.nii"}, r"phase must be one of"),
    ({"s1_f2_ED.nii.gz": 3}, {"regex": r"(?P<subject>s\d)_f(?P<frame>\d)_(?P<phase>ED)", "phases": {"ED": 1}},
     r"frame 2 is ED, but the recipe's phases puts ED at frame 1"),
    ({"s1_f4.nii.gz": (8, 8, 4, 3)}, {"regex": r"(?P<subject>s\d)_f(?P<frame>\d)"},
     r"a 4-D label map \(3 frames\) numbers its frames by T index"),
    ({"s 1.nii.gz": 3, "s_1.nii.gz": 3}, {"regex": r"(?P<subject>s.1)"}, r"give the same item id 'n-s_1'"),
])
def test_bad_layouts_are_named(tmp_path, files, kwargs, message):
    for name, shape in files.items():
        if shape == 3:
            save_nifti(tmp_path / name, frame_volume(0), AFFINE)
        else:
            save_4d(tmp_path / name, shape[3])
    with pytest.raises(InputError, match=message):
        index_nifti(tmp_path, "n", {"lv": LV}, **kwargs)


# Subject names as real layouts have them: letters, digits, '-', '_', '.', never the separator.
names = st.text(string.ascii_letters + string.digits + "-_.", min_size=1, max_size=12).filter(
    lambda s: s not in (".", "..") and not s.startswith("."))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(layout=st.dictionaries(names, st.dictionaries(st.integers(0, 300), st.sampled_from(["ED", "es", ""]),
                                                     min_size=1, max_size=3), min_size=1, max_size=4),
       nested=st.booleans())
def test_regex_recovers_subject_frame_and_phase_from_any_name(tmp_path_factory, layout, nested):
    """Whatever the names (dots, dashes, frame numbers with or without zeros), the index gives back
    exactly the subjects, frames and phases written into them."""
    # item ids are file-name safe: names that differ only in '.' vs '_' would share one (a named error)
    assume(len({re.sub(r"[^A-Za-z0-9_-]+", "_", s) for s in layout}) == len(layout))
    # phases must be unique per subject (one ED, one ES), as real data has them
    layout = {s: {f: p for f, p in frames.items() if p == "" or f == min(g for g, q in frames.items() if q == p)}
              for s, frames in layout.items()}
    root = tmp_path_factory.mktemp("layout")
    for s, frames in layout.items():
        for f, p in frames.items():
            name = f"{s}_fr{f}{'_' + p if p else ''}_seg.nii.gz"
            save_nifti(root / (f"{s}/{name}" if nested else name), frame_volume(0), AFFINE)
    rx = r"(?:^|/)(?P<subject>[^/]+)_fr(?P<frame>\d+)(?:_(?P<phase>ED|ES|ed|es))?_seg\.nii\.gz$"
    items = index_nifti(root, "n", {"lv": LV}, regex=rx)
    got = {(i.subject, i.frame): i.phase for i in items}
    assert got == {(s, f): p.upper() for s, frames in layout.items() for f, p in frames.items()}
    assert len({i.item_id for i in items}) == len(items)


# --- CSV frame tables ------------------------------------------------------------------------------


def write_table(root: Path, text: str) -> Path:
    (root / "frames.csv").write_text(text)
    return root / "frames.csv"


def test_frame_table_names_files_frames_phases_and_provenance(tmp_path):
    save_nifti(tmp_path / "p01" / "p01_ed.nii.gz", frame_volume(0), AFFINE)
    save_nifti(tmp_path / "p01" / "p01_es.nii.gz", frame_volume(1), AFFINE)
    save_4d(tmp_path / "p02_4d.nii.gz", 4)
    save_4d(tmp_path / "p03_4d.nii.gz", 3)
    write_table(tmp_path, "File,Subject,Frame,Phase,provenance,group\n"
                "p01/p01_ed.nii.gz,p01,1,ed,,NOR\n"
                "p01/p01_es.nii.gz,p01,8,ES,,NOR\n"
                "p02_4d.nii.gz,p02,,,predicted,DCM\n"  # every T index of p02
                "p02_4d.nii.gz,p02,2,ES,predicted,DCM\n"
                "\n"
                "p03_4d.nii.gz,p03,0,ED,,HCM\n")  # only T index 0 of p03
    items = index_nifti(tmp_path, "t", {"lv": LV}, frame_table="frames.csv")
    assert summary(items) == [
        ("p01", 1, "ED", "annotated", None), ("p01", 8, "ES", "annotated", None),
        ("p02", 0, "", "predicted", 0), ("p02", 1, "", "predicted", 1), ("p02", 2, "ES", "predicted", 2),
        ("p02", 3, "", "predicted", 3), ("p03", 0, "ED", "annotated", 0),
    ]
    assert items[0].extra == {"group": "NOR"} and items[2].extra == {"group": "DCM", "n_frames": 4}


@pytest.mark.parametrize("table, message", [
    ("file,subject,frame\nnope.nii.gz,p01,1\n", r"frames.csv: row 2: file 'nope.nii.gz' not found under"),
    ("file,subject,frame\np01.nii.gz,p01,1\np01b.nii.gz,p01,1\n", r"both claim subject 'p01' frame 1"),
    ("file,subject,frame\ncine.nii.gz,p02,5\n", r"frames.csv: row 2: frame 5 out of range for cine.nii.gz, .* 3 frames"),
    ("file,subject,frame\np01.nii.gz,p01,-1\n", r"row 2: frame must be a non-negative integer, got '-1'"),
    ("file,frame\np01.nii.gz,1\n", r"header needs columns file and subject"),
    ("file,subject\n", r"has a header and no rows"),
    ("file,subject\np01.nii.gz\n", r"row 2: 1 fields, the header has 2"),
    ("file,subject,phase\np01.nii.gz,p01,systole\n", r"row 2: phase must be one of \['ED', 'ES'\]"),
    ("file,subject\np01.nii.gz,a\np01.nii.gz,b\n", r"row 3: p01.nii.gz is claimed by subjects \['a', 'b'\]"),
    ("file,subject,frame\ncine.nii.gz,p02,1\ncine.nii.gz,p02,1\n", r"row 3: cine.nii.gz frame 1 is named twice"),
])
def test_frame_table_faults_are_named(tmp_path, table, message):
    save_nifti(tmp_path / "p01.nii.gz", frame_volume(0), AFFINE)
    save_nifti(tmp_path / "p01b.nii.gz", frame_volume(0), AFFINE)
    save_4d(tmp_path / "cine.nii.gz", 3)
    write_table(tmp_path, table)
    with pytest.raises(InputError, match=message):
        index_nifti(tmp_path, "t", {"lv": LV}, frame_table="frames.csv")
    with pytest.raises(InputError, match=r"frame_table: .*other.csv not found"):
        index_nifti(tmp_path, "t", {"lv": LV}, frame_table="other.csv")


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rows=st.lists(st.tuples(st.sampled_from(["a.nii.gz", "b.nii.gz"]), st.sampled_from(["s1", "s2"]),
                               st.one_of(st.none(), st.integers(0, 3)), st.sampled_from(["", "ED", " es "])),
                     min_size=1, max_size=4),
       pad=st.sampled_from(["", " ", "\t"]))
def test_frame_table_parses_or_names_the_fault(tmp_path_factory, rows, pad):
    """Any table over two 3-D files either indexes exactly its rows or fails with a named error."""
    root = tmp_path_factory.mktemp("table")
    for f in ("a.nii.gz", "b.nii.gz"):
        save_nifti(root / f, frame_volume(0), AFFINE)
    text = "file,subject,frame,phase\n" + "".join(
        f"{pad}{f}{pad},{s},{'' if n is None else n},{p}\n" for f, s, n, p in rows)
    write_table(root, text)
    try:
        items = index_nifti(root, "t", {"lv": LV}, frame_table="frames.csv")
    except InputError as e:
        assert re.search(r"frames.csv|both claim|named twice|claimed by subjects", str(e)), str(e)
        return
    key = lambda x: (x[0], -1 if x[1] is None else x[1], x[2])  # noqa: E731
    assert sorted(((i.subject, i.frame, i.phase) for i in items), key=key) == sorted(
        ((s, n, p.strip().upper()) for _, s, n, p in rows), key=key)


# --- ACDC with predicted 4-D maps ------------------------------------------------------------------


def write_acdc(root: Path, name: str, gt: list[int], ed: int, es: int, nb: int, pred_T: int | None = None) -> None:
    pdir = root / name
    pdir.mkdir(parents=True)
    (pdir / "Info.cfg").write_text(f"ED: {ed}\nES: {es}\nGroup: NOR\nNbFrame: {nb}\n")
    for f in gt:
        save_nifti(pdir / f"{name}_frame{f:02d}_gt.nii.gz", frame_volume(f - 1), AFFINE)
    save_nifti(pdir / f"{name}_frame01.nii.gz", frame_volume(0).astype(np.int16) * 40, AFFINE)  # an image
    if pred_T:
        save_4d(pdir / f"{name}_4d_pred.nii.gz", pred_T)


def test_acdc_reads_predicted_4d_maps_where_present(tmp_path):
    write_acdc(tmp_path, "patient001", [1, 4], ed=1, es=4, nb=5, pred_T=5)
    write_acdc(tmp_path, "patient002", [1, 3], ed=1, es=3, nb=4)
    items = index_acdc(tmp_path, "acdc")
    assert summary(items) == [
        ("patient001", 1, "ED", "annotated", None), ("patient001", 2, "", "predicted", 1),
        ("patient001", 3, "", "predicted", 2), ("patient001", 4, "ES", "annotated", None),
        ("patient001", 5, "", "predicted", 4),
        ("patient002", 1, "ED", "annotated", None), ("patient002", 3, "ES", "annotated", None),
    ]
    assert items[1].item_id == "acdc-patient001-f02" and items[1].cycle_fraction == pytest.approx(1 / 5)
    for li in items:  # ACDC frame f is T index f - 1 of the prediction: the same volume here
        labels, affine = read_label_map(li.path, ACDC_TABLE, t=li.t)
        assert (labels == STRUCTURES["lv"]).sum() == li.frame and np.allclose(affine, AFFINE)
    assert index_acdc(tmp_path, "acdc", predicted="")[1].frame == 4  # predictions switched off


def index_errors(items: list[LabelItem]) -> dict[str, str]:
    """The failed items' ids and errors (label_maps.failed_item)."""
    return {li.item_id: li.extra["index_error"] for li in items if "index_error" in li.extra}


def test_acdc_predicted_map_faults_are_named_as_failed_items_and_the_rest_kept(tmp_path):
    write_acdc(tmp_path, "patient001", [1], ed=1, es=4, nb=6, pred_T=5)
    write_acdc(tmp_path, "patient002", [1, 3], ed=1, es=3, nb=4)
    items = index_acdc(tmp_path, "acdc")
    [(name, error)] = index_errors(items).items()
    assert name == "acdc-patient001-patient001_4d_pred_nii_gz"
    assert re.search(r"patient001_4d_pred.nii.gz: 5 frames \(T\) .* NbFrame: 6", error)
    assert summary([li for li in items if li.item_id != name]) == [
        ("patient001", 1, "ED", "annotated", None), ("patient002", 1, "ED", "annotated", None),
        ("patient002", 3, "ES", "annotated", None)]
    save_nifti(tmp_path / "patient001" / "patient001_4d_pred.nii.gz", frame_volume(0), AFFINE)
    assert "a 3-D predicted label map (predicted = '{subject}_4d_pred.nii*') must name its frame" in \
        index_errors(index_acdc(tmp_path, "acdc"))[name]
    (tmp_path / "patient001" / "patient001_4d_pred.nii.gz").write_bytes(b"")  # a copy cut short
    assert "not a readable NIfTI file" in index_errors(index_acdc(tmp_path, "acdc"))[name]
    # only predictions, no _gt at all: still a patient
    other = tmp_path / "other"
    write_acdc(other, "patient009", [], ed=1, es=2, nb=2, pred_T=2)
    assert summary(index_acdc(other, "acdc")) == [("patient009", 1, "ED", "predicted", 0),
                                                  ("patient009", 2, "ES", "predicted", 1)]


def test_acdc_patients_without_a_usable_info_cfg_fail_alone_and_its_name_takes_any_case(tmp_path):
    for name in ("patient001", "patient002", "patient003", "patient004"):
        write_acdc(tmp_path, name, [1, 2], ed=1, es=2, nb=3)
    (tmp_path / "patient002" / "Info.cfg").write_text("ED: 1\nNbFrame: 3\n")
    (tmp_path / "patient003" / "Info.cfg").rename(tmp_path / "patient003" / "info.cfg")
    (tmp_path / "patient004" / "Info.cfg").unlink()
    items = index_acdc(tmp_path, "acdc")
    errors = index_errors(items)
    assert sorted(errors) == ["acdc-patient002-Info_cfg", "acdc-patient004-patient004_frame01_gt_nii_gz"]
    assert errors["acdc-patient002-Info_cfg"].endswith("patient002/Info.cfg: missing 'ES' in Info.cfg")
    assert "patient004: _gt frames but no Info.cfg" in errors["acdc-patient004-patient004_frame01_gt_nii_gz"]
    assert [(li.subject, li.frame) for li in items if li.item_id not in errors] == [
        ("patient001", 1), ("patient001", 2), ("patient003", 1), ("patient003", 2)]


def test_the_meshes_stage_fails_a_failed_item_with_its_error(tmp_path):
    from stages import meshes

    from meshsar_builder.dataset.label_maps import failed_item
    from meshsar_builder.pipeline.runner import Context, Item

    li = failed_item("acdc", "patient004", tmp_path / "x_gt.nii.gz", "patient004: _gt frames but no Info.cfg")
    ctx = Context(out=tmp_path, recipe=R.load(MANIFESTS / "acdc.toml"))
    item = Item(li.item_id, (f"{li.item_id}.ply",), data=(li.to_json(), ("lv",), "direct", False))
    with pytest.raises(InputError, match="patient004: _gt frames but no Info.cfg"):
        meshes.run(ctx, item)


# --- recipe keys -----------------------------------------------------------------------------------


@pytest.mark.parametrize("keys, message", [
    ('kind = "nifti"\nlabels = { lv = 1 }\nregex = "(?P<subj>x)"', r"regex: needs a named group \(\?P<subject>"),
    ('kind = "nifti"\nlabels = { lv = 1 }\nregex = "(?P<subject>x"', r"regex: not a regular expression"),
    ('kind = "nifti"\nlabels = { lv = 1 }\nregex = "(?P<subject>x)(?P<frames>y)"', r"regex: named groups must be among"),
    ('kind = "nifti"\nlabels = { lv = 1 }\nregex = "(?P<subject>x)"\nframe_table = "a.csv"', r"regex: give either regex or frame_table"),
    ('kind = "nifti"\nlabels = { lv = 1 }\nframe_table = "a.txt"', r"frame_table: must be a .csv file"),
    ('kind = "nifti"\nlabels = { lv = 1 }\nframe_table = "a.csv"\npattern = "*.nii"', r"pattern: a frame_table names"),
    ('kind = "nifti"\nlabels = { lv = 1 }\nphases = { MS = 3 }', r"phases: keys must be among \['ED', 'ES'\]"),
    ('kind = "nifti"\nlabels = { lv = 1 }\nphases = { ED = 3, ES = 3 }', r"phases: ED and ES must be different"),
    ('kind = "nifti"\nlabels = { lv = 1 }\nphases = { ED = -1 }', r"phases: frame numbers must be >= 0"),
    ('kind = "nifti"\nlabels = { lv = 1 }\nprovenance = "guessed"', r"provenance: must be 'annotated' or 'predicted'"),
    ('kind = "acdc"\nregex = "(?P<subject>x)"', r"regex: only a nifti source takes regex"),
    ('kind = "nifti"\nlabels = { lv = 1 }\npredicted = "*_pred.nii.gz"', r"predicted: only an acdc source"),
    ('kind = "acdc"\npredicted = "*_pred.png"', r"predicted: must match NIfTI files"),
    ('kind = "phantom"\nsubjects = 1\ncohort = "c"', r"cohort: only a label-map source"),
    ('kind = "acdc"\ncohort = "a b"', r"cohort: letters, digits"),
])
def test_bad_frame_keys_are_named(keys, message):
    with pytest.raises(RecipeError, match=r"#1 " + message):
        R.parse(f'name = "t"\n[[sources]]\n{keys}\n', "t.toml")


# --- the shipped recipes for these layouts, on generated files -------------------------------------


def source(recipe: str, name: str | None = None) -> SourceSpec:
    specs = R.load(MANIFESTS / recipe).sources
    return specs[0] if name is None else next(s for s in specs if s.name == name)


def test_acdc_recipe_indexes_the_acdc_layout(tmp_path, monkeypatch):
    monkeypatch.setenv("MESHSAR_DATA", str(tmp_path))
    root = tmp_path / "ACDC" / "database" / "training"
    write_acdc(root, "patient001", [1, 3], ed=1, es=3, nb=4, pred_T=4)
    write_acdc(root, "patient002", [1, 2], ed=1, es=2, nb=3)
    spec = source("acdc.toml")
    assert spec.data_path() == root and spec.predicted == "{subject}_4d_pred.nii*"
    got = summary(index_source(spec, spec.data_path()))
    assert got == [("patient001", 1, "ED", "annotated", None), ("patient001", 2, "", "predicted", 1),
                   ("patient001", 3, "ES", "annotated", None), ("patient001", 4, "", "predicted", 3),
                   ("patient002", 1, "ED", "annotated", None), ("patient002", 2, "ES", "annotated", None)]


def test_sa_frames_recipe_indexes_the_per_frame_file_layout(tmp_path, monkeypatch):
    monkeypatch.setenv("MESHSAR_DATA", str(tmp_path))
    for s in ("1000213", "1000458", "2001007"):
        for ph in ("ED", "ES"):
            data = np.where(frame_volume(0) == LV, 1, frame_volume(0)).astype(np.uint8)  # UK Biobank: 1 = LV
            save_nifti(tmp_path / "sa_frames" / s / f"{s}_sa_{ph}_gt.nii.gz", data, AFFINE)
        save_nifti(tmp_path / "sa_frames" / s / f"{s}_sa.nii.gz", frame_volume(0), AFFINE)  # the image
    spec = source("sa_frames.toml")
    with pytest.warns(InputWarning, match="skipped 3 file"):
        items = index_source(spec, spec.data_path())
    assert [(i.subject, i.frame, i.phase) for i in items] == [
        (s, None, ph) for s in ("1000213", "1000458", "2001007") for ph in ("ED", "ES")]
    assert items[0].item_id == "sa-1000213-ED" and items[0].table == {1: "lv", 2: "myo", 3: "rv"}
    labels, _ = read_label_map(items[0].path, items[0].table, t=items[0].t)
    assert (labels == STRUCTURES["lv"]).sum() == 1


def test_cine_4d_recipe_indexes_a_table_and_4d_predictions_in_one_cohort(tmp_path, monkeypatch):
    monkeypatch.setenv("MESHSAR_DATA", str(tmp_path))
    gt, pred = tmp_path / "cine" / "annotated", tmp_path / "cine" / "predicted"
    rows = ["file,subject,frame,phase"]
    for s, es in (("p01", 9), ("p02", 7)):
        for f, ph in ((1, "ED"), (es, "ES")):
            save_nifti(gt / s / f"{s}_frame{f:02d}_gt.nii.gz", frame_volume(f), AFFINE)
            rows.append(f"{s}/{s}_frame{f:02d}_gt.nii.gz,{s},{f},{ph}")
        save_4d(pred / f"{s}_seg4d.nii.gz", 3)
    (gt / "frames.csv").write_text("\n".join(rows) + "\n")
    a, b = source("cine_4d.toml", "gt"), source("cine_4d.toml", "pred")
    assert a.cohort == b.cohort == "cine"
    assert summary(index_source(a, a.data_path())) == [
        ("p01", 1, "ED", "annotated", None), ("p01", 9, "ES", "annotated", None),
        ("p02", 1, "ED", "annotated", None), ("p02", 7, "ES", "annotated", None)]
    assert summary(index_source(b, b.data_path())) == [
        (s, t, "ED" if t == 0 else "", "predicted", t) for s in ("p01", "p02") for t in range(3)]


def test_every_recipe_for_real_layouts_parses():
    for name in ("acdc.toml", "sa_frames.toml", "cine_4d.toml"):
        assert R.load(MANIFESTS / name).sources


# --- the meshes stage reads just its frame ---------------------------------------------------------


def test_a_build_meshes_each_frame_of_a_4d_map(tmp_path, tmp_recipe):
    from meshsar_builder.pipeline.runner import build

    from .conftest import ball_volume

    frames = []
    for r in (9.0, 7.0, 8.0):
        mask, affine = ball_volume((28, 28, 28), (1, 1, 1), r)
        frames.append(mask.astype(np.uint8))
    save_nifti(tmp_path / "data" / "s1_cine.nii.gz", np.stack(frames, axis=-1), affine)
    recipe = tmp_recipe(f'name = "c"\n[[sources]]\nkind = "nifti"\npath = "{tmp_path / "data"}"\n'
                        f'labels = {{ lv = 1 }}\nregex = "(?P<subject>s\\\\d)_cine"\nphases = {{ ED = 0, ES = 1 }}\n'
                        f'use = "direct"\n')
    results = build(R.load(recipe), tmp_path / "out", until="meshes")
    assert not results.failures
    import json

    recs = [json.loads((tmp_path / "out" / "meshes" / f"nifti-s1-f{t:02d}.json").read_text()) for t in range(3)]
    vols = [r["volume_ml"] for r in recs]
    assert vols[1] < vols[2] < vols[0]  # each item meshed its own T index
    assert [(r["frame"], r["phase"]) for r in recs] == [(0, "ED"), (1, "ES"), (2, "")]
    assert [nib.load(str(tmp_path / "data" / "s1_cine.nii.gz")).shape[3]] == [3]


def test_a_failing_frame_of_a_4d_map_is_named_by_its_t_index(tmp_path, tmp_recipe):
    """One file holds every frame: a frame's failure names the file and its T index, and the others build."""
    from meshsar_builder.pipeline.runner import build

    from .conftest import ball_volume

    (small, affine), (large, _) = (ball_volume((28, 28, 28), (1, 1, 1), r) for r in (9.0, 16.0))  # 16: on the border
    save_nifti(tmp_path / "data" / "s1_cine.nii.gz", np.stack([small, large], axis=-1).astype(np.uint8), affine)
    recipe = tmp_recipe(f'name = "c"\n[[sources]]\nkind = "nifti"\npath = "{tmp_path / "data"}"\n'
                        f'labels = {{ lv = 1 }}\nregex = "(?P<subject>s\\\\d)_cine"\nuse = "direct"\n')
    results = build(R.load(recipe), tmp_path / "out", until="meshes")
    (failure,) = results.failures
    assert failure["item"] == "nifti-s1-f01"
    assert "s1_cine.nii.gz (T index 1): the label map's border cuts the heart" in failure["message"]
    assert (tmp_path / "out" / "meshes" / "nifti-s1-f00.ply").exists()


def _remeshed(source: str, frame: int, phase: str = "", provenance: str = "annotated", subject: str = "p01") -> dict:
    return {"source": source, "subject": subject, "frame": frame, "phase": phase, "provenance": provenance,
            "use": "direct", "cycle_fraction": None}


def test_a_frame_two_sources_of_a_cohort_give_enters_once_the_annotated_one():
    """An annotated table (ED, ES) and a 4-D prediction of every frame, one cohort: frame 0 and 2 came twice, so a
    6-frame cycle had 8 entries and one physical frame two samples. Now the annotated map is kept (the other named
    in its record); two annotated maps of a frame, or ED at two frame numbers (1-based against 0-based), are named."""
    records = {"gt-p01-f00": _remeshed("gt", 0, "ED"), "gt-p01-f02": _remeshed("gt", 2, "ES"),
               **{f"pred-p01-f{t:02d}": _remeshed("pred", t, "ED" if t == 0 else "", "predicted") for t in range(6)},
               "other-p02-f00": _remeshed("other", 0, "ED", subject="p02")}
    cohorts = {"gt": "cine", "pred": "cine"}
    kept = direct_meshes(records, cohorts)
    assert sorted(kept) == ["gt-p01-f00", "gt-p01-f02", "other-p02-f00", "pred-p01-f01", "pred-p01-f03",
                            "pred-p01-f04", "pred-p01-f05"]
    assert kept["gt-p01-f00"]["replaces"] == ["pred-p01-f00"] and "replaces" not in kept["pred-p01-f01"]
    assert [len(mids) for mids, _ in subject_series(kept, cohorts)] == [6, 1]
    assert len(direct_meshes(records)) == len(records)  # no cohort: sources' subjects are their own
    one_based = {**records, "gt-p01-f00": _remeshed("gt", 1, "ED")}
    del one_based["gt-p01-f02"]
    with pytest.raises(InputError, match=r"cohort 'cine': subject 'p01' has its ED frame at gt frame 1 "
                                         r"\(gt-p01-f00\), pred frame 0 \(pred-p01-f00\)"):
        direct_meshes(one_based, cohorts)
    with pytest.raises(InputError, match=r"gt-p01-f02 and pred-p01-f02 both give subject 'p01' frame 2"):
        direct_meshes({**records, "pred-p01-f02": _remeshed("pred", 2)}, cohorts)
