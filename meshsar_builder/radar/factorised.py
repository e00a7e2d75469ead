"""The factorised echo: the forward counterpart of fast factorised back-projection (DESIGN section 4).

radar.series' per-pair series, run on each cluster's coarse grid of antennas and interpolated
onto the aperture; radar.echo.echo calls it for echo_method "factorised".
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np

import meshsar_builder.radar.series as per_pair  # looked up at call time (the bench times its series)
from meshsar_builder.pipeline.errors import MeshsarError
from meshsar_builder.radar.imaging import phasor
from meshsar_builder.radar.jit import KERNEL_OPTIONS, NUMBA_MISSING, njit
from meshsar_builder.radar.params import DELAY_S_PER_MM, Aperture
from meshsar_builder.radar.series import _cos_sin

# A cluster c of facets (or points) with centre x_c and radius rho_c (its farthest corner) has, with the centre's
# own phase removed,
#     r_c(a, n) = s_c(a, n) exp(-j 2 pi (f_n tau_c(a) - S tau_c(a)^2 / 2)),  tau_c = 2 |a - x_c| / c,
# smooth over the aperture: across it the phase of each term moves by at most
# w = 2 k_max rho_c H / R_min (H the aperture's half-width along an axis, R_min the
# nearest antenna's distance to x_c), so its Chebyshev coefficients decay like J_l(w).
# So s_c is needed only on a q_x x q_y Chebyshev grid, q the fewest terms whose Bessel
# tail is below FACTORISED_TOLERANCE; r_c is interpolated from there onto the antennas
# (barycentric formula, one axis after the other, as two BLAS products) and the phase
# put back (_spread_cluster). Across frequency r_c is smooth too: its terms' delays lie within
# +-2 rho_c / c of the centre's, so over the band B its phase moves by at most w_f = 2 pi (B / 2) (2 rho_c / c),
# and a Chebyshev series in frequency of M terms (the same Bessel bound at FREQUENCY_TOLERANCE, plus one for the
# 1 / k^2 amplitude) carries it. Each node's N samples are fitted by least squares with those M polynomials (well
# conditioned on uniform samples while M <= N / 2: Lebesgue constant < 3), the series cut where the tail of its
# coefficients over the nodes holds less than FREQUENCY_TOLERANCE^2 of their energy, and the coefficients
# interpolated instead of the samples. On the demo heart the bound asks for 8-11 terms and the cut keeps 5-7 of
# them, 10-14 channels instead of 128: the interpolation takes 63-66 ms a view instead of 88.
#
# The items are grouped in cubes of FACTORISED_CELL_MM; a cube whose grid would not be
# FACTORISED_GAIN times smaller than the aperture is summed on the aperture itself (small
# apertures). The series sums run in one kernel call per kind (facets, point scatterers).
#
# Where a facet turns away within the aperture (cos theta = 0 on a line across it) r_c has
# a kink that no smooth interpolant follows: that, not the tolerance, sets the error
# floor, measured relative L2 1-3e-5 against the series on the demo heart, where 45 % of
# the visible facets turn away somewhere in the aperture (tests pin <= 1e-4, DESIGN
# section 4). The sums run in fixed order, and BLAS splits matrix products across threads
# by rows and columns, never along a sum, so the bytes do not depend on thread counts.

# Measured (one core, three views, the specular echo): on the demo heart, cubes of 20, 25 and 30 mm take
# 0.31-0.35, 0.31-0.35 and 0.35-0.37 s a view (smaller cubes: more clusters to interpolate; larger: larger
# grids to sum on), but the error on a sphere with random bumps (not a heart) rises from 5-9e-5 at 30 mm to
# 0.9-1.6e-4 at 25 and 1.1-2.3e-4 at 20, beyond the 1e-4 budget: smaller clusters get fewer nodes across the
# kinks. A cluster of cubes of cubes (a second level) did not pay for its extra grids. A per-axis bound (the
# lateral phase slope instead of rho) took 36 % of the grid antennas off (the echo 0.24-0.26 s against 0.33-0.35),
# and the bumpy sphere's error to 1.4-2.9e-4 (1.2-2.5e-4 with that bound raised by 30 %): the bound is close.
# Since each cluster's interpolation is checked (below), the bound is a first grid, not a guarantee: at 1e-3
# instead of 1e-4 the demo heart's grids hold 15 % fewer antennas (its echo with the diffuse part 0.34-0.36
# against 0.39-0.43 s a view, 1.4-2.6e-5 from the series on 300 antennas) and no cluster is refined.
FACTORISED_CELL_MM = 30.0
FACTORISED_GAIN = 2.0
FACTORISED_TOLERANCE = 1e-3
# The frequency series' bound and cut: it moves the demo heart's echo by 3e-6 relative L2, below the
# factorisation's 1-3e-5 (fixed series of 6 and 8 terms: 4e-5 and 4e-7).
FREQUENCY_TOLERANCE = 1e-5
# The series' truncation for point scatterers on the grids: 10-40x below their factorisation error (1-4e-4, the
# Lambert kink), and 4 terms fewer than CHEBYSHEV_TOLERANCE at a 26 mm range half-width. On the demo heart's three
# views the diffuse part's error against its direct sum is the same to 3 digits at 1e-7, 1e-5 and 1e-4, and 1e-5
# takes 5-10 ms a view less than 1e-7. Facets keep CHEBYSHEV_TOLERANCE: their corner weights amplify the series'
# error up to CORNER_GAIN_LIMIT times.
POINT_SERIES_TOLERANCE = 1e-5
# The grid bound above is for a smooth remainder. Where a facet turns away within the aperture, its lobe's kink
# (kappa cos theta at 0) converges slowly; on a cluster of the silhouette, where every facet turns away, the
# bound's grid left 1-4 % of the cluster's own echo (0.1-1.6 % of the echo's norm) and a sphere with 12 bumps at
# 1.0-1.2e-4 of the direct sum, beyond DESIGN's 1e-4. So each cluster's facet sums are read as Chebyshev
# coefficients over its grid at CHECK_FREQUENCIES frequencies (no extra sums) and the clusters whose last
# TAIL_COEFFICIENTS hold the most energy are refined, REFINE_FACTOR times finer, until the tails left are within
# SPATIAL_TOLERANCE of the clusters' energy; after REFINE_ROUNDS rounds, or where a grid would not be
# FACTORISED_GAIN times smaller than the aperture, a cluster is summed on the aperture itself. Scaled for the
# kink's l^-2 decay (_unconverged), the estimate was 0.55-0.9 of the true error of the bumpy sphere's worst
# clusters, and 0.73-1.3 of the whole echo's on four bumpy shapes and the demo heart, which end 2.4-6.2e-5 from the
# series (docs/radar.md).
CHECK_FREQUENCIES = 4
TAIL_COEFFICIENTS = 2
SPATIAL_TOLERANCE = 5e-5
REFINE_FACTOR = 1.4
REFINE_ROUNDS = 3


class _Group(NamedTuple):
    """Items summed on one grid: a cluster's Chebyshev grid about its centre (radius rho, mm), or the aperture
    itself (centre None: no interpolation)."""

    items: np.ndarray  # (K,) int, into the parts' items concatenated
    node_x: np.ndarray  # (qx,) float mm
    node_y: np.ndarray  # (qy,) float mm
    centre: np.ndarray | None = None  # (3,) float mm
    rho: float = 0.0


def _chebyshev_nodes(axis: np.ndarray, count: int) -> np.ndarray:
    """count Chebyshev extrema spanning axis (increasing), or axis itself where it has no more points."""
    if count >= len(axis):
        return axis
    return (axis[0] + axis[-1]) / 2 - (axis[-1] - axis[0]) / 2 * np.cos(np.pi * np.arange(count) / (count - 1))


def _barycentric(nodes: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(len(axis), len(nodes)) the interpolation matrix from Chebyshev extrema (or axis itself) to axis.

    The barycentric formula of the second kind (weights (-1)^i, halved at the ends); where
    the nodes are the axis, the identity.
    """
    if len(nodes) == len(axis) and np.array_equal(nodes, axis):
        return np.eye(len(axis))
    weights = (-1.0) ** np.arange(len(nodes))
    weights[[0, -1]] *= 0.5
    diff = axis[:, None] - nodes[None, :]
    hit = diff == 0
    matrix = weights / np.where(hit, 1.0, diff)
    matrix /= matrix.sum(axis=1, keepdims=True)
    on_node = hit.any(axis=1)
    matrix[on_node] = hit[on_node]
    return matrix


