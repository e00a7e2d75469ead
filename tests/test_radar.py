"""Radar echo: parameters, views, visibility, echo accuracy, noise and seeding."""

import dataclasses
import json
import math

import numpy as np
import pytest
import trimesh

import meshsar_builder.radar.echo as RE
import meshsar_builder.radar.params as RP
import meshsar_builder.radar.series as RS
import meshsar_builder.radar.render as RR
import meshsar_builder.radar.visibility as RV
from meshsar_builder.pipeline.errors import MeshsarError
from meshsar_builder.radar.imaging import ImageParams

SMALL = dict(aperture=(12, 10), step_mm=4.0, n_samples=24, echo_decimation=(3, 2, 2))


def small_radar(**overrides):
    return RP.RadarParams(**{**SMALL, **overrides})


def ellipsoid(subdivisions=2):
    mesh = trimesh.creation.icosphere(subdivisions, radius=1.0)
    return mesh.vertices * np.array([50.0, 40.0, 60.0]), mesh.faces


# ------------------------------------------------------------------ parameters and geometry


@pytest.mark.parametrize("field, value, words", [
    ("views", ("anterior", "lateral"), "views: unknown view"),
    ("step_mm", 0.0, "step_mm: must be positive"),
    ("snr_db", float("nan"), "snr_db"),
    ("facet", "vertex", "facet: must be one of"),
    ("reflectivity", "phong", "reflectivity: must be one of"),
    ("image_snr_db", float("nan"), "image_snr_db"),
    ("echo_decimation", (5, 5, 100), "echo_decimation: entry 2"),
    ("aperture", (80,), "aperture: must be 2 integers"),
    ("kappa", 1.5, "kappa: must lie in [0, 1]"),
    ("device", "gpu", 'device: must be "cpu", "cuda" or "cuda:N"'),
    ("device", "cuda:", "device: must be"),
])
def test_bad_parameters_name_the_field(field, value, words):
    with pytest.raises(ValueError, match=words.replace("[", r"\[").replace("]", r"\]")):
        RP.RadarParams(**{field: value})


def test_one_noise_setting_at_a_time():
    assert RP.RadarParams().image_snr_db == RP.DEFAULT_IMAGE_SNR_DB and RP.RadarParams().snr_db is None
    assert RP.RadarParams(snr_db=30).image_snr_db is None
    with pytest.raises(ValueError, match="set one of snr_db"):
        RP.RadarParams(snr_db=30.0, image_snr_db=25.0)


def test_parameters_accept_recipe_values():
    radar = RP.RadarParams(z0_mm=300, views=["left"], aperture=[40, 40], snr_db=float("inf"))
    assert radar.z0_mm == 300.0 and isinstance(radar.z0_mm, float)
    assert radar.views == ("left",) and radar.aperture == (40, 40)


@pytest.mark.parametrize("view", list(RP.VIEW_FRAMES))
def test_view_frames_are_right_handed_and_orthonormal(view):
    u, v, w = RP.view_frame(view)
    np.testing.assert_allclose(RP.view_frame(view) @ RP.view_frame(view).T, np.eye(3))
    np.testing.assert_allclose(np.cross(u, v), w)


def test_aperture_is_centred_on_the_view_axis_at_z0_row_major():
    radar = small_radar()
    positions = RP.aperture_positions(radar, "left")
    u, v, w = RP.view_frame("left")
    np.testing.assert_allclose(positions.mean(axis=0), radar.z0_mm * w, atol=1e-12)
    np.testing.assert_allclose(positions @ w, radar.z0_mm)
    grid = positions.reshape(*radar.aperture, 3)
    np.testing.assert_allclose((grid[1, 0] - grid[0, 0]) @ u, radar.step_mm)  # first axis runs along u
    np.testing.assert_allclose((grid[0, 1] - grid[0, 0]) @ v, radar.step_mm)


def test_frequencies_follow_the_chirp():
    radar = RP.RadarParams(t0_s=2e-6)
    f = RP.frequencies(radar)
    assert f[0] == pytest.approx(77e9 + 100e12 * 2e-6)
    assert f[-1] - f[0] == pytest.approx(100e12 * 63 / 1.6e6)
    assert len(f) * (f[1] - f[0]) == pytest.approx(4.0e9)


