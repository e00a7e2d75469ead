"""
Geometry is in millimetres in the heart frame; frequencies in Hz, delays in s.
Per view: Embree visibility of every facet from a few probe points on the
aperture, then the coherent sum over visible facets of

    s(m, n) = sum_k V_k A_k(m) exp(j 2 pi f_n tau_km) [exp(-j pi S tau_km^2)]

for every antenna m of the synthetic aperture and frequency sample n, then SAR
images (sar.py) and the echo decimated for the trainer's radar loss.
"""

from __future__ import annotations

import math

import numpy as np

from meshsar_builder.pipeline.errors import MeshsarError
from meshsar_builder.radar.imaging import invalid
from meshsar_builder.radar.params import DIRECT_TERMS_PER_CHUNK, ECHO_METHODS, SPEED_OF_LIGHT_M_PER_S, RadarParams

# ---------------------------------------------------------------- echo


def _amplitude_and_delay(points, normals, weights, positions, radar: RadarParams):
    """(M, K) amplitude w_k g(cos theta_km) / R_km^2 and round-trip delay tau_km (s).

    R is in mm, so the amplitude is dimensionless (area mm^2 over R^2 mm^2).
    R^2 comes from |a|^2 - 2 a.c + |c|^2 (a BLAS product): in float64 at heart scale
    its error is ~1e-14 mm, 1e-13 rad of phase.
    """
    r2 = positions @ (-2.0 * points.T)
    r2 += np.einsum("mc,mc->m", positions, positions)[:, None]
    r2 += np.einsum("kc,kc->k", points, points)[None, :]
    np.maximum(r2, np.finfo(np.float64).tiny, out=r2)
    r = np.sqrt(r2)
    cos = positions @ normals.T
    cos -= np.einsum("kc,kc->k", normals, points)[None, :]
    cos /= r
    np.maximum(cos, 0.0, out=cos)
    # g(x) = (1 - kappa) x^p + kappa x for x > 0; x = 0 already gives g = 0.
    # An integral p by repeated products: 3x faster than a float power.
    if float(radar.p).is_integer() and radar.p <= 8:
        power = cos.copy()
        for _ in range(int(radar.p) - 1):
            power *= cos
    else:
        power = cos**radar.p
    power *= 1.0 - radar.kappa
    cos *= radar.kappa
    power += cos
    power *= weights[None, :]
    power /= r2
    r *= 2e-3 / SPEED_OF_LIGHT_M_PER_S
    return power, r


def _uniform_step(freqs: np.ndarray) -> float:
    step = (freqs[-1] - freqs[0]) / (len(freqs) - 1) if len(freqs) > 1 else 0.0
    if not np.allclose(np.diff(freqs), step, rtol=1e-9, atol=0):
        raise ValueError(f"freqs: the chebyshev echo needs uniformly spaced frequencies, got {freqs!r}")
    return step


def _sum_direct(amp, tau, freqs, radar):
    """Reference: every term's phase in float64 and its own complex exponential."""
    cycles = tau[:, :, None] * freqs[None, None, :]
    if radar.rvp:
        cycles -= (0.5 * radar.slope_hz_per_s * tau**2)[:, :, None]
    return np.einsum("mk,mkn->mn", amp, np.exp(2j * np.pi * cycles))


