"""Trainer benchmark: milliseconds per training step on the CPU or a GPU, at the default and paper sizes.

A step is forward, every loss, backward and the Adam update, on a synthetic batch
shaped like the demo dataset (3 views of 2 x 128 x 128 images, a 2,562-vertex
ellipsoid as ground truth, the default radar's decimated echo). Timed without and
with the radar term (it is off during the warm-up epochs). Every timing is the
minimum of a few repeats after a warm-up step: the machines this runs on are shared.
On CUDA (`meshsar bench trainer --device cuda`) every timing is also taken with
mixed precision ([run] amp: float16 autocast and the gradient scaler), and the
result goes to trainer-cuda.json beside the CPU's trainer.json.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from meshsar_builder.pipeline.errors import InputError
from meshsar_builder.pipeline.io import write_json
from meshsar_builder.radar.differentiable import echo_torch
from meshsar_builder.radar.imaging import ImageParams
from meshsar_builder.radar.params import RadarParams, index_metadata
from meshsar_builder.trainer.config import TrainConfig
from meshsar_builder.trainer.train import (
    DatasetGeometry,
    autocast_factory,
    build_model,
    load_config,
    sample_generators,
    step_terms,
)

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


def step_ms(config: TrainConfig, radar_on: bool, geometry: DatasetGeometry, batch: dict,
            device: torch.device | None = None, amp: bool = False) -> float:
    """Minimum milliseconds of one training step of a config's model and losses, as train() runs it
    (autocast over the forward when amp, the gradient scaler on CUDA); device: the CPU unless given."""
    device = device or torch.device("cpu")
    torch.manual_seed(0)
    model = build_model(config, {"frames": geometry.frames, "fov_mm": geometry.fov_mm,
                                 "channels": list(config.data.channels), "template_radius_mm": 50.0}).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.optim.lr)
    scaler = torch.amp.GradScaler(device.type, enabled=amp and device.type == "cuda")
    autocast = autocast_factory(device, amp)
    sub = {k: v[: config.data.batch_size] for k, v in batch.items()}
    sar = sub["sar"].to(device)
    best = np.inf
    for repeat in range(REPEATS + 1):
        synchronize(device)
        start = time.perf_counter()
        terms = step_terms(model, model, sub, sar, geometry, config, config.radar_loss.weight if radar_on else 0.0,
                           sample_generators(0, repeat, [str(k) for k in range(len(sub["verts"]))]), autocast)
        optimizer.zero_grad(set_to_none=True)
        scaler.scale(terms["total"]).backward()
        scaler.step(optimizer)
        scaler.update()
        synchronize(device)
        if not torch.isfinite(terms["total"]):
            raise FloatingPointError(f"{config.name}: non-finite loss in a benchmark step (amp={amp})")
        if repeat:  # the first step warms allocators and kernels
            best = min(best, time.perf_counter() - start)
    return 1000 * best


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work, so host timers measure it."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def result_name(device: str) -> str:
    """The JSON file a run on `device` writes: trainer.json on the CPU, trainer-cuda.json on a GPU."""
    return "trainer.json" if torch.device(device).type == "cpu" else "trainer-cuda.json"


def run(out_dir: str | Path, device: str = "cpu") -> dict:
    """Time the default and paper configs on `device`, write out_dir/trainer.json (trainer-cuda.json for a GPU),
    return its contents. On CUDA each is timed in fp32 and with mixed precision (amp)."""
    device = torch.device(device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InputError("bench trainer --device cuda: CUDA is not available")
    radar = RadarParams()
    geometry = DatasetGeometry.from_index(index_metadata(radar, ImageParams()))
    batch = synthetic_batch(4, geometry, radar)
    result = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
              "torch": torch.__version__, "threads": torch.get_num_threads(), "repeats": REPEATS}
    precisions = {"fp32": False, "amp": True} if device.type == "cuda" else {"fp32": False}
    for name in ("default", "paper"):
        config = load_config(CONFIGS / f"{name}.toml")
        result[name] = {"batch_size": config.data.batch_size}
        for precision, amp in precisions.items():
            entry = result[name] if precision == "fp32" else result[name].setdefault(precision, {})
            entry["ms_per_step"] = step_ms(config, False, geometry, batch, device, amp)
            entry["ms_per_step_with_radar"] = step_ms(config, True, geometry, batch, device, amp)
            entry["steps_per_second"] = 1000 / entry["ms_per_step"]
            entry["steps_per_second_with_radar"] = 1000 / entry["ms_per_step_with_radar"]
            entry["ms_per_sample"] = entry["ms_per_step"] / config.data.batch_size
            entry["radar_step_ratio"] = entry["ms_per_step_with_radar"] / entry["ms_per_step"]
        if "amp" in precisions:
            result[name]["amp_speedup"] = result[name]["ms_per_step"] / result[name]["amp"]["ms_per_step"]
            result[name]["amp_speedup_with_radar"] = (result[name]["ms_per_step_with_radar"]
                                                      / result[name]["amp"]["ms_per_step_with_radar"])
    result["paper_over_default_per_sample"] = result["paper"]["ms_per_sample"] / result["default"]["ms_per_sample"]
    write_json(Path(out_dir) / result_name(str(device)), result)
    return result