def _interpolation(nodes: np.ndarray, axis: np.ndarray, transposed: bool = False) -> np.ndarray:
    """_barycentric(nodes, axis) in float32, read-only (its transpose, contiguous, with transposed), cached: the
    clusters of a build share their node counts and axes, so their matrices (8 ms a view to build afresh)."""
    return _cached_interpolation(nodes.tobytes(), axis.tobytes(), transposed)


@functools.lru_cache(maxsize=512)
def _cached_interpolation(nodes: bytes, axis: bytes, transposed: bool) -> np.ndarray:
    matrix = _barycentric(np.frombuffer(nodes), np.frombuffer(axis))
    matrix = np.ascontiguousarray(matrix.T if transposed else matrix, dtype=np.float32)
    matrix.flags.writeable = False
    return matrix


@functools.lru_cache(maxsize=64)
def _frequency_series(samples: int, terms: int) -> tuple[np.ndarray, np.ndarray]:
    """(fit (N, M) float64, basis (N, M) float32), read-only: the least-squares fit of `terms` Chebyshev
    polynomials to `samples` uniform samples of [-1, 1], and those polynomials there; the identities where a
    series would not be shorter than half the samples (no saving, and a fit on uniform samples conditions
    worse beyond it)."""
    if 2 * terms > samples:
        fit, basis = np.eye(samples), np.eye(samples, dtype=np.float32)
    else:
        vandermonde = np.polynomial.chebyshev.chebvander(np.linspace(-1.0, 1.0, samples), terms - 1)
        fit, basis = np.linalg.pinv(vandermonde).T, vandermonde.astype(np.float32)
    fit, basis = np.ascontiguousarray(fit), np.ascontiguousarray(basis)
    fit.flags.writeable = basis.flags.writeable = False
    return fit, basis


