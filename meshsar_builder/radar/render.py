"""One sample's radar data: per view visibility, echo, noise, images, the decimated echo and the loss grid's echo."""

from __future__ import annotations

import dataclasses

import math
import time

import numpy as np
import trimesh

from meshsar_builder.radar.appearance import surface_depth, view_appearance
from meshsar_builder.radar.diffuse import Scatterers, draw_scatterers, lambert, place, seen_by
from meshsar_builder.radar.echo import echo
from meshsar_builder.radar.imaging import ImageParams, view_volume, volume_images
from meshsar_builder.radar.noise import add_noise, draw_seeds, unit_noise
from meshsar_builder.radar.params import (
    SPEED_OF_LIGHT_M_PER_S,
    RadarParams,
    aperture,
    aperture_axes,
    frequencies,
    grid_indices,
    probe_points,
    view_frame,
)
from meshsar_builder.radar.visibility import embree_intersector, facet_geometry, scatterer_points, visibility


def noise_scale(signal_power: float, signal_peak: float, noise_rms: float, radar: RadarParams) -> float:
    """The noise amplitude sigma (echo units) that radar's snr_db or image_snr_db asks for; 0 for no noise.

    snr_db: sigma^2 = mean |s|^2 / 10^(snr/10), per raw sample. image_snr_db: the RMS of
    the unit noise's image (noise_rms) times sigma lies that many dB below the noise-free
    image's peak (signal_peak).
    """
    if radar.snr_db is not None:
        return 0.0 if math.isinf(radar.snr_db) else math.sqrt(signal_power / 10 ** (radar.snr_db / 10))
    if math.isinf(radar.image_snr_db) or noise_rms == 0:
        return 0.0
    return signal_peak / noise_rms / 10 ** (radar.image_snr_db / 20)


def _view_signal(tri, points, diffuse, vis, radar: RadarParams, view: str, freqs, view_echo, diffuse_on,
                 face_vis=None):
    """One view's noise-free echo (Nx, Ny, Nf) complex of the facets that it sees (vis > 0), the diffuse part's
    own mean power on the diffuse_on grid (None without a diffuse part) and its visible scatterers' count.
    face_vis: the visibility of the faces the scatterers lie on, where the facets are those faces split
    (echo_facets); default vis."""
    seen = vis > 0
    grid = aperture(radar, view)  # the numba echo factorises on the grid
    lit = seen_by(*diffuse, vis if face_vis is None else face_vis) if diffuse is not None else None
    if lit is None:
        signal = view_echo(tri[seen], vis[seen], grid, freqs, radar, points=points[seen])
        return signal.reshape(*radar.aperture, radar.n_samples), None, 0
    signal, diffuse_echo = view_echo(tri[seen], vis[seen], grid, freqs, radar, points=points[seen],
                                     diffuse=(*lit, lambert(radar)), diffuse_on=diffuse_on)
    return (signal.reshape(*radar.aperture, radar.n_samples), float(np.mean(np.abs(diffuse_echo) ** 2)),
            len(lit[2]))


