"""`meshsar bench radar --device cuda`: the GPU radar (radar/gpu.py) per view against one CPU core of the same run.

Writes radar-cuda.json (bench.radar.run arranges the one pinned core): per view of the demo
heart at default physics, the CPU's production view (view_seconds, the diffuse part
included) and the same model's direct sum on DIRECT_ANTENNAS antennas (direct_check), then
the GPU's production echo (factorised, its grids summed on the GPU), diffuse part and imaging
of that view, its direct sum over the whole aperture, and `targets` with `met` flags for
issue 32's GPU budgets: the GPU's direct sum >= GPU_TARGET_SPEEDUP times the same direct sum
on one core, and the view's float32 channels against the CPU's before storage (intensity
within GPU_TARGET_INTENSITY, depth within one range slice on GPU_TARGET_DEPTH of the pixels).
"""

from __future__ import annotations

import sys
import time

import numpy as np

from meshsar_builder.bench.radar import (
    REPEATS,
    THREAD_VARIABLES,
    _best,
    direct_check,
    pin_one_core,
    relative,
    view_seconds,
)
from meshsar_builder.pipeline.io import write_json

GPU_TARGET_SPEEDUP = 50.0
GPU_TARGET_INTENSITY = 1e-5
GPU_TARGET_DEPTH = 0.99


def gpu_row(verts, faces, radar, images, cpu_views: list[dict], scatterers=None, device: str = "cuda") -> dict:
    """Per view, the echo, the diffuse part and imaging on `device` against one CPU core in this run.

    cpu_views : per view of radar.views, view_seconds' dict of the CPU path (its seconds,
    `signal`, `volume`, `seen`, `vis`), with direct_check's keys where the direct sum was
    timed. scatterers : the diffuse part's (radar.diffuse.Scatterers), as view_seconds had
    them. Visibility and placing the scatterers stay on the CPU, so the view's visibility
    seconds are the CPU's. Timings are best of REPEATS after a warm-up call (the kernel's
    compile, the CUDA context, cuFFT plans), which is timed on its own; results come back
    to the host, so each timing includes the transfers and waits for the device.
    Skipped, with the reason, without torch or CUDA.
    """
    try:
        import torch
    except ImportError as error:
        return {"skipped": f"torch is not installed ({error})"}
    if not torch.cuda.is_available():
        return {"skipped": "no CUDA device: torch.cuda.is_available() is false"}
    import meshsar_builder.radar.diffuse as RD
    import meshsar_builder.radar.gpu as RG
    import meshsar_builder.radar.params as RP
    from meshsar_builder.radar.imaging import range_slices, volume_images

    freqs, (x_mm, y_mm) = RP.frequencies(radar), RP.aperture_axes(radar)
    d_mm = range_slices(radar.z0_mm, images.fov_mm, freqs)
    one_slice = (d_mm[1] - d_mm[0]) / (images.fov_mm / 2)  # in the depth channel's units
    shape = (*radar.aperture, radar.n_samples)
    start = time.perf_counter()
    first = cpu_views[0]
    RG.echo(verts[faces][first["seen"]][:8], first["vis"][first["seen"]][:8],
            RP.aperture_positions(radar, radar.views[0])[:8], freqs, radar, device=device, method="direct")
    RG.view_volume(first["signal"], freqs, x_mm, y_mm, radar.z0_mm, images, device=device)
    warm_up = time.perf_counter() - start
    torch.cuda.reset_peak_memory_stats(device)
    placed = None if scatterers is None else RD.place(verts, faces, scatterers, radar)
    views = []
    for view, cpu in zip(radar.views, cpu_views):
        tri, vis = verts[faces][cpu["seen"]], cpu["vis"][cpu["seen"]]
        positions = RP.aperture(radar, view)
        t_echo, signal = _best(lambda: RG.echo(tri, vis, positions, freqs, radar, device=device))
        t_direct, direct = _best(lambda: RG.echo(tri, vis, positions, freqs, radar, device=device, method="direct"))
        t_diffuse = 0.0
        if placed is not None:  # as render_sample adds it: in the same call, and alone on the stored grid
            lit = RD.seen_by(*placed, scatterers.face, cpu["vis"])
            t_both, _ = _best(lambda: RG.echo(tri, vis, positions, freqs, radar, diffuse=(*lit, RD.lambert(radar)),
                                              diffuse_on=RP.grid_indices(radar, radar.echo_decimation),
                                              device=device))
            t_diffuse = max(t_both - t_echo, 0.0)
        signal = signal.reshape(shape)
        t_img, volume = _best(lambda: RG.view_volume(signal, freqs, x_mm, y_mm, radar.z0_mm, images, device=device))
        seconds_view = cpu["seconds_visibility"] + t_echo + t_diffuse + 2 * t_img
        mine, theirs = (dict(zip(images.channels, volume_images(v, freqs, radar.z0_mm, images)))
                        for v in (volume, cpu["volume"]))
        row = {"view": view, "seconds_echo": t_echo, "seconds_diffuse": t_diffuse, "seconds_imaging": 2 * t_img,
               "seconds_view": seconds_view, "cpu_seconds_view": cpu["seconds_view"],
               "speedup_view": cpu["seconds_view"] / seconds_view, "speedup_echo": cpu["seconds_echo"] / t_echo,
               # both factorised, the grids summed directly here and by the per-pair series there
               "echo_relative_error": relative(signal, cpu["signal"]),
               "volume_relative_error": relative(volume, cpu["volume"]),
               "seconds_echo_direct": t_direct,
               # the factorisation's own error, against the whole aperture's direct sum
               "echo_factorised_relative_error": relative(signal, direct.reshape(shape))}
        if "seconds_echo_direct_scaled" in cpu:  # against the same model, summed directly on the CPU
            row["speedup_echo_direct"] = cpu["seconds_echo_direct_scaled"] / t_direct
            row["echo_direct_relative_error"] = relative(direct[cpu["direct_antennas"]], cpu["direct"])
        if "intensity" in mine:
            gap = np.abs(mine["intensity"] - theirs["intensity"])
            row["intensity_max_difference"] = float(gap.max())
            row["intensity_within_target"] = float(np.mean(gap <= GPU_TARGET_INTENSITY))
        if "depth" in mine:
            row["depth_within_one_slice"] = float(np.mean(np.abs(mine["depth"] - theirs["depth"]) <= one_slice))
        views.append(row)
    return {"device": torch.cuda.get_device_name(torch.device(device)), "torch": torch.__version__,
            "facet": radar.facet, "warm_up_seconds": warm_up,
            "peak_memory_bytes": int(torch.cuda.max_memory_allocated(device)),
            "imaging_chunk_bytes": RG.DEVICE_CHUNK_BYTES, "views": views, "targets": gpu_targets(views)}


