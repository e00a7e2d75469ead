"""The physical-optics facet echo (DESIGN section 4): the facet integral, its reference, canonical targets,
convergence under refinement of the same surface, and the fast series' guard."""

import dataclasses
import math

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

import meshsar_builder.radar.echo as RE
import meshsar_builder.radar.facet as RF
import meshsar_builder.radar.params as RP
import meshsar_builder.radar.series as RS
import meshsar_builder.radar.visibility as RV
from meshsar_builder.radar.imaging import ImageParams, view_images


def relative_error(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def subdivide(tri, n):
    """(K n^2, 3, 3) sub-triangles of each triangle of tri (K, 3, 3) on a uniform barycentric grid; parent (K n^2,)."""
    corners = []
    for i in range(n):
        for j in range(n - i):
            corners.append(((i, j), (i + 1, j), (i, j + 1)))
            if j < n - i - 1:
                corners.append(((i + 1, j), (i + 1, j + 1), (i, j + 1)))
    bary = np.array([[[(n - a - b) / n, a / n, b / n] for a, b in c] for c in corners])  # (n^2, 3, 3)
    sub = np.einsum("sij,kjc->ksic", bary, tri)
    return sub.reshape(-1, 3, 3), np.repeat(np.arange(len(tri)), len(corners))


def centroid_rule(tri, q, n):
    """F(q) of each triangle (K,) summed over n^2 sub-triangles, each its area times the phase at its centroid."""
    sub, parent = subdivide(tri, n)
    centres, _, areas = RV.triangle_geometry(sub)
    phase = np.einsum("sc,sc->s", q[parent], centres - tri.mean(axis=1)[parent])
    return np.bincount(parent, areas * np.cos(phase), len(tri)) + 1j * np.bincount(parent, areas * np.sin(phase),
                                                                                   len(tri))


def quadrature(tri, q, n):
    """The integral's independent reference: the centroid rule (error ~ 1/n^2) Richardson-extrapolated from n, 2n."""
    return (4 * centroid_rule(tri, q, 2 * n) - centroid_rule(tri, q, n)) / 3


# ------------------------------------------------------------------ the facet integral

coordinate = st.floats(-3.0, 3.0, allow_nan=False)


@settings(max_examples=40, deadline=None)
@given(st.lists(coordinate, min_size=9, max_size=9), st.lists(st.floats(-6.0, 6.0), min_size=3, max_size=3))
def test_facet_integral_matches_quadrature(corners, q):
    tri = np.array(corners).reshape(1, 3, 3)
    area = RV.triangle_geometry(tri)[2][0]
    q = np.array(q)[None]
    exact = RF.facet_integral(tri, q)[0]
    assert abs(exact) <= area * (1 + 1e-12)
    # Phase spread across the facet up to ~50 rad: 64 and 128 sub-triangles per side resolve it.
    # The 1e-12 floor is the sub-triangles' rounding where two corners coincide (area 0 exactly,
    # the reference ~4e-15): far below 1e-5 of any facet these coordinates make.
    assert abs(exact - quadrature(tri, q, 64)[0]) <= 1e-5 * area + 1e-12


def test_facet_integral_is_the_area_at_normal_incidence_and_continuous_near_it():
    rng = np.random.default_rng(0)
    tri = rng.normal(size=(4, 3, 3)) * 2
    _, normals, areas = RV.triangle_geometry(tri)
    np.testing.assert_allclose(RF.facet_integral(tri, 5.0 * normals), areas, rtol=1e-14)
    edge = (tri[:, 1] - tri[:, 0]) / np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1, keepdims=True)
    # Tilting q across the series / recursion switch and through nearly coincident corners.
    for tilt in (1e-12, 1e-7, 1e-3, 0.15, 0.3, 0.6, 1.2):
        q = 5.0 * normals + tilt * edge
        np.testing.assert_allclose(RF.facet_integral(tri, q), quadrature(tri, q, 60), rtol=1e-6)


