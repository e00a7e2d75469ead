"""Prediction (`meshsar predict`) from a split and from an images file; the mean-shape baseline."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import trimesh

torch = pytest.importorskip("torch")

from meshsar_builder.cli import main  # noqa: E402
from meshsar_builder.dataset.readers import MeshSARDataset  # noqa: E402
from meshsar_builder.pipeline.errors import InputError  # noqa: E402
from meshsar_builder.trainer import evaluate as E  # noqa: E402
from meshsar_builder.trainer import metrics as M  # noqa: E402
from meshsar_builder.trainer import predict as P  # noqa: E402
from meshsar_builder.trainer import train as T  # noqa: E402

from .test_train import TINY_CONFIG, make_dataset  # noqa: E402


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    data = make_dataset(tmp_path_factory.mktemp("data"))
    run = tmp_path_factory.mktemp("run")
    # 20 refinement steps, not the default's 160: the tests check what refinement does, not how far it goes
    T.train(T.parse_config(TINY_CONFIG.replace("epochs = 2", "epochs = 1") + "\n[refine]\nsteps = 20\n"), data,
            out=run, progress=False)
    return data, run


def test_predict_a_split_and_the_same_images_from_a_file(tiny_run, tmp_path, capsys):
    data, run = tiny_run
    assert main(["predict", str(run), "--data", str(data), "--out", str(tmp_path / "split")]) == 0
    test = MeshSARDataset(data, "test")
    assert sorted(p.stem for p in (tmp_path / "split").glob("*.ply")) == sorted(test.ids)
    assert (tmp_path / "split" / "gallery.png").stat().st_size > 0
    model, _, info = T.load_run(run)
    first = trimesh.load(tmp_path / "split" / f"{test.ids[0]}.ply", process=False)
    with torch.no_grad():
        direct = model(test[0]["sar"][None])[-1][1][0].numpy()  # the final stage's vertices
    np.testing.assert_allclose(first.vertices, direct, atol=1e-5)
    np.testing.assert_array_equal(first.faces, model.topology()["faces"].numpy())

    # The same samples as an images file, views reversed: predict picks the run's views by name.
    index = T.read_index(data)
    sar = np.stack([test[i]["sar"].numpy() for i in range(len(test))])[:, ::-1]
    flipped = {**index, "views": index["views"][::-1]}
    file = P.write_images(tmp_path / "images.npz", sar, flipped, test.ids)
    assert main(["predict", str(run), "--images", str(file), "--device", "cpu"]) == 0
    out = run / "predict-images"
    assert capsys.readouterr().out.strip().endswith(str(out))
    for sid in test.ids:
        a = trimesh.load(out / f"{sid}.ply", process=False).vertices
        b = trimesh.load(tmp_path / "split" / f"{sid}.ply", process=False).vertices
        np.testing.assert_allclose(a, b, atol=1e-5)


def test_bad_images_files_name_the_file_and_the_problem(tiny_run, tmp_path):
    data, run = tiny_run
    index = T.read_index(data)
    sar = np.zeros((2, 3, 2, 32, 32), np.float32)
    views, channels = [v["name"] for v in index["views"]], list(index["channels"])
    np.savez(tmp_path / "nosar.npz", index=np.array(json.dumps({k: index[k] for k in P.IMAGE_KEYS})))
    with pytest.raises(InputError, match="nosar.npz: missing array 'sar'"):
        P.read_images(tmp_path / "nosar.npz", views, channels, index["fov_mm"])
    P.write_images(tmp_path / "fov.npz", sar, {**index, "fov_mm": index["fov_mm"] * 2})
    with pytest.raises(InputError, match="fov.npz: fov_mm"):
        P.read_images(tmp_path / "fov.npz", views, channels, index["fov_mm"])
    P.write_images(tmp_path / "shape.npz", sar[:, :2], index)
    with pytest.raises(InputError, match=r"shape.npz: 'sar' must be \(n, 3 views"):
        P.read_images(tmp_path / "shape.npz", views, channels, index["fov_mm"])
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="junk.npz: cannot read"):
        P.read_images(tmp_path / "junk.npz", views, channels, index["fov_mm"])
    with pytest.raises(InputError, match="either --data"):
        P.predict(run)


def test_mean_shape_of_offset_spheres_is_the_middle_sphere_at_the_origin():
    sphere = trimesh.creation.icosphere(4)
    meshes = [(sphere.vertices * r + offset, sphere.faces)
              for r, offset in ((20.0, [5.0, 0, 0]), (25.0, [0, -7.0, 3.0]), (30.0, [0, 0, 0]))]
    # Inside fractions 1, 2/3, 1/3 by radius band: the half level lies at r = 25.
    verts, faces = E.mean_shape(meshes, voxel_mm=1.0)
    radius = np.linalg.norm(verts, axis=1)
    assert abs(radius.mean() - 25.0) < 0.3 and radius.max() - radius.min() < 1.5
    mesh = trimesh.Trimesh(verts, faces, process=False)
    assert mesh.is_watertight and M.signed_volume(verts, faces) == pytest.approx(4 / 3 * np.pi * 25**3, rel=0.03)


def test_predict_refine_writes_the_refined_meshes_and_an_images_file_is_refused(tiny_run, tmp_path):
    data, run = tiny_run
    plain = P.predict(run, data, out=tmp_path / "plain", gallery=0)
    refined = P.predict(run, data, out=tmp_path / "refined", gallery=0, refine=True)
    test = MeshSARDataset(data, "test")
    moved = []
    for sid in test.ids:
        a = trimesh.load(plain / f"{sid}.ply", process=False)
        b = trimesh.load(refined / f"{sid}.ply", process=False)
        np.testing.assert_array_equal(a.faces, b.faces)
        moved.append(np.linalg.norm(b.vertices - a.vertices, axis=1).max())
    config = T.load_run(run)[1]
    # every vertex moves at most step_mm a step, the farthest exactly that on the first
    assert all(config.refine.step_mm * 0.99 <= m <= config.refine.steps * config.refine.step_mm + 1e-6 for m in moved)
    file = P.write_images(tmp_path / "images.npz", np.stack([test[i]["sar"].numpy() for i in range(len(test))]),
                          T.read_index(data), test.ids)
    with pytest.raises(InputError, match="images.npz: an images file holds no echo"):
        P.predict(run, images=file, refine=True)


def test_refine_settings_come_from_the_run_folders_config_and_nothing_else_does(tiny_run, tmp_path):
    """[refine] acts after training: RUN/config.toml sets it for predict and evaluate, without retraining;
    the model and every other key stay the checkpoint's, and a broken file is named."""
    import shutil

    data, run = tiny_run
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    text = (run / "config.toml").read_text()
    assert "steps = 20" in text
    (copy / "config.toml").write_text(text.replace("epochs = 1", "epochs = 9").replace("steps = 20",
                                                                                     "steps = 3\nstep_mm = 0.1"))
    original, edited = T.load_run(run)[1], T.load_run(copy)[1]
    assert (edited.refine.steps, edited.refine.step_mm) == (3, 0.1) and edited.optim == original.optim
    plain = P.predict(copy, data, out=tmp_path / "plain", gallery=0)
    refined = P.predict(copy, data, out=tmp_path / "refined", gallery=0, refine=True)
    for sid in MeshSARDataset(data, "test").ids:
        a, b = (trimesh.load(folder / f"{sid}.ply", process=False) for folder in (plain, refined))
        assert 0.099 <= np.linalg.norm(b.vertices - a.vertices, axis=1).max() <= 3 * 0.1 + 1e-6
    E.evaluate(copy, data, renders=0, samples=200, progress=False, refine=True, baselines=False)
    assert "steps = 3, step_mm = 0.1" in (copy / "eval-seed-0-refine" / "summary.md").read_text()
    (copy / "config.toml").write_text(text.replace("steps = 20", "steps = -1"))
    with pytest.raises(Exception, match="config.toml"):
        T.load_run(copy)


