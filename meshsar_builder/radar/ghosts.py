"""Ghost level of a decimated echo grid: how much aliasing a sub-sampled echo adds to its focused image.

The radar loss's stored target, `echo_clean`, lives on a decimation of the production
echo grid (`[radar] loss_decimation`, DESIGN section 7). Sub-sampling the aperture by
a_x, a_y makes the antenna step a_x * step_mm, whose grating lobes lie about
lambda R / (2 a_x step) from a target (139 mm at 81 GHz for a 4 mm step at 300 mm,
inside a 160 mm field of view); sub-sampling the frequencies by a_f makes range
periodic with c / (2 a_f df). The grid is chosen by measurement, here:

    ghost level = max over the focused volume, outside the target's main lobe, of
                  |I_dec| / max |I_dec| - |I_ref| / max |I_ref|             (in dB)

I_ref is the focused image (radar.imaging.view_volume: the production window, image grid
and range slices) of the reference grid's echo, I_dec that of the same echo sub-sampled
to the candidate grid. Only what decimating adds counts: the reference's own sidelobes
cancel, a grating lobe or a range alias shows at its full level. The main lobe is the
voxels within EXCLUDE_LATERAL_MM across and EXCLUDE_RANGE_MM in range of the target, where
the coarser grid's wider or narrower lobe is a change of resolution, not a ghost.

Targets are the worst case: point scatterers near the field of view's edges and corners,
at the front, centre and back of a heart's depth (edge_targets), each facing the
aperture centre with the recipe's reflectivity pattern, so each antenna sees it; the
largest level over them is the grid's. mesh_ghost_level measures an extended target
(the facet echo of a mesh, visibility included) the same way, over the whole volume.
"""

from __future__ import annotations

import math

import numpy as np

from meshsar_builder.radar.echo import echo as facet_echo
from meshsar_builder.radar.echo import point_echo
from meshsar_builder.radar.imaging import ImageParams, pixel_centres, range_slices, view_volume
from meshsar_builder.radar.params import (
    RadarParams,
    aperture_axes,
    aperture_positions,
    decimation_indices,
    frequencies,
    probe_points,
    view_frame,
)

# The issue-28 criterion: the loss grid's ghost level inside the field of view.
GHOST_LIMIT_DB = -25.0
# The main lobe left out around a point target: ~3 cross-range resolutions of the default
# aperture (lambda R / 2L = 3.5 mm; the Hann window doubles it), and one range resolution
# (c / 2B = 37.5 mm) either side. Grating lobes of any grid coarser than the production
# one lie >= 90 mm away, range aliases >= c / (2 a_f df) = 150 mm for a_f <= 16.
EXCLUDE_LATERAL_MM = 12.0
EXCLUDE_RANGE_MM = 37.5
# Worst-case targets: this far inside the field of view's edge, and at these depths along w
# (mm from the heart centre toward the radar; a heart reaches about +-60 mm).
EDGE_MARGIN_MM = 5.0
DEPTHS_MM = (-60.0, 0.0, 60.0)


def edge_targets(images: ImageParams, depths_mm: tuple[float, ...] = DEPTHS_MM) -> np.ndarray:
    """(T, 3) view coordinates (u, v, w) mm of the worst-case point targets.

    The centre, the middle of an edge along u, along v, and a corner, each at every depth:
    e = fov / 2 - EDGE_MARGIN_MM. A corner target seen from the nearest depth makes the
    steepest angles to the aperture, so its grating lobes are the strongest.
    """
    e = images.fov_mm / 2 - EDGE_MARGIN_MM
    return np.array([(u, v, w) for w in depths_mm for u, v in ((0.0, 0.0), (e, 0.0), (0.0, e), (e, e))])


def _decimated(radar: RadarParams, decimation) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kept indices along x, y and frequency of `radar`'s full grid for decimation (ax, ay, af)."""
    return tuple(decimation_indices(size, factor)
                 for size, factor in zip((*radar.aperture, radar.n_samples), decimation))


def _normalised_magnitude(echo: np.ndarray, keep, radar: RadarParams, images: ImageParams) -> np.ndarray:
    """|focused volume| / its maximum, (S, H, W) float64, of the full-grid echo sub-sampled at keep."""
    x_mm, y_mm = aperture_axes(radar)
    freqs = frequencies(radar)
    kx, ky, kf = keep
    volume = view_volume(echo[np.ix_(kx, ky, kf)], freqs[kf], x_mm[kx], y_mm[ky], radar.z0_mm, images)
    magnitude = np.abs(volume).astype(np.float64)
    return magnitude / max(float(magnitude.max()), 1e-300)


def _level_db(added: np.ndarray) -> float:
    return 20 * math.log10(max(float(added.max()), 1e-15)) if added.size else -math.inf


def _voxel_coordinates(radar: RadarParams, images: ImageParams, freqs: np.ndarray):
    """(w (S,), v (H,), u (W,)) of the focused volume's voxel centres, view coordinates in mm."""
    u, v = pixel_centres(images.size, images.fov_mm)
    w = radar.z0_mm - range_slices(radar.z0_mm, images.fov_mm, freqs)
    return w, v, u