def echo_facets(verts: np.ndarray, faces: np.ndarray,
                radar: RadarParams) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The facets the echo sums: the mesh, its facets wider than the plane wave holds across split.

    verts : (n, 3) float mm; faces : (m, 3) int. The facet integral (DESIGN section 4) takes the wave across
    each facet as plane; across a facet of width D at range R the round trip's curvature adds up to
    pi D^2 / (2 lambda R) of phase. Edges longer than sqrt(lambda R) / 4 (a 16th of that at the far-field
    bound's pi / 8; 7.4 mm at the defaults: the shortest wavelength, R from the mesh's point nearest an
    aperture) are bisected (trimesh; a watertight mesh stays so), which leaves the surface as it was.
    Measured on a 100 x 60 mm plate against it cut 1.25 mm fine (16 x 16 antennas 10 mm apart, 1 GHz):
    as 2 triangles 1.4 relative L2 off; split to 14.6 mm edges (the far-field bound) 0.078 facing the view and
    0.22 turned 30 degrees; to 7.5 mm 0.024 and 0.13; to 3.8 mm 0.004 and 0.041 (a turned plate's weak echo
    is mostly its edges'). The remeshed meshes (2.5 mm edges) stay whole; registered ones (a 6,000-vertex
    template stretched over a subject) reach 11.6 mm in places, and those faces are split.
    Returns (verts (j, 3), faces (q, 3), parent (q,) int, each facet's face of the input), parent None where
    nothing was split."""
    reach = max(float((verts @ view_frame(view)[2]).max()) for view in radar.views)
    wavelength_mm = 1e3 * SPEED_OF_LIGHT_M_PER_S / float(frequencies(radar).max())
    limit = math.sqrt(wavelength_mm * (radar.z0_mm - reach)) / 4
    longest = np.linalg.norm(verts[faces] - verts[np.roll(faces, 1, axis=1)], axis=2).max()
    if longest <= limit:
        return verts, faces, None
    return trimesh.remesh.subdivide_to_size(verts, faces, limit, max_iter=64, return_index=True)


def check_mesh(verts: np.ndarray, faces: np.ndarray, radar: RadarParams) -> None:
    """ValueError naming what makes a mesh one the radar cannot simulate, where it would give silent garbage.

    verts : (n, 3) float mm, heart frame; faces : (m, 3) int. Refused: non-finite vertices
    (a NaN drops its facets, the diffuse part and the rays' bounds), indices out of range,
    no faces, a face repeating another's vertices (a coplanar copy does not shadow it, so
    both echo), a closed surface wound inward (it faces away from every antenna: a blank
    sample) and a vertex at or behind a view's aperture plane (the 1 / R^2 law and the
    imaging assume targets in front of it).
    """
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ValueError(f"verts: shape must be (n, 3), got {verts.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu":
        raise ValueError(f"faces: must be (m, 3) integer vertex indices (triangles), got {faces.dtype} {faces.shape}")
    if not len(faces):
        raise ValueError("faces: the mesh has no faces")
    if faces.min() < 0 or faces.max() >= len(verts):
        raise ValueError(f"faces: vertex indices must lie in [0, {len(verts)}), got {faces.min()} to {faces.max()}")
    bad = ~np.isfinite(verts).all(axis=1)
    if bad.any():
        raise ValueError(f"verts: {int(bad.sum())} vertices have non-finite coordinates (the first: vertex "
                         f"{int(np.flatnonzero(bad)[0])})")
    _, counts = np.unique(np.sort(faces, axis=1), axis=0, return_counts=True)
    if (counts > 1).any():
        raise ValueError(f"faces: {int((counts - 1).sum())} faces repeat another face's three vertices; each copy "
                         f"would add its echo again")
    mesh = trimesh.Trimesh(verts, faces, process=False)
    if mesh.is_watertight and mesh.volume < 0:
        raise ValueError(f"faces: wound inward (the closed surface encloses {mesh.volume / 1000:.1f} ml); DESIGN "
                         f"section 4 wants them counter-clockwise seen from outside")
    for view in radar.views:
        reach = float((verts @ view_frame(view)[2]).max())
        if reach >= radar.z0_mm:
            raise ValueError(f"verts: the mesh reaches {reach:.1f} mm toward the {view} aperture, whose plane lies at "
                             f"z0_mm = {radar.z0_mm} mm: every vertex must lie in front of every aperture")


def check_field_of_view(verts: np.ndarray, radar: RadarParams, images: ImageParams) -> None:
    """ValueError where a mesh reaches beyond its images: every vertex must lie within fov_mm / 2 of the heart centre
    along each view's u and v (the pixels) and w (the range slices, z0 +- fov_mm / 2).

    verts : (n, 3) float mm, heart frame. What lies beyond is not left out but imaged wrongly: an 8 mm sphere
    90-140 mm off the axis (fov 160 mm) put the image's peak on its edge column, at 200 mm on the opposite edge
    (the aperture's 2 mm step aliases its steep angles, and the padded FFT wraps)."""
    half = images.fov_mm / 2
    for view in radar.views:
        reach = np.abs(verts @ view_frame(view).T).max(axis=0)  # (3,) along u, v, w
        axis = int(np.argmax(reach))
        if reach[axis] > half:
            raise ValueError(f"verts: the mesh reaches {reach[axis]:.1f} mm from the heart centre along the {view} "
                             f"view's {'uvw'[axis]} axis, beyond its images' fov_mm / 2 = {half:g} mm: what lies "
                             f"outside is imaged aliased onto the image, not left out; raise [images] fov_mm, or "
                             f"cut the great vessels shorter ([meshing] vessel_length_mm)")


def specular_loss_echo(verts: np.ndarray, faces: np.ndarray, radar: RadarParams) -> np.ndarray:
    """The noise-free echo (V, Lx, Ly, Lf) complex64 of a mesh's specular part on loss_grid(radar), as render_sample
    computes echo_clean (the full echo sub-sampled), with no diffuse part: `meshsar bench radar-loss` scans
    candidate meshes with it (facet "random" would draw its points from a generator seeded 0).

    verts : (n, 3) float mm, heart frame; faces : (F, 3) int; ValueError as check_mesh says.
    """
    verts, faces = np.asarray(verts, dtype=np.float64), np.asarray(faces)
    check_mesh(verts, faces, radar)
    verts, faces, _ = echo_facets(verts, faces, radar)
    points = scatterer_points(verts, faces, radar.facet, np.random.default_rng(0))
    intersector = embree_intersector(verts, faces)
    keep_loss = np.ix_(*grid_indices(radar, radar.loss_decimation))
    view_echo, _ = view_functions(radar.device)
    tri, freqs = verts[faces], frequencies(radar)
    out = []
    for view in radar.views:
        vis, _ = visibility(verts, faces, probe_points(radar, view), intersector)
        signal = _view_signal(tri, points, None, vis, radar, view, freqs, view_echo, None)[0]
        out.append(signal[keep_loss].astype(np.complex64))
    return np.stack(out)


def compile_kernels(radar: RadarParams, images: ImageParams) -> None:
    """Compile the radar's CPU kernels, or load them from numba's on-disk cache (a build's warm-up: Stage.warm):
    render_sample of a 30 mm sphere with these parameters, which runs every kernel that a heart runs (the facet
    and scatterer series, the factorised echo's interpolation, the focusing) on the same array types. One view:
    every view runs the same kernels, and the rest would be work beside the build's workers (0.35 s of a core
    each). Nothing for another device."""
    if radar.device != "cpu":
        return
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=30.0)
    one_view = dataclasses.replace(radar, views=radar.views[:1])
    render_sample(np.asarray(sphere.vertices), np.asarray(sphere.faces), one_view, images, np.random.default_rng(0))