def test_facet_integral_of_an_edge_across_q():
    """Two corners at the same phase (an edge perpendicular to q's in-plane part): the confluent case."""
    tri = np.array([[[0.0, 0, 0], [2.0, 0, 0], [0.7, 1.5, 0]]])
    for qy in (0.0, 1e-9, 1e-4, 2.0, 7.0):
        q = np.array([[0.0, qy, 3.0]]) + np.array([[1e-10, 0, 0]])
        np.testing.assert_allclose(RF.facet_integral(tri, q), quadrature(tri, q, 60), rtol=1e-6)


# ------------------------------------------------------------------ the echo against its reference


def test_production_echo_matches_the_sub_triangle_reference():
    """Facets split into sub-triangles <= lambda/20 (and lambda/40, Richardson-extrapolated: converged), each a
    point scatterer with its parent's amplitude and delay and its own plane-wave phase: the facet model summed by
    brute force, term by term. The production path matches it to 1e-4."""
    mesh = trimesh.creation.icosphere(2, radius=1.0)
    verts = mesh.vertices * np.array([20.0, 16.0, 24.0])  # 4-7 mm facets: larger than the default's, a harder case
    radar = RP.RadarParams(aperture=(4, 4), step_mm=40.0, n_samples=16, echo_decimation=(1, 1, 1))
    positions, freqs = RP.aperture_positions(radar, "left"), RP.frequencies(radar)
    vis, _ = RV.visibility(verts, mesh.faces, RP.probe_points(radar, "left"))
    seen = vis > 0
    tri = verts[mesh.faces][seen]
    production = RE.echo(tri, vis[seen], positions, freqs, radar)
    centres, normals, areas = RV.triangle_geometry(tri)
    offset = positions[:, None, :] - centres[None]  # (M, K, 3)
    r = np.linalg.norm(offset, axis=2)
    cos = np.maximum(np.einsum("mkc,kc->mk", offset, normals) / r, 0)
    amplitude = vis[seen] * (0.7 * cos**4 + 0.3 * cos) / r**2  # (M, K)
    toward = -offset / r[..., None]
    tau = 2e-3 * r / RP.SPEED_OF_LIGHT_M_PER_S
    wavelength = 1e3 * RP.SPEED_OF_LIGHT_M_PER_S / freqs.max()
    n = math.ceil(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max() / (wavelength / 20))

    def brute_force(n):
        sub, parent = subdivide(tri, n)
        sub_centres, _, sub_areas = RV.triangle_geometry(sub)
        out = np.zeros((len(positions), len(freqs)), dtype=complex)
        path = np.einsum("mkc,kc->mk", toward[:, parent], sub_centres - centres[parent])  # (M, S) mm
        for i, f in enumerate(freqs):
            k = 2 * np.pi * f / (1e3 * RP.SPEED_OF_LIGHT_M_PER_S)
            # Each parent's n^2 sub-triangles are contiguous (subdivide): its integral is their block's sum.
            integral = (sub_areas * np.exp(2j * k * path)).reshape(len(positions), len(tri), -1).sum(axis=2)  # (M, K)
            out[:, i] = np.sum(amplitude * integral * np.exp(2j * np.pi * (f * tau - 0.5 * radar.slope_hz_per_s
                                                                          * tau**2)), axis=1)
        return out

    coarse = brute_force(n)
    assert relative_error(production, coarse) <= 1e-3  # lambda/20 alone: its centroid rule's own error
    assert relative_error(production, (4 * brute_force(2 * n) - coarse) / 3) <= 1e-4


def test_long_range_span_falls_back_to_the_direct_sum_never_truncates():
    """Scatterers from 0.3 m to 3 m: the series would need more terms than samples; the echo stays exact."""
    radar = RP.RadarParams(aperture=(3, 3), z0_mm=3000.0, n_samples=64, facet="centroid", echo_decimation=(1, 1, 1))
    points = np.array([[0.0, 0.0, 0.0], [0.0, 2700.0, 0.0], [10.0, -40.0, 5.0]])
    normals = np.tile([0.0, 1.0, 0.0], (3, 1))
    positions, freqs = RP.aperture_positions(radar, "anterior"), RP.frequencies(radar)
    with pytest.warns(UserWarning, match="range span of .* mm needs"):
        fast = RE.point_echo(points, normals, np.ones(3), positions, freqs, radar, method="chebyshev")
    direct = RE.point_echo(points, normals, np.ones(3), positions, freqs, radar, method="direct")
    assert relative_error(fast, direct) <= 1e-9