def test_decimation_keeps_a_centred_grid():
    np.testing.assert_array_equal(RP.decimation_indices(80, 5), np.arange(2, 80, 5))
    np.testing.assert_array_equal(RP.decimation_indices(64, 2), np.arange(0, 64, 2))
    grid = RP.echo_grid(RP.RadarParams())
    assert grid["frequencies_hz"].shape == (32,)
    for view, positions in grid["positions_mm"].items():
        assert positions.shape == (256, 3)
        np.testing.assert_allclose(positions.mean(axis=0), 300.0 * RP.view_frame(view)[2], atol=1e-9)


def test_index_metadata_is_plain_json_with_the_contract_keys():
    meta = RP.index_metadata(RP.RadarParams(snr_db=math.inf), ImageParams())
    text = json.dumps(meta, allow_nan=False)
    assert set(json.loads(text)) >= {"views", "fov_mm", "image_size", "channels", "radar", "echo_grid", "loss_grid"}
    assert set(meta["radar"]) == {"f0_hz", "slope_hz_per_s", "fs_hz", "n_samples", "t0_s", "aperture", "step_mm",
                                  "z0_mm", "snr_db", "image_snr_db", "rvp", "p", "kappa", "facet",
                                  "reflectivity", "probes", "echo_decimation", "loss_decimation", "diffuse",
                                  "diffuse_sigma0_db", "diffuse_density_per_mm2"}
    assert meta["radar"]["loss_decimation"] == [1, 1, 4] and meta["radar"]["echo_decimation"] == [5, 5, 2]
    assert len(meta["loss_grid"]["positions_mm"]["left"]) == 80 * 80 and len(meta["loss_grid"]["frequencies_hz"]) == 16
    assert meta["radar"]["snr_db"] is None and meta["radar"]["image_snr_db"] is None
    assert [v["name"] for v in meta["views"]] == ["anterior", "left", "superior"]
    assert len(meta["echo_grid"]["positions_mm"]["left"]) == 16 * 16


# ------------------------------------------------------------------ visibility


def test_intersector_is_embree():
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    verts, faces = ellipsoid(1)
    assert isinstance(RV.embree_intersector(verts, faces), RayMeshIntersector)


def test_occlusion_query_answers_as_the_closest_hit_search():
    """EmbreeOccluder (any hit) and trimesh's intersector (closest hit) block the same rays on
    tori turned to every axis (each view sees one part of the ring behind another), from
    every view's probes, and give the same visibility."""
    rings = []
    for k, axis in enumerate(np.eye(3)):
        ring = trimesh.creation.torus(major_radius=40.0, minor_radius=12.0, major_sections=48, minor_sections=16)
        ring.apply_transform(trimesh.geometry.align_vectors([0, 0, 1], axis))
        ring.apply_translation(np.roll([120.0, 0, 0], k))
        rings.append(ring)
    mesh = trimesh.util.concatenate(rings)
    verts, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    radar = RP.RadarParams()
    probe_sets = [RP.probe_points(radar, view) for view in radar.views]
    closest, rays = RV.visibilities(verts, faces, probe_sets, RV.embree_intersector(verts, faces))
    occluded, same_rays = RV.visibilities(verts, faces, probe_sets, RV.EmbreeOccluder(verts, faces))
    assert rays == same_rays
    for a, b in zip(closest, occluded):
        np.testing.assert_array_equal(a, b)
    facing = sum(np.count_nonzero(np.einsum("fc,fpc->fp", RV.facet_geometry(verts, faces)[1],
                                            p[None] - RV.facet_geometry(verts, faces)[0][:, None]) > 0)
                 for p in probe_sets)
    assert sum(np.count_nonzero(v) for v in occluded) and rays == facing
    assert any(np.any((v > 0) & (v < 1)) for v in occluded)  # partly hidden facets: occlusion happened