def _echo_direct(points, normals, weights, positions, freqs, radar):
    """The reference sum, antennas in chunks so that memory stays bounded for any M and K."""
    out = np.zeros((len(positions), len(freqs)), dtype=np.complex128)
    chunk = max(1, DIRECT_TERMS_PER_CHUNK // (len(points) * len(freqs)))
    for start in range(0, len(positions), chunk):
        amp, tau = _amplitude_and_delay(points, normals, weights, positions[start : start + chunk], radar)
        out[start : start + chunk] = _sum_direct(amp, tau, freqs, radar)
    return out


# ---------------------------------------------------------------- production echo (numba)
#
# For antenna m, with n' = n - (N - 1)/2 and f_c the centre frequency,
#     s(m, n) = sum_k c_k exp(j 2 pi x_k n'),  c_k = A_k exp(j 2 pi tau_k (f_c - S tau_k / 2) [rvp]),
# x_k = df tau_k = beta R_k cycles per sample (beta = df 2e-3 / c per mm). With R_k = R_m + h t_k,
# R_m the middle of antenna m's range interval and h the largest half-width over antennas
# (so |t_k| <= 1), Jacobi-Anger gives exp(j w t) = sum_l eps_l j^l J_l(w) T_l(t) (eps_0 = 1,
# else 2), hence
#     s(m, n) = exp(j 2 pi beta R_m n') sum_l G_l(m) B_l(n'),  G_l(m) = sum_k c_k T_l(t_k),
#     B_l(n') = eps_l j^l J_l(2 pi beta h n').
# The series is cut at the first L whose tail sum_{l >= L} eps_l |J_l(w_max)| is below
# CHEBYSHEV_TOLERANCE, which bounds each term's relative error. The echo is band-limited
# (the mesh spans a few range cells), so ~14 terms replace the N = 64 samples, and each
# costs a few real flops per antenna-facet pair; T_l comes from the three-term recurrence.
#
# The kernels are compiled by numba with fastmath off (no reassociation, no FMA
# contraction) and loops in a fixed order; every antenna is summed on its own, in one
# thread, so the bytes do not depend on thread counts or BLAS (the batched matmul this
# replaced did depend on them). The innermost loops run over the facets of a block with no
# loop-carried reduction, so LLVM's loop vectorizer makes them SIMD without reordering any
# sum: each lane keeps its own partial sums, added at the end in a fixed tree. cos / sin
# are polynomials (below), not libm calls, so that they vectorize too. A lobe power p
# that is not an integer goes through libm pow, in a loop of its own (slower, still exact).
#
# Measured on one core in one run (2-core machine shared with other jobs; min of 3):
# 6,400 antennas x 3,460-3,696 visible facets x 64 samples, the three default views of
# the 100 x 80 x 120 mm ellipsoid (bench_radar), against the direct sum timed on 48
# antennas and scaled (26-31 s): this 0.14-0.18 s (170-190x; L = 13-14; relative L2
# error 2-5e-10); the complex64 baby-step giant-step phasors with a batched BLAS matmul
# that it replaced 0.61-0.86 s (36-44x, error 8e-7); a float64 phasor recurrence
# re-anchored every 32 samples, fused and vectorized like this kernel, 0.51-0.60 s
# (43-57x): 64 complex steps per pair against ~14 real ones. Earlier, on 2,850 facets
# against 0.38 s for the matmul: FINUFFT 1-D type 1 per antenna (plan reused, eps 1e-6)
# 0.52 s, mostly per-antenna overhead; FINUFFT 2-D type 1 with the antenna as an on-grid
# coordinate 0.78 s; Jacobi-Anger in float32 numpy 0.39-0.57 s (memory-bound there).
# Within the kernel: per-pair terms ~40%, the Chebyshev passes ~50%, the rest ~10%. The
# first call in a process compiles the kernels (~2.5 s) or loads them from numba's cache
# in __pycache__ (~0.2 s).

try:
    from numba import njit
except ImportError as _numba_error:  # a declared dependency: fail when the echo is asked for
    _NUMBA_MISSING = f"the production radar echo needs numba (pip install numba); importing it failed: {_numba_error}"

    def njit(*args, **kwargs):
        def missing(*a, **k):
            raise MeshsarError(_NUMBA_MISSING)

        return lambda function: missing
else:
    _NUMBA_MISSING = None

# Facets per block of the vectorized loops: the block's working set (5 + 2 L arrays of
# this many float64) stays in L1 cache. A power of two: the lanes are added as a tree.
FACETS_PER_BLOCK = 256
# Truncation of the Chebyshev series (see above); measured relative L2 error against the
# direct sum ~1e-9, five orders below the 1e-4 that DESIGN section 4 allows.
CHEBYSHEV_TOLERANCE = 1e-8
_TINY = float(np.finfo(np.float64).tiny)
_KERNEL_OPTIONS = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)


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


