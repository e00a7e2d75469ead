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