def factorised_clusters(centres: np.ndarray, corners: np.ndarray, grid: Aperture, k_max: float):
    """The factorised echo's plan for items on an aperture (see above).

    centres : (K, 3) float mm, a facet's centre or a point; corners : (K, C, 3) float mm,
    the points each item spans (its corners, or the point itself); k_max : rad/mm.
    Returns (direct (D,) int, the items summed on the aperture itself; clusters: per
    cluster (centre (3,) float, rho float mm, items (Kc,) int, node_x (qx,), node_y (qy,) float mm)).
    """
    frame = np.asarray(grid.frame, dtype=np.float64)
    x_all, y_all = (np.asarray(axis, dtype=np.float64) for axis in (grid.x_mm, grid.y_mm))
    cell = np.floor(centres / FACTORISED_CELL_MM).astype(np.int64)
    cell -= cell.min(axis=0)
    extent = cell.max(axis=0) + 1
    _, cube = np.unique((cell[:, 0] * extent[1] + cell[:, 1]) * extent[2] + cell[:, 2], return_inverse=True)
    order = np.argsort(cube, kind="stable")
    starts = np.searchsorted(cube[order], np.arange(cube.max() + 1))
    spans = corners[order]  # (K, C, 3), grouped by cube
    low = np.minimum.reduceat(spans.min(axis=1), starts)
    high = np.maximum.reduceat(spans.max(axis=1), starts)
    x_c = (low + high) / 2  # (G, 3)
    rho = np.sqrt(np.maximum.reduceat(np.sum((spans - x_c[cube[order], None]) ** 2, axis=2).max(axis=1), starts))
    u, v, w = (x_c @ frame.T).T
    dx = np.maximum.reduce([x_all[0] - u, np.zeros_like(u), u - x_all[-1]])  # to the aperture's rectangle
    dy = np.maximum.reduce([y_all[0] - v, np.zeros_like(v), v - y_all[-1]])
    r_min = np.maximum(np.sqrt(dx * dx + dy * dy + (grid.z0_mm - w) ** 2), 1e-6)
    half = np.array([(axis[-1] - axis[0]) / 2 for axis in (x_all, y_all)])
    q = per_pair._series_order((2 * k_max * rho / r_min)[:, None] * half, FACTORISED_TOLERANCE) + 1  # (G, 2)
    members = np.split(order, starts[1:])
    direct = q.prod(axis=1) * FACTORISED_GAIN > len(x_all) * len(y_all)
    clusters = [(x_c[g], rho[g], members[g], _chebyshev_nodes(x_all, q[g, 0]), _chebyshev_nodes(y_all, q[g, 1]))
                for g in np.flatnonzero(~direct)]
    summed_on_aperture = [np.zeros(0, dtype=np.int64)] + [members[g] for g in np.flatnonzero(direct)]
    return np.sort(np.concatenate(summed_on_aperture)), clusters


