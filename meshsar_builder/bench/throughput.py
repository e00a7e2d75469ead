"""Radar-stage throughput: samples a second when P worker processes render samples side by side on one device.

A build's radar stage is many independent `render_sample` items on its workers; with
`device = "cuda"` they share the machine's GPU. `meshsar bench radar-throughput
[--device cuda]` times that directly: for each worker count P (1, half the cores, all of
them), P spawned processes, each pinned to one core with one thread for numpy, BLAS and
numba, render SAMPLES demo-heart samples at default physics after a warm-up sample (numba's
kernels, the CUDA context), started together at a barrier. Samples a second is P x SAMPLES
over the span from the first start to the last finish. Writes radar_throughput.json (or
radar_throughput-cuda.json).
"""

from __future__ import annotations

import multiprocessing
import os
import time
from pathlib import Path

import numpy as np

from meshsar_builder.bench import result_name
from meshsar_builder.bench.radar import THREAD_VARIABLES
from meshsar_builder.pipeline.io import write_json

SAMPLES = 4


def worker_counts(cores: int) -> list[int]:
    """1, half the cores and all of them, without repeats."""
    return sorted({1, max(1, cores // 2), cores})


def _render(args) -> tuple[float, float]:
    """One worker: pin to its core, warm up, wait for the others, render; (start, end) wall-clock seconds."""
    import dataclasses

    import meshsar_builder.radar.params as RP
    import meshsar_builder.radar.render as RR
    from meshsar_builder.radar.imaging import ImageParams

    index, core, verts, faces, samples, device, barrier = args
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {core})
    radar, images = dataclasses.replace(RP.RadarParams(), device=device), ImageParams()
    RR.render_sample(verts, faces, radar, images, np.random.default_rng(index))
    barrier.wait()
    start = time.time()
    for sample in range(samples):
        RR.render_sample(verts, faces, radar, images, np.random.default_rng([index, sample]))
    return start, time.time()


def measure(verts: np.ndarray, faces: np.ndarray, processes: int, samples: int = SAMPLES, device: str = "cpu") -> dict:
    """Samples a second of `processes` workers rendering `samples` each of the mesh (verts (n, 3) mm, faces (m, 3))."""
    cores = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else list(range(os.cpu_count()))
    saved = {name: os.environ.get(name) for name in THREAD_VARIABLES}
    os.environ.update({name: "1" for name in THREAD_VARIABLES})  # read once, as spawned workers load numpy
    try:
        context = multiprocessing.get_context("spawn")
        with context.Manager() as manager:
            barrier = manager.Barrier(processes)
            with context.Pool(processes) as pool:
                spans = pool.map(_render, [(i, cores[i % len(cores)], verts, faces, samples, device, barrier)
                                           for i in range(processes)])
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
    wall = max(end for _, end in spans) - min(start for start, _ in spans)
    return {"processes": processes, "samples_each": samples, "wall_seconds": wall,
            "samples_per_second": processes * samples / wall}


def run(out_dir: Path, verts: np.ndarray, faces: np.ndarray, device: str = "cpu", counts: list[int] | None = None,
        samples: int = SAMPLES) -> dict:
    """Each worker count's samples a second on `device`, into out_dir / result_name("radar-throughput", device)."""
    from meshsar_builder.radar.render import view_functions

    view_functions(device)  # a missing torch or GPU is named before any worker starts
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    result = {"device": device, "cores": cores, "faces": int(len(faces)),
              "runs": [measure(verts, faces, count, samples, device) for count in (counts or worker_counts(cores))]}
    if device != "cpu":
        import torch

        result["device_name"] = torch.cuda.get_device_name(torch.device(device))
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / result_name("radar-throughput", device), result)
    return result