@njit(**_KERNEL_OPTIONS)
def _range_bounds(facets, positions, low, high):
    """Per antenna, the least and greatest distance to a facet (mm) into low, high (M,)."""
    n_facets, block = facets.shape[1], FACETS_PER_BLOCK
    r2 = np.empty(block)
    lo = np.empty(block)
    hi = np.empty(block)
    for m in range(positions.shape[0]):
        ax, ay, az = positions[m, 0], positions[m, 1], positions[m, 2]
        lo[:] = np.inf
        hi[:] = 0.0
        for start in range(0, n_facets, block):
            px, py, pz = facets[0, start:start + block], facets[1, start:start + block], facets[2, start:start + block]
            for k in range(px.shape[0]):
                dx, dy, dz = ax - px[k], ay - py[k], az - pz[k]
                r2[k] = dx * dx + dy * dy + dz * dz
            for k in range(px.shape[0]):
                lo[k] = min(lo[k], r2[k])
                hi[k] = max(hi[k], r2[k])
        a, b = lo[0], hi[0]
        for k in range(1, block):
            a = min(a, lo[k])
            b = max(b, hi[k])
        low[m] = math.sqrt(max(a, _TINY))
        high[m] = math.sqrt(max(b, _TINY))


@njit(**_KERNEL_OPTIONS)
def _chebyshev_echo(facets, positions, centre_mm, inv_half_mm, tau_per_mm, f_centre, half_slope, p, p_int,
                    kappa, coef_re, coef_im, cycles_per_mm, n_centre, out):
    """Echo of every antenna into out (M, 2 N) float64 (a complex128 (M, N) viewed as floats).

    facets : (7, K) rows x, y, z, nx, ny, nz, weight; centre_mm : (M,) R_m; coef_re, coef_im :
    (L, N) B_l(n'). p_int >= 0: the lobe power p is that integer (< 16), done by products.
    """
    n_facets, block = facets.shape[1], FACETS_PER_BLOCK
    n_terms, n_samples = coef_re.shape
    dist = np.empty(block)
    cos_theta = np.empty(block)
    lobe = np.empty(block)
    t = np.empty(block)
    c_re = np.empty(block)
    c_im = np.empty(block)
    t_even = np.empty(block)  # T_l(t) of the last even l, then of the last odd l
    t_odd = np.empty(block)
    acc_re = np.empty((n_terms, block))  # per lane partial sums of G_l
    acc_im = np.empty((n_terms, block))
    s_re = np.empty(n_samples)
    s_im = np.empty(n_samples)
    d_re = np.empty(n_samples)
    d_im = np.empty(n_samples)
    for m in range(positions.shape[0]):
        ax, ay, az, r_m = positions[m, 0], positions[m, 1], positions[m, 2], centre_mm[m]
        acc_re[:] = 0.0
        acc_im[:] = 0.0
        for start in range(0, n_facets, block):
            px, py, pz = facets[0, start:start + block], facets[1, start:start + block], facets[2, start:start + block]
            nx, ny, nz = facets[3, start:start + block], facets[4, start:start + block], facets[5, start:start + block]
            weight = facets[6, start:start + block]
            size = px.shape[0]
            for k in range(size):  # distance and cos(theta) of each pair
                dx, dy, dz = ax - px[k], ay - py[k], az - pz[k]
                r = math.sqrt(max(dx * dx + dy * dy + dz * dz, _TINY))
                dist[k] = r
                cos_theta[k] = max((nx[k] * dx + ny[k] * dy + nz[k] * dz) / r, 0.0)
            if p_int >= 0:  # not inside the loop: pow is a libm call, which would keep it scalar
                for k in range(size):
                    x = cos_theta[k]
                    x2 = x * x
                    x4 = x2 * x2
                    lobe[k] = ((x if p_int & 1 else 1.0) * (x2 if p_int & 2 else 1.0)
                               * (x4 if p_int & 4 else 1.0) * (x4 * x4 if p_int & 8 else 1.0))
            else:
                for k in range(size):
                    lobe[k] = cos_theta[k] ** p
            for k in range(size):  # amplitude, phase at f_centre and t of each pair
                r = dist[k]
                amp = weight[k] * ((1.0 - kappa) * lobe[k] + kappa * cos_theta[k]) / (r * r)
                tau = r * tau_per_mm
                cos, sin = _cos_sin(tau * (f_centre - half_slope * tau))
                c_re[k] = amp * cos
                c_im[k] = amp * sin
                t[k] = (r - r_m) * inv_half_mm
            a0_re, a0_im = acc_re[0], acc_im[0]
            for k in range(size):  # l = 0
                a0_re[k] += c_re[k]
                a0_im[k] += c_im[k]
            if n_terms > 1:
                a1_re, a1_im = acc_re[1], acc_im[1]
                for k in range(size):  # l = 1
                    a1_re[k] += c_re[k] * t[k]
                    a1_im[k] += c_im[k] * t[k]
                    t_even[k] = 1.0
                    t_odd[k] = t[k]
            for l in range(2, n_terms - 1, 2):  # l and l + 1 in one pass: half the loads and stores
                e_re, e_im, o_re, o_im = acc_re[l], acc_im[l], acc_re[l + 1], acc_im[l + 1]
                for k in range(size):
                    even = 2.0 * t[k] * t_odd[k] - t_even[k]
                    odd = 2.0 * t[k] * even - t_odd[k]
                    t_even[k] = even
                    t_odd[k] = odd
                    e_re[k] += c_re[k] * even
                    e_im[k] += c_im[k] * even
                    o_re[k] += c_re[k] * odd
                    o_im[k] += c_im[k] * odd
            if n_terms > 2 and n_terms % 2 == 1:  # the last, even, l
                e_re, e_im = acc_re[n_terms - 1], acc_im[n_terms - 1]
                for k in range(size):
                    even = 2.0 * t[k] * t_odd[k] - t_even[k]
                    e_re[k] += c_re[k] * even
                    e_im[k] += c_im[k] * even
        width = block  # add the lanes: a fixed tree of vectorized halvings
        while width > 1:
            width //= 2
            for l in range(n_terms):
                lane_re, lane_im = acc_re[l], acc_im[l]
                for k in range(width):
                    lane_re[k] += lane_re[k + width]
                    lane_im[k] += lane_im[k + width]
        s_re[:] = 0.0
        s_im[:] = 0.0
        for l in range(n_terms):
            g_re, g_im = acc_re[l, 0], acc_im[l, 0]
            b_re, b_im = coef_re[l], coef_im[l]
            for n in range(n_samples):
                s_re[n] += g_re * b_re[n] - g_im * b_im[n]
                s_im[n] += g_re * b_im[n] + g_im * b_re[n]
        shift = r_m * cycles_per_mm  # demodulate: exp(j 2 pi x_m n')
        for n in range(n_samples):
            cos, sin = _cos_sin(shift * (n - n_centre))
            d_re[n] = cos
            d_im[n] = sin
        row = out[m]
        for n in range(n_samples):
            row[2 * n] = s_re[n] * d_re[n] - s_im[n] * d_im[n]
            row[2 * n + 1] = s_re[n] * d_im[n] + s_im[n] * d_re[n]