@njit(inline="always")
def _centre_phases(r, f_first, df, half_slope, tau_per_mm):
    """exp(j 2 pi (f_first tau - half_slope tau^2)) and exp(j 2 pi df tau), tau = r tau_per_mm: the
    first frequency's phase and the step to the next (4 floats)."""
    tau = r * tau_per_mm
    b_re, b_im = _cos_sin(tau * (f_first - half_slope * tau))
    s_re, s_im = _cos_sin(df * tau)
    return b_re, b_im, s_re, s_im


@njit(**KERNEL_OPTIONS)
def _spread_cluster(summed, first_row, columns, node_x, node_y, interp_x, interp_y_t, fit, basis, chop, centre, frame,
                    z0, x_mm, y_mm, f_first, df, half_slope, tau_per_mm, out):
    """Add one cluster's echo, known on its coarse grid, to every antenna.

    summed : (G, N_all) complex, the coarse sums: this cluster's echo on its grid (node_x (qx,), node_y (qy,)) at
    node (a, b) is row first_row + a qy + b, its frequency k column columns[k] (N,) int (the whole sums and an
    index, not a strided view of them: one layout, so one compiled variant, as radar/jit.py asks);
    interp_x : (Nx, qx) float32, interp_y_t : (qy, Ny) float32; fit : (N, M) float64, the least-squares fit of
    M series terms to N samples (transposed), basis : (N, M) float32, the terms at the samples, both the identity
    for no series (M = N); chop : the series is cut after the fewest terms whose coefficients beyond hold at most
    chop^2 of their energy over the nodes; centre : (3,) x_c; frame : (3, 3); out : (Nx, 2 N, Ny) float,
    antenna (i, j)'s real and imaginary parts in out[i, 2n] and out[i, 2n + 1] (so that the loops over j are
    contiguous).

    Each node's samples are demodulated and fitted (a double-precision matrix product), then the coefficients
    interpolated and the samples rebuilt: three single-precision products (BLAS; their rounding, 2e-7 relative
    L2 on the demo heart, is below the factorisation's 1e-5), the last two one antenna row at a time so that
    their result stays in cache for the phases. The phases go over frequencies by a recurrence (64 products:
    error ~1e-14) in double precision, vectorized over a row's antennas: one array written per loop, so that
    the compiler can prove the loops free of aliasing and use SIMD (3.5x faster than one loop writing four
    arrays; the same bytes).
    """
    qx, qy, n = len(node_x), len(node_y), len(columns)
    nodes = qx * qy
    ux, uy, uz = frame[0, 0], frame[0, 1], frame[0, 2]
    vx, vy, vz = frame[1, 0], frame[1, 1], frame[1, 2]
    wx, wy, wz = z0 * frame[2, 0] - centre[0], z0 * frame[2, 1] - centre[1], z0 * frame[2, 2] - centre[2]
    demodulated = np.empty((2, nodes, n))  # times the conjugate phase: real parts of every node, then imaginary
    for a in range(qx):
        for b in range(qy):
            dx = wx + node_x[a] * ux + node_y[b] * vx
            dy = wy + node_x[a] * uy + node_y[b] * vy
            dz = wz + node_x[a] * uz + node_y[b] * vz
            p_re, p_im, s_re, s_im = _centre_phases(math.sqrt(dx * dx + dy * dy + dz * dz), f_first, df, half_slope,
                                                    tau_per_mm)
            node = a * qy + b
            d_re, d_im = demodulated[0, node], demodulated[1, node]
            for k in range(n):
                re, im = summed[first_row + node, columns[k]].real, summed[first_row + node, columns[k]].imag
                d_re[k] = re * p_re + im * p_im
                d_im[k] = im * p_re - re * p_im
                p_re, p_im = p_re * s_re - p_im * s_im, p_re * s_im + p_im * s_re
    series = fit.shape[1] < n  # else the samples themselves are interpolated
    fitted = np.dot(demodulated.reshape(2 * nodes, n), fit) if series else demodulated.reshape(2 * nodes, n)
    terms = fitted.shape[1]  # (2 nodes, M): the terms' real parts at every node, then their imaginary parts
    if series:  # cut the tail whose energy over the nodes is within chop^2 of the whole's
        energy = np.sum(fitted * fitted, axis=0)
        tail, whole = 0.0, energy.sum()
        while terms > 1 and tail + energy[terms - 1] <= chop * chop * whole:
            tail += energy[terms - 1]
            terms -= 1
        basis = np.ascontiguousarray(basis[:, :terms])
    coefficients = np.empty((qx, 2 * terms, qy), dtype=np.float32)  # transposed, so that each row's product is
    for a in range(qx):  # contiguous
        for b in range(qy):
            for m in range(terms):
                coefficients[a, 2 * m, b] = fitted[a * qy + b, m]
                coefficients[a, 2 * m + 1, b] = fitted[nodes + a * qy + b, m]
    along_x = np.dot(interp_x, coefficients.reshape(qx, 2 * terms * qy))  # (Nx, 2 M qy)
    ny = interp_y_t.shape[1]
    phases = np.empty((4, ny))  # per antenna of the row: the phase (re, im) at the current frequency, its step
    p_re, p_im, s_re, s_im = phases[0], phases[1], phases[2], phases[3]
    for i in range(interp_x.shape[0]):
        fine = np.dot(along_x[i].reshape(2 * terms, qy), interp_y_t)  # (2 M, Ny): term m's re, im in rows 2m, 2m+1
        # (N, 2 Ny): frequency k's real parts, then its imaginary parts
        samples = np.dot(basis, fine.reshape(terms, 2 * ny)) if series else fine.reshape(n, 2 * ny)
        for j in range(ny):
            dx = wx + x_mm[i] * ux + y_mm[j] * vx
            dy = wy + x_mm[i] * uy + y_mm[j] * vy
            dz = wz + x_mm[i] * uz + y_mm[j] * vz
            p_re[j], p_im[j], s_re[j], s_im[j] = _centre_phases(math.sqrt(dx * dx + dy * dy + dz * dz), f_first, df,
                                                                half_slope, tau_per_mm)
        row = out[i]
        for k in range(n):
            re, im, o_re, o_im = samples[k, :ny], samples[k, ny:], row[2 * k], row[2 * k + 1]
            for j in range(ny):
                o_re[j] += re[j] * p_re[j] - im[j] * p_im[j]
            for j in range(ny):
                o_im[j] += re[j] * p_im[j] + im[j] * p_re[j]
            for j in range(ny):
                step_re = p_re[j] * s_re[j] - p_im[j] * s_im[j]
                p_im[j] = p_re[j] * s_im[j] + p_im[j] * s_re[j]
                p_re[j] = step_re