def test_convex_sphere_is_about_half_visible_and_never_self_occluded():
    mesh = trimesh.creation.icosphere(3, radius=40.0)
    radar = RP.RadarParams()
    probes = RP.probe_points(radar, "anterior")
    vis, rays = RV.visibility(mesh.vertices, mesh.faces, probes)
    centres, normals, areas = RV.facet_geometry(mesh.vertices, mesh.faces)
    facing = np.einsum("fc,fpc->fp", normals, probes[None] - centres[:, None]) > 0
    # Convex: a facet sees every probe it faces.
    np.testing.assert_array_equal(vis, facing.mean(axis=1))
    assert rays == facing.sum()
    # The cap seen from distance D is (1 - r/D) / 2 of the sphere: 0.43 at 40 / 300 mm.
    fraction = vis @ areas / areas.sum()
    assert 0.38 < fraction < 0.5


def test_facet_behind_a_plate_is_hidden_and_one_beside_it_is_seen():
    tiny = np.array([[-1.0, 0, -1], [1, 0, -1], [0, 0, 1]])  # normal +y: faces the anterior radar
    verts = np.concatenate([
        tiny,
        tiny + [200.0, 0, 0],
        [[-30.0, 50, -30], [30, 50, -30], [30, 50, 30], [-30, 50, 30]],  # plate at y = 50
    ])
    faces = np.array([[0, 2, 1], [3, 5, 4], [6, 7, 8], [6, 8, 9]])
    _, normals, _ = RV.facet_geometry(verts, faces)
    assert normals[0] @ [0, 1, 0] > 0.99
    vis, _ = RV.visibility(verts, faces, RP.probe_points(RP.RadarParams(), "anterior"))
    assert vis[0] == 0.0
    assert vis[1] == 1.0


# ------------------------------------------------------------------ echo


def test_single_scatterer_echo_matches_the_formula():
    radar = small_radar(kappa=0.2, p=3.0)
    point, normal = np.array([[5.0, -10.0, 7.0]]), np.array([[0.0, 0.6, 0.8]])
    positions = RP.aperture_positions(radar, "superior")
    f = RP.frequencies(radar)
    offset = positions - point
    r = np.linalg.norm(offset, axis=1)
    cos = offset @ normal[0] / r
    gain = np.where(cos > 0, 0.8 * cos**3 + 0.2 * cos, 0)
    tau = 2 * r * 1e-3 / RP.SPEED_OF_LIGHT_M_PER_S
    expected = (2.5 * gain / r**2)[:, None] * np.exp(
        2j * np.pi * f[None] * tau[:, None] - 1j * np.pi * radar.slope_hz_per_s * tau[:, None] ** 2
    )
    for method in RP.ECHO_METHODS:
        got = RE.point_echo(point, normal, [2.5], positions, f, radar, method=method)
        np.testing.assert_allclose(got, expected, rtol=2e-6, atol=2e-6 * np.abs(expected).max())


def relative_error(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def echo_case(mesh_name, overrides, view="left"):
    """Arguments of RE.echo for the visible facets of a test mesh, on a 16 x 16 aperture; and its keywords."""
    radar = RP.RadarParams(**{"aperture": (16, 16), "step_mm": 5.0, **overrides})
    mesh = {
        "icosphere": lambda: trimesh.creation.icosphere(3, radius=50.0),
        "torus": lambda: trimesh.creation.torus(major_radius=45.0, minor_radius=15.0),
        "box": lambda: trimesh.creation.box((90.0, 70.0, 110.0)).subdivide().subdivide(),
    }[mesh_name]()
    assert mesh.is_watertight
    points = RV.scatterer_points(mesh.vertices, mesh.faces, radar.facet, np.random.default_rng(1))
    vis, _ = RV.visibility(mesh.vertices, mesh.faces, RP.probe_points(radar, view))
    seen = vis > 0
    args = (mesh.triangles[seen], vis[seen], RP.aperture_positions(radar, view), RP.frequencies(radar), radar)
    return args, {"points": points[seen]}


@pytest.mark.parametrize("mesh_name, overrides", [
    ("icosphere", {}),
    ("icosphere", {"facet": "centroid"}),
    ("icosphere", {"rvp": False, "t0_s": 3e-6, "n_samples": 50, "reflectivity": "po"}),
    ("torus", {"facet": "random", "p": 2.5, "kappa": 0.1}),
    ("torus", {"p": 2.5, "kappa": 0.1}),
    ("torus", {"p": 3.0, "n_samples": 256, "z0_mm": 150.0}),  # a 16 GHz sweep: 37 terms
    ("box", {"n_samples": 16, "f0_hz": 60e9}),  # facets parallel to the aperture: the exact pairs
])
def test_chebyshev_echo_matches_direct(mesh_name, overrides):
    args, keywords = echo_case(mesh_name, overrides)
    fast, direct = RE.echo(*args, method="chebyshev", **keywords), RE.echo(*args, method="direct", **keywords)
    assert relative_error(fast, direct) <= 1e-6


def test_chebyshev_echo_is_deterministic_under_threads():
    """Same bytes on repeats and from concurrent threads (the kernel is serial and releases the GIL)."""
    from concurrent.futures import ThreadPoolExecutor

    args, _ = echo_case("icosphere", {})
    first = RE.echo(*args).tobytes()
    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(lambda _: RE.echo(*args).tobytes(), range(4)))
    assert all(result == first for result in results)