def _chebyshev_coefficients(omega: np.ndarray, tolerance: float) -> np.ndarray:
    """(L, N) complex B_l = eps_l j^l J_l(omega_n), L the fewest terms whose tail is below tolerance."""
    from scipy.special import jv

    w_max = float(np.abs(omega).max())
    orders = np.arange(int(w_max) + 64)
    bound = np.abs(jv(orders, w_max)) * np.where(orders == 0, 1.0, 2.0)
    tail = np.cumsum(bound[::-1])[::-1]  # tail[L] = sum over l >= L
    n_terms = max(int(np.argmax(tail <= tolerance)), 1)
    l = orders[:n_terms, None]
    # J_l(-w) = (-1)^l J_l(w): evaluate at |w| and restore the sign.
    bessel = jv(l, np.abs(omega)[None, :]) * np.where(omega[None, :] < 0, (-1.0) ** l, 1.0)
    return np.where(l == 0, 1.0, 2.0) * (1j**l) * bessel


def _echo_chebyshev(points, normals, weights, positions, freqs, radar):
    """The production echo: the range bounds, the series' coefficients, then the kernel."""
    if _NUMBA_MISSING:
        raise MeshsarError(_NUMBA_MISSING)
    n = len(freqs)
    df = _uniform_step(freqs)
    facets = np.ascontiguousarray(np.concatenate([points.T, normals.T, weights[None, :]]))
    positions = np.ascontiguousarray(positions)
    low, high = np.empty(len(positions)), np.empty(len(positions))
    _range_bounds(facets, positions, low, high)
    centre = (low + high) / 2
    half = max(float(np.max(high - low)) / 2, 1e-6)  # mm; a floor for a single range
    tau_per_mm = 2e-3 / SPEED_OF_LIGHT_M_PER_S
    cycles_per_mm = df * tau_per_mm
    n_centre = (n - 1) / 2
    coef = _chebyshev_coefficients(2 * np.pi * cycles_per_mm * half * (np.arange(n) - n_centre),
                                   CHEBYSHEV_TOLERANCE)
    p = float(radar.p)
    p_int = int(p) if p.is_integer() and p < 16 else -1
    out = np.empty((len(positions), n), dtype=np.complex128)
    _chebyshev_echo(facets, positions, centre, 1.0 / half, tau_per_mm, freqs[0] + df * n_centre,
                    0.5 * radar.slope_hz_per_s if radar.rvp else 0.0, p, p_int, float(radar.kappa),
                    np.ascontiguousarray(coef.real), np.ascontiguousarray(coef.imag), cycles_per_mm, n_centre,
                    out.view(np.float64))
    return out