def series_sums(points, normals, weights, offsets, positions, first, last, freqs, radar, out, tolerance=None) -> bool:
    """Add to out (M, N) complex128 antenna m's echo of the items first[m]:last[m] by radar.series' per-pair series
    (at `tolerance`, default its own); False, out untouched, where a range span is too wide for the series.

    points, normals (K, 3), weights (K,), offsets (K, 3, 3) or None: one part's items (echo_factorised); positions
    (M, 3) mm. The sums of the factorised echo's grids on the CPU; radar.gpu.device_sums takes the same arguments.
    """
    rows = per_pair._kernel_rows(points, normals, weights, offsets)
    return per_pair._series_echo(rows, positions, first, last, freqs, radar, out=out, tolerance=tolerance) is not None


def echo_factorised(parts, grid, freqs, last_on=None, sums=series_sums):
    """The factorised echo on an aperture grid (see above) of one or more parts summed.

    parts : tuples (points, normals, weights, offsets, radar) of one kind each: facets
    (offsets (K, 3, 3)) or point scatterers (offsets None), radar giving their pattern.
    The parts share the clusters, so one interpolation serves them all. Returns (Nx Ny, N)
    complex128; None where a cluster's range span is too wide for the series (then the direct
    sum is the faster one). Each cluster's interpolation of the facets is checked and its grid
    refined where it has not converged (_unconverged).

    last_on : (ix, iy, i_freq) int index arrays of a sub-grid of the aperture's axes and of
    freqs (uniformly spaced): then also the last part's echo alone there, (len(ix) len(iy),
    len(i_freq)) complex128, from its own coarse sums on the first grids interpolated onto the
    sub-grid only (a part of point scatterers keeps its own budget there; refining is for facets).
    With the two parts that radar.echo makes, the whole echo keeps its bytes (below).

    sums : what sums the items on the grids (series_sums' arguments and result): the CPU's
    series, or a device's direct sum (radar.gpu), which never runs out of terms.
    """
    if NUMBA_MISSING:
        raise MeshsarError(NUMBA_MISSING)
    centres = np.concatenate([part[0] for part in parts])
    corners = np.concatenate([part[0][:, None, :] + (0.0 if part[3] is None else part[3]) * np.ones((1, 3, 1))
                              for part in parts])  # (K, 3, 3): a point is its own three corners
    direct, clusters = factorised_clusters(centres, corners, grid, float(per_pair._wavenumbers(freqs).max()))
    frame = np.ascontiguousarray(grid.frame, dtype=np.float64)
    x_mm, y_mm = (np.asarray(axis, dtype=np.float64) for axis in (grid.x_mm, grid.y_mm))
    # Groups: the items summed on the aperture itself (centre None), then each cluster on its own grid.
    groups = [_Group(direct, x_mm, y_mm)] * bool(len(direct)) + [_Group(items, nx, ny, c, rho)
                                                                 for c, rho, items, nx, ny in clusters]
    half_slope = 0.5 * parts[0][4].slope_hz_per_s if parts[0][4].rvp else 0.0
    columns = np.unique(np.linspace(0, len(freqs) - 1, CHECK_FREQUENCIES).round().astype(np.int64))
    summing = functools.partial(_summed_on_groups, parts, frame, grid.z0_mm, freqs, half_slope, columns, sums)
    alone = []

    def interpolated_alone(summed):  # the last part's own sums, before the others add to them
        alone.append(_interpolated(summed, groups, frame, grid.z0_mm, x_mm, y_mm, freqs, half_slope,
                                   tuple(np.asarray(index) for index in last_on)))

    summed, check = summing(groups, None if last_on is None else interpolated_alone)
    if summed is None:
        return None  # a span too wide for the series (warned): the caller sums directly
    for round_ in range(REFINE_ROUNDS + 1):
        flagged = [] if check is None else _unconverged(check, groups, x_mm, y_mm)
        if not flagged:
            break
        groups, summed, check = _refined(groups, summed, check, flagged, round_ == REFINE_ROUNDS, summing, x_mm, y_mm)
        if summed is None:
            return None
    whole = _interpolated(summed, groups, frame, grid.z0_mm, x_mm, y_mm, freqs, half_slope)
    return whole if last_on is None else (whole, alone[0])