@pytest.mark.parametrize("aperture, level, antennas", [
    ((6, 5), 2, "RP.aperture_positions(radar, 'left')"),  # the per-pair series
    ((80, 80), 3, "RP.aperture(radar, 'left')"),  # factorised: its interpolation's BLAS products too
])
def test_echo_bytes_do_not_depend_on_thread_settings(aperture, level, antennas):
    """BLAS, OpenMP and numba thread counts of 1 and 2 give the same echo bytes."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    script = (
        "import hashlib, numpy as np, trimesh\n"
        "import meshsar_builder.radar.echo as RE, meshsar_builder.radar.params as RP\n"
        f"radar = RP.RadarParams(aperture={aperture}, n_samples=16)\n"
        f"mesh = trimesh.creation.icosphere({level}, radius=50.0)\n"
        f"out = RE.echo(mesh.triangles, np.ones(len(mesh.faces)), {antennas}, RP.frequencies(radar), radar)\n"
        "print(hashlib.sha256(out.tobytes()).hexdigest())\n"
    )
    digests = set()
    for threads in ("1", "2"):
        env = {**os.environ, **{name: threads for name in (
            "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")}}
        run = subprocess.run([sys.executable, "-c", script], env=env, cwd=Path(__file__).parents[1],
                             capture_output=True, text=True, check=True)
        digests.add(run.stdout.strip())
    assert len(digests) == 1


def test_chebyshev_echo_needs_uniform_frequencies():
    args, _ = echo_case("box", {"n_samples": 7})
    args = list(args)
    args[3] = args[3] * np.linspace(1, 1.01, 7) ** 2
    with pytest.raises(ValueError, match="uniformly spaced"):
        RE.echo(*args, method="chebyshev")
    RE.echo(*args, method="direct")


def test_missing_numba_is_a_clear_error(monkeypatch):
    monkeypatch.setattr(RS, "_NUMBA_MISSING", "the radar echo needs numba (pip install numba)")
    with pytest.raises(MeshsarError, match="needs numba"):
        RE.echo(*echo_case("box", {"n_samples": 7})[0])


def test_echo_without_scatterers_is_zero():
    radar = small_radar()
    for facet in RP.FACET_MODELS:
        out = RE.echo(np.zeros((0, 3, 3)), np.zeros(0), RP.aperture_positions(radar, "left"),
                      RP.frequencies(radar), dataclasses.replace(radar, facet=facet))
        assert out.shape == (120, 24) and not out.any()


def test_random_scatterers_lie_inside_their_facets():
    verts, faces = ellipsoid(2)
    points = RV.scatterer_points(verts, faces, "random", np.random.default_rng(3))
    tri = verts[faces]
    bary = trimesh.triangles.points_to_barycentric(tri, points)
    assert (bary > -1e-9).all()
    np.testing.assert_allclose(bary.sum(axis=1), 1.0)
    centres, normals, _ = RV.facet_geometry(verts, faces)
    np.testing.assert_allclose(np.einsum("fc,fc->f", points - centres, normals), 0, atol=1e-9)
    assert not np.allclose(points, centres)


@pytest.mark.parametrize("snr_db", [0.0, 12.0, 30.0])
def test_raw_noise_has_the_asked_snr(snr_db):
    verts, faces = ellipsoid(2)
    radar = small_radar(snr_db=snr_db, views=("left",))
    clean = RR.render_sample(verts, faces, dataclasses.replace(radar, snr_db=math.inf), ImageParams(size=16),
                             np.random.default_rng(5))
    noisy = RR.render_sample(verts, faces, radar, ImageParams(size=16), np.random.default_rng(5))
    stats = noisy["views"][0]
    assert stats["noise_power"] == pytest.approx(stats["signal_power"] / 10 ** (snr_db / 10))
    assert stats["raw_snr_db"] == pytest.approx(snr_db)
    added = noisy["echo"].astype(complex) - clean["echo"]
    measured = 10 * np.log10(stats["signal_power"] / np.mean(np.abs(added) ** 2))
    assert abs(measured - snr_db) < 1.0  # the decimated echo's 60 samples: within a dB
    assert clean["views"][0]["noise_floor_db"] is None and clean["views"][0]["noise_power"] == 0


@pytest.mark.parametrize("image_snr_db", [15.0, 25.0])
def test_image_noise_floor_sits_where_asked(image_snr_db):
    """The image of the added noise alone has its RMS image_snr_db below the noise-free image's peak."""
    from meshsar_builder.radar.imaging import view_volume

    verts, faces = ellipsoid(2)
    radar = small_radar(image_snr_db=image_snr_db, views=("anterior",))
    images = ImageParams(size=16)
    clean = dataclasses.replace(radar, image_snr_db=math.inf)
    out = RR.render_sample(verts, faces, radar, images, np.random.default_rng(8))
    assert out["views"][0]["noise_floor_db"] == pytest.approx(image_snr_db)
    # Independently: image the noise that the echo carries (full echo rebuilt on a grid without decimation).
    full = dataclasses.replace(radar, echo_decimation=(1, 1, 1))
    noisy = RR.render_sample(verts, faces, full, images, np.random.default_rng(8))["echo"][0].astype(complex)
    noise_free = RR.render_sample(verts, faces, dataclasses.replace(clean, echo_decimation=(1, 1, 1)), images,
                                  np.random.default_rng(8))["echo"][0].astype(complex)
    x, y = RP.aperture_axes(radar)
    f = RP.frequencies(radar)
    peak = np.abs(view_volume(noise_free, f, x, y, radar.z0_mm, images)).max()
    rms = np.sqrt(np.mean(np.abs(view_volume(noisy - noise_free, f, x, y, radar.z0_mm, images)) ** 2))
    assert 20 * np.log10(peak / rms) == pytest.approx(image_snr_db, abs=0.1)