@pytest.mark.parametrize("w_max", [30.0, 1000.0, 3000.0])
def test_jacobi_anger_coefficients_converge_at_any_span(w_max):
    """exp(j w t) = sum_l B_l T_l(t) to the tolerance for |w| <= w_max (the old search stopped at w + 64)."""
    omega = np.linspace(-w_max, w_max, 7)
    coef = RS._chebyshev_coefficients(omega, RS._series_order(w_max, 1e-10))
    t = np.linspace(-1, 1, 101)
    chebyshev = np.cos(np.arange(len(coef))[:, None] * np.arccos(t)[None])  # (L, T)
    series = coef.T @ chebyshev  # (N, T)
    np.testing.assert_allclose(series, np.exp(1j * omega[:, None] * t[None]), atol=1e-8)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(1e-6, 200.0), min_size=1, max_size=300), st.sampled_from([1e-10, 1e-5]))
def test_order_buckets_cover_each_antenna_with_its_own_series_length(halves, tolerance):
    """Every antenna's bucket reaches at least its own half-width (so |t| <= 1) with a series long enough for it,
    the buckets' lengths rise strictly, and none is longer than one length for all antennas would be."""
    halves = np.array(halves)
    omega_per_mm = 2 * np.pi * 0.17 / 2
    bucket, half = RS._order_buckets(halves, omega_per_mm, tolerance)
    lengths = RS._series_order(omega_per_mm * half, tolerance)
    assert np.all(half[bucket] >= halves)
    assert np.all(lengths[bucket] >= RS._series_order(omega_per_mm * halves, tolerance))
    assert np.all(np.diff(lengths) > 0)
    assert lengths.max() == RS._series_order(omega_per_mm * halves.max(), tolerance)


@pytest.mark.parametrize("tolerance", [None, 1e-5])
def test_series_with_a_length_per_antenna_matches_the_direct_sum_per_antenna(tolerance):
    """Antennas summing sets of scatterers whose range spans differ 40-fold, interleaved so that the buckets of
    series lengths cross the kernel's batches: each antenna's series echo is its own set's direct sum."""
    radar = RP.RadarParams(aperture=(15, 12), n_samples=32, facet="centroid", echo_decimation=(1, 1, 1))
    positions, freqs = RP.aperture_positions(radar, "anterior"), RP.frequencies(radar)
    rng = np.random.default_rng(3)
    spans = (2.0, 20.0, 80.0)  # mm: each set's extent along the view
    sets = [rng.uniform(-1, 1, (n, 3)) * [20.0, span / 2, 20.0] for n, span in zip((7, 40, 90), spans)]
    points = np.concatenate(sets)
    normals = np.tile([0.0, 1.0, 0.0], (len(points), 1))
    weights = rng.uniform(0.5, 1.5, len(points)) * np.exp(2j * np.pi * rng.uniform(size=len(points)))
    stops = np.cumsum([len(one) for one in sets])
    which = rng.integers(0, 3, len(positions))
    first, last = (stops - [len(one) for one in sets])[which], stops[which]
    rows = RS._kernel_rows(points, normals, weights, None)
    series = RS._series_echo(rows, positions, first, last, freqs, radar, tolerance=tolerance)
    for i, one in enumerate(sets):
        mine = which == i
        direct = RS._echo_direct(points[first[mine][0]:last[mine][0]], normals[:len(one)],
                                 weights[first[mine][0]:last[mine][0]], None, positions[mine], freqs, radar)
        assert relative_error(series[mine], direct) <= (1e-9 if tolerance is None else 1e-5)


# ------------------------------------------------------------------ canonical targets


