"""The GPU radar's direct sum as one CUDA kernel (numba-cuda): the echo of radar/gpu.py on a CUDA device.

The same model as differentiable.echo_chunk (DESIGN section 4), scalar and fused. One
block per antenna; each of its WARPS warps takes groups of GROUP frequencies, and the
warp's lanes split the facets. Per antenna-facet pair a lane computes the geometry once
(distance, lobe, amplitude, delay, the corner phases, their sort and spread). Every
angle in the sum is linear in the frequency index (the frequencies are evenly spaced and
the chirp term does not depend on them), so each complex exponential of the pair (four
in the facet integral's closed form, one in its near-normal series and for a point) is
evaluated at the group's first frequency and then advanced by a fixed phasor step: at
most 8 sine-cosine pairs per 16 terms, where echo_chunk evaluates 6 sines or cosines a
term. The lanes' partial sums
are added in a fixed order, so every run gives the same bytes. Nothing of size
antennas x facets x frequencies is stored: the element-wise torch version made ~85
passes over such arrays per chunk and was bound by memory traffic.

Float64 throughout, as the torch path. The phasor steps and the summation order differ
from it, so the two agree to rounding: ~1e-13 relative, set by the ~700 rad phases.
Point scatterers take complex weights directly (the diffuse part), so one launch serves
them.

numba-cuda is an optional dependency of a GPU build (the `gpu` extra). Setting
NUMBA_ENABLE_CUDASIM=1 before numba is imported runs this kernel in numba's simulator on
the CPU, which is how CI tests it (tests/test_radar_gpu.py).
"""

from __future__ import annotations

import functools
import math

import numpy as np

from meshsar_builder.pipeline.errors import MeshsarError
from meshsar_builder.radar.differentiable import SERIES_GAP, SERIES_IM, SERIES_RE, SERIES_TERMS
from meshsar_builder.radar.params import DELAY_S_PER_MM, SPEED_OF_LIGHT_M_PER_S, RadarParams

try:
    from numba import cuda, float64
except ImportError as _numba_error:
    cuda = None
    _CUDA_MISSING = (f"the GPU echo needs numba-cuda (pip install 'meshsar-builder[gpu]'); importing it failed: "
                     f"{_numba_error}")
else:
    _CUDA_MISSING = None

WARP = 32
WARPS = 4  # per block: each takes every WARPS-th group of frequencies
GROUP = 16  # frequencies a thread carries by phasor recurrence: 2 x GROUP float64 accumulators in registers
HALF_TERMS = len(SERIES_RE)


