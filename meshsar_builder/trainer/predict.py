"""`meshsar predict RUN --data OUT [--split seed-S --subset test] | --images FILE.npz`: meshes from images.

Writes one PLY per sample (heart frame, mm) and gallery.png (every view of every
prediction, beside the ground truth when the data has it) to --out (default
RUN/predict-<split>-<subset> or RUN/predict-<file stem>), on any device.

An images file (write_images makes one) is an .npz with
    sar         (n, V, C, H, W) float, the views and channels in the order `index` lists them
    index       0-d str: JSON of the dataset index's keys IMAGE_KEYS (views, fov_mm, image_size,
                channels, radar, echo_grid), as index.json holds them
    sample_ids  (n,) str, optional (default sample-00000, ...)
The run's views and channels are picked from it by name; its fov_mm must be the run's.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from pathlib import Path

import numpy as np
import torch
import trimesh

from meshsar_builder.dataset.readers import MeshSARDataset
from meshsar_builder.dataset.shards import read_index
from meshsar_builder.pipeline.errors import InputError
from meshsar_builder.pipeline.io import write_bytes
from meshsar_builder.trainer.train import load_run, pick_device, split_seed

IMAGE_KEYS = ("views", "fov_mm", "image_size", "channels", "radar", "echo_grid")


def write_images(path: str | os.PathLike, sar: np.ndarray, index: dict, sample_ids: list[str] | None = None) -> Path:
    """An images file for `meshsar predict --images`: sar (n, V, C, H, W), the index's IMAGE_KEYS."""
    path = Path(path)
    arrays = {"sar": np.asarray(sar), "index": np.array(json.dumps({k: index[k] for k in IMAGE_KEYS}))}
    if sample_ids is not None:
        arrays["sample_ids"] = np.array(sample_ids)
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    write_bytes(path, buffer.getvalue())
    return path


def read_images(path: str | os.PathLike, view_names: list[str], channels: list[str],
                fov_mm: float) -> tuple[list[str], torch.Tensor, dict]:
    """(sample ids, sar (n, V, C, H, W) float32 of the given views and channels, index keys) of an images file.

    InputError naming the file and the problem when it is unreadable, lacks a key, has the wrong
    shape, lacks a view or channel the run uses, or was imaged with another field of view.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise InputError(f"{path}: cannot read the images file ({type(e).__name__}: {e})") from e
    for key in ("sar", "index"):
        if key not in arrays:
            raise InputError(f"{path}: missing array {key!r} (an images file holds sar, index and optionally sample_ids)")
    try:
        index = json.loads(str(arrays["index"]))
    except ValueError as e:
        raise InputError(f"{path}: 'index' is not JSON ({e})") from e
    missing = [k for k in IMAGE_KEYS if k not in index]
    if missing:
        raise InputError(f"{path}: 'index' lacks {missing}")
    sar = arrays["sar"]
    names = [v["name"] for v in index["views"]]
    if sar.ndim != 5 or sar.shape[1] != len(names) or sar.shape[2] != len(index["channels"]):
        raise InputError(f"{path}: 'sar' must be (n, {len(names)} views, {len(index['channels'])} channels, H, W), "
                         f"got {sar.shape}")
    lacking = [v for v in view_names if v not in names] + [c for c in channels if c not in index["channels"]]
    if lacking:
        raise InputError(f"{path}: the run uses views/channels {lacking} that the file does not hold")
    if not np.isclose(float(index["fov_mm"]), fov_mm):
        raise InputError(f"{path}: fov_mm {index['fov_mm']} differs from the run's {fov_mm}")
    ids = [str(s) for s in arrays["sample_ids"]] if "sample_ids" in arrays else [f"sample-{i:05d}" for i in range(len(sar))]
    if len(ids) != len(sar):
        raise InputError(f"{path}: {len(ids)} sample_ids for {len(sar)} samples")
    picked = sar[:, [names.index(v) for v in view_names]][:, :, [index["channels"].index(c) for c in channels]]
    return ids, torch.from_numpy(picked.astype(np.float32)), index


def predict(run: str | os.PathLike, data: str | os.PathLike | None = None, split: str = "seed-0",
            subset: str = "test", images: str | os.PathLike | None = None, device: str = "cpu",
            out: str | os.PathLike | None = None, checkpoint: str = "best", gallery: int | None = None,
            refine: bool = False) -> Path:
    """Predict a mesh per sample of `subset` of `split` in `data`, or per sample of an images file.

    refine: each mesh refined against its sample's recorded echo (refine.sample_refiner, the run's
    [refine]; needs `data`, which holds the echo) before it is written; the gallery shows the
    prediction beside it. Returns the output folder (PLY per sample, gallery.png of every
    sample or the first `gallery`; default RUN/predict-<split>-<subset>[-refine]).
    """
    from meshsar_builder.trainer.evaluate import render_gallery  # pyvista and matplotlib only when drawing

    if (data is None) == (images is None):
        raise InputError("predict: give either --data (a built dataset) or --images (an images file)")
    run = Path(run)
    torch_device = pick_device(device, 0)
    model, config, info = load_run(run, torch_device, checkpoint)
    if refine and images is not None:
        raise InputError(f"{images}: an images file holds no echo; --refine needs --data, whose shards hold it")
    if images is not None:
        ids, sar, index = read_images(images, info["view_names"], info["channels"], info["fov_mm"])
        samples = [(sid, sar[i], None, None) for i, sid in enumerate(ids)]
        out = Path(out) if out is not None else run / f"predict-{Path(images).stem}"
    else:
        index = read_index(data)
        dataset = MeshSARDataset(data, subset, seed=split_seed(split), channels=list(info["channels"]),
                                 noisy_loss_echo=refine)
        names = [v["name"] for v in index["views"]]
        missing = [v for v in info["view_names"] if v not in names]
        if missing:
            raise InputError(f"{data}: lacks the views {missing} the run was trained on")
        view_index = [names.index(v) for v in info["view_names"]]
        samples = ((s["sample_id"], s["sar"][view_index], (s["verts"].double().numpy(), s["faces"].numpy()), s)
                   for s in map(dataset.__getitem__, range(len(dataset))))
        out = Path(out) if out is not None else run / f"predict-{split}-{subset}{'-refine' if refine else ''}"
    refined = None
    if refine:
        from meshsar_builder.trainer.refine import sample_refiner

        refined = sample_refiner(index, config)
    rows = []
    for sample_id, sar, truth, sample in samples:
        verts, faces = model.predict_mesh(sar)
        meshes = [("prediction", (verts, faces))]
        if refined is not None:
            verts = refined(verts, model.topology(), sample)
            meshes.append(("refined", (verts, faces)))
        write_bytes(out / f"{sample_id}.ply", trimesh.Trimesh(verts, faces, process=False).export(file_type="ply"))
        if gallery is None or len(rows) < gallery:
            rows.append((sample_id, ([("truth", truth)] if truth is not None else []) + meshes))
    if rows:
        views = [v for name in info["view_names"] for v in index["views"] if v["name"] == name]
        render_gallery(rows, views, info["fov_mm"], out / "gallery.png")
    return out
