"""The echo's diffuse (speckle) part (radar/diffuse.py, issue 29): scatterers, echo, and speckle statistics.

Statistics are taken as issue 29 asks: on the linear intensity |I|^2 of the focused volume at
the plate's range, a PSF width away from the edges, one sample per resolution cell, pooled
over seeds, window "none".
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import trimesh
from scipy import stats

import meshsar_builder.radar.diffuse as RD
import meshsar_builder.radar.echo as RE
import meshsar_builder.radar.params as RP
import meshsar_builder.radar.render as RR
import meshsar_builder.radar.visibility as RV
from meshsar_builder.bench import speckle as SP
from meshsar_builder.radar.imaging import ImageParams

SEEDS = range(5)


def plate(width_mm, height_mm, step_mm=2.0, jitter=0.0, seed=0):
    """speckle.plate, its interior vertices moved in the plane by up to jitter steps: another tessellation."""
    verts, faces = SP.plate(width_mm, height_mm, step_mm)
    if jitter:
        frame = RP.view_frame("anterior")
        u, v = verts @ frame[0], verts @ frame[1]
        inner = (np.abs(u) < width_mm / 2 - 1e-6) & (np.abs(v) < height_mm / 2 - 1e-6)
        shift = np.random.default_rng(seed).uniform(-jitter, jitter, (len(verts), 2)) * step_mm * inner[:, None]
        verts = verts + shift[:, :1] * frame[0] + shift[:, 1:] * frame[1]
    return verts, faces


# ------------------------------------------------------------------ scatterers


def test_scatterers_follow_the_area_whatever_the_tessellation():
    """The count is density x area (within one scatterer) on two tessellations; every point lies in its face."""
    for jitter in (0.0, 0.3):
        verts, faces = plate(100.0, 60.0, step_mm=2.0 if not jitter else 3.0, jitter=jitter)
        area = trimesh.Trimesh(verts, faces, process=False).area
        s = RD.draw_scatterers(verts, faces, 0.25, np.random.default_rng(1))
        assert abs(len(s.face) - 0.25 * area) <= 1
        assert np.all(s.bary >= 0) and np.allclose(s.bary.sum(axis=1), 1)
        # no clumps: every 20 x 20 mm patch holds its share within a few scatterers
        points, _, _ = RD.place(verts, faces, s, RP.RadarParams())
        u = points @ RP.view_frame("anterior")[0]
        counts = np.histogram(u, bins=5, range=(-50, 50))[0]
        assert np.all(np.abs(counts - 0.25 * area / 5) <= 0.25 * area / 5 * 0.15)


def test_same_seed_same_scatterers_and_frames_move_them_with_the_surface():
    verts, faces = plate(60.0, 40.0)
    a = RD.draw_scatterers(verts, faces, 0.5, np.random.default_rng(7))
    b = RD.draw_scatterers(verts, faces, 0.5, np.random.default_rng(7))
    assert all(np.array_equal(x, y) for x, y in zip(dataclasses.astuple(a), dataclasses.astuple(b)))
    radar = RP.RadarParams()
    points, _, weights = RD.place(verts, faces, a, radar)
    # another frame: the same faces stretched 2x along u; scatterers keep their barycentric place
    stretched = verts * np.array([2.0, 1.0, 1.0])
    moved, _, stretched_weights = RD.place(stretched, faces, a, radar)
    np.testing.assert_allclose(moved, points * np.array([2.0, 1.0, 1.0]), atol=1e-9)
    # the amplitude follows the local area change: twice the area, twice the power
    np.testing.assert_allclose(np.abs(stretched_weights) ** 2, 2 * np.abs(weights) ** 2, rtol=1e-12)
    # the expected power is beta x area, whatever the density
    area = trimesh.Trimesh(verts, faces, process=False).area
    dense = RD.draw_scatterers(verts, faces, 4.0, np.random.default_rng(3))
    for s in (a, dense):
        power = np.sum(np.abs(RD.place(verts, faces, s, radar)[2]) ** 2)
        expected = RD.mean_power_per_area(radar) * area
        assert power == pytest.approx(expected, rel=5 / math.sqrt(len(s.face)))


def test_scatterers_refuse_a_mesh_with_other_faces():
    verts, faces = plate(20.0, 20.0)
    s = RD.draw_scatterers(verts, faces, 1.0, np.random.default_rng(0))
    with pytest.raises(ValueError, match="faces: the scatterers were drawn on a mesh of"):
        RD.place(verts, faces[:-2], s, RP.RadarParams())


def test_bad_diffuse_keys_name_the_key():
    with pytest.raises(ValueError, match="diffuse_density_per_mm2: must lie in"):
        RP.RadarParams(diffuse_density_per_mm2=0.0)
    with pytest.raises(ValueError, match="diffuse_sigma0_db: must be finite"):
        RP.RadarParams(diffuse_sigma0_db=-math.inf)
    with pytest.raises(ValueError, match="diffuse: must be true or false"):
        RP.RadarParams(diffuse="yes")


# ------------------------------------------------------------------ the echo


def test_complex_weights_match_the_direct_sum():
    """The production kernel's phase row against the direct sum's complex weights."""
    radar = RP.RadarParams(aperture=(12, 12), step_mm=8.0)
    verts, faces = plate(60.0, 60.0, step_mm=4.0)
    s = RD.draw_scatterers(verts, faces, 0.3, np.random.default_rng(2))
    points, normals, weights = RD.place(verts + np.array([3.0, 5.0, -2.0]), faces, s, radar)
    args = (points, normals, weights, RP.aperture_positions(radar, "anterior"), RP.frequencies(radar),
            RD.lambert(radar))
    fast, direct = RE.point_echo(*args, method="chebyshev"), RE.point_echo(*args, method="direct")
    assert np.linalg.norm(fast - direct) / np.linalg.norm(direct) <= 1e-8
    # linear in the weights: a real weight's echo is the complex one's with a zero phase
    real = RE.point_echo(points, normals, np.abs(weights), *args[3:])
    rotated = RE.point_echo(points, normals, np.abs(weights) * np.exp(0.7j), *args[3:])
    np.testing.assert_allclose(rotated, real * np.exp(0.7j), rtol=0, atol=1e-9 * np.abs(real).max())


def test_render_adds_the_diffuse_echo_and_off_gives_the_specular_bytes():
    verts = trimesh.creation.icosphere(2, radius=40.0).vertices * np.array([1.0, 0.8, 1.2])
    faces = trimesh.creation.icosphere(2, radius=40.0).faces
    radar = RP.RadarParams(aperture=(12, 10), step_mm=10.0, n_samples=24, echo_decimation=(1, 1, 1),
                           loss_decimation=(1, 1, 1), image_snr_db=math.inf, views=("left",))
    images = ImageParams(size=16)
    off = RR.render_sample(verts, faces, dataclasses.replace(radar, diffuse=False), images, np.random.default_rng(5))
    again = RR.render_sample(verts, faces, dataclasses.replace(radar, diffuse=False, diffuse_sigma0_db=-3.0),
                             images, np.random.default_rng(5))
    on = RR.render_sample(verts, faces, radar, images, np.random.default_rng(5))
    # off: the same bytes whatever the diffuse keys; the noise seeds do not move when it is on
    assert off["sar"].tobytes() == again["sar"].tobytes() and off["echo"].tobytes() == again["echo"].tobytes()
    assert off["views"][0]["diffuse_power"] is None and np.array_equal(off["noise_seed"], on["noise_seed"])
    # on: the specular echo plus the scatterers' own echo, visibility-weighted, under Lambert's law
    s = RD.draw_scatterers(verts, faces, radar.diffuse_density_per_mm2, np.random.default_rng(5).spawn(1)[0])
    points, normals, weights = RD.place(verts, faces, s, radar)
    vis, _ = RV.visibility(verts, faces, RP.probe_points(radar, "left"))
    lit = vis[s.face] > 0
    diffuse = RE.point_echo(points[lit], normals[lit], weights[lit] * vis[s.face][lit],
                            RP.aperture_positions(radar, "left"), RP.frequencies(radar), RD.lambert(radar),
                            method="direct")
    got = on["echo_clean"][0].reshape(diffuse.shape) - off["echo_clean"][0].reshape(diffuse.shape)
    assert np.linalg.norm(got - diffuse) / np.linalg.norm(diffuse) <= 1e-5
    assert on["views"][0]["visible_scatterers"] == lit.sum() > 0
    # its own power where the shards keep the echo: here the full grid
    np.testing.assert_allclose(on["views"][0]["diffuse_power"], np.mean(np.abs(diffuse) ** 2), rtol=1e-6)


def test_diffuse_power_is_the_diffuse_echo_on_the_stored_echo_grid():
    verts = trimesh.creation.icosphere(2, radius=40.0).vertices
    faces = trimesh.creation.icosphere(2, radius=40.0).faces
    radar = RP.RadarParams(aperture=(12, 10), step_mm=10.0, n_samples=24, echo_decimation=(3, 2, 4),
                           loss_decimation=(1, 1, 1), image_snr_db=math.inf, views=("superior",))
    on = RR.render_sample(verts, faces, radar, ImageParams(size=16), np.random.default_rng(2))
    s = RD.draw_scatterers(verts, faces, radar.diffuse_density_per_mm2, np.random.default_rng(2).spawn(1)[0])
    vis, _ = RV.visibility(verts, faces, RP.probe_points(radar, "superior"))
    lit = RD.seen_by(*RD.place(verts, faces, s, radar), s.face, vis)
    full = RE.point_echo(*lit, RP.aperture_positions(radar, "superior"), RP.frequencies(radar), RD.lambert(radar),
                         method="direct").reshape(12, 10, 24)
    kept = full[np.ix_(*RP.grid_indices(radar, radar.echo_decimation))]
    assert kept.size == 4 * 5 * 6
    # interpolated there from the factorised echo's clusters: within twice its diffuse part's budget (1-4e-4)
    np.testing.assert_allclose(on["views"][0]["diffuse_power"], np.mean(np.abs(kept) ** 2), rtol=1e-3)


# ------------------------------------------------------------------ speckle statistics


@pytest.fixture(scope="module")
def plates():
    """|I|^2 at the plate's range for a 100 x 60 mm plate and the same plate twice as tall, per seed."""
    small, large = SP.plate(100.0, 60.0), SP.plate(100.0, 120.0)
    return {name: [SP.diffuse_intensity(*mesh, seed) for seed in SEEDS]
            for name, mesh in (("small", small), ("large", large))}


