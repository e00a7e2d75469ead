"""The echo's sums (DESIGN section 4): the direct sum, the reference, and the per-pair Chebyshev series.

Geometry is in millimetres in the heart frame; frequencies in Hz, delays in s.
For every antenna m of a view's synthetic aperture and frequency sample n,

    s(m, n) = sum_k V_k g(cos theta_km) / R_km^2 exp(j 2 pi f_n tau_km) [exp(-j pi S tau_km^2)] F_k(q_kmn)

with F_k the physical-optics integral of exp(j q.(x - c_k)) over facet k (a facet), or its
weight (a point scatterer). radar.echo is the public entry; radar.factorised runs this
module's series on coarse grids of antennas.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from meshsar_builder.pipeline.errors import MeshsarError
from meshsar_builder.radar.facet import (
    SERIES_SPREAD,
    SERIES_TERMS,
    _divided_difference,
    _divided_differences,
    _series_coefficients,
    _series_value,
)
from meshsar_builder.radar.imaging import SPEED_OF_LIGHT_MM_PER_S
from meshsar_builder.radar.jit import KERNEL_OPTIONS as _KERNEL_OPTIONS
from meshsar_builder.radar.jit import NUMBA_MISSING as _NUMBA_MISSING
from meshsar_builder.radar.jit import njit
from meshsar_builder.radar.params import DELAY_S_PER_MM, DIRECT_TERMS_PER_CHUNK, RadarParams

_TINY = float(np.finfo(np.float64).tiny)


# ---------------------------------------------------------------- reference (direct) sum


def _pattern(radar: RadarParams) -> tuple[float, float]:
    """(p, kappa) of g: the recipe's lobe, or g(x) = x for reflectivity "po"."""
    return (1.0, 1.0) if radar.reflectivity == "po" else (radar.p, radar.kappa)


def _wavenumbers(freqs: np.ndarray) -> np.ndarray:
    """k_n = 2 pi f_n / c in rad/mm, (N,)."""
    return 2 * np.pi * freqs / SPEED_OF_LIGHT_MM_PER_S


def _reflectivity_factor(freqs: np.ndarray, radar: RadarParams) -> np.ndarray:
    """(N,) the physical-optics amplitude k_n / 2 pi (1/mm) for reflectivity "po", else ones."""
    return freqs / SPEED_OF_LIGHT_MM_PER_S if radar.reflectivity == "po" else np.ones_like(freqs)


def _amplitude_and_delay(points, normals, weights, positions, radar: RadarParams):
    """(M, K) amplitude w_k g(cos theta_km) / R_km^2 and round-trip delay tau_km (s).

    R is in mm, so the amplitude is w's unit over mm^2. R^2 comes from |a|^2 - 2 a.c + |c|^2
    (a BLAS product): in float64 at heart scale its error is ~1e-14 mm, 1e-13 rad of phase.
    """
    p, kappa = _pattern(radar)
    r2 = positions @ (-2.0 * points.T)
    r2 += np.einsum("mc,mc->m", positions, positions)[:, None]
    r2 += np.einsum("kc,kc->k", points, points)[None, :]
    np.maximum(r2, np.finfo(np.float64).tiny, out=r2)
    r = np.sqrt(r2)
    cos = positions @ normals.T
    cos -= np.einsum("kc,kc->k", normals, points)[None, :]
    cos /= r
    np.maximum(cos, 0.0, out=cos)
    amplitude = ((1.0 - kappa) * cos**p + kappa * cos) * weights[None, :] / r2
    return amplitude, r * DELAY_S_PER_MM, r


