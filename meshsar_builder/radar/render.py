"""One sample's radar data: per view visibility, echo, noise, SAR images and the decimated echo."""

from __future__ import annotations

import time

import numpy as np

from meshsar_builder.radar.echo import add_noise, echo
from meshsar_builder.radar.imaging import ImageParams, view_images
from meshsar_builder.radar.params import (
    RadarParams,
    aperture_axes,
    aperture_positions,
    decimation_indices,
    frequencies,
    probe_points,
)
from meshsar_builder.radar.visibility import embree_intersector, facet_geometry, scatterer_points, visibility


def render_sample(verts: np.ndarray, faces: np.ndarray, radar: RadarParams, images: ImageParams,
                  rng: np.random.Generator) -> dict:
    """SAR images and decimated echo of one mesh for every view of `radar`.

    verts : (n, 3) float mm, heart frame; faces : (F, 3) int; rng : the sample's
    generator (seeding.item_rng(seed, "radar", sample_id)). Random scatterers are
    drawn from rng first, then view i's noise comes from the i-th of
    rng.spawn(len(views)), so each (sample, view) has its own noise stream.

    Returns `sar` (V, C, H, W) float16, `echo` (V, Ex, Ey, Ef) complex64 on the grid
    of echo_grid(radar), and `views`: per view a dict of `name`, `visible_facets`
    (V_k > 0), `visible_area_mm2` (sum of V_k area_k), `signal_power`,
    `noise_power`, `rays`, and `seconds` for visibility, echo and imaging.
    """
    verts, faces = np.asarray(verts, dtype=np.float64), np.asarray(faces)
    _, normals, areas = facet_geometry(verts, faces)
    points = scatterer_points(verts, faces, radar.scatterer, rng)
    noise_rngs = rng.spawn(len(radar.views))
    intersector = embree_intersector(verts, faces)
    freqs = frequencies(radar)
    x_mm, y_mm = aperture_axes(radar)
    keep_x, keep_y, keep_f = (decimation_indices(size, factor) for size, factor
                              in zip((*radar.aperture, radar.n_samples), radar.echo_decimation))
    sar, decimated, stats = [], [], []
    for view, noise_rng in zip(radar.views, noise_rngs):
        t0 = time.perf_counter()
        vis, rays = visibility(verts, faces, probe_points(radar, view), intersector)
        t1 = time.perf_counter()
        seen = vis > 0
        signal = echo(points[seen], normals[seen], (vis * areas)[seen], aperture_positions(radar, view), freqs, radar)
        signal_power = float(np.mean(np.abs(signal) ** 2))
        signal, noise_power = add_noise(signal, radar.snr_db, noise_rng)
        signal = signal.reshape(*radar.aperture, radar.n_samples)
        t2 = time.perf_counter()
        sar.append(view_images(signal, freqs, x_mm, y_mm, radar.z0_mm, images))
        t3 = time.perf_counter()
        decimated.append(signal[np.ix_(keep_x, keep_y, keep_f)])
        stats.append({
            "name": view, "visible_facets": int(seen.sum()), "visible_area_mm2": float(vis @ areas),
            "signal_power": signal_power, "noise_power": noise_power, "rays": rays,
            "seconds": {"visibility": t1 - t0, "echo": t2 - t1, "imaging": t3 - t2},
        })
    return {
        "sar": np.stack(sar).astype(np.float16),
        "echo": np.stack(decimated).astype(np.complex64),
        "views": stats,
    }