def test_diffuse_plate_speckle_is_fully_developed(plates):
    """Contrast std / mean of intensity 1 +- 0.1; amplitude Rayleigh (Lilliefors-type: scale estimated)."""
    pooled = np.concatenate([SP.interior(i, 100.0, 60.0).ravel() for i in plates["small"]])
    pooled = pooled / pooled.mean()
    assert len(pooled) >= 1000
    assert pooled.std() == pytest.approx(1.0, abs=0.1)
    # |I|^2 exponential <=> |I| Rayleigh; the scale is fitted, so the null distribution is simulated
    fit = stats.goodness_of_fit(stats.expon, pooled, known_params={"loc": 0.0}, statistic="ks",
                                n_mc_samples=199, rng=np.random.default_rng(0))
    assert fit.pvalue > 0.01, fit
    # and not a test that cannot fail: a plate with one scatterer per 20 mm^2 is patchy, not exponential
    sparse = RP.RadarParams(diffuse_density_per_mm2=0.05)
    patchy = np.concatenate([SP.interior(SP.diffuse_intensity(*SP.plate(100.0, 60.0), s, sparse), 100.0, 60.0).ravel()
                             for s in SEEDS])
    assert patchy.std() / patchy.mean() > 1.2


def test_twice_the_plate_twice_the_power_same_mean_intensity(plates):
    small = np.mean([i.sum() for i in plates["small"]])
    large = np.mean([i.sum() for i in plates["large"]])
    assert 10 * math.log10(large / small) == pytest.approx(3.0, abs=0.5)
    mean_small = np.mean([SP.interior(i, 100.0, 60.0).mean() for i in plates["small"]])
    mean_large = np.mean([SP.interior(i, 100.0, 120.0).mean() for i in plates["large"]])
    assert abs(10 * math.log10(mean_large / mean_small)) <= 0.5


