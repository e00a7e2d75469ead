"""Trainer benchmark: milliseconds per training step on the CPU or a GPU, at the default and paper sizes.

A step is forward, every loss, backward and the Adam update, on a synthetic batch
shaped like the demo dataset (3 views of 2 x 128 x 128 images, a 2,562-vertex
ellipsoid as ground truth, the default radar's decimated echo, and for the focused
radar loss each ellipsoid's target volume, made by the loss's own image-domain model:
the trainer focuses a sample's echo_clean once and keeps it, so no step pays for it).
Timed without and with the radar term (it is off during the warm-up epochs), in steps that
alternate between the two (medians, and the median of the paired ratios, which `targets`
judges against issue 28's 1.5), and the radar term's own forward + backward per sample
(`radar_ms_per_sample`, the minimum of a few repeats after a warm-up). The machines this
runs on are shared, hence the pairing.
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

from meshsar_builder.bench import result_name
from meshsar_builder.pipeline.errors import InputError
from meshsar_builder.pipeline.io import write_json
from meshsar_builder.radar.differentiable import echo_torch
from meshsar_builder.radar.imaging import ImageParams
from meshsar_builder.radar.params import RadarParams, index_metadata
from meshsar_builder.trainer.config import TrainConfig
from meshsar_builder.trainer.dataset_geometry import DatasetGeometry
from meshsar_builder.trainer.train import (
    autocast_factory,
    build_model,
    load_config,
    sample_generators,
    step_terms,
)

CONFIGS = Path(__file__).resolve().parents[2] / "manifests" / "train"
REPEATS = 3  # the radar term alone: the minimum of this many
STEPS = 7  # training steps of each kind, interleaved (step_timings)
TARGET_RADAR_STEP_RATIO = 1.5  # issue 28 item 3: a step with the radar term at most this many times one without


def synthetic_batch(batch_size: int, geometry: DatasetGeometry, radar: RadarParams) -> dict:
    """A batch as collate_meshes makes it: ellipsoids, random images, each mesh's own echo."""
    rng = np.random.default_rng(0)
    sphere = trimesh.creation.icosphere(4)
    verts = [torch.tensor(sphere.vertices * rng.uniform(40, 60, 3), dtype=torch.float32) for _ in range(batch_size)]
    faces = torch.tensor(sphere.faces)
    echo = torch.stack([torch.stack([echo_torch(v, faces, geometry.positions[k], geometry.freqs, radar)
                                     for k in range(len(geometry.view_names))]) for v in verts])  # (B, V, M, F)
    sar = torch.rand(batch_size, len(geometry.view_names), 2, 128, 128, generator=torch.Generator().manual_seed(0))
    # the echo where the raw and profile losses read it: echo_clean on the loss grid, else the echo grid's
    out = {"verts": verts, "faces": [faces] * batch_size, "echo_clean" if geometry.full_radar else "echo": echo,
           "sar": sar, "sample_id": [str(k) for k in range(batch_size)]}
    if geometry.full_radar is not None:
        from meshsar_builder.trainer.train import focused_params

        setup = geometry.focused_setup(focused_params(load_config(CONFIGS / "default.toml").radar_loss))
        with torch.no_grad():
            out["radar_targets"] = torch.stack([torch.stack([setup.predicted(v[None], faces, k)[0]
                                                             for k in range(len(geometry.view_names))])
                                                for v in verts])
    return out


def radar_ms_per_sample(config: TrainConfig, geometry: DatasetGeometry, batch: dict) -> float:
    """Minimum milliseconds per sample of the radar term alone (forward + backward) on the batch's meshes."""
    from meshsar_builder.trainer import losses as L
    from meshsar_builder.trainer.model import icosphere_levels

    rc = config.radar_loss
    levels, faces, _ = icosphere_levels(config.model.template_level)
    size = config.data.batch_size
    verts = torch.stack([torch.as_tensor(levels[-1] * 50, dtype=torch.float32) for _ in range(size)])
    faces_t = torch.as_tensor(faces[-1])
    edges = torch.as_tensor(L.mesh_edges(faces[-1]))
    best = np.inf
    for repeat in range(REPEATS + 1):
        v = verts.clone().requires_grad_(True)
        start = time.perf_counter()
        if rc.mode in L.FOCUSED_MODES:
            from meshsar_builder.trainer.train import focused_params

            params = focused_params(rc)
            targets = geometry.focused_targets({k: batch[k][:size] for k in ("radar_targets",)}, params, rc.target)
            loss = L.focused_radar_loss(L.smooth_gradient(v, edges, rc.smooth_iterations), faces_t, targets,
                                        geometry.focused_setup(params), mode=rc.mode)
        else:
            echo = geometry.echo_targets({k: v[:size] for k, v in batch.items() if k.startswith("echo")},
                                         "clean" if geometry.full_radar else "recorded")
            positions = geometry.positions
            if 0 < rc.antennas < positions.shape[1]:
                positions, echo = positions[:, : rc.antennas], echo[:, :, : rc.antennas]
            loss = L.radar_loss(v, faces_t, echo, positions, geometry.centres, geometry.freqs, geometry.radar,
                                rc.mode, rc.beta)
        loss.backward()
        if repeat:
            best = min(best, time.perf_counter() - start)
    return 1000 * best / size