def test_render_sample_is_seeded_and_shaped():
    verts, faces = ellipsoid(2)
    radar = small_radar(facet="random", snr_db=30.0, views=("anterior", "superior"))
    images = ImageParams(size=16)
    first = RR.render_sample(verts, faces, radar, images, np.random.default_rng(11))
    again = RR.render_sample(verts, faces, radar, images, np.random.default_rng(11))
    other = RR.render_sample(verts, faces, radar, images, np.random.default_rng(12))
    assert first["sar"].shape == (2, 2, 16, 16) and first["sar"].dtype == np.float16
    assert first["echo"].shape == (2, 4, 5, 12) and first["echo"].dtype == np.complex64
    assert first["sar"].tobytes() == again["sar"].tobytes()
    assert first["echo"].tobytes() == again["echo"].tobytes()
    assert first["echo"].tobytes() != other["echo"].tobytes()
    facets = len(RR.echo_facets(verts, faces, radar)[1])  # its long facets split
    for stats in first["views"]:
        assert 0 < stats["visible_facets"] < facets
        assert stats["noise_power"] == pytest.approx(stats["signal_power"] / 1000)
    intensity = first["sar"][:, 0].astype(np.float32)
    assert intensity.max() == 1.0 and intensity.min() >= 0.0


def test_decimated_echo_is_the_full_echo_on_the_echo_grid():
    verts, faces = ellipsoid(1)
    radar = small_radar(snr_db=math.inf, views=("left",), diffuse=False)  # the diffuse part: test_diffuse
    out = RR.render_sample(verts, faces, radar, ImageParams(size=8), np.random.default_rng(0))
    verts, faces, _ = RR.echo_facets(verts, faces, radar)  # its long facets split
    vis, _ = RV.visibility(verts, faces, RP.probe_points(radar, "left"))
    grid = RP.echo_grid(radar)
    seen = vis > 0
    expected = RE.echo(verts[faces][seen], vis[seen], grid["positions_mm"]["left"], grid["frequencies_hz"], radar,
                       method="direct")
    np.testing.assert_allclose(out["echo"][0].reshape(expected.shape), expected, rtol=0,
                               atol=1e-5 * np.abs(expected).max())