def gpu_targets(views: list[dict]) -> dict:
    """Issue 32's GPU budgets over the gpu row's views, each with a `met` flag (left out where not measured)."""
    targets = {}
    speedups = [v["speedup_echo_direct"] for v in views if "speedup_echo_direct" in v]
    if speedups:
        targets["speedup_echo_direct"] = {"target": GPU_TARGET_SPEEDUP, "measured_min": min(speedups),
                                          "met": min(speedups) >= GPU_TARGET_SPEEDUP}
    if all("intensity_max_difference" in v for v in views):
        worst = max(v["intensity_max_difference"] for v in views)
        targets["intensity_max_difference"] = {"target": GPU_TARGET_INTENSITY, "measured_max": worst,
                                               "met": worst <= GPU_TARGET_INTENSITY}
    if all("depth_within_one_slice" in v for v in views):
        least = min(v["depth_within_one_slice"] for v in views)
        targets["depth_within_one_slice"] = {"target": GPU_TARGET_DEPTH, "measured_min": least,
                                             "met": least >= GPU_TARGET_DEPTH}
    return targets


def measure(verts: np.ndarray, faces: np.ndarray, device: str = "cuda") -> dict:
    """The GPU row at default physics for a mesh (verts (n, 3) mm, faces (m, 3)); call on one core (run() does)."""
    import meshsar_builder.radar.diffuse as RD
    import meshsar_builder.radar.params as RP
    import meshsar_builder.radar.visibility as RV
    from meshsar_builder.radar.imaging import ImageParams

    radar, images = RP.RadarParams(), ImageParams()
    intersector = RV.embree_intersector(verts, faces)
    scatterers = RD.draw_scatterers(verts, faces, radar.diffuse_density_per_mm2, np.random.default_rng(0))
    cpu_views = []
    for view in radar.views:
        cpu = view_seconds(verts, faces, intersector, radar, images, view, scatterers)
        cpu_views.append({**cpu, **direct_check(verts, faces, radar, view, cpu)})
    return {"mesh_faces": int(len(faces)), "repeats": REPEATS,
            "threads": "CPU: one core: child process with " + ", ".join(f"{name}=1" for name in THREAD_VARIABLES)
                       + ", pinned with sched_setaffinity",
            **gpu_row(verts, faces, radar, images, cpu_views, scatterers, device)}


def _main(mesh_path: str, result_path: str, device: str) -> None:
    pin_one_core()
    with np.load(mesh_path) as mesh:
        write_json(result_path, measure(mesh["verts"], mesh["faces"], device))


if __name__ == "__main__":
    _main(*sys.argv[1:])