def far_field_power(tri, radar, distance_mm):
    """Mean |echo|^2 over the sweep at one antenna distance_mm along +y, facets lit by it (convex targets)."""
    antenna = np.array([[0.0, distance_mm, 0.0]])
    centres, normals, _ = RV.triangle_geometry(tri)
    lit = np.einsum("kc,kc->k", antenna - centres, normals) > 0
    signal = RE.echo(tri[lit], np.ones(lit.sum()), antenna, RP.frequencies(radar), radar)
    return float(np.mean(np.abs(signal) ** 2))


def plate(side_mm, n=4):
    """A square plate in the x-z plane facing +y, cut into 2 n^2 triangles, (2 n^2, 3, 3)."""
    grid = np.linspace(-side_mm / 2, side_mm / 2, n + 1)
    tri = []
    for i in range(n):
        for j in range(n):
            a, b = [grid[i], 0, grid[j]], [grid[i + 1], 0, grid[j]]
            c, d = [grid[i + 1], 0, grid[j + 1]], [grid[i], 0, grid[j + 1]]
            tri += [[a, c, b], [a, d, c]]
    return np.array(tri, dtype=float)


def sphere(radius_mm, level):
    mesh = trimesh.creation.icosphere(level, radius=radius_mm)
    return mesh.vertices[mesh.faces]


PO = RP.RadarParams(reflectivity="po")
FAR_MM = 2000.0  # beyond 2 D^2 / lambda for the 20 mm plate (0.2 m) and the 40 mm sphere (0.8 m)


def test_plate_and_sphere_echo_ratio_is_the_radar_cross_section_ratio():
    """sigma_plate / sigma_sphere = (4 pi A^2 / lambda^2) / (pi a^2), within 1 dB, averaged over the sweep."""
    side, radius = 20.0, 20.0
    wavelength = 1e3 * RP.SPEED_OF_LIGHT_M_PER_S / RP.frequencies(PO)
    expected = np.mean(4 * np.pi * side**4 / wavelength**2) / (np.pi * radius**2)
    measured = far_field_power(plate(side), PO, FAR_MM) / far_field_power(sphere(radius, 5), PO, FAR_MM)
    assert abs(10 * np.log10(measured / expected)) <= 1.0


def test_plate_of_twice_the_side_is_12_db_stronger():
    gain = far_field_power(plate(20.0), PO, FAR_MM) / far_field_power(plate(10.0), PO, FAR_MM)
    assert 10 * np.log10(gain) == pytest.approx(12.04, abs=0.5)


def test_sphere_echo_does_not_depend_on_its_tessellation():
    coarse, fine = (far_field_power(sphere(20.0, level), PO, FAR_MM) for level in (4, 6))
    assert abs(10 * np.log10(coarse / fine)) < 0.5


# ------------------------------------------------------------------ the same surface, two tessellations


def midpoint_subdivision(verts, faces, times):
    """The same piecewise-flat surface with every edge halved `times` times."""
    for _ in range(times):
        verts, faces = trimesh.remesh.subdivide(verts, faces)
    return verts, faces


def view_echo_and_intensity(verts, faces, radar, images, view):
    vis, _ = RV.visibility(verts, faces, RP.probe_points(radar, view))
    seen = vis > 0
    freqs, (x, y) = RP.frequencies(radar), RP.aperture_axes(radar)
    signal = RE.echo(verts[faces][seen], vis[seen], RP.aperture(radar, view), freqs, radar)  # production: factorised
    intensity = view_images(signal.reshape(*radar.aperture, -1), freqs, x, y, radar.z0_mm, images)[0]
    return signal, intensity


def ncc(a, b):
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def convergence(verts, faces, radar):
    """Per default view: relative L2 of the noise-free echo and intensity NCC, ~2.5 mm facets vs 4x finer."""
    images = ImageParams(size=64)
    fine = midpoint_subdivision(verts, faces, 2)
    out = {}
    for view in radar.views:
        coarse_echo, coarse_image = view_echo_and_intensity(verts, faces, radar, images, view)
        fine_echo, fine_image = view_echo_and_intensity(*fine, radar, images, view)
        out[view] = (relative_error(coarse_echo, fine_echo), ncc(coarse_image, fine_image))
    return out