def test_chebyshev_echo_matches_direct_on_a_phantom_heart(tmp_path):
    """A whole-heart phantom mesh, visible facets weighted as the radar stage does, one view."""
    from meshsar_builder.dataset.label_maps import read_label_map
    from meshsar_builder.dataset.sources import MMWHS_TABLE
    from meshsar_builder.geometry import phantom_heart
    from meshsar_builder.geometry.meshing import MeshingParams, labels_to_surface

    path = phantom_heart.write_mmwhs_subject(tmp_path, "ct_train_1001", np.random.default_rng(3), voxel_mm=(2.0, 2.0, 2.0))
    surf = labels_to_surface(*read_label_map(path, MMWHS_TABLE), ["lv", "myo", "rv", "la", "ra", "aorta", "pa"],
                             MeshingParams(spacing_mm=2.0))
    verts = surf.verts - (surf.verts.min(axis=0) + surf.verts.max(axis=0)) / 2
    radar = RP.RadarParams(aperture=(8, 8), step_mm=20.0)  # the 160 mm aperture, 64 antennas: the direct sum's cost
    vis, _ = RV.visibility(verts, surf.faces, RP.probe_points(radar, "anterior"))
    seen = vis > 0
    args = (verts[surf.faces][seen], vis[seen], RP.aperture_positions(radar, "anterior"), RP.frequencies(radar), radar)
    assert seen.sum() > 1000
    assert relative_error(RE.echo(*args, method="chebyshev"), RE.echo(*args, method="direct")) <= 1e-6


def test_noise_alone_draws_no_depth():
    """A pure-noise volume with its own RMS as the noise level: no pixel is detected, so depth stays 0."""
    from meshsar_builder.radar.imaging import range_slices, volume_images

    rng = np.random.default_rng(4)
    images = ImageParams(size=64)
    freqs = RP.frequencies(RP.RadarParams())
    slices = len(range_slices(300.0, 160.0, freqs))
    noise = (rng.standard_normal((slices, 64, 64)) + 1j * rng.standard_normal((slices, 64, 64))) / math.sqrt(2)
    intensity, depth = volume_images(noise, freqs, 300.0, images, noise_rms=1.0)
    assert (intensity > 0.1).mean() > 0.9  # the noise is displayed...
    assert (depth != 0).mean() < 1e-3  # ...but not taken for a surface
    assert (volume_images(noise, freqs, 300.0, images)[1] != 0).mean() > 0.9  # without the noise level it would be