@functools.cache
def _kernel():
    """The kernel, made once per process on first use (numba compiles it at its first launch)."""

    @cuda.jit(device=True)
    def phasor(angle):
        return math.cos(angle), math.sin(angle)

    @cuda.jit(device=True)
    def times(re, im, step_re, step_im):
        return re * step_re - im * step_im, re * step_im + im * step_re

    @cuda.jit
    def echo_kernel(centres, normals, w_re, w_im, edges, positions, first, last, inv_k, f0, df, k0, dk, k_min,
                    half_slope, lobe_p, kappa, po_lobe, po_facet, series_re, series_im, out_re, out_im):
        """out (M, N): antenna m = block's sum over facets first[m]:last[m], frequencies by groups (warps), facets by
        lanes."""
        acc_re = cuda.local.array(GROUP, float64)
        acc_im = cuda.local.array(GROUP, float64)
        h_even = cuda.local.array(HALF_TERMS, float64)
        h_odd = cuda.local.array(HALF_TERMS, float64)
        part_re = cuda.shared.array((WARPS, WARP), float64)
        part_im = cuda.shared.array((WARPS, WARP), float64)
        m = cuda.blockIdx.x
        warp, lane = cuda.threadIdx.x // WARP, cuda.threadIdx.x % WARP
        n_freqs = out_re.shape[1]
        ax, ay, az = positions[m, 0], positions[m, 1], positions[m, 2]
        for base in range(0, n_freqs, WARPS * GROUP):  # the same trips in every warp: they meet at the barriers
            n0 = base + warp * GROUP
            for i in range(GROUP):
                acc_re[i], acc_im[i] = 0.0, 0.0
            k_start = k0 + n0 * dk
            for f in range(first[m] + lane, last[m] if n0 < n_freqs else 0, WARP):
                dx, dy, dz = ax - centres[f, 0], ay - centres[f, 1], az - centres[f, 2]
                r2 = dx * dx + dy * dy + dz * dz
                r = math.sqrt(r2)
                cos = max((dx * normals[f, 0] + dy * normals[f, 1] + dz * normals[f, 2]) / r, 0.0)
                lobe = cos if po_lobe else (1 - kappa) * cos**lobe_p + kappa * cos
                a_re, a_im = w_re[f] * lobe / r2, w_im[f] * lobe / r2
                delay = r * DELAY_S_PER_MM
                # the phase 2 pi (f_n tau - S tau^2 / 2) is linear in n: a start and a step
                phase = 2 * math.pi * (delay * (f0 + n0 * df) - half_slope * delay * delay)
                d_phase = 2 * math.pi * delay * df
                if not po_facet:  # a point scatterer: exp(j phase)
                    e_re, e_im = phasor(phase)
                    s_re, s_im = phasor(d_phase)
                    for i in range(GROUP):
                        acc_re[i] += a_re * e_re - a_im * e_im
                        acc_im[i] += a_re * e_im + a_im * e_re
                        e_re, e_im = times(e_re, e_im, s_re, s_im)
                    continue
                b0 = -2 * (dx * edges[f, 0, 0] + dy * edges[f, 0, 1] + dz * edges[f, 0, 2]) / r
                b1 = -2 * (dx * edges[f, 1, 0] + dy * edges[f, 1, 1] + dz * edges[f, 1, 2]) / r
                b2 = -2 * (dx * edges[f, 2, 0] + dy * edges[f, 2, 1] + dz * edges[f, 2, 2]) / r
                lo, hi = min(b0, b1, b2), max(b0, b1, b2)
                mid = b0 + b1 + b2 - lo - hi
                if (hi - lo) * k_min > SERIES_GAP:
                    # 2 (e^{j up} U - e^{j low} L) / (j k (hi - lo)); U = sin(x_u) / x_u, x_u = (hi - mid) k / 2,
                    # and every angle linear in n: four phasors, each advanced by its own step
                    up_re, up_im = phasor(phase + (mid + hi) * k_start / 2)
                    up_sre, up_sim = phasor(d_phase + (mid + hi) * dk / 2)
                    low_re, low_im = phasor(phase + (mid + lo) * k_start / 2)
                    low_sre, low_sim = phasor(d_phase + (mid + lo) * dk / 2)
                    xu_re, xu_im = phasor((hi - mid) * k_start / 2)
                    xu_sre, xu_sim = phasor((hi - mid) * dk / 2)
                    xl_re, xl_im = phasor((lo - mid) * k_start / 2)
                    xl_sre, xl_sim = phasor((lo - mid) * dk / 2)
                    to_u = 2 / (hi - mid) if hi != mid else 0.0  # sin(x_u) / x_u = sin(x_u) to_u / k
                    to_l = 2 / (lo - mid) if lo != mid else 0.0
                    scale = 2 / (hi - lo)
                    for i in range(GROUP):
                        over_k = inv_k[n0 + i]
                        upper = xu_im * to_u * over_k if hi != mid else 1.0
                        lower = xl_im * to_l * over_k if lo != mid else 1.0
                        re = scale * over_k * (upper * up_im - lower * low_im)
                        im = -scale * over_k * (upper * up_re - lower * low_re)
                        acc_re[i] += a_re * re - a_im * im
                        acc_im[i] += a_re * im + a_im * re
                        up_re, up_im = times(up_re, up_im, up_sre, up_sim)
                        low_re, low_im = times(low_re, low_im, low_sre, low_sim)
                        xu_re, xu_im = times(xu_re, xu_im, xu_sre, xu_sim)
                        xl_re, xl_im = times(xl_re, xl_im, xl_sre, xl_sim)
                    continue
                # near normal incidence: the series about the corner phases' mean (facet_phasor's)
                centre = (b0 + b1 + b2) / 3
                w0, w1, w2 = b0 - centre, b1 - centre, b2 - centre
                e2, e3 = w0 * w1 + w0 * w2 + w1 * w2, w0 * w1 * w2
                h0, h1, h2 = 1.0, 0.0, -e2  # h_p = -e2 h_{p-2} + e3 h_{p-3}
                h_even[0], h_odd[0], h_even[1] = series_re[0], 0.0, series_re[1] * h2
                for p in range(3, SERIES_TERMS):
                    h0, h1, h2 = h1, h2, -e2 * h1 + e3 * h0
                    if p % 2 == 0:
                        h_even[p // 2] = series_re[p // 2] * h2
                    else:
                        h_odd[p // 2] = series_im[p // 2] * h2
                c_re, c_im = phasor(phase + centre * k_start)
                s_re, s_im = phasor(d_phase + centre * dk)
                for i in range(GROUP):
                    k = k_start + i * dk
                    k2 = k * k
                    sum_re, sum_im = 0.0, 0.0
                    for q in range(HALF_TERMS - 1, -1, -1):  # Horner in k^2
                        sum_re = sum_re * k2 + h_even[q]
                        sum_im = sum_im * k2 + h_odd[q]
                    sum_im = sum_im * k
                    re, im = c_re * sum_re - c_im * sum_im, c_im * sum_re + c_re * sum_im
                    acc_re[i] += a_re * re - a_im * im
                    acc_im[i] += a_re * im + a_im * re
                    c_re, c_im = times(c_re, c_im, s_re, s_im)
            for i in range(GROUP):  # the lanes hold facet subsets: lane 0 sums them, in a fixed order
                part_re[warp, lane], part_im[warp, lane] = acc_re[i], acc_im[i]
                cuda.syncthreads()
                if lane == 0 and n0 + i < n_freqs:
                    v_re, v_im = 0.0, 0.0
                    for j in range(WARP):
                        v_re += part_re[warp, j]
                        v_im += part_im[warp, j]
                    out_re[m, n0 + i], out_im[m, n0 + i] = v_re, v_im
                cuda.syncthreads()

    return echo_kernel


def uniform(freqs: np.ndarray) -> bool:
    """Whether freqs (N,) are evenly spaced (to 1e-9 of a step), as the kernel's phasor recurrence needs."""
    freqs = np.asarray(freqs, dtype=np.float64)
    steps = np.diff(freqs)
    return len(steps) == 0 or bool(np.all(np.abs(steps - steps[0]) <= 1e-9 * abs(steps[0])) and steps[0] != 0)



def direct_sum(scatterers: np.ndarray, normals: np.ndarray, weights: np.ndarray, edges: np.ndarray | None,
               positions: np.ndarray, freqs: np.ndarray, radar: RadarParams, index: int = 0,
               first: np.ndarray | None = None, last: np.ndarray | None = None) -> np.ndarray:
    """(M, N) complex128: sum_k w_k g(cos theta_km) / R^2 exp(j 2 pi (f_n tau - S tau^2 / 2)) F_k / A_k, on a GPU.

    scatterers, normals (K, 3) mm; weights (K,) real or complex; edges (K, 3, 3) corners
    minus centroid for the facet integral, or None for point scatterers; positions (M, 3)
    mm; freqs (N,) Hz, evenly spaced (uniform); index the CUDA device. first, last (M,) int:
    antenna m sums the scatterers first[m]:last[m] only (the factorised echo's grids, each
    with its cluster's items); default all of them. echo_chunk's sum, in one launch.
    """
    if _CUDA_MISSING:
        raise MeshsarError(_CUDA_MISSING)
    freqs = np.asarray(freqs, dtype=np.float64)
    if not uniform(freqs):
        raise ValueError("freqs: the CUDA echo needs evenly spaced frequencies")
    kernel = _kernel()
    weights = np.asarray(weights)
    to_k = 2e-3 * math.pi / SPEED_OF_LIGHT_M_PER_S  # Hz to rad/mm
    f0, df = freqs[0], (freqs[-1] - freqs[0]) / max(len(freqs) - 1, 1)
    groups = -(-len(freqs) // GROUP)
    inv_k = 1 / ((f0 + df * np.arange(groups * GROUP)) * to_k)  # whole groups: the kernel's loops have fixed trips
    po_facet = edges is not None
    m, n = len(positions), len(freqs)
    first = np.zeros(m, dtype=np.int64) if first is None else np.asarray(first, dtype=np.int64)
    last = np.full(m, len(weights), dtype=np.int64) if last is None else np.asarray(last, dtype=np.int64)
    if m == 0 or not np.any(last > first):
        return np.zeros((m, n), dtype=np.complex128)
    host = [np.ascontiguousarray(a, dtype=np.float64) for a in (
        scatterers, normals, weights.real, weights.imag if np.iscomplexobj(weights) else np.zeros(len(weights)),
        edges if po_facet else np.zeros((1, 3, 3)), positions)]
    host += [np.ascontiguousarray(first), np.ascontiguousarray(last), inv_k]
    with cuda.gpus[index]:
        args = [cuda.to_device(a) for a in host]
        out_re, out_im = cuda.device_array((m, n)), cuda.device_array((m, n))
        try:  # the first launch compiles
            kernel[m, WARPS * WARP](*args, f0, df, f0 * to_k, df * to_k, freqs.min() * to_k,
                                    0.5 * radar.slope_hz_per_s if radar.rvp else 0.0, float(radar.p),
                                    float(radar.kappa), radar.reflectivity == "po", po_facet,
                                    cuda.to_device(SERIES_RE), cuda.to_device(SERIES_IM), out_re, out_im)
        except Exception as error:  # e.g. numba-cuda 0.30.4 under numpy 2.5, which removed np.row_stack
            raise MeshsarError(f"the CUDA echo kernel failed to compile or run on cuda:{index}: "
                               f"{type(error).__name__}: {error} ({_versions()})") from error
        out = out_re.copy_to_host() + 1j * out_im.copy_to_host()
    # the physical-optics factor k / 2 pi
    return out * (freqs * (to_k / (2 * math.pi))) if radar.reflectivity == "po" else out


def _versions() -> str:
    from importlib.metadata import PackageNotFoundError, version

    found = []
    for name in ("numba", "numba-cuda", "numpy"):
        try:
            found.append(f"{name} {version(name)}")
        except PackageNotFoundError:
            found.append(f"{name} not installed")
    return ", ".join(found)
