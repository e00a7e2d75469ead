"""The radar loss's stored target (issue 28): the loss grid's ghost level, echo_clean, the recorded noise regenerated."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import trimesh

import meshsar_builder.radar.params as RP
import meshsar_builder.radar.render as RR
from meshsar_builder.pipeline import recipe as R
from meshsar_builder.pipeline.errors import RecipeError
from meshsar_builder.radar import ghosts as G
from meshsar_builder.radar.imaging import ImageParams
from meshsar_builder.radar.noise import recorded_echo, unit_noise

SMALL = dict(aperture=(12, 10), step_mm=4.0, n_samples=24, echo_decimation=(3, 2, 2))


def ellipsoid(subdivisions=2):
    mesh = trimesh.creation.icosphere(subdivisions, radius=1.0)
    return mesh.vertices * np.array([50.0, 40.0, 60.0]), mesh.faces


# ---------------------------------------------------------------- the grid, by its ghost level


def test_default_loss_grid_keeps_ghosts_below_the_limit_and_coarser_grids_do_not():
    """Point targets at the field of view's corner nearest the radar (steepest angles: strongest grating
    lobes) and at its centre, far side (range aliases): the production grid decimated by the default
    loss_decimation stays <= -25 dB; a 4 mm aperture, or every 16th frequency, does not."""
    radar, images = RP.RadarParams(), ImageParams(size=96)
    e = images.fov_mm / 2 - G.EDGE_MARGIN_MM
    targets = [(e, e, 60.0), (0.0, 0.0, -60.0)]
    coarse_aperture, coarse_range = (2, 2, 4), (1, 1, 16)
    result = G.point_ghost_levels(radar, images, [radar.loss_decimation, coarse_aperture, coarse_range], targets)
    worst = result["worst_db"]
    assert radar.loss_decimation == RP.DEFAULT_LOSS_DECIMATION == (1, 1, 4)
    assert worst[str(list(radar.loss_decimation))] <= G.GHOST_LIMIT_DB - 15  # measured -52 dB (128 px)
    corner, centre = (result["levels_db"][str(list(d))] for d in (coarse_aperture, coarse_range))
    assert corner[0] > -6  # the corner's grating lobe is about as strong as the target itself
    assert centre[1] > G.GHOST_LIMIT_DB  # range aliases 150 mm apart: inside the 160 mm of range slices


def test_ghost_level_sees_nothing_without_decimation():
    radar, images = RP.RadarParams(aperture=(16, 16), step_mm=10.0, n_samples=16), ImageParams(size=32)
    result = G.point_ghost_levels(radar, images, [(1, 1, 1)], [(0.0, 0.0, 0.0)])
    assert result["worst_db"]["[1, 1, 1]"] == -300.0  # identical images: the floor of _level_db


def test_loss_decimation_is_validated_naming_the_key():
    with pytest.raises(ValueError, match="loss_decimation: entry 2 exceeds the grid size 64"):
        RP.RadarParams(loss_decimation=(1, 1, 100))
    with pytest.raises(ValueError, match="loss_decimation: entries must be >= 1"):
        RP.RadarParams(loss_decimation=(0, 1, 4))
    with pytest.raises(ValueError, match="loss_decimation: must be 3 integers"):
        RP.RadarParams(loss_decimation=(1, 4))
    text = 'name = "x"\n[[sources]]\nkind = "phantom"\nsubjects = 1\n[radar]\nloss_decimation = [1, 1, 128]\n'
    with pytest.raises(RecipeError, match=r"x.toml: \[radar\] loss_decimation: entry 2"):
        R.parse(text, "x.toml")


def test_loss_grid_is_the_decimated_full_grid_in_the_index():
    radar = RP.RadarParams(**SMALL, loss_decimation=(2, 1, 3))
    grid, meta = RP.loss_grid(radar), RP.index_metadata(radar, ImageParams(size=8))
    ix, iy, i_f = RP.grid_indices(radar, (2, 1, 3))
    assert list(ix) == [0, 2, 4, 6, 8, 10] and list(iy) == list(range(10))
    assert list(i_f) == [1, 4, 7, 10, 13, 16, 19, 22]
    assert np.array_equal(grid["frequencies_hz"], RP.frequencies(radar)[i_f])
    full = RP.aperture_positions(radar, "anterior").reshape(12, 10, 3)
    assert np.array_equal(grid["positions_mm"]["anterior"], full[np.ix_(ix, iy)].reshape(-1, 3))
    assert meta["loss_grid"]["frequencies_hz"] == grid["frequencies_hz"].tolist()
    assert meta["radar"]["loss_decimation"] == [2, 1, 3] and meta["radar"]["echo_decimation"] == [3, 2, 2]


# ---------------------------------------------------------------- echo_clean and the recorded noise


@pytest.mark.parametrize("noise", [dict(image_snr_db=20.0), dict(snr_db=10.0)])
def test_recorded_echo_is_regenerated_exactly_from_clean_seed_and_sigma(noise):
    """With the loss grid the full grid, the echo grid is a subset of it: echo_clean plus the noise regenerated
    from each view's seed and sigma equals the stored recorded echo bit for bit; on a coarser loss grid the
    regenerated echo is the same numbers at its own samples."""
    verts, faces = ellipsoid(2)
    images = ImageParams(size=16)
    radar = RP.RadarParams(**SMALL, **noise, views=("anterior", "left"), loss_decimation=(1, 1, 1))
    out = RR.render_sample(verts, faces, radar, images, np.random.default_rng(7))
    full = (*radar.aperture, radar.n_samples)
    keep = RP.grid_indices(radar, radar.loss_decimation)
    assert out["echo_clean"].shape == (2, *full) and out["echo_clean"].dtype == np.complex64
    assert out["noise_seed"].dtype == np.uint64 and out["noise_seed"].shape == (2,)
    assert out["noise_sigma"].dtype == np.float64 and np.all(out["noise_sigma"] > 0)
    at_echo = np.ix_(*RP.grid_indices(radar, radar.echo_decimation))
    recorded = []
    for v in range(2):
        noisy = recorded_echo(out["echo_clean"][v], out["noise_seed"][v], out["noise_sigma"][v], full, keep)
        assert noisy.dtype == np.complex64 and noisy[at_echo].tobytes() == out["echo"][v].tobytes()
        recorded.append(noisy)
    coarse = RR.render_sample(verts, faces, dataclasses.replace(radar, loss_decimation=(2, 3, 4)), images,
                              np.random.default_rng(7))
    at_loss = np.ix_(*RP.grid_indices(radar, (2, 3, 4)))
    assert coarse["echo_clean"].shape == (2, 6, 3, 6)
    assert np.array_equal(coarse["noise_seed"], out["noise_seed"]) and coarse["echo"].tobytes() == out["echo"].tobytes()
    for v in range(2):
        assert coarse["echo_clean"][v].tobytes() == out["echo_clean"][v][at_loss].tobytes()
        noisy = recorded_echo(coarse["echo_clean"][v], coarse["noise_seed"][v], coarse["noise_sigma"][v], full,
                              RP.grid_indices(radar, (2, 3, 4)))
        assert noisy.tobytes() == recorded[v][at_loss].tobytes()


@pytest.mark.parametrize("seed", [0, 1, 2**63 + 5])
def test_unit_noise_is_the_documented_draw(seed):
    """A reader of another version regenerates the same noise: pairs of standard normals from default_rng(seed),
    (real, imaginary) in that order, over sqrt(2), bit for bit (the form the build drew before it was sped up)."""
    shape = (5, 4, 6)
    pairs = np.random.default_rng(seed).standard_normal((*shape, 2))
    documented = (pairs @ np.array([1.0, 1.0j])) / np.sqrt(2)
    noise = unit_noise(shape, np.uint64(seed))
    assert noise.dtype == np.complex128 and noise.shape == shape
    assert noise.tobytes() == documented.tobytes()


def test_echo_clean_is_the_noise_free_echo():
    """The same sample without noise: the same echo_clean and seeds, sigma 0, and the recorded echo is the clean one."""
    verts, faces = ellipsoid(2)
    images = ImageParams(size=16)
    radar = RP.RadarParams(**SMALL, views=("superior",), loss_decimation=(1, 1, 1))
    noisy = RR.render_sample(verts, faces, radar, images, np.random.default_rng(3))
    clean = RR.render_sample(verts, faces, dataclasses.replace(radar, image_snr_db=math.inf), images,
                             np.random.default_rng(3))
    assert noisy["echo_clean"].tobytes() == clean["echo_clean"].tobytes()
    assert np.array_equal(noisy["noise_seed"], clean["noise_seed"]) and clean["noise_sigma"].tolist() == [0.0]
    at_echo = np.ix_(*RP.grid_indices(radar, radar.echo_decimation))
    assert clean["echo"][0].tobytes() == clean["echo_clean"][0][at_echo].tobytes()
    assert noisy["echo"][0].tobytes() != clean["echo"][0].tobytes()
    # The noise added is sigma times the seed's unit noise: its power is sigma^2.
    added = noisy["echo"][0].astype(complex) - clean["echo"][0]
    unit = unit_noise((*radar.aperture, radar.n_samples), noisy["noise_seed"][0])[at_echo]
    np.testing.assert_allclose(added, noisy["noise_sigma"][0] * unit, rtol=0, atol=1e-6 * np.abs(noisy["echo"]).max())