def _summed_on_groups(parts, frame, z0_mm, freqs, half_slope, columns, sums, groups, after_last=None):
    """The coarse sums (G, N) complex128 of every part on the groups' grids (rows: each group's nodes in turn) and
    the facets' own sums at the frequencies `columns`, each cluster's with its centre's phase removed, (G, C)
    complex64 (None without facets); (None, None) where a range span is too wide for the series. The last part is
    summed first, then after_last(sums) is called, then the others add to the same sums."""
    kind = np.repeat(np.arange(len(parts)), [len(part[0]) for part in parts])
    start_of = np.cumsum([0] + [len(part[0]) for part in parts])
    sizes = np.array([len(group.node_x) * len(group.node_y) for group in groups])
    grids = np.concatenate([Aperture(frame, z0_mm, group.node_x, group.node_y).positions for group in groups])
    summed = np.zeros((len(grids), len(freqs)), dtype=np.complex128)
    check = None
    for i in [len(parts) - 1] + list(range(len(parts) - 1)):  # the last part first: 0 + p + f is f + p, the same bytes
        points, normals, weights, offsets, radar = parts[i]
        before = summed[:, columns] if offsets is not None else None  # a copy: the facets' own sums are the change
        mine = [group.items[kind[group.items] == i] - start_of[i] for group in groups]
        counts = np.array([len(items) for items in mine])
        stops = np.cumsum(counts)
        order = np.concatenate(mine)
        if not sums(points[order], normals[order], weights[order], None if offsets is None else offsets[order], grids,
                    np.repeat(stops - counts, sizes), np.repeat(stops, sizes), freqs, radar, summed,
                    None if offsets is not None else POINT_SERIES_TOLERANCE):
            return None, None
        if offsets is not None:
            check = (0 if check is None else check) + (summed[:, columns] - before)
        if i == len(parts) - 1 and after_last is not None:
            after_last(summed)
    if check is not None:  # each node's delay to its cluster's centre (the aperture's group is not checked)
        centre = np.repeat([np.zeros(3) if g.centre is None else g.centre for g in groups], sizes, axis=0)
        tau = np.linalg.norm(grids - centre, axis=1)[:, None] * DELAY_S_PER_MM
        check = check.astype(np.complex64) * phasor(half_slope * tau * tau - tau * freqs[columns])
    return summed, check


