"""Speckle statistics of the diffuse part on a flat plate (issue 29 item 3), for `meshsar bench radar` and the tests.

Measured as a radar imaging researcher would: on the linear intensity |I|^2 of the focused
volume at the plate's range (the anterior view, the plate in its (u, v) plane at w = 0,
facing the radar), a PSF width away from the edges, one sample per resolution cell, pooled
over seeds, window "none" unless said otherwise.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

import meshsar_builder.radar.diffuse as RD
import meshsar_builder.radar.echo as RE
import meshsar_builder.radar.params as RP
from meshsar_builder.radar.imaging import ImageParams, pixel_centres, range_slices, view_volume
from meshsar_builder.radar.visibility import facet_geometry

NO_WINDOW = ImageParams(window="none")


def plate(width_mm: float, height_mm: float, step_mm: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """A flat plate in the anterior view's (u, v) plane at w = 0, facing the radar: verts (n, 3) mm, faces (F, 3)."""
    nu, nv = int(round(width_mm / step_mm)) + 1, int(round(height_mm / step_mm)) + 1
    u, v = np.meshgrid(np.linspace(-width_mm / 2, width_mm / 2, nu), np.linspace(-height_mm / 2, height_mm / 2, nv),
                       indexing="ij")
    frame = RP.view_frame("anterior")
    verts = u.reshape(-1, 1) * frame[0] + v.reshape(-1, 1) * frame[1]
    idx = np.arange(nu * nv).reshape(nu, nv)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    _, normals, _ = facet_geometry(verts, faces)
    back = normals @ frame[2] < 0
    faces[back] = faces[back][:, ::-1]
    return verts, faces


def diffuse_intensity(verts, faces, seed: int, radar: RP.RadarParams | None = None,
                      images: ImageParams = NO_WINDOW) -> np.ndarray:
    """|I|^2 (H, W) at w = 0 of a mesh's diffuse echo alone (every scatterer seen), anterior view."""
    radar = radar or RP.RadarParams()
    scatterers = RD.draw_scatterers(verts, faces, radar.diffuse_density_per_mm2, np.random.default_rng(seed))
    points, normals, weights = RD.place(verts, faces, scatterers, radar)
    return point_intensity(points, normals, weights, radar, images)


def point_intensity(points, normals, weights, radar: RP.RadarParams | None = None,
                    images: ImageParams = NO_WINDOW) -> np.ndarray:
    """|I|^2 (H, W) at w = 0 of point scatterers (K, 3) under Lambert's law, anterior view."""
    radar = radar or RP.RadarParams()
    freqs = RP.frequencies(radar)
    echo = RE.point_echo(points, normals, weights, RP.aperture_positions(radar, "anterior"), freqs, RD.lambert(radar))
    volume = view_volume(echo.reshape(*radar.aperture, -1), freqs, *RP.aperture_axes(radar), radar.z0_mm, images)
    d = range_slices(radar.z0_mm, images.fov_mm, freqs)
    return np.abs(volume[int(np.argmin(np.abs(d - radar.z0_mm)))].astype(np.complex128)) ** 2


def resolution_mm(radar: RP.RadarParams | None = None) -> float:
    """Cross-range resolution lambda_min z0 / (2 L), L the aperture's length (the PSF's first null, window none)."""
    radar = radar or RP.RadarParams()
    wavelength = RP.SPEED_OF_LIGHT_M_PER_S * 1e3 / RP.frequencies(radar).max()
    return wavelength * radar.z0_mm / (2 * radar.aperture[0] * radar.step_mm)


def interior(intensity: np.ndarray, width_mm: float, height_mm: float, images: ImageParams = NO_WINDOW,
             every_cell: bool = True) -> np.ndarray:
    """The plate's pixels (rows v, columns u) a PSF width (2 resolutions) from its edges; one per resolution cell."""
    margin = 2 * resolution_mm()
    u, v = pixel_centres(images.size, images.fov_mm)
    inside = intensity[np.ix_(np.abs(v) < height_mm / 2 - margin, np.abs(u) < width_mm / 2 - margin)]
    step = max(1, math.ceil(resolution_mm() / (images.fov_mm / images.size))) if every_cell else 1
    return inside[::step, ::step]