def _broken(case: str):
    """(verts, faces) of a 30 mm icosphere with one defect."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=30.0)
    verts, faces = np.array(sphere.vertices), np.array(sphere.faces)
    if case == "nan":
        verts[7, 1] = np.nan
    elif case == "index":
        faces[3, 2] = len(verts)
    elif case == "negative":
        faces[3, 2] = -1
    elif case == "quads":
        faces = np.c_[faces, faces[:, :1]]
    elif case == "empty":
        faces = faces[:0]
    elif case == "duplicate":
        faces = np.r_[faces, faces[:5, ::-1]]  # the same triangles, wound the other way
    elif case == "inward":
        faces = faces[:, ::-1]
    elif case == "behind":
        verts = verts + 300.0 * RP.view_frame("left")[2]  # its centre on the left aperture's plane
    return verts, faces


@pytest.mark.parametrize("case, message", [
    ("nan", r"verts: 1 vertices have non-finite coordinates \(the first: vertex 7\)"),
    ("index", r"faces: vertex indices must lie in \[0, 162\), got 0 to 162"),
    ("negative", r"got -1 to 161"),
    ("quads", r"faces: must be \(m, 3\) integer vertex indices \(triangles\), got int64 \(320, 4\)"),
    ("empty", r"faces: the mesh has no faces"),
    ("duplicate", r"faces: 5 faces repeat another face's three vertices"),
    ("inward", r"faces: wound inward \(the closed surface encloses -1\d\d\.\d ml\)"),
    ("behind", r"reaches 330\.0 mm toward the left aperture, whose plane lies at z0_mm = 300\.0 mm"),
])
def test_a_mesh_the_radar_cannot_simulate_is_refused_naming_the_problem(case, message):
    """Each of these gave a plausible-looking sample before (a NaN vertex: no speckle; inward faces: a blank image;
    a duplicate: its echo twice; behind the aperture: 63x the power), or an error deep in numpy."""
    radar = RP.RadarParams(aperture=(8, 8), step_mm=20.0, n_samples=16, echo_decimation=(1, 1, 1),
                           loss_decimation=(1, 1, 1))
    verts, faces = _broken(case)
    with pytest.raises(ValueError, match=message):
        RR.render_sample(verts, faces, radar, ImageParams(size=16), np.random.default_rng(0))
    with pytest.raises(ValueError, match=message):
        RR.specular_loss_echo(verts, faces, radar)


@pytest.mark.parametrize("view, axis, shift", [("left", 0, 55.0), ("anterior", 1, -60.0), ("superior", 2, 51.0)])
def test_a_mesh_reaching_beyond_the_images_is_refused_naming_view_and_axis(view, axis, shift):
    """A 30 mm sphere moved 51-60 mm along one axis of a view reaches past fov / 2 = 80 mm: along u or v its echo
    would land aliased on the image's edge, along w beyond the range slices (views are orthogonal: one view at a
    time, or the first view that sees the reach along any of its axes is named). In a wide enough field, it runs."""
    radar = RP.RadarParams(aperture=(8, 8), step_mm=20.0, n_samples=16, echo_decimation=(1, 1, 1),
                           loss_decimation=(1, 1, 1), views=(view,))
    verts, faces = _broken("none")
    moved = verts + shift * RP.view_frame(view)[axis]
    reach = 30.0 + abs(shift)
    message = rf"the mesh reaches {reach:.1f} mm from the heart centre along the {view} view's {'uvw'[axis]} axis"
    with pytest.raises(ValueError, match=message + r", beyond its images' fov_mm / 2 = 80 mm"):
        RR.render_sample(moved, faces, radar, ImageParams(size=16), np.random.default_rng(0))
    wider = ImageParams(size=16, fov_mm=2 * reach + 1.0)
    assert RR.render_sample(moved, faces, radar, wider, np.random.default_rng(0))["views"][0]["visible_facets"] > 0


def test_a_range_window_reaching_behind_the_aperture_and_an_open_surface():
    """z0 within fov / 2 is refused; an open surface (no winding to judge) and the sphere itself are simulated."""
    radar = RP.RadarParams(aperture=(8, 8), step_mm=20.0, n_samples=16, echo_decimation=(1, 1, 1),
                           loss_decimation=(1, 1, 1), views=("anterior",))
    verts, faces = _broken("none")
    with pytest.raises(ValueError, match=r"z0_mm: the range slices span z0 \+- fov_mm / 2 = 70\.0 \+- 80\.0 mm"):
        RR.render_sample(verts, faces, dataclasses.replace(radar, z0_mm=70.0), ImageParams(size=16),
                         np.random.default_rng(0))
    front = faces[(verts[faces].mean(axis=1) @ RP.view_frame("anterior")[2]) > 0]
    for kept in (faces, front):
        out = RR.render_sample(verts, kept, radar, ImageParams(size=16), np.random.default_rng(0))
        assert out["views"][0]["visible_facets"] > 0 and out["views"][0]["signal_power"] > 0


def _plate(cells_u: int, cells_v: int, tilt_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """A 100 x 60 mm plate facing the anterior view, turned tilt_deg about its v axis, cut into cells_u x cells_v
    squares of two triangles each."""
    u, v, w = RP.view_frame("anterior")
    t = math.radians(tilt_deg)
    across, normal = math.cos(t) * u - math.sin(t) * w, math.sin(t) * u + math.cos(t) * w
    a, b = np.meshgrid(np.linspace(-50, 50, cells_u + 1), np.linspace(-30, 30, cells_v + 1), indexing="ij")
    verts = a.reshape(-1, 1) * across + b.reshape(-1, 1) * v + 10.0 * normal
    k = np.arange(cells_u)[:, None] * (cells_v + 1) + np.arange(cells_v)[None, :]
    corner = np.stack([k, k + cells_v + 1, k + cells_v + 2, k + 1], axis=-1).reshape(-1, 4)
    faces = np.concatenate([corner[:, [0, 1, 2]], corner[:, [0, 2, 3]]])
    return verts, faces if (np.cross(*(verts[faces[0, 1:]] - verts[faces[0, 0]])) @ normal) > 0 else faces[:, ::-1]


@pytest.mark.parametrize("tilt_deg", [0.0, 10.0])
def test_facets_wider_than_the_plane_wave_holds_are_split_so_the_echo_does_not_depend_on_the_cut(tilt_deg,
                                                                                                  monkeypatch):
    """The facet integral takes the wave across a facet as plane: a 100 x 60 mm plate as 2 triangles (117 mm
    edges) was 1.4 relative L2 off the same plate cut 2.5 mm fine. Its facets are split to sqrt(lambda R) / 2
    (RR.echo_facets); a mesh within that bound is simulated as it is."""
    radar = RP.RadarParams(aperture=(16, 16), step_mm=10.0, n_samples=16, echo_decimation=(1, 1, 1),
                           loss_decimation=(1, 1, 1), views=("anterior",), diffuse=False, image_snr_db=math.inf)
    images = ImageParams(size=32)

    def echo(mesh):
        return RR.render_sample(*mesh, radar, images, np.random.default_rng(0))["echo_clean"].astype(complex)

    fine, coarse = _plate(40, 24, tilt_deg), _plate(1, 1, tilt_deg)
    assert RR.echo_facets(*fine, radar)[2] is None  # within the bound: not split
    assert len(RR.echo_facets(*coarse, radar)[1]) > 2
    reference = echo(fine)
    assert np.linalg.norm(echo(coarse) - reference) / np.linalg.norm(reference) < 0.03
    monkeypatch.setattr(RR, "echo_facets", lambda verts, faces, radar: (verts, faces, None))
    assert np.linalg.norm(echo(coarse) - reference) / np.linalg.norm(reference) > 0.5  # unsplit


def test_a_split_mesh_keeps_its_diffuse_scatterers_on_its_own_faces(monkeypatch):
    """A 12-triangle box (60 mm faces): its scatterers are drawn on its own faces (a template's name them), each
    lit as its split parts are, area-weighted; its flat faces' parts see the probes as the whole face does, so
    the diffuse part is the unsplit box's to rounding while the specular part is not."""
    radar = RP.RadarParams(aperture=(16, 16), step_mm=10.0, n_samples=16, echo_decimation=(1, 1, 1),
                           loss_decimation=(1, 1, 1), views=("anterior", "left"), image_snr_db=math.inf)
    box = trimesh.creation.box((60.0, 40.0, 50.0))

    def views():
        out = RR.render_sample(np.asarray(box.vertices), np.asarray(box.faces), radar, ImageParams(size=32),
                               np.random.default_rng(1))
        return [(view["diffuse_power"], view["visible_scatterers"], view["visible_facets"]) for view in out["views"]]

    split = views()
    monkeypatch.setattr(RR, "echo_facets", lambda verts, faces, radar: (verts, faces, None))
    whole = views()
    for (power, lit, facets), (power_whole, lit_whole, facets_whole) in zip(split, whole):
        assert lit == lit_whole > 0 and power == pytest.approx(power_whole, rel=1e-6)
        assert facets > 10 * facets_whole