def step_timings(config: TrainConfig, geometry: DatasetGeometry, batch: dict, device: torch.device | None = None,
                 amp: bool = False) -> dict[str, list[float]]:
    """Milliseconds of STEPS training steps of a config's model and losses without (`off`) and with (`on`) the
    radar term, as train() runs them (autocast over the forward when amp, the gradient scaler on CUDA).

    The two kinds alternate, off then on, after a warm-up step of each (allocators, kernels),
    so that a shared machine's slow spells fall on both alike: the paired ratios hold where
    the minimum of a few steps of each kind moved the ratio by 0.2 from run to run.
    device: the CPU unless given.
    """
    device = device or torch.device("cpu")
    sub = {k: v[: config.data.batch_size] for k, v in batch.items()}
    sar = sub["sar"].to(device)
    runs = {}
    for kind in ("off", "on"):
        torch.manual_seed(0)
        model = build_model(config, {"frames": geometry.frames, "fov_mm": geometry.fov_mm,
                                     "channels": list(config.data.channels), "template_radius_mm": 50.0}).to(device)
        runs[kind] = (model, torch.optim.Adam(model.parameters(), lr=config.optim.lr),
                      torch.amp.GradScaler(device.type, enabled=amp and device.type == "cuda"))
    autocast = autocast_factory(device, amp)
    timings = {"off": [], "on": []}
    for repeat in range(STEPS + 1):
        for kind, (model, optimizer, scaler) in runs.items():
            synchronize(device)
            start = time.perf_counter()
            weight = config.radar_loss.weight if kind == "on" else 0.0
            terms = step_terms(model, model, sub, sar, geometry, config, weight,
                               sample_generators(0, repeat, [str(k) for k in range(len(sub["verts"]))]), autocast)
            optimizer.zero_grad(set_to_none=True)
            scaler.scale(terms["total"]).backward()
            scaler.step(optimizer)
            scaler.update()
            synchronize(device)
            if not torch.isfinite(terms["total"]):
                raise FloatingPointError(f"{config.name}: non-finite loss in a benchmark step (amp={amp})")
            if repeat:  # the first step of each kind warms allocators and kernels
                timings[kind].append(1000 * (time.perf_counter() - start))
    return timings


def step_summary(timings: dict[str, list[float]]) -> dict:
    """Medians of step_timings, and the radar term's cost as the median of the paired ratios on / off."""
    off, on = np.asarray(timings["off"]), np.asarray(timings["on"])
    return {"ms_per_step": float(np.median(off)), "ms_per_step_with_radar": float(np.median(on)),
            "radar_step_ratio": float(np.median(on / off)), "steps_timed": len(off)}


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work, so host timers measure it."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


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
              "torch": torch.__version__, "threads": torch.get_num_threads(), "repeats": REPEATS,
              "steps": STEPS}
    precisions = {"fp32": False, "amp": True} if device.type == "cuda" else {"fp32": False}
    for name in ("default", "paper"):
        config = load_config(CONFIGS / f"{name}.toml")
        result[name] = {"batch_size": config.data.batch_size}
        for precision, amp in precisions.items():
            entry = result[name] if precision == "fp32" else result[name].setdefault(precision, {})
            entry.update(step_summary(step_timings(config, geometry, batch, device, amp)))
            entry["steps_per_second"] = 1000 / entry["ms_per_step"]
            entry["steps_per_second_with_radar"] = 1000 / entry["ms_per_step_with_radar"]
            entry["ms_per_sample"] = entry["ms_per_step"] / config.data.batch_size
            if precision == "fp32":
                entry["radar_mode"] = config.radar_loss.mode
                entry["radar_ms_per_sample"] = radar_ms_per_sample(config, geometry, batch)
        if "amp" in precisions:
            result[name]["amp_speedup"] = result[name]["ms_per_step"] / result[name]["amp"]["ms_per_step"]
            result[name]["amp_speedup_with_radar"] = (result[name]["ms_per_step_with_radar"]
                                                      / result[name]["amp"]["ms_per_step_with_radar"])
    result["paper_over_default_per_sample"] = result["paper"]["ms_per_sample"] / result["default"]["ms_per_sample"]
    ratio = result["default"]["radar_step_ratio"]
    result["targets"] = {"radar_step_ratio": {"target": TARGET_RADAR_STEP_RATIO, "measured": ratio,
                                              "met": ratio <= TARGET_RADAR_STEP_RATIO, "config": "default"}}
    write_json(Path(out_dir) / result_name("trainer", str(device)), result)
    return result