def _unconverged(check, groups, x_mm, y_mm) -> list[int]:
    """The clusters (indices into groups) whose interpolation of the facets has not converged: the fewest, largest
    error first, without which the estimated error is within SPATIAL_TOLERANCE of the estimated echo.

    check : (G, C) the facets' sums on the groups' grids at C frequencies, each cluster's centre phase removed
    (_summed_on_groups). A cluster's estimate: those sums as Chebyshev coefficients over its grid (DCT-I along each
    axis it interpolates, not along one whose nodes are the aperture's own); its error, the energy of its last
    TAIL_COEFFICIENTS along each such axis; the echo's, the clusters' energies summed (as if incoherent).
    """
    tails, wholes = np.zeros(len(groups)), np.zeros(len(groups))
    for g, (group, values) in enumerate(zip(groups, _blocks(check, groups))):
        if group.centre is None:
            continue
        qx, qy = len(group.node_x), len(group.node_y)
        along_x, along_y = qx < len(x_mm), qy < len(y_mm)  # Chebyshev extrema, not the aperture's own axis
        coefficients = values.reshape(qx, qy, -1)
        if along_x:
            coefficients = (_dct_matrix(qx) @ coefficients.reshape(qx, -1)).reshape(qx, qy, -1)
        if along_y:
            coefficients = _dct_matrix(qy) @ coefficients
        energy = np.sum(coefficients.real**2 + coefficients.imag**2, axis=2)
        # A kink's coefficients decay like l^-2: what lies beyond the last two (truncated and aliased) holds about
        # q / 3 times their energy.
        tail = energy[-TAIL_COEFFICIENTS:].sum() * qx / 3 if along_x else 0.0
        if along_y:
            tail += energy[:-TAIL_COEFFICIENTS if along_x else None, -TAIL_COEFFICIENTS:].sum() * qy / 3
        tails[g] = tail
        wholes[g] = energy.sum()
    order = np.argsort(tails)[::-1]
    left = tails[order][::-1].cumsum()[::-1]  # left[k]: the error of every cluster from order[k] on
    return [int(g) for g, rest in zip(order, left) if rest > SPATIAL_TOLERANCE**2 * wholes.sum()]


@functools.lru_cache(maxsize=64)
def _dct_matrix(count: int) -> np.ndarray:
    """(count, count) complex64, read-only: the Chebyshev coefficients of a polynomial from its values at count
    Chebyshev extrema (a DCT-I, its first and last rows and columns halved)."""
    index = np.arange(count)
    matrix = 2.0 / (count - 1) * np.cos(np.pi * np.outer(index, index) / (count - 1))
    matrix[:, [0, -1]] /= 2
    matrix[[0, -1]] /= 2
    matrix = matrix.astype(np.complex64)  # as the sums it meets: no conversion a call
    matrix.flags.writeable = False
    return matrix


def _blocks(array, groups) -> list:
    """array's rows split into each group's nodes, in turn (views)."""
    return np.split(array, np.cumsum([len(group.node_x) * len(group.node_y) for group in groups])[:-1])