def test_evaluate_refine_tables_before_and_after_with_a_paired_test(tiny_run):
    from scipy import stats

    data, run = tiny_run
    E.evaluate(run, data, renders=0, samples=500, progress=False, refine=True)
    out = run / "eval-seed-0-refine"
    with open(out / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    methods = {r["method"] for r in rows}
    assert {"sar2mesh", "sar2mesh+refine", "template", "mean_shape"} <= methods and "template+refine" not in methods
    paired = json.loads((out / "refine.json").read_text())
    ids = sorted({r["sample_id"] for r in rows})
    for column in ("dice", "assd_mm"):
        before = [next(float(r[column]) for r in rows if r["sample_id"] == i and r["method"] == "sar2mesh") for i in ids]
        after = [next(float(r[column]) for r in rows if r["sample_id"] == i and r["method"] == "sar2mesh+refine")
                 for i in ids]
        expected = stats.wilcoxon(after, before).pvalue if before != after else 1.0
        assert paired["sar2mesh"][column]["p"] == pytest.approx(expected) and paired["sar2mesh"][column]["n"] == len(ids)
        assert paired["sar2mesh"][column]["median_difference"] == pytest.approx(np.median(np.subtract(after, before)))
    assert not (run / "eval-seed-0" / "refine.json").exists()  # the plain evaluation's folder is left alone


def test_evaluate_refine_reads_the_echo_of_another_build_of_the_same_samples(tiny_run, tmp_path, capsys):
    import shutil

    data, run = tiny_run
    E.evaluate(run, data, renders=0, samples=500, progress=False, refine=True)
    twin = shutil.copytree(data, tmp_path / "twin")  # the same samples, echoes and all
    # by the CLI: --refine-echo implies --refine and prints the folder's summary
    assert main(["evaluate", str(run), "--data", str(data), "--samples", "500", "--renders", "0",
                 "--refine-echo", str(twin)]) == 0
    assert "refined against twin's echo" in capsys.readouterr().out

    def refined(folder):
        with open(run / folder / "metrics.csv", newline="") as f:
            return sorted((r["sample_id"], r["assd_mm"]) for r in csv.DictReader(f) if r["method"] == "sar2mesh+refine")

    assert E.eval_folder("seed-0", True, twin) == "eval-seed-0-refine-twin"
    assert refined("eval-seed-0-refine-twin") == refined("eval-seed-0-refine")
    other = make_dataset(tmp_path / "other", radii=(40, 60))  # other meshes under the same ids
    with pytest.raises(InputError, match=r"other: sample s\d's mesh differs"):
        E.evaluate(run, data, renders=0, samples=500, progress=False, refine=True, refine_echo=other)
