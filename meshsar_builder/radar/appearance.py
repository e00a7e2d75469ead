"""What a view's images look like against the mesh they image: speckle share, glint contrast, depth error.

Per view (DESIGN section 5 images, issue 29):
- `speckle_share`: the share of the heart's silhouette (pixels whose ray along -w meets the
  mesh) whose intensity lies within SPECKLE_WITHIN_DB of the view's peak: speckle-dominated
  images fill the silhouette, specular glints cover a few patches of it;
- `peak_over_median_db`: the view's peak over the median intensity inside the silhouette
  (a lower bound where the median is below the displayed range): glints stay visible;
- `depth_error_median_mm`, `depth_within_5mm`: per detected pixel (depth channel non-zero),
  the distance along its ray from the depth read to where the ray meets the mesh; a
  detected pixel whose ray misses the mesh counts as infinitely far.
"""

from __future__ import annotations

import numpy as np

from meshsar_builder.radar.imaging import ImageParams, pixel_centres
from meshsar_builder.radar.params import view_frame
from meshsar_builder.radar.visibility import embree_intersector

SPECKLE_WITHIN_DB = 20.0


def surface_depth(verts: np.ndarray, faces: np.ndarray, view: str, images: ImageParams,
                  intersector=None) -> np.ndarray:
    """(H, W) float: the w (mm, heart frame) where each pixel's ray along -w first meets the mesh, NaN if it misses.

    verts : (n, 3) float mm, heart frame; faces : (F, 3) int. Rays start beyond the mesh's
    extent on the radar's side, through the pixel centres (radar.imaging.pixel_centres).
    """
    verts = np.asarray(verts, dtype=np.float64)
    intersector = embree_intersector(verts, faces) if intersector is None else intersector
    u_axis, v_axis, w_axis = view_frame(view)
    u, v = pixel_centres(images.size, images.fov_mm)
    start = float(np.abs(verts).max()) * 2 + 1.0
    grid = v[:, None, None] * v_axis + u[None, :, None] * u_axis + start * w_axis  # (H, W, 3)
    origins = grid.reshape(-1, 3)
    directions = np.broadcast_to(-w_axis, origins.shape)
    depth = np.full(len(origins), np.nan)
    locations, ray, _ = intersector.intersects_location(origins, directions, multiple_hits=False)
    depth[ray] = locations @ w_axis
    return depth.reshape(images.size, images.size)


def view_appearance(channels: np.ndarray, surface_w: np.ndarray, images: ImageParams) -> dict:
    """The figures above for one view from its channels (C, H, W) (radar.imaging.volume_images) and surface_depth (H, W)."""
    names = list(images.channels)
    intensity = np.asarray(channels[names.index("intensity")], dtype=np.float64)
    inside = np.isfinite(surface_w)
    out = {"silhouette_px": int(inside.sum())}
    if inside.any():
        decibels = (intensity[inside] - 1) * images.dynamic_range_db
        out["speckle_share"] = float(np.mean(decibels >= -SPECKLE_WITHIN_DB))
        out["peak_over_median_db"] = float(-np.median(decibels))
    if "depth" in names:
        depth = np.asarray(channels[names.index("depth")], dtype=np.float64)
        detected = depth != 0
        error = np.abs(depth * images.fov_mm / 2 - surface_w)[detected]
        error[~np.isfinite(error)] = np.inf
        out["detected_px"] = int(detected.sum())
        if detected.any():
            out["depth_error_median_mm"] = float(np.median(error))
            out["depth_within_5mm"] = float(np.mean(error <= 5.0))
    return out