def fwhm_mm(profile: np.ndarray, spacing_mm: float) -> float:
    """Full width at half maximum of a single-peaked profile (linear interpolation between samples)."""
    peak = int(np.argmax(profile))
    half = profile[peak] / 2
    right = peak + int(np.argmax(profile[peak:] < half))
    left = peak - int(np.argmax(profile[peak::-1] < half))
    hi = right - 1 + (profile[right - 1] - half) / (profile[right - 1] - profile[right])
    lo = left + 1 - (profile[left + 1] - half) / (profile[left + 1] - profile[left])
    return float((hi - lo) * spacing_mm)


def grain_over_psf(intensities: list[np.ndarray], width_mm: float, height_mm: float,
                   images: ImageParams = NO_WINDOW) -> float:
    """FWHM of the mean-subtracted intensity's autocovariance along u (mean over the images) over the PSF intensity's."""
    radar, pixel = RP.RadarParams(), images.fov_mm / images.size
    psf = point_intensity(np.zeros((1, 3)), RP.view_frame("anterior")[2][None], np.ones(1), radar, images)
    psf_width = fwhm_mm(psf[np.unravel_index(np.argmax(psf), psf.shape)[0]], pixel)
    widths = []
    for intensity in intensities:
        patch = interior(intensity, width_mm, height_mm, images, every_cell=False)
        centred = patch - patch.mean()
        power = np.abs(np.fft.fft2(centred, s=[2 * n for n in centred.shape])) ** 2  # zero-padded: no wrap-around
        autocovariance = np.fft.fftshift(np.real(np.fft.ifft2(power)))
        widths.append(fwhm_mm(autocovariance[autocovariance.shape[0] // 2], pixel))
    return float(np.mean(widths) / psf_width)


def plate_statistics(seeds: int = 5) -> dict:
    """Issue 29's checks (a) and (b) at the default density and sigma0: a 100 x 60 mm plate and one twice as tall.

    `contrast` (std / mean of pooled intensity, 1 for fully developed speckle), `ks_pvalue`
    (exponential intensity, scale fitted: a Lilliefors-type test by Monte Carlo),
    `doubled_area_power_db` (+3 expected), `doubled_area_mean_db` (0 expected),
    `grain_over_psf` (window none, 1 expected) and `grain_over_psf_hann` (about 1.29).
    """
    from scipy import stats

    small, large = plate(100.0, 60.0), plate(100.0, 120.0)
    hann = dataclasses.replace(NO_WINDOW, window="hann")
    images = {"small": [diffuse_intensity(*small, s) for s in range(seeds)],
              "large": [diffuse_intensity(*large, s) for s in range(seeds)]}
    pooled = np.concatenate([interior(i, 100.0, 60.0).ravel() for i in images["small"]])
    pooled = pooled / pooled.mean()
    fit = stats.goodness_of_fit(stats.expon, pooled, known_params={"loc": 0.0}, statistic="ks", n_mc_samples=199,
                                rng=np.random.default_rng(0))
    power = {k: np.mean([i.sum() for i in v]) for k, v in images.items()}
    mean = {"small": np.mean([interior(i, 100.0, 60.0).mean() for i in images["small"]]),
            "large": np.mean([interior(i, 100.0, 120.0).mean() for i in images["large"]])}
    return {
        "seeds": seeds, "pooled_cells": int(len(pooled)),
        "contrast": float(pooled.std()),
        "ks_pvalue": float(fit.pvalue),
        "doubled_area_power_db": float(10 * math.log10(power["large"] / power["small"])),
        "doubled_area_mean_db": float(10 * math.log10(mean["large"] / mean["small"])),
        "grain_over_psf": grain_over_psf(images["small"], 100.0, 60.0),
        "grain_over_psf_hann": grain_over_psf([diffuse_intensity(*small, s, images=hann) for s in range(seeds)],
                                              100.0, 60.0, hann),
    }


# ------------------------------------------------------------------ speckle over a cycle, tessellation (checks c, d)

CYCLE_VIEW = "anterior"
# The speckle component is intensity over its local mean: a Gaussian of this many mm (about three
# PSF widths of the Hann-windowed images) takes the mean.
LOCAL_MEAN_SIGMA_MM = 8.0
# Display range for the linear intensity read back from the channel: wide, so little is clipped.
WIDE = ImageParams(dynamic_range_db=80.0)


def view_intensity(verts, faces, scatterers, seed: int, radar: RP.RadarParams | None = None,
                   images: ImageParams = WIDE) -> tuple[np.ndarray, np.ndarray]:
    """Linear intensity (H, W) of CYCLE_VIEW without noise, and the silhouette mask (H, W), for a mesh and its scatterers."""
    from meshsar_builder.radar.appearance import surface_depth
    from meshsar_builder.radar.render import render_sample

    radar = dataclasses.replace(radar or RP.RadarParams(), views=(CYCLE_VIEW,), image_snr_db=math.inf)
    sar = render_sample(verts, faces, radar, images, np.random.default_rng(seed), scatterers)["sar"][0, 0]
    intensity = 10 ** ((sar.astype(np.float64) - 1) * images.dynamic_range_db / 10)
    return intensity, np.isfinite(surface_depth(verts, faces, CYCLE_VIEW, images))


def speckle_component(intensity: np.ndarray, images: ImageParams = WIDE) -> np.ndarray:
    """Intensity (H, W) over its local mean (Gaussian of LOCAL_MEAN_SIGMA_MM)."""
    from scipy.ndimage import gaussian_filter

    local = gaussian_filter(intensity, LOCAL_MEAN_SIGMA_MM / (images.fov_mm / images.size))
    return intensity / np.maximum(local, np.finfo(float).tiny)


def ncc(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """Normalised cross-correlation of two images over mask."""
    x, y = a[mask] - a[mask].mean(), b[mask] - b[mask].mean()
    return float((x * y).sum() / np.sqrt((x * x).sum() * (y * y).sum()))


def cycle_correlation(frames: list[np.ndarray], faces: np.ndarray, density: float, seed: int,
                      radar: RP.RadarParams | None = None) -> dict:
    """Speckle NCC against frame spacing for frames verts (n, 3) sharing faces (F, 3), heart frame.

    `shared`: the scatterers drawn once on the first frame and attached by face and
    barycentric coordinates (the build's frames in correspondence); `fresh`: drawn anew on
    every frame. Per spacing k, the mean NCC of the speckle components of frames i and i + k
    over the pixels inside both silhouettes.
    """
    shared = RD.draw_scatterers(frames[0], faces, density, np.random.default_rng(seed))
    components = {"shared": [], "fresh": []}
    masks = []
    for i, verts in enumerate(frames):
        fresh = RD.draw_scatterers(verts, faces, density, np.random.default_rng([seed, i + 1]))
        for kind, scatterers in (("shared", shared), ("fresh", fresh)):
            intensity, mask = view_intensity(verts, faces, scatterers, seed, radar)
            components[kind].append(speckle_component(intensity))
        masks.append(mask)
    out = {}
    for kind, images in components.items():
        out[kind] = {}
        for spacing in range(1, len(frames)):
            pairs = [ncc(images[i], images[i + spacing], masks[i] & masks[i + spacing])
                     for i in range(len(frames) - spacing)]
            out[kind][spacing] = float(np.mean(pairs))
    return out


def silhouette_statistics(verts, faces, seeds: int, density: float) -> dict:
    """Mean linear intensity and contrast (std / mean) inside CYCLE_VIEW's silhouette, each averaged over seeds.

    The whole image (specular and diffuse, no noise); the scatterers are drawn on this mesh.
    """
    means, contrasts = [], []
    for seed in range(seeds):
        scatterers = RD.draw_scatterers(verts, faces, density, np.random.default_rng(seed))
        intensity, mask = view_intensity(verts, faces, scatterers, seed)
        means.append(intensity[mask].mean())
        contrasts.append(intensity[mask].std() / intensity[mask].mean())
    return {"mean_intensity": float(np.mean(means)), "contrast": float(np.mean(contrasts))}


def run(out_dir, data, surface, frames: int = 10, seeds: int = 5) -> dict:
    """`meshsar bench speckle`: checks (c) and (d) of issue 29 on a build; writes out_dir/speckle.json.

    (c) `surface` (verts (n, 3), faces (F, 3): the demo heart before remeshing) remeshed at
    2.5 and 1.25 mm edges: mean intensity and contrast inside
    the silhouette within 5 %, over `seeds` draws. (d) the build's first beating subject:
    speckle NCC against frame spacing over its first `frames` frames in correspondence, with
    the scatterers attached (shared) and drawn anew per frame (fresh); and two shape-model
    samples' speckle components, which should not correlate.
    """
    from pathlib import Path

    from meshsar_builder.dataset.frames import merge_cycles
    from meshsar_builder.geometry.meshfile import read_ply
    from meshsar_builder.geometry.remesh import RemeshParams, remesh
    from meshsar_builder.pipeline.errors import InputError
    from meshsar_builder.pipeline.io import read_json, write_json

    data = Path(data)
    density = RP.RadarParams().diffuse_density_per_mm2
    tessellations = {}
    for edge in (2.5, 1.25):
        verts, faces = remesh(*surface, RemeshParams(edge_mm=edge))
        verts = verts - (verts.min(axis=0) + verts.max(axis=0)) / 2
        tessellations[edge] = {"faces": int(len(faces)), **silhouette_statistics(verts, faces, seeds, density)}
    coarse, fine = tessellations[2.5], tessellations[1.25]
    tessellation = {"edges_mm": tessellations,
                    "mean_difference": abs(coarse["mean_intensity"] / fine["mean_intensity"] - 1),
                    "contrast_difference": abs(coarse["contrast"] / fine["contrast"] - 1)}

    cycles = merge_cycles(read_json(path) for path in sorted((data / "track").glob("*-cycle-*.json"))
                          if not path.name.startswith("."))  # a sidecar, not a temporary being written
    if not cycles:
        raise InputError(f"bench speckle: {data} has no beating subject (track stage); build manifests/demo.toml there")
    track = cycles[0]
    center = np.asarray(read_json(data / "remesh" / f"{track['reference']}.json")["center_mm"])
    ids = [mid for mid in track["frames"] if mid in track["in_correspondence"]][:frames]
    meshes = [read_ply(data / "track" / f"{mid}.ply") for mid in ids]
    cycle = cycle_correlation([v - center for v, _, _ in meshes], meshes[0][1], density, seed=0)
    samples = sorted((data / "ssm" / "samples").glob("*.ply"))[:2]
    components, masks = [], []
    for k, path in enumerate(samples):
        verts, faces, _ = read_ply(path)
        verts = verts - (verts.min(axis=0) + verts.max(axis=0)) / 2
        scatterers = RD.draw_scatterers(verts, faces, density, np.random.default_rng(k))
        intensity, mask = view_intensity(verts, faces, scatterers, k)
        components.append(speckle_component(intensity))
        masks.append(mask)
    two_subjects = ncc(*components, masks[0] & masks[1])
    result = {
        "data": str(data), "seeds": seeds, "frames": ids, "view": CYCLE_VIEW,
        "tessellation": tessellation, "cycle_ncc": cycle, "two_subjects": [p.stem for p in samples],
        "two_subjects_ncc": two_subjects,
        "targets": {
            "speckle_tessellation_mean": {"target": "<= 0.05", "measured": tessellation["mean_difference"],
                                          "met": tessellation["mean_difference"] <= 0.05},
            "speckle_tessellation_contrast": {"target": "<= 0.05", "measured": tessellation["contrast_difference"],
                                              "met": tessellation["contrast_difference"] <= 0.05},
            "speckle_frames_correlate": {"target": "shared NCC at spacing 1 > fresh + 0.3",
                                         "measured": [cycle["shared"][1], cycle["fresh"][1]],
                                         "met": cycle["shared"][1] > cycle["fresh"][1] + 0.3},
            "speckle_two_subjects_ncc": {"target": "< 0.1", "measured": two_subjects, "met": abs(two_subjects) < 0.1},
        },
    }
    write_json(Path(out_dir) / "speckle.json", result)
    return result