# A 160 mm aperture at 5 mm (rather than 2 mm) keeps the test quick; both tessellations see the same one.
CONVERGENCE_RADAR = RP.RadarParams(aperture=(32, 32), step_mm=5.0, snr_db=math.inf)


@pytest.mark.slow
def test_ellipsoid_echo_converges_under_refinement():
    mesh = trimesh.creation.icosphere(5, radius=1.0)  # ~2.5 mm edges at this size
    verts = mesh.vertices * np.array([50.0, 40.0, 60.0])
    for view, (error, correlation) in convergence(verts, mesh.faces, CONVERGENCE_RADAR).items():
        assert error <= 0.03, view
        assert correlation >= 0.97, view


@pytest.mark.slow
def test_phantom_heart_echo_converges_under_refinement():
    from meshsar_builder.bench.suite import demo_mesh

    verts, faces = demo_mesh()
    for view, (error, correlation) in convergence(verts, faces, CONVERGENCE_RADAR).items():
        assert error <= 0.03, view
        assert correlation >= 0.97, view


def test_centroid_model_is_kept_as_an_option():
    mesh = trimesh.creation.icosphere(2, radius=40.0)
    radar = RP.RadarParams(aperture=(4, 4), step_mm=20.0, n_samples=16, echo_decimation=(1, 1, 1))
    positions, freqs = RP.aperture_positions(radar, "superior"), RP.frequencies(radar)
    centres, normals, areas = RV.triangle_geometry(mesh.triangles)
    centroid = RE.echo(mesh.triangles, np.ones(len(areas)), positions, freqs, dataclasses.replace(radar, facet="centroid"))
    np.testing.assert_array_equal(centroid, RE.point_echo(centres, normals, areas, positions, freqs, radar))
    assert relative_error(RE.echo(mesh.triangles, np.ones(len(areas)), positions, freqs, radar), centroid) > 0.05


def test_factorised_echo_falls_back_to_the_direct_sum_on_a_long_range_span():
    """Facets and a scatterer from 0.3 m to 3 m on an aperture grid: the factorised call hands back to the direct
    sum, for the whole echo and for the diffuse part alone on a sub-grid."""
    from meshsar_builder.radar.diffuse import lambert

    radar = RP.RadarParams(aperture=(4, 3), z0_mm=3000.0, n_samples=64, echo_decimation=(1, 1, 1),
                           loss_decimation=(1, 1, 1))
    tri = np.array([[[0.0, 0.0, 0.0], [0.0, 0.0, 4.0], [4.0, 0.0, 0.0]],
                    [[0.0, 2700.0, 0.0], [0.0, 2700.0, 4.0], [4.0, 2700.0, 0.0]]])
    diffuse = (np.array([[10.0, -40.0, 5.0]]), np.array([[0.0, 1.0, 0.0]]), np.array([0.5 + 0.2j]), lambert(radar))
    grid, freqs = RP.aperture(radar, "anterior"), RP.frequencies(radar)
    sub = (np.array([1, 3]), np.array([0, 2]), np.arange(0, 64, 4))
    with pytest.warns(UserWarning, match="range span of .* mm needs"):
        whole, alone = RE.echo(tri, np.ones(2), grid, freqs, radar, diffuse=diffuse, diffuse_on=sub)
    direct = RE.echo(tri, np.ones(2), grid, freqs, radar, method="direct", diffuse=diffuse)
    assert relative_error(whole, direct) <= 1e-12
    there = RP.Aperture(grid.frame, grid.z0_mm, np.asarray(grid.x_mm)[sub[0]], np.asarray(grid.y_mm)[sub[1]])
    expected = RE.point_echo(*diffuse[:3], there.positions, freqs[sub[2]], diffuse[3], method="direct")
    assert relative_error(alone, expected) <= 1e-12