def view_functions(device: str):
    """(echo, view_volume) of a view for radar.device: the numba echo and numpy imaging on "cpu", else torch's.

    The torch module is imported only for a CUDA device, so a CPU build never needs torch.
    All take and return numpy arrays; visibility (Embree), the diffuse scatterers and the
    noise stay on the CPU either way.
    """
    if device == "cpu":
        return echo, view_volume
    from meshsar_builder.radar import gpu

    return gpu.view_functions(device)


def render_sample(verts: np.ndarray, faces: np.ndarray, radar: RadarParams, images: ImageParams,
                  rng: np.random.Generator, scatterers: Scatterers | None = None) -> dict:
    """SAR images, decimated echo and the loss grid's noise-free echo of one mesh for every view of `radar`.

    verts : (n, 3) float mm, heart frame; faces : (F, 3) int; rng : the sample's
    generator (seeding.item_rng(seed, "radar", sample_id)). Random facet points
    (facet "random") are drawn from rng first, then one uint64 noise seed per view
    (radar.noise.draw_seeds): each (sample, view) has its own noise stream,
    radar.noise.unit_noise of its seed on the full grid, which a reader regenerates from
    the seed alone.

    scatterers : the diffuse part's scatterers (radar.diffuse), drawn on a mesh with these
    faces (the subject's reference frame, stages/radar.py); None draws them on this mesh
    from a generator spawned from rng, which leaves rng's own stream (the noise seeds) as
    it was. With radar.diffuse false there is no diffuse part and the bytes are those of
    the specular echo alone. The diffuse echo of the scatterers on visible facets (weight
    times the host facet's visibility, Lambert's law) is added to the facet echo, in the
    same call (the factorised echo interpolates both at once, and the diffuse part alone
    onto the stored echo grid for its power).

    The noise is drawn with unit power and imaged on its own (imaging is linear), so
    each view knows its image-domain noise floor and can scale the noise to
    radar.image_snr_db. Returns `sar` (V, C, H, W) float16, `echo` (V, Ex, Ey, Ef)
    complex64 on the grid of echo_grid(radar), the recorded echo (radar.noise.add_noise
    of the complex64 noise-free echo and sigma times the unit noise there), `echo_clean`
    (V, Lx, Ly, Lf) complex64, the noise-free echo on loss_grid(radar) (a sub-sample of
    the full echo computed for the images: no extra echo cost), `noise_seed` (V,) uint64,
    `noise_sigma` (V,) float64 (0 without noise), and `views`: per view a dict of `name`,
    `visible_facets` (V_k > 0), `visible_area_mm2` (sum of V_k area_k), `signal_power`
    and `noise_power` (mean per raw sample), `diffuse_power` (the diffuse echo's own mean
    power on the stored echo grid, interpolated there from its own sums; null without it) and
    `visible_scatterers`, `raw_snr_db`, `noise_floor_db` (the
    image noise's RMS in dB below the noise-free image's peak; null without noise), `rays`,
    `appearance` (radar.appearance.view_appearance: speckle share, glint contrast, depth
    error against the mesh), and `seconds` for visibility, echo (the diffuse part and its
    power included) and imaging (with the noise's draw and the appearance).

    radar.device picks where each view's echo and imaging run (view_functions); the noise
    is drawn here on the CPU from rng either way, so a CUDA build differs from a CPU
    build only by floating-point rounding. ValueError for a mesh check_mesh or check_field_of_view refuses, or a
    z0_mm within fov_mm / 2 (range slices behind the aperture).
    """
    verts, faces = np.asarray(verts, dtype=np.float64), np.asarray(faces)
    check_mesh(verts, faces, radar)
    if radar.z0_mm <= images.fov_mm / 2:
        raise ValueError(f"z0_mm: the range slices span z0 +- fov_mm / 2 = {radar.z0_mm} +- {images.fov_mm / 2} mm, "
                         f"which reaches behind the aperture: z0_mm must exceed fov_mm / 2")
    check_field_of_view(verts, radar, images)
    diffuse = None
    if radar.diffuse:  # on the mesh's own faces: a template's scatterers name them
        if scatterers is None:
            scatterers = draw_scatterers(verts, faces, radar.diffuse_density_per_mm2, rng.spawn(1)[0])
        diffuse = (*place(verts, faces, scatterers, radar), scatterers.face)
    verts, faces, parent = echo_facets(verts, faces, radar)
    tri = verts[faces]
    areas = facet_geometry(verts, faces)[2]
    face_areas = None if parent is None else np.bincount(parent, areas)  # of the faces split
    points = scatterer_points(verts, faces, radar.facet, rng)
    seeds = draw_seeds(rng, len(radar.views))
    intersector = embree_intersector(verts, faces)
    freqs = frequencies(radar)
    x_mm, y_mm = aperture_axes(radar)
    echo_indices = grid_indices(radar, radar.echo_decimation)  # (x, y, frequency) kept
    keep = np.ix_(*echo_indices)
    keep_loss = np.ix_(*grid_indices(radar, radar.loss_decimation))
    shape = (*radar.aperture, radar.n_samples)
    noisy = radar.snr_db != math.inf and radar.image_snr_db != math.inf
    view_echo, volume_of = view_functions(radar.device)
    sar, decimated, clean, sigmas, stats = [], [], [], [], []
    for view, seed in zip(radar.views, seeds):
        t0 = time.perf_counter()
        vis, rays = visibility(verts, faces, probe_points(radar, view), intersector)
        t1 = time.perf_counter()
        seen = vis > 0
        # a split face is as visible as its parts, by area
        face_vis = None if parent is None else np.divide(np.bincount(parent, vis * areas), face_areas,
                                                         out=np.zeros(len(face_areas)), where=face_areas > 0)
        signal, diffuse_power, n_scatterers = _view_signal(tri, points, diffuse, vis, radar, view, freqs, view_echo,
                                                           echo_indices, face_vis)
        t2 = time.perf_counter()
        signal_power = float(np.mean(np.abs(signal) ** 2))
        noise = unit_noise(shape, seed) if noisy else None
        volume = volume_of(signal, freqs, x_mm, y_mm, radar.z0_mm, images)
        peak = float(np.abs(volume).max())
        sigma, floor_db, image_noise = 0.0, None, 0.0
        if noisy:
            noise_volume = volume_of(noise, freqs, x_mm, y_mm, radar.z0_mm, images)
            slice_rms = np.sqrt(np.mean(np.abs(noise_volume.astype(np.complex128)) ** 2, axis=(1, 2)))  # (S,)
            noise_rms = float(np.sqrt(np.mean(slice_rms**2)))
            sigma = noise_scale(signal_power, peak, noise_rms, radar)
            if sigma > 0:
                volume = volume + np.complex64(sigma) * noise_volume
                image_noise = sigma * slice_rms  # the depth's detection test takes it at each peak's range
                floor_db = 20 * math.log10(peak / (sigma * noise_rms)) if peak > 0 else None
        sar.append(volume_images(volume, freqs, radar.z0_mm, images, image_noise))
        look = view_appearance(sar[-1], surface_depth(verts, faces, view, images, intersector), images)
        t3 = time.perf_counter()
        decimated.append(add_noise(signal[keep].astype(np.complex64), sigma, None if noise is None else noise[keep]))
        clean.append(signal[keep_loss].astype(np.complex64))
        sigmas.append(sigma)
        noise_power = sigma**2
        stats.append({
            "name": view, "visible_facets": int(seen.sum()), "visible_area_mm2": float(vis @ areas),
            "signal_power": signal_power, "noise_power": noise_power, "diffuse_power": diffuse_power,
            "visible_scatterers": n_scatterers,
            "raw_snr_db": 10 * math.log10(signal_power / noise_power) if noise_power > 0 and signal_power > 0 else None,
            "noise_floor_db": floor_db, "rays": rays, "appearance": look,
            "seconds": {"visibility": t1 - t0, "echo": t2 - t1, "imaging": t3 - t2},
        })
    return {
        "sar": np.stack(sar).astype(np.float16),
        "echo": np.stack(decimated).astype(np.complex64),
        "echo_clean": np.stack(clean),
        "noise_seed": seeds,
        "noise_sigma": np.array(sigmas, dtype=np.float64),
        "views": stats,
    }