def test_speckle_grain_is_the_psf(plates):
    """Autocovariance of the mean-subtracted intensity: FWHM within 25 % of the PSF intensity's -3 dB width."""
    assert SP.grain_over_psf(plates["small"], 100.0, 60.0) == pytest.approx(1.0, rel=0.25)


def test_fwhm_of_a_gaussian():
    x = np.arange(-40, 41) * 0.5
    assert SP.fwhm_mm(np.exp(-x**2 / (2 * 3.0**2)), 0.5) == pytest.approx(2 * math.sqrt(2 * math.log(2)) * 3.0, rel=1e-3)


def test_frames_sharing_scatterers_give_correlated_speckle():
    """Check (d) on a beating ellipsoid: attached scatterers correlate frame to frame, fresh draws do not."""
    sphere = trimesh.creation.icosphere(3, radius=1.0)
    base = sphere.vertices * np.array([50.0, 40.0, 35.0])
    frames = [base * (1 - 0.01 * i) for i in range(4)]  # 1 % contraction per frame: ~0.5 mm
    radar = RP.RadarParams(aperture=(32, 32), step_mm=5.0, n_samples=32)
    corr = SP.cycle_correlation(frames, sphere.faces, 0.25, seed=3, radar=radar)
    assert corr["shared"][1] > 0.9 and corr["shared"][1] > corr["fresh"][1] + 0.3
    # the correlation fades as the frames move further apart
    assert corr["shared"][1] > corr["shared"][2] > corr["shared"][3]
    # fresh draws keep only the glints in common (measured 0.23-0.27 here); with the diffuse
    # part dominant, nothing: the speckle itself is independent
    rough = SP.cycle_correlation(frames, sphere.faces, 0.25, seed=3,
                                 radar=dataclasses.replace(radar, diffuse_sigma0_db=20.0))
    assert all(abs(value) < 0.1 for value in rough["fresh"].values()) and rough["shared"][1] > 0.9