def point_ghost_levels(radar: RadarParams, images: ImageParams, decimations, targets: np.ndarray | None = None,
                       view: str = "anterior") -> dict:
    """Ghost level (dB) of each decimation for each point target, against the full grid of `radar`.

    decimations : list of (ax, ay, af); targets : (T, 3) view coordinates (u, v, w) mm,
    default edge_targets(images). Returns {"targets": (T, 3) list, "levels_db": {str(dec):
    [T levels]}, "worst_db": {str(dec): max level}}. The reference is radar's own grid
    (decimation (1, 1, 1) reads -inf): to measure the production grid itself, pass a
    finer radar and decimate it to the production step.
    """
    targets = edge_targets(images) if targets is None else np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    frame = view_frame(view)
    positions = aperture_positions(radar, view)
    centre = radar.z0_mm * frame[2]
    freqs = frequencies(radar)
    shape = (*radar.aperture, radar.n_samples)
    w_vox, v_vox, u_vox = _voxel_coordinates(radar, images, freqs)
    keeps = {tuple(d): _decimated(radar, d) for d in decimations}
    full = _decimated(radar, (1, 1, 1))
    levels = {str(list(d)): [] for d in keeps}
    for u, v, w in targets:
        point = u * frame[0] + v * frame[1] + w * frame[2]
        normal = (centre - point) / np.linalg.norm(centre - point)
        echo = point_echo(point[None], normal[None], np.ones(1), positions, freqs, radar).reshape(shape)
        reference = _normalised_magnitude(echo, full, radar, images)
        lobe = ((np.abs(w_vox - w) <= EXCLUDE_RANGE_MM)[:, None, None]
                & (np.hypot(v_vox[:, None] - v, u_vox[None, :] - u) <= EXCLUDE_LATERAL_MM)[None])
        for d, keep in keeps.items():
            added = _normalised_magnitude(echo, keep, radar, images) - reference
            levels[str(list(d))].append(_level_db(added[~lobe]))
    return {"targets": targets.tolist(), "levels_db": levels,
            "worst_db": {key: max(values) for key, values in levels.items()}}


def mesh_ghost_level(verts: np.ndarray, faces: np.ndarray, radar: RadarParams, images: ImageParams, decimations,
                     view: str = "anterior") -> dict[str, float]:
    """Ghost level (dB) of each decimation for a mesh's noise-free facet echo, over the whole volume.

    verts (n, 3) mm in the heart frame, faces (m, 3). Visibility and the echo are those of
    the build (radar.render); no main lobe is left out, so the figure also counts how the
    coarser grid reshapes the surface's own lobes: an upper bound on its ghosts.
    """
    from meshsar_builder.radar.visibility import embree_intersector, visibility

    verts, faces = np.asarray(verts, dtype=np.float64), np.asarray(faces)
    vis, _ = visibility(verts, faces, probe_points(radar, view), embree_intersector(verts, faces))
    seen = vis > 0
    freqs = frequencies(radar)
    echo = facet_echo(verts[faces][seen], vis[seen], aperture_positions(radar, view), freqs, radar)
    echo = echo.reshape(*radar.aperture, radar.n_samples)
    reference = _normalised_magnitude(echo, _decimated(radar, (1, 1, 1)), radar, images)
    return {str(list(d)): _level_db(_normalised_magnitude(echo, _decimated(radar, d), radar, images) - reference)
            for d in decimations}


CANDIDATES = ((1, 1, 2), (1, 1, 4), (1, 1, 8), (1, 1, 16), (2, 2, 1), (2, 2, 4), (2, 2, 8), (3, 3, 4), (4, 4, 4),
              (5, 5, 2))


def main() -> None:
    """`python -m meshsar_builder.radar.ghosts`: the candidate grids' ghost levels at the default radar, as JSON.

    Point targets (edge_targets) against the production grid; the production grid itself
    (step 2 mm) against a 1 mm aperture of the same extent; a heart-sized ellipsoid
    (100 x 80 x 120 mm, 20,480 facets) per default view. About two minutes on one core.
    """
    import json

    import trimesh

    radar, images = RadarParams(), ImageParams()
    points = point_ghost_levels(radar, images, CANDIDATES)
    fine = RadarParams(aperture=(2 * radar.aperture[0] - 1, 2 * radar.aperture[1] - 1), step_mm=radar.step_mm / 2)
    production = point_ghost_levels(fine, images, [(2, 2, 1), (2, 2, 4), (2, 2, 8)])
    sphere = trimesh.creation.icosphere(5)
    verts = sphere.vertices * np.array([50.0, 40.0, 60.0])
    meshes = {view: mesh_ghost_level(verts, sphere.faces, radar, images, CANDIDATES, view) for view in radar.views}
    print(json.dumps({"limit_db": GHOST_LIMIT_DB, "default": list(radar.loss_decimation), "point_targets": points,
                      "production_grid_against_1mm": production, "ellipsoid": meshes}, indent=1))


if __name__ == "__main__":
    main()
