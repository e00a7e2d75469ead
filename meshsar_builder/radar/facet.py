"""The physical-optics integral of a flat facet, exp(j q.(x - c)) over the triangle (DESIGN section 4).

Compiled with numba: the production echo's kernel calls these per antenna-facet pair.
"""

from __future__ import annotations

import math

import numpy as np

from meshsar_builder.pipeline.errors import MeshsarError
from meshsar_builder.radar.jit import KERNEL_OPTIONS as _KERNEL_OPTIONS
from meshsar_builder.radar.jit import NUMBA_MISSING as _NUMBA_MISSING
from meshsar_builder.radar.jit import njit
from meshsar_builder.radar.visibility import triangle_geometry

# Below this phase spread k (max b - min b) (rad) the divided difference is summed as
# its Taylor series about the corners' mean: 18 terms reach 1e-16 there.
SERIES_SPREAD = 1.0
SERIES_TERMS = 18


# ---------------------------------------------------------------- the facet integral
#
# F(q) = int_facet exp(j q.(x - c)) dA is, by the Hermite-Genocchi formula, 2 A times the
# second divided difference of exp at j alpha_i, alpha_i = q.(p_i - c) at the corners:
#     F = 2 A sum_i exp(j alpha_i) / prod_{l != i} (j alpha_i - j alpha_l).
# That sum cancels catastrophically where corners' phases nearly coincide (normal incidence,
# or an edge across q), so _divided_difference evaluates it robustly: a Taylor series when
# the spread is small, else the recursion f[a, b, c] = (f[b, c] - f[a, b]) / (c - a) with c
# the corner farthest from the other two and f[a, b] = e^a phi1(b - a), phi1 computed as a
# sinc. For the monostatic echo q = 2 k u (u the unit vector from the antenna to c), so
# alpha_i = k b_i with b_i = 2 u.(p_i - c) (mm): one function of (b, k) serves every k.


@njit(inline="always")
def _phi1(x):
    """(exp(j x) - 1) / (j x) for real x, exact at 0: exp(j x / 2) sin(x / 2) / (x / 2)."""
    y = 0.5 * x
    sinc = 1.0 - y * y / 6.0 if abs(y) < 1e-4 else math.sin(y) / y
    return complex(math.cos(y) * sinc, math.sin(y) * sinc)


@njit(inline="always")
def _series_coefficients(b0, b1, b2, a):
    """a (SERIES_TERMS,) <- h_p(b0, b1, b2) / (p + 2)!, the Taylor coefficients of the divided difference.

    h_p, the complete homogeneous polynomials, over one variable, then two and three by
    h_p <- h_p + b h_{p-1}; then DD[exp](j k b) = sum_p a_p (j k)^p.
    """
    a[0] = 1.0
    for p in range(1, SERIES_TERMS):
        a[p] = a[p - 1] * b0
    for p in range(1, SERIES_TERMS):
        a[p] += b1 * a[p - 1]
    for p in range(1, SERIES_TERMS):
        a[p] += b2 * a[p - 1]
    factorial = 2.0
    for p in range(SERIES_TERMS):
        a[p] /= factorial
        factorial *= p + 3


@njit(inline="always")
def _series_value(a, k):
    """sum_p a_p (j k)^p by Horner's rule, complex."""
    z = complex(0.0, k)
    value = complex(a[SERIES_TERMS - 1], 0.0)
    for p in range(SERIES_TERMS - 2, -1, -1):
        value = value * z + a[p]
    return value


@njit(**_KERNEL_OPTIONS)
def _divided_difference(b0, b1, b2, k, work):
    """Second divided difference of exp at j k b0, j k b1, j k b2 (b mm, k rad/mm), complex; 1/2 when all equal.

    work : (SERIES_TERMS,) float scratch.
    """
    lo, hi = min(b0, min(b1, b2)), max(b0, max(b1, b2))
    mid = b0 + b1 + b2 - lo - hi
    if k * (hi - lo) < SERIES_SPREAD:  # the series about the corners' mean
        mean = (b0 + b1 + b2) / 3.0
        _series_coefficients(b0 - mean, b1 - mean, b2 - mean, work)
        return _series_value(work, k) * complex(math.cos(k * mean), math.sin(k * mean))
    if mid - lo < hi - mid:  # lo, mid the close pair; hi the far corner
        a, b, c = lo, mid, hi
    else:
        a, b, c = hi, mid, lo
    first = complex(math.cos(k * a), math.sin(k * a)) * _phi1(k * (b - a))   # f[a, b]
    second = complex(math.cos(k * b), math.sin(k * b)) * _phi1(k * (c - b))  # f[b, c]
    return (second - first) / complex(0.0, k * (c - a))


@njit(**_KERNEL_OPTIONS)
def _divided_differences(b, k, out):
    """out (P, N) complex: _divided_difference of b (P, 3) at every k (N,)."""
    work = np.empty(SERIES_TERMS)
    for i in range(b.shape[0]):
        for n in range(k.shape[0]):
            out[i, n] = _divided_difference(b[i, 0], b[i, 1], b[i, 2], k[n], work)


def facet_integral(tri: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Physical-optics integral F(q) = int exp(j q.(x - c)) dA over each triangle, complex (..., K).

    tri : (K, 3, 3) float corners (mm); q : (..., K, 3) float wave vectors (rad/mm).
    Exact (closed form, robust where corners' phases nearly coincide): the area at q
    normal to the facet, |F| <= area always.
    """
    if _NUMBA_MISSING:
        raise MeshsarError(_NUMBA_MISSING)
    tri = np.asarray(tri, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    centres, _, areas = triangle_geometry(tri)
    alpha = np.einsum("...kc,kic->...ki", q, tri - centres[:, None, :])  # (..., K, 3)
    out = np.empty((alpha[..., 0].size, 1), dtype=np.complex128)
    _divided_differences(np.ascontiguousarray(alpha.reshape(-1, 3)), np.ones(1), out)
    return 2 * areas * out.reshape(alpha.shape[:-1])