def _refined(groups, summed, check, flagged, last, summing, x_mm, y_mm):
    """(groups, summed, check) with each flagged cluster on a grid REFINE_FACTOR times finer along the axes it
    interpolates, or, on the last round or where that grid would not be FACTORISED_GAIN times smaller than the
    aperture, its items summed on the aperture itself (one group with the items already there); the group on the
    aperture first, then the clusters kept, then the refined ones. None sums where a span is too wide."""
    renewed, moved = [], []
    for g in flagged:
        items, nx, ny, centre, rho = groups[g]
        nx, ny = (_chebyshev_nodes(full, math.ceil(REFINE_FACTOR * len(nodes))) for nodes, full in
                  ((nx, x_mm), (ny, y_mm)))
        if last or len(nx) * len(ny) * FACTORISED_GAIN > len(x_mm) * len(y_mm):
            moved.append(items)
        else:
            renewed.append(_Group(items, nx, ny, centre, rho))
    fresh = renewed + ([_Group(np.concatenate(moved), x_mm, y_mm)] if moved else [])
    fresh_summed, fresh_check = summing(fresh)
    if fresh_summed is None:
        return groups, None, None
    old = list(zip(groups, _blocks(summed, groups), _blocks(check, groups)))
    new = list(zip(fresh, _blocks(fresh_summed, fresh), _blocks(fresh_check, fresh)))
    aperture = [entry for entry in old[:1] + new if entry[0].centre is None]
    if len(aperture) == 2:  # the items already on the aperture and those moved there: one group
        (first, s0, c0), (second, s1, c1) = aperture
        aperture = [(_Group(np.concatenate([first.items, second.items]), x_mm, y_mm), s0 + s1, c0 + c1)]
    flagged = set(flagged)
    kept = [entry for g, entry in enumerate(old) if g not in flagged and entry[0].centre is not None]
    ordered = aperture + kept + [entry for entry in new if entry[0].centre is not None]
    return ([group for group, _, _ in ordered], np.concatenate([rows for _, rows, _ in ordered]),
            np.concatenate([rows for _, _, rows in ordered]))


def _interpolated(summed, groups, frame, z0_mm, x_mm, y_mm, freqs, half_slope, sub=None):
    """The echo (Nx Ny, N) complex128 on the aperture from the coarse sums (G, N) on the groups' grids (rows: the
    group summed on the aperture itself, if any, then each cluster's grid); or with sub = (ix, iy, i_freq) on that
    sub-grid of the aperture and freqs (uniformly spaced), (len(ix) len(iy), len(i_freq)).
    """
    nx, ny, n = len(x_mm), len(y_mm), len(freqs)
    ix, iy, i_freq = (slice(None),) * 3 if sub is None else sub
    if sub is not None and len(i_freq) > 1 and np.all(np.diff(i_freq) == i_freq[1] - i_freq[0]):
        i_freq = slice(i_freq[0], i_freq[-1] + 1, i_freq[1] - i_freq[0])  # the coarse sums' columns as views
    x_sub, y_sub, f_sub = x_mm[ix], y_mm[iy], freqs[i_freq]
    lx, ly, lf = len(x_sub), len(y_sub), len(f_sub)
    out = np.zeros((lx, 2 * lf, ly))  # antenna (i, j), frequency k: out[i, 2 k (+1), j]
    start = 0
    if groups and groups[0].centre is None:
        on_aperture = np.ascontiguousarray(summed[:nx * ny].reshape(nx, ny, n)[ix][:, iy][:, :, i_freq])
        out.reshape(lx, lf, 2, ly)[:] = on_aperture[..., None].view(np.float64).transpose(0, 2, 3, 1)
        start = nx * ny
    tau_per_mm = DELAY_S_PER_MM
    df = per_pair._uniform_step(f_sub)
    columns = np.ascontiguousarray(np.arange(n)[i_freq])  # a sub-grid's frequencies, in the sums' columns
    # The series' terms by the Bessel bound over the band (w_f above, per mm of rho), one more for the 1 / k^2.
    w_per_mm = np.pi * (f_sub[-1] - f_sub[0]) * tau_per_mm
    clusters = [group for group in groups if group.centre is not None]
    terms = per_pair._series_order(w_per_mm * np.array([group.rho for group in clusters]), FREQUENCY_TOLERANCE)
    for (_, node_x, node_y, centre, _), most in zip(clusters, np.atleast_1d(terms) + 1):
        qx, qy = len(node_x), len(node_y)
        fit, basis = _frequency_series(lf, int(most))
        _spread_cluster(summed, start, columns, node_x, node_y,
                        _interpolation(node_x, x_sub),  # each row on its own: a sub-grid's rows
                        _interpolation(node_y, y_sub, transposed=True), fit, basis, FREQUENCY_TOLERANCE, centre,
                        frame, float(z0_mm), x_sub, y_sub, float(f_sub[0]), df, half_slope, tau_per_mm, out)
        start += qx * qy
    out = out.reshape(lx, lf, 2, ly)
    echo = np.empty((lx, ly, lf), dtype=np.complex128)  # filled part by part: a tenth of the time of out's sum
    echo.real = out[:, :, 0].transpose(0, 2, 1)
    echo.imag = out[:, :, 1].transpose(0, 2, 1)
    return echo.reshape(-1, lf)