def test_appearance_measures_silhouette_share_and_depth_against_the_mesh():
    """radar.appearance on a plate facing the anterior view, with channels made by hand."""
    from meshsar_builder.radar.appearance import surface_depth, view_appearance

    verts, faces = SP.plate(60.0, 40.0)
    images = ImageParams(size=32)
    surface = surface_depth(verts + RP.view_frame("anterior")[2] * 7.0, faces, "anterior", images)
    inside = np.isfinite(surface)
    assert inside.mean() == pytest.approx(60 * 40 / 160**2, abs=0.02) and np.allclose(surface[inside], 7.0)
    intensity = np.where(inside, 1.0, 0.0)
    intensity[inside.nonzero()[0][0], inside.nonzero()[1][0]] = 0.4  # one pixel 24 dB down
    depth = np.where(inside, (7.0 + 4.0) / (images.fov_mm / 2), 0.0)  # read 4 mm off the plate
    look = view_appearance(np.stack([intensity, depth]), surface, images)
    assert look["speckle_share"] == pytest.approx(1 - 1 / inside.sum())
    assert look["depth_error_median_mm"] == pytest.approx(4.0) and look["depth_within_5mm"] == 1.0
    depth[~inside] = 0.5  # detections off the mesh count as infinitely far
    look = view_appearance(np.stack([intensity, depth]), surface, images)
    assert look["detected_px"] == depth.size and look["depth_within_5mm"] == pytest.approx(inside.mean())


def test_multilooked_depth_follows_a_tilted_diffuse_plate():
    """A plate turned 35 deg about v, diffuse part alone: each pixel's peak range scatters by
    several mm (speckle); multilooked it reads the plane within a PSF's share of its slope."""
    from scipy.ndimage import binary_erosion
    from scipy.spatial.transform import Rotation

    from meshsar_builder.radar.appearance import surface_depth
    from meshsar_builder.radar.imaging import view_volume, volume_images

    radar, freqs = RP.RadarParams(), RP.frequencies(RP.RadarParams())
    verts, faces = SP.plate(80.0, 60.0)
    verts = verts @ Rotation.from_rotvec(np.radians(35) * RP.view_frame("anterior")[1]).as_matrix().T
    surface = surface_depth(verts, faces, "anterior", ImageParams())
    inside = binary_erosion(np.isfinite(surface), iterations=6)  # a PSF width from the edges
    errors = {0.0: [], 3.0: []}
    for seed in range(3):
        scatterers = RD.draw_scatterers(verts, faces, radar.diffuse_density_per_mm2, np.random.default_rng(seed))
        points, normals, weights = RD.place(verts, faces, scatterers, radar)
        echo = RE.point_echo(points, normals, weights, RP.aperture(radar, "anterior"), freqs, RD.lambert(radar))
        volume = view_volume(echo.reshape(*radar.aperture, -1), freqs, *RP.aperture_axes(radar), radar.z0_mm,
                             ImageParams())
        for looks in errors:
            depth = volume_images(volume, freqs, radar.z0_mm, ImageParams(depth_looks_mm=looks))[1]
            assert (depth[inside] != 0).all()
            errors[looks].append(depth[inside] * 80.0 - surface[inside])
    own, looked = np.concatenate(errors[0.0]), np.concatenate(errors[3.0])
    assert np.median(np.abs(own)) > 3.5  # speckle: the per-pixel peak range is this far off
    assert np.median(np.abs(looked)) < 0.5 * np.median(np.abs(own)) and np.median(np.abs(looked)) < 2.0
    # Range migration with this aperture reads ~1 mm towards the radar (test_sar), per pixel or looked.
    assert abs(np.median(looked)) < 1.5 and np.mean(np.abs(looked) <= 5.0) > 0.95
