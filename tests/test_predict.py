"""Prediction (`meshsar predict`) from a split and from an images file; the mean-shape baseline."""

from __future__ import annotations

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
    T.train(T.parse_config(TINY_CONFIG.replace("epochs = 2", "epochs = 1")), data, out=run, progress=False)
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