def _echo_direct(points, normals, weights, offsets, positions, freqs, radar):
    """The reference sum: every term's phase in float64 and its own complex exponential.

    offsets : (K, 3, 3) corners minus centres for the facet integral, or None for point
    scatterers. Antennas go in chunks, so that memory stays bounded for any M and K.
    """
    out = np.zeros((len(positions), len(freqs)), dtype=np.complex128)
    wavenumbers = _wavenumbers(freqs)
    factor = _reflectivity_factor(freqs, radar)
    chunk = max(1, DIRECT_TERMS_PER_CHUNK // (len(points) * len(freqs)))
    for start in range(0, len(positions), chunk):
        antennas = positions[start : start + chunk]
        amp, tau, r = _amplitude_and_delay(points, normals, weights, antennas, radar)
        if offsets is not None:
            toward = (points[None, :, :] - antennas[:, None, :]) / r[:, :, None]  # (m, K, 3) antenna to facet
            b = 2 * np.einsum("mkc,kic->mki", toward, offsets)
        cycles = tau[:, :, None] * freqs[None, None, :]
        if radar.rvp:
            cycles -= (0.5 * radar.slope_hz_per_s * tau**2)[:, :, None]
        terms = amp[:, :, None] * np.exp(2j * np.pi * cycles)
        if offsets is not None:
            dd = np.empty((b.shape[0] * b.shape[1], len(freqs)), dtype=np.complex128)
            _divided_differences(np.ascontiguousarray(b.reshape(-1, 3)), wavenumbers, dd)
            terms *= 2 * dd.reshape(terms.shape)  # F / area = 2 DD; the area is in the weights
        out[start : start + chunk] = np.einsum("mkn,n->mn", terms, factor)
    return out


# ---------------------------------------------------------------- production echo (numba)
#
# For antenna m, with n' = n - (N - 1)/2 and f_c the centre frequency,
#     s(m, n) = sum_k c_k exp(j 2 pi x_k n'),  c_k = A_k exp(j 2 pi tau_k (f_c - S tau_k / 2) [rvp]),
# x_k = df tau_k = beta R_k cycles per sample (beta = df 2e-3 / c per mm). With R_k = R_m + h t_k,
# R_m the middle of antenna m's range interval and h the largest half-width over the antennas of
# m's bucket (so |t_k| <= 1; antennas are bucketed by the series length their own span needs,
# _order_buckets), Jacobi-Anger gives exp(j w t) = sum_l eps_l j^l J_l(w) T_l(t) (eps_0 = 1,
# else 2), hence
#     s(m, n) = exp(j 2 pi beta R_m n') sum_l G_l(m) B_l(n'),  G_l(m) = sum_k c_k T_l(t_k),
#     B_l(n') = eps_l j^l J_l(2 pi beta h n').
# The series is cut, per bucket, at the first L whose tail sum_{l >= L} eps_l |J_l(w_max)| is
# below CHEBYSHEV_TOLERANCE, which bounds each term's relative error. The echo is band-limited
# (the mesh spans a few range cells), so ~14 terms replace the N = 64 samples, and each
# costs a few real flops per antenna-facet pair; T_l comes from the three-term recurrence.
#
# The facet integral enters as three point scatterers per facet. With b_i = 2 u.(p_i - c),
#     F_k(k_n) = -(2 A / k_n^2) sum_i exp(j k_n b_i) / P_i,  P_i = (b_i - b_l)(b_i - b_l'),
# so corner i is a scatterer at range R_k + b_i / 2 with the frequency-free weight
# -2 A / P_i, and the common 1 / k_n^2 multiplies each antenna's finished row. Where some
# |P_i| < 2 / (CORNER_GAIN_LIMIT k_min^2) (the corners' weights would exceed the area
# CORNER_GAIN_LIMIT times and cancel), the pair is left out of the series and added exactly
# per frequency with _divided_difference: facets within ~1 degree of normal incidence, about
# 1e-4 of the pairs on a heart.
#
# The kernels are compiled by numba with fastmath off (no reassociation, no FMA
# contraction) and loops in a fixed order; every antenna is summed on its own, in one
# thread. The innermost loops take the scatterers of a block WIDTH at a time into WIDTH
# partial sums per term, with no reduction inside a chunk, so LLVM's loop vectorizer makes
# them SIMD without reordering any sum; the lanes are added at the end in a fixed tree.
# cos / sin are polynomials (below), not libm calls, so that they vectorize too. A lobe
# power p that is not an integer goes through libm pow, in a loop of its own (slower, still
# exact). B_l(n') is real for even l and imaginary for odd l, so the sums G_l of
# SERIES_BATCH antennas meet it in two real matrix products (BLAS). BLAS splits a product
# across threads by rows and columns, never along its sum, so the bytes do not depend on
# thread counts; they depend on the BLAS build, as the factorised echo's interpolation does.
#
# The first call in a process compiles the kernels or loads them from numba's cache in
# __pycache__. What this kernel replaced, measured: docs/radar.md, design notes.

# Scatterers per block of the vectorized loops; the facet integral fills a block with the
# three corners of LANES // 3 facets.
LANES = 256
# Partial sums per series term (a power of two: they are added as a tree at the end). A block's
# items go through them WIDTH at a time, so each antenna clears and adds WIDTH lanes per term,
# not one per item: a factorised cluster's coarse antenna sums only ~150 items. Measured on the
# demo heart's factorised echo (one core): 8 and 16 lose the vectorizer (2x slower), 32 and 64
# are alike; against a lane per item, the facets' series -20 % and the diffuse part's -25 %.
WIDTH = 32
# Truncation of the Chebyshev series (see above); measured relative L2 error against the
# direct sum ~1e-9, five orders below the 1e-4 that DESIGN section 4 allows (1e-10 costs one
# term more than 1e-8 and lets the corner weights grow 100 times larger, see below).
CHEBYSHEV_TOLERANCE = 1e-10
# Largest |corner weight| / area kept in the series (see above): the series' relative error
# 1e-10 grows at most to ~3e-6 of such a facet's integral.
CORNER_GAIN_LIMIT = 1e4
# Antennas whose series sums G_l meet B_l(n') in one matrix product: as a loop per antenna the product took
# 13 % of a factorised echo's series (whose coarse antennas sum ~150 items each); batched, BLAS does it at
# its own rate.
SERIES_BATCH = 64


@njit(inline="always")
def _cos_sin(cycles):
    """cos and sin of 2 pi cycles, error < 1e-11: Taylor polynomials of the half angle in [-pi/2, pi/2], doubled."""
    h = math.pi * (cycles - math.floor(cycles + 0.5))
    h2 = h * h
    s = h * (1.0 + h2 * (-1.0 / 6 + h2 * (1.0 / 120 + h2 * (-1.0 / 5040 + h2 * (1.0 / 362880 + h2 * (
        -1.0 / 39916800 + h2 * (1.0 / 6227020800 + h2 * (-1.0 / 1307674368000))))))))
    c = 1.0 + h2 * (-0.5 + h2 * (1.0 / 24 + h2 * (-1.0 / 720 + h2 * (1.0 / 40320 + h2 * (
        -1.0 / 3628800 + h2 * (1.0 / 479001600 + h2 * (-1.0 / 87178291200 + h2 * (1.0 / 20922789888000))))))))
    return c * c - s * s, 2.0 * c * s


@njit(inline="always")
def _integer_power(x, p_int):
    """x ** p_int for 0 <= p_int < 16 by products (no libm call, so loops stay SIMD)."""
    x2 = x * x
    x4 = x2 * x2
    return ((x if p_int & 1 else 1.0) * (x2 if p_int & 2 else 1.0)
            * (x4 if p_int & 4 else 1.0) * (x4 * x4 if p_int & 8 else 1.0))


@njit(**_KERNEL_OPTIONS)
def _range_bounds(facets, reach, positions, first, last, low, high):
    """Per antenna m, the least and greatest range (mm) of the points of items first[m]:last[m], into low, high
    (M,): an item's distance from the antenna less and plus its reach (K,) (how far a facet's corners' ranges
    can lie from its centre's; 0 for points); 0 and 0 for an antenna with none."""
    block, po = LANES, facets.shape[0] == 13
    lo = np.empty(block)
    hi = np.empty(block)
    for m in range(positions.shape[0]):
        if last[m] <= first[m]:
            low[m] = 0.0
            high[m] = 0.0
            continue
        ax, ay, az = positions[m, 0], positions[m, 1], positions[m, 2]
        lanes = min(block, last[m] - first[m])  # only these are filled: a cluster's antenna sums ~100 items
        lo[:lanes] = np.inf
        hi[:lanes] = -np.inf
        for start in range(first[m], last[m], block):
            stop = min(start + block, last[m])
            px, py, pz, spread = facets[0, start:stop], facets[1, start:stop], facets[2, start:stop], reach[start:stop]
            if po:  # each facet's range less and plus its reach
                for k in range(px.shape[0]):
                    dx, dy, dz = ax - px[k], ay - py[k], az - pz[k]
                    r = math.sqrt(dx * dx + dy * dy + dz * dz)
                    lo[k] = min(lo[k], r - spread[k])
                    hi[k] = max(hi[k], r + spread[k])
            else:  # points: squared distances, and one square root an antenna
                for k in range(px.shape[0]):
                    dx, dy, dz = ax - px[k], ay - py[k], az - pz[k]
                    lo[k] = min(lo[k], dx * dx + dy * dy + dz * dz)
                    hi[k] = max(hi[k], dx * dx + dy * dy + dz * dz)
        a, b = lo[0], hi[0]
        for k in range(1, lanes):
            a = min(a, lo[k])
            b = max(b, hi[k])
        low[m], high[m] = (a, b) if po else (math.sqrt(a), math.sqrt(b))


@njit(**_KERNEL_OPTIONS)
def _chebyshev_echo(facets, positions, first, last, sequence, bucket, centre_mm, inv_half_mm, terms, tau_per_mm,
                    f_centre, half_slope, p, p_int, kappa, flag_limit, coef_even, coef_odd, cycles_per_mm, n_centre,
                    freqs, wavenumbers, factor, reflectivity, out):
    """Echo of every antenna added to out (M, 2 N) float64 (a complex128 (M, N) viewed as floats).

    facets : (8, K) rows x, y, z, nx, ny, nz, |weight|, arg(weight) / 2 pi (cycles) for point
    scatterers, or (13, K) rows x, ..., weight and the corner offsets p_0 - c, p_1 - c (rows
    7-12) for the facet integral; antenna m sums facets first[m]:last[m] (M,); centre_mm : (M,) R_m;
    the antennas go in the order sequence (M,), grouped by their series bucket[m] (M,) (see _order_buckets), whose
    half-width is 1 / inv_half_mm[q] and length terms[q] (Q,); coef_even : (Q, ceil(L / 2), N) B_l(n') of the even
    l, real; coef_odd : (Q, max(floor(L / 2), 1), N) B_l(n') / j of the odd l, real, each zero beyond the bucket's
    own terms (L the longest); freqs, wavenumbers (rad/mm), factor, reflectivity : (N,): each finished row
    is multiplied by factor, and a pair added exactly carries reflectivity. p_int >= 0: the lobe
    power p is that integer (< 16), done by products.
    """
    po = facets.shape[0] == 13
    n_facets = facets.shape[1]
    per_block = LANES // 3 if po else LANES
    _, n_even, n_samples = coef_even.shape
    n_odd = coef_odd.shape[1]
    longest = terms.max()
    # G_l of SERIES_BATCH antennas, real parts in rows b and imaginary parts in rows SERIES_BATCH + b, and the
    # pairs added exactly: the product with B_l runs once a batch is full, as two real matrix products (BLAS)
    g_even = np.zeros((2 * SERIES_BATCH, n_even))
    g_odd = np.zeros((2 * SERIES_BATCH, n_odd))
    members = np.empty(SERIES_BATCH, dtype=np.int64)  # the batch's antennas
    exact_rows = np.empty((SERIES_BATCH, 2 * n_samples))
    dist = np.empty(per_block)
    cos_theta = np.empty(per_block)
    lobe = np.empty(per_block)
    b_0 = np.empty(per_block)
    b_1 = np.empty(per_block)
    exact = np.empty(per_block)
    t = np.zeros(LANES)
    c_re = np.zeros(LANES)
    c_im = np.zeros(LANES)
    t_even = np.empty(LANES)  # T_l(t) of the last even l, then of the last odd l
    t_odd = np.empty(LANES)
    acc_re = np.empty((longest, WIDTH))  # per lane partial sums of G_l
    acc_im = np.empty((longest, WIDTH))
    d_re = np.empty(n_samples)
    d_im = np.empty(n_samples)
    flagged = np.empty(n_facets, dtype=np.int64)
    work = np.empty(SERIES_TERMS)
    k_max = wavenumbers.max()
    b = 0  # the antenna's row in the batch
    for i_antenna in range(positions.shape[0]):
        m = sequence[i_antenna]
        own = bucket[m]
        n_terms, inv_half = terms[own], inv_half_mm[own]
        ax, ay, az, r_m = positions[m, 0], positions[m, 1], positions[m, 2], centre_mm[m]
        acc_re[:] = 0.0
        acc_im[:] = 0.0
        n_flagged = 0
        for start in range(first[m], last[m], per_block):
            stop = min(start + per_block, last[m])
            size = stop - start
            px, py, pz = facets[0, start:stop], facets[1, start:stop], facets[2, start:stop]
            nx, ny, nz = facets[3, start:stop], facets[4, start:stop], facets[5, start:stop]
            weight = facets[6, start:stop]
            if po:  # distance, cos(theta) and b_i = 2 u.(p_i - c), u from the antenna to the facet
                ox0, oy0, oz0 = facets[7, start:stop], facets[8, start:stop], facets[9, start:stop]
                ox1, oy1, oz1 = facets[10, start:stop], facets[11, start:stop], facets[12, start:stop]
                for k in range(size):
                    dx, dy, dz = ax - px[k], ay - py[k], az - pz[k]
                    r = math.sqrt(max(dx * dx + dy * dy + dz * dz, _TINY))
                    inv_r = 1.0 / r
                    dist[k] = r
                    cos_theta[k] = max((nx[k] * dx + ny[k] * dy + nz[k] * dz) * inv_r, 0.0)
                    b_0[k] = -2.0 * inv_r * (dx * ox0[k] + dy * oy0[k] + dz * oz0[k])
                    b_1[k] = -2.0 * inv_r * (dx * ox1[k] + dy * oy1[k] + dz * oz1[k])
            else:  # distance and cos(theta) of each pair
                for k in range(size):
                    dx, dy, dz = ax - px[k], ay - py[k], az - pz[k]
                    r = math.sqrt(max(dx * dx + dy * dy + dz * dz, _TINY))
                    dist[k] = r
                    cos_theta[k] = max((nx[k] * dx + ny[k] * dy + nz[k] * dz) / r, 0.0)
            if p_int >= 0:  # not inside the loop: pow is a libm call, which would keep it scalar
                for k in range(size):
                    lobe[k] = _integer_power(cos_theta[k], p_int)
            else:
                for k in range(size):
                    lobe[k] = cos_theta[k] ** p
            if po:
                for k in range(size):  # three corner scatterers per pair, in lanes k, k + size, k + 2 size
                    r = dist[k]
                    amp = -2.0 * weight[k] * ((1.0 - kappa) * lobe[k] + kappa * cos_theta[k]) / (r * r)
                    tau = r * tau_per_mm
                    rvp = half_slope * tau * tau
                    b0 = b_0[k]
                    b1 = b_1[k]
                    b2 = -b0 - b1
                    p0 = (b0 - b1) * (b0 - b2)
                    p1 = (b1 - b0) * (b1 - b2)
                    p2 = (b2 - b0) * (b2 - b1)
                    close = min(abs(p0), min(abs(p1), abs(p2))) < flag_limit
                    exact[k] = 1.0 if close else 0.0
                    amp = 0.0 if close else amp / (p0 * p1 * p2)  # one division for the three weights
                    w0 = amp * p1 * p2
                    w1 = amp * p0 * p2
                    w2 = amp * p0 * p1
                    cos, sin = _cos_sin((tau + 0.5 * b0 * tau_per_mm) * f_centre - rvp)
                    c_re[k] = w0 * cos
                    c_im[k] = w0 * sin
                    t[k] = (r + 0.5 * b0 - r_m) * inv_half
                    cos, sin = _cos_sin((tau + 0.5 * b1 * tau_per_mm) * f_centre - rvp)
                    c_re[k + size] = w1 * cos
                    c_im[k + size] = w1 * sin
                    t[k + size] = (r + 0.5 * b1 - r_m) * inv_half
                    cos, sin = _cos_sin((tau + 0.5 * b2 * tau_per_mm) * f_centre - rvp)
                    c_re[k + 2 * size] = w2 * cos
                    c_im[k + 2 * size] = w2 * sin
                    t[k + 2 * size] = (r + 0.5 * b2 - r_m) * inv_half
                for k in range(size):  # scalar, rare: the pairs to add exactly
                    if exact[k] != 0.0:
                        flagged[n_flagged] = start + k
                        n_flagged += 1
                size = 3 * size  # a short last block runs only its own lanes
            else:
                phase = facets[7, start:stop]
                for k in range(size):  # amplitude, phase at f_centre and t of each pair
                    r = dist[k]
                    amp = weight[k] * ((1.0 - kappa) * lobe[k] + kappa * cos_theta[k]) / (r * r)
                    tau = r * tau_per_mm
                    cos, sin = _cos_sin(tau * (f_centre - half_slope * tau) + phase[k])
                    c_re[k] = amp * cos
                    c_im[k] = amp * sin
                    t[k] = (r - r_m) * inv_half
            padded = -(-size // WIDTH) * WIDTH
            for k in range(size, padded):  # zero weights: they add exactly 0
                c_re[k] = 0.0
                c_im[k] = 0.0
                t[k] = 0.0
            a0_re, a0_im = acc_re[0], acc_im[0]
            for j in range(0, padded, WIDTH):  # l = 0
                for q in range(WIDTH):
                    a0_re[q] += c_re[j + q]
                    a0_im[q] += c_im[j + q]
            if n_terms > 1:
                a1_re, a1_im = acc_re[1], acc_im[1]
                for j in range(0, padded, WIDTH):  # l = 1
                    for q in range(WIDTH):
                        k = j + q
                        a1_re[q] += c_re[k] * t[k]
                        a1_im[q] += c_im[k] * t[k]
                        t_even[k] = 1.0
                        t_odd[k] = t[k]
            for l in range(2, n_terms - 1, 2):  # l and l + 1 in one pass: half the loads and stores
                e_re, e_im, o_re, o_im = acc_re[l], acc_im[l], acc_re[l + 1], acc_im[l + 1]
                for j in range(0, padded, WIDTH):
                    for q in range(WIDTH):
                        k = j + q
                        even = 2.0 * t[k] * t_odd[k] - t_even[k]
                        odd = 2.0 * t[k] * even - t_odd[k]
                        t_even[k] = even
                        t_odd[k] = odd
                        e_re[q] += c_re[k] * even
                        e_im[q] += c_im[k] * even
                        o_re[q] += c_re[k] * odd
                        o_im[q] += c_im[k] * odd
            if n_terms > 2 and n_terms % 2 == 1:  # the last, even, l
                e_re, e_im = acc_re[n_terms - 1], acc_im[n_terms - 1]
                for j in range(0, padded, WIDTH):
                    for q in range(WIDTH):
                        k = j + q
                        even = 2.0 * t[k] * t_odd[k] - t_even[k]
                        e_re[q] += c_re[k] * even
                        e_im[q] += c_im[k] * even
        width = WIDTH  # add the lanes: a fixed tree of vectorized halvings
        while width > 1:
            width //= 2
            for l in range(n_terms):
                lane_re, lane_im = acc_re[l], acc_im[l]
                for k in range(width):
                    lane_re[k] += lane_re[k + width]
                    lane_im[k] += lane_im[k + width]
        members[b] = m
        g_even[b::SERIES_BATCH] = 0.0  # rows b and SERIES_BATCH + b: terms beyond the bucket's meet zero coefficients
        g_odd[b::SERIES_BATCH] = 0.0
        for l in range(n_terms):
            g = g_even if l % 2 == 0 else g_odd
            g[b, l // 2] = acc_re[l, 0]
            g[SERIES_BATCH + b, l // 2] = acc_im[l, 0]
        row = exact_rows[b]
        row[:] = 0.0
        for i in range(n_flagged):  # the pairs left out of the series, summed term by term
            k = flagged[i]
            dx, dy, dz = ax - facets[0, k], ay - facets[1, k], az - facets[2, k]
            r = math.sqrt(max(dx * dx + dy * dy + dz * dz, _TINY))
            x = max((facets[3, k] * dx + facets[4, k] * dy + facets[5, k] * dz) / r, 0.0)
            power = _integer_power(x, p_int) if p_int >= 0 else x**p
            amp = 2.0 * facets[6, k] * ((1.0 - kappa) * power + kappa * x) / (r * r)
            b0 = -2.0 * (dx * facets[7, k] + dy * facets[8, k] + dz * facets[9, k]) / r
            b1 = -2.0 * (dx * facets[10, k] + dy * facets[11, k] + dz * facets[12, k]) / r
            b2 = -b0 - b1
            tau = r * tau_per_mm
            series = k_max * (max(b0, max(b1, b2)) - min(b0, min(b1, b2))) < SERIES_SPREAD
            if series:  # near normal incidence, the usual case: one set of coefficients for all k
                _series_coefficients(b0, b1, b2, work)
            for n in range(n_samples):
                cos, sin = _cos_sin(tau * (freqs[n] - half_slope * tau))
                dd = _series_value(work, wavenumbers[n]) if series else _divided_difference(
                    b0, b1, b2, wavenumbers[n], work)
                term = amp * reflectivity[n] * dd
                row[2 * n] += term.real * cos - term.imag * sin
                row[2 * n + 1] += term.real * sin + term.imag * cos
        last_of_batch = (b == SERIES_BATCH - 1 or i_antenna == positions.shape[0] - 1
                         or bucket[sequence[i_antenna + 1]] != own)  # a batch shares its bucket's coefficients
        if last_of_batch:
            # s = sum_l G_l B_l = sum over even l of G_l B_l + j sum over odd l of G_l (B_l / j), each real
            s_even = np.dot(g_even, coef_even[own])  # (2 SERIES_BATCH, N): rows b real, SERIES_BATCH + b imaginary
            s_odd = np.dot(g_odd, coef_odd[own])
            for a in range(b + 1):
                m_a = members[a]
                shift = centre_mm[m_a] * cycles_per_mm  # demodulate: exp(j 2 pi x_m n'), then the common factor
                for n in range(n_samples):
                    cos, sin = _cos_sin(shift * (n - n_centre))
                    d_re[n] = cos * factor[n]
                    d_im[n] = sin * factor[n]
                e_re, e_im, o_re, o_im = s_even[a], s_even[SERIES_BATCH + a], s_odd[a], s_odd[SERIES_BATCH + a]
                row, exact_row = out[m_a], exact_rows[a]
                for n in range(n_samples):
                    s_re = e_re[n] - o_im[n]
                    s_im = e_im[n] + o_re[n]
                    row[2 * n] += (s_re * d_re[n] - s_im * d_im[n]) + exact_row[2 * n]
                    row[2 * n + 1] += (s_re * d_im[n] + s_im * d_re[n]) + exact_row[2 * n + 1]
            b = 0
        else:
            b += 1


def _series_order(w_max, tolerance: float):
    """The fewest Jacobi-Anger terms L with sum_{l >= L} eps_l |J_l(w_max)| <= tolerance (at least 1).

    w_max : float, or an array of them (then an int array of their orders, of its shape, in one Bessel call).
    J_l(w) decays faster than exponentially once l exceeds w by a few w^(1/3), so the
    orders searched reach w + 20 w^(1/3) + 64; a tail that has not converged there is an
    error, never a silent cut.
    """
    from scipy.special import jv

    w = np.asarray(w_max, dtype=np.float64).reshape(-1)
    top = float(w.max()) if len(w) else 0.0
    # Bessel calls cost ~0.5 us each: first a short range of orders, kept where the last order's bound shows that
    # the orders left out add nothing at this tolerance, then the full range.
    for count in (int(top + 4 * top ** (1 / 3)) + 16, int(top + 20 * top ** (1 / 3)) + 64):
        orders = np.arange(count)[:, None]
        bound = np.abs(jv(orders, w[None, :])) * np.where(orders == 0, 1.0, 2.0)
        tail = np.cumsum(bound[::-1], axis=0)[::-1]  # tail[L] = sum over l >= L
        converged = tail <= tolerance
        if (bound[-1] <= 1e-6 * tolerance).all():
            break
    if not converged.any(axis=0).all():
        worst = float(w[~converged.any(axis=0)].max())
        raise MeshsarError(f"chebyshev echo: the Jacobi-Anger series did not converge to {tolerance:g} within "
                           f"{len(orders)} terms (w_max = {worst:.1f}); use echo_method = \"direct\"")
    terms = np.maximum(np.argmax(converged, axis=0), 1)
    return terms.reshape(np.shape(w_max)) if np.ndim(w_max) else int(terms[0])


def _chebyshev_coefficients(omega: np.ndarray, terms: int) -> np.ndarray:
    """(L, N) complex B_l = eps_l j^l J_l(omega_n), L = terms (_series_order of max |omega| at the tolerance)."""
    from scipy.special import jv

    l = np.arange(terms)[:, None]
    # J_l(-w) = (-1)^l J_l(w): evaluate at |w| and restore the sign.
    bessel = jv(l, np.abs(omega)[None, :]) * np.where(omega[None, :] < 0, (-1.0) ** l, 1.0)
    return np.where(l == 0, 1.0, 2.0) * (1j**l) * bessel


def _uniform_step(freqs: np.ndarray) -> float:
    step = (freqs[-1] - freqs[0]) / (len(freqs) - 1) if len(freqs) > 1 else 0.0
    if not np.allclose(np.diff(freqs), step, rtol=1e-9, atol=0):
        raise ValueError(f"freqs: the chebyshev echo needs uniformly spaced frequencies, got {freqs!r}")
    return step


def _kernel_rows(points, normals, weights, offsets) -> np.ndarray:
    """The kernel's (8, K) point rows or (13, K) facet rows (see _chebyshev_echo)."""
    # A complex weight enters as its modulus and a phase in cycles (0 for a real weight: x + 0.0
    # is x, so real weights give the bytes they gave before phases existed).
    rows = [points.T, normals.T, np.abs(weights)[None, :]]
    if offsets is not None:
        rows += [offsets[:, 0].T, offsets[:, 1].T]
    else:
        rows.append((np.angle(weights) / (2 * np.pi))[None, :])
    return np.ascontiguousarray(np.concatenate(rows))


def _series_echo(rows, positions, first, last, freqs, radar, out=None, tolerance=None):
    """(M, N) complex128: antenna m's echo of the kernel rows first[m]:last[m], added to out (default zeros);
    None, out untouched, where the series would need more terms than there are frequency samples (then the
    direct sum is faster).

    tolerance : the series' truncation (default CHEBYSHEV_TOLERANCE, read at the call, as the bench varies it).
    """
    n = len(freqs)
    df = _uniform_step(freqs)
    positions = np.ascontiguousarray(positions)
    low, high = np.empty(len(positions)), np.empty(len(positions))
    _range_bounds(rows, _item_reach(rows), positions, first, last, low, high)
    centre = (low + high) / 2
    tau_per_mm = DELAY_S_PER_MM
    cycles_per_mm = df * tau_per_mm
    n_centre = (n - 1) / 2
    tolerance = CHEBYSHEV_TOLERANCE if tolerance is None else tolerance
    bucket, halves = _order_buckets(np.maximum((high - low) / 2, 1e-6), 2 * np.pi * cycles_per_mm * n_centre, tolerance)
    terms = np.atleast_1d(_series_order(2 * np.pi * cycles_per_mm * n_centre * halves, tolerance))  # one Bessel call
    if terms.max() > n:
        warnings.warn(f"chebyshev echo: a range span of {2 * halves.max():.0f} mm needs {terms.max()} series terms "
                      f"for {n} frequency samples; using the direct sum", stacklevel=4)
        return None
    coefs = [_chebyshev_coefficients(2 * np.pi * cycles_per_mm * half * (np.arange(n) - n_centre), length)
             for half, length in zip(halves, terms)]
    coef_even = np.zeros((len(coefs), (terms.max() + 1) // 2, n))
    coef_odd = np.zeros((len(coefs), max(terms.max() // 2, 1), n))
    for q, coef in enumerate(coefs):
        coef_even[q, :len(coef[0::2])] = coef.real[0::2]
        coef_odd[q, :len(coef[1::2])] = coef.imag[1::2]
    p, kappa = _pattern(radar)
    p_int = int(p) if float(p).is_integer() and p < 16 else -1
    wavenumbers = _wavenumbers(freqs)
    reflectivity = _reflectivity_factor(freqs, radar)
    facets = rows.shape[0] == 13
    factor = reflectivity / wavenumbers**2 if facets else reflectivity
    flag_limit = 2.0 / (CORNER_GAIN_LIMIT * float(wavenumbers.min()) ** 2)
    out = np.zeros((len(positions), n), dtype=np.complex128) if out is None else out
    _chebyshev_echo(rows, positions, first, last, np.argsort(bucket, kind="stable"), bucket, centre, 1.0 / halves,
                    terms, tau_per_mm, freqs[0] + df * n_centre, 0.5 * radar.slope_hz_per_s if radar.rvp else 0.0,
                    float(p), p_int, float(kappa), flag_limit, coef_even, coef_odd, cycles_per_mm, n_centre, freqs,
                    wavenumbers, factor, reflectivity, out.view(np.float64))
    return out


# Antenna range half-widths per bucket of _order_buckets: their largest over this many equal steps.
ORDER_STEPS = 64


def _order_buckets(halves: np.ndarray, omega_per_mm: float, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Antennas grouped by the series length their own range span needs: (bucket (M,) int, half (Q,) float mm).

    halves : (M,) float mm, each antenna's range half-width; omega_per_mm : the series' largest argument per mm of
    it. A bucket's half is its antennas' largest (so |t| <= 1), the buckets' lengths rise; the half-widths are
    pooled over ORDER_STEPS equal steps (one Bessel call), then steps of equal length merged (docs/radar.md)."""
    step = np.minimum((halves * (ORDER_STEPS / halves.max())).astype(np.intp), ORDER_STEPS - 1)
    top = np.zeros(ORDER_STEPS)  # each step's largest half-width (0 where none falls)
    np.maximum.at(top, step, halves)
    used = np.flatnonzero(top)
    lengths, bucket_of_used = np.unique(_series_order(omega_per_mm * top[used], tolerance), return_inverse=True)
    half = np.zeros(len(lengths))
    np.maximum.at(half, bucket_of_used, top[used])
    bucket_of_step = np.zeros(ORDER_STEPS, dtype=np.int8)  # int8: the kernel's visiting order is a radix sort
    bucket_of_step[used] = bucket_of_used
    return bucket_of_step[step], half


def _item_reach(rows: np.ndarray) -> np.ndarray:
    """(K,) how far (mm) each facet's corners lie from its centre (the third offset is minus the sum of the other
    two), which bounds how far their ranges lie from its centre's; 0 for points. Per facet, not the largest (7.7 mm
    on the demo heart against a median of 2.0): that one widened every antenna's range span."""
    if rows.shape[0] != 13:
        return np.zeros(rows.shape[1])
    first, second = rows[7:10], rows[10:13]
    return np.sqrt(np.max([np.sum(first**2, axis=0), np.sum(second**2, axis=0), np.sum((first + second) ** 2, axis=0)],
                          axis=0))


def _echo_chebyshev(points, normals, weights, offsets, positions, freqs, radar):
    """The per-pair series echo; the direct sum (with a warning naming the range span) where the series would
    need more terms than there are frequency samples."""
    if _NUMBA_MISSING:
        raise MeshsarError(_NUMBA_MISSING)
    first, last = np.zeros(len(positions), dtype=np.int64), np.full(len(positions), len(points), dtype=np.int64)
    out = _series_echo(_kernel_rows(points, normals, weights, offsets), positions, first, last, freqs, radar)
    return _echo_direct(points, normals, weights, offsets, positions, freqs, radar) if out is None else out