def echo(points: np.ndarray, normals: np.ndarray, weights: np.ndarray, positions: np.ndarray,
         freqs: np.ndarray, radar: RadarParams, method: str | None = None) -> np.ndarray:
    """Noise-free echo s(m, n) of scatterers (DESIGN section 4), complex128 (M, N).

    points : (K, 3) float mm, one scatterer per facet; normals : (K, 3) float, unit;
    weights : (K,) float, visibility times facet area (mm^2);
    positions : (M, 3) float mm, antennas; freqs : (N,) float Hz (uniform for "chebyshev").
    method : "direct" (reference) or "chebyshev" (production, relative L2 error ~1e-9);
    default radar.echo_method. "chebyshev" gives the same bytes for the same arguments
    whatever the thread settings; an antenna's last bits depend on the other antennas of
    the call (through the common range half-width), not on how the call is scheduled.
    """
    method = radar.echo_method if method is None else method
    if method not in ECHO_METHODS:
        raise invalid("method", f"must be one of {', '.join(ECHO_METHODS)}", method)
    points, normals, positions = (np.asarray(x, dtype=np.float64).reshape(-1, 3) for x in (points, normals, positions))
    weights, freqs = np.asarray(weights, dtype=np.float64), np.asarray(freqs, dtype=np.float64)
    if len(points) == 0 or len(positions) == 0:
        return np.zeros((len(positions), len(freqs)), dtype=np.complex128)
    summer = _echo_chebyshev if method == "chebyshev" else _echo_direct
    return summer(points, normals, weights, positions, freqs, radar)


def add_noise(signal: np.ndarray, snr_db: float, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """signal plus complex white Gaussian noise `snr_db` below its mean power; and that noise power.

    inf adds nothing (and draws nothing from rng).
    """
    if math.isinf(snr_db):
        return signal, 0.0
    noise_power = float(np.mean(np.abs(signal) ** 2)) / 10 ** (snr_db / 10)
    noise = rng.standard_normal((*signal.shape, 2)) @ np.array([1.0, 1.0j])
    return signal + math.sqrt(noise_power / 2) * noise, noise_power


