"""Trainer benchmark: milliseconds per training step on the CPU, at the default and paper sizes.

A step is forward, every loss, backward and the Adam update, on a synthetic batch
shaped like the demo dataset (3 views of 2 x 128 x 128 images, a 2,562-vertex
ellipsoid as ground truth, the default radar's decimated echo). Timed without and
with the radar term (it is off during the warm-up epochs). Every timing is the
minimum of a few repeats after a warm-up step: the machines this runs on are shared.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from meshsar_builder.pipeline.io import write_json
from meshsar_builder.radar.differentiable import echo_torch
from meshsar_builder.radar.imaging import ImageParams
from meshsar_builder.radar.params import RadarParams, index_metadata
from meshsar_builder.trainer.train import DatasetGeometry, batch_losses, build_model, load_config, sample_generators

CONFIGS = Path(__file__).resolve().parents[2] / "manifests" / "train"
REPEATS = 3


def synthetic_batch(batch_size: int, geometry: DatasetGeometry, radar: RadarParams) -> dict:
    """A batch as collate_meshes makes it: ellipsoids, random images, each mesh's own echo."""
    rng = np.random.default_rng(0)
    sphere = trimesh.creation.icosphere(4)
    verts = [torch.tensor(sphere.vertices * rng.uniform(40, 60, 3), dtype=torch.float32) for _ in range(batch_size)]
    faces = torch.tensor(sphere.faces)
    ex, ey = radar.aperture[0] // radar.echo_decimation[0], radar.aperture[1] // radar.echo_decimation[1]
    echo = torch.stack([torch.stack([echo_torch(v, faces, geometry.positions[k], geometry.freqs, radar)
                                     .reshape(ex, ey, -1) for k in range(len(geometry.view_names))]) for v in verts])
    return {"verts": verts, "faces": [faces] * batch_size, "echo": echo,
            "sar": torch.rand(batch_size, len(geometry.view_names), 2, 128, 128, generator=torch.Generator().manual_seed(0))}


def step_ms(config_name: str, radar_on: bool, geometry: DatasetGeometry, batch: dict) -> float:
    """Minimum milliseconds of one training step of a shipped config's model and losses."""
    config = load_config(CONFIGS / f"{config_name}.toml")
    torch.manual_seed(0)
    model = build_model(config, {"frames": geometry.frames, "fov_mm": geometry.fov_mm,
                                 "channels": list(config.data.channels), "template_radius_mm": 50.0})
    optimizer = torch.optim.Adam(model.parameters(), lr=config.optim.lr)
    sub = {k: v[: config.data.batch_size] for k, v in batch.items()}
    best = np.inf
    for repeat in range(REPEATS + 1):
        start = time.perf_counter()
        meshes = model(sub["sar"])
        terms = batch_losses(meshes, model, sub, geometry, config, config.radar_loss.weight if radar_on else 0.0,
                             sample_generators(0, repeat, [str(k) for k in range(len(sub["verts"]))]))
        optimizer.zero_grad(set_to_none=True)
        terms["total"].backward()
        optimizer.step()
        if repeat:  # the first step warms allocators and kernels
            best = min(best, time.perf_counter() - start)
    return 1000 * best


def run(out_dir: str | Path) -> dict:
    """Time the default and paper configs, write out_dir/trainer.json, return its contents."""
    radar = RadarParams()
    geometry = DatasetGeometry.from_index(index_metadata(radar, ImageParams()))
    batch = synthetic_batch(4, geometry, radar)
    result = {"device": "cpu", "threads": torch.get_num_threads(), "repeats": REPEATS}
    for name in ("default", "paper"):
        config = load_config(CONFIGS / f"{name}.toml")
        result[name] = {
            "batch_size": config.data.batch_size,
            "ms_per_step": step_ms(name, False, geometry, batch),
            "ms_per_step_with_radar": step_ms(name, True, geometry, batch),
        }
        entry = result[name]
        entry["ms_per_sample"] = entry["ms_per_step"] / config.data.batch_size
        entry["radar_step_ratio"] = entry["ms_per_step_with_radar"] / entry["ms_per_step"]
    result["paper_over_default_per_sample"] = result["paper"]["ms_per_sample"] / result["default"]["ms_per_sample"]
    write_json(Path(out_dir) / "trainer.json", result)
    return result
