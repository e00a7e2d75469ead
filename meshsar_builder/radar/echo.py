"""The radar echo of a mesh's facets and of point scatterers (DESIGN section 4).

Geometry is in millimetres in the heart frame; frequencies in Hz, delays in s.
For every antenna m of a view's synthetic aperture and frequency sample n,

    s(m, n) = sum_k V_k g(cos theta_km) / R_km^2 exp(j 2 pi f_n tau_km) [exp(-j pi S tau_km^2)] F_k(q_kmn)

with F_k the physical-optics integral of exp(j q.(x - c_k)) over facet k
(facet = "po"), or its area (facet = "centroid" / "random": one point scatterer
per facet). `point_echo` is the same sum for point scatterers; the SAR images
and the decimated echo of a sample are made in render.py. The sums: radar.series
(the direct sum and the per-pair series) and radar.factorised.
"""

from __future__ import annotations

import functools

import numpy as np

from meshsar_builder.radar.factorised import echo_factorised, series_sums
from meshsar_builder.radar.imaging import invalid
from meshsar_builder.radar.params import ECHO_METHODS, Aperture, RadarParams
from meshsar_builder.radar.series import _echo_chebyshev, _echo_direct
from meshsar_builder.radar.visibility import triangle_geometry


def _summed(parts, positions, freqs, method, radar, last_on=None, sums=None):
    """The echo (M, N) complex128 of parts (tuples points, normals, weights, offsets, radar: see
    radar.factorised.echo_factorised) on positions, an (M, 3) array or an Aperture, by method (default
    radar.echo_method). last_on : (ix, iy, i_freq) indices of a sub-grid of an Aperture and of freqs:
    then (echo, the last part's echo alone on that sub-grid), as echo_factorised returns them.

    sums : a device's direct sum (radar.gpu.device_sums, factorised.series_sums' arguments), which then
    sums the factorised echo's grids and, for "direct" and "chebyshev", the antennas themselves; default
    the CPU's series and direct sum.

    "factorised" needs an Aperture and the facet integral (a part with offsets); otherwise
    the series runs. For point scatterers alone the factorisation measured no faster
    (their pairs cost a quarter of a facet's, so the interpolation costs what it saves);
    with facets they share the facets' clusters, and the interpolation costs them nothing.
    Under Lambert's law the cos theta kink is a point's whole lobe, so the diffuse part
    is 1-4e-4 off its direct sum (against 1-5e-5 for the facets: docs/radar.md).
    """
    method = radar.echo_method if method is None else method
    if method not in ECHO_METHODS:
        raise invalid("method", f"must be one of {', '.join(ECHO_METHODS)}", method)
    freqs = np.asarray(freqs, dtype=np.float64)
    grid = positions if isinstance(positions, Aperture) else None
    positions = np.asarray(positions.positions if grid is not None else positions, dtype=np.float64).reshape(-1, 3)
    if last_on is not None:
        if grid is None:
            raise ValueError("positions: an echo on a sub-grid needs the antennas as an Aperture")
        ix, iy, i_freq = (np.asarray(index) for index in last_on)
        sub = Aperture(grid.frame, grid.z0_mm, np.asarray(grid.x_mm)[ix], np.asarray(grid.y_mm)[iy])
        if not len(parts[-1][0]):  # nothing in the last part: the rest alone, and zeros
            return (_summed(parts[:-1], grid, freqs, method, radar, sums=sums),
                    np.zeros((len(ix) * len(iy), len(i_freq)), dtype=np.complex128))
    parts = [part for part in parts if len(part[0])]
    if not parts or len(positions) == 0:
        empty = np.zeros((len(positions), len(freqs)), dtype=np.complex128)
        return empty if last_on is None else (empty, np.zeros((len(sub.positions), len(i_freq)), dtype=np.complex128))
    if method == "factorised" and grid is not None and any(part[3] is not None for part in parts):
        factorised = echo_factorised(parts, grid, freqs, last_on, series_sums if sums is None else sums)
        if factorised is not None:
            return factorised
        method = "direct"  # a range span too wide for the series (warned)
    summer = _echo_direct if method == "direct" else _echo_chebyshev
    if sums is not None:
        summer = functools.partial(_all_items, sums)
    whole = sum(summer(*part[:4], positions, freqs, part[4]) for part in parts)
    return whole if last_on is None else (whole, summer(*parts[-1][:4], sub.positions, freqs[i_freq], parts[-1][4]))


def _all_items(sums, points, normals, weights, offsets, positions, freqs, radar):
    """(M, N) complex128: every antenna's sum over all the items, by a device's sums."""
    out = np.zeros((len(positions), len(freqs)), dtype=np.complex128)
    sums(points, normals, weights, offsets, positions, np.zeros(len(positions), dtype=np.int64),
         np.full(len(positions), len(weights), dtype=np.int64), freqs, radar, out)
    return out


def _point_part(points, normals, weights, radar):
    """A part of point scatterers in the summers' float64 / complex128 arrays."""
    points, normals = (np.asarray(x, dtype=np.float64).reshape(-1, 3) for x in (points, normals))
    weights = np.asarray(weights)
    return points, normals, weights.astype(np.complex128 if np.iscomplexobj(weights) else np.float64), None, radar


def point_echo(points: np.ndarray, normals: np.ndarray, weights: np.ndarray, positions: np.ndarray | Aperture,
               freqs: np.ndarray, radar: RadarParams, method: str | None = None, sums=None) -> np.ndarray:
    """Noise-free echo s(m, n) of point scatterers (DESIGN section 4), complex128 (M, N).

    points : (K, 3) float mm; normals : (K, 3) float, unit; weights : (K,) float or complex
    (mm^2: a facet's visibility times its area, or a diffuse scatterer's complex amplitude);
    positions : (M, 3) float mm, antennas, or a view's params.Aperture (M = Nx Ny, row-major);
    freqs : (N,) float Hz (uniform but for "direct"). method : "direct" (the reference),
    "chebyshev" (the per-pair series, relative L2 error ~1e-9) or "factorised" (the series
    here: see _summed); default radar.echo_method. The series gives the same bytes for the
    same arguments whatever the thread settings; an antenna's last bits depend on the other
    antennas of the call (through the common range half-width), not on how the call is
    scheduled. sums : a device's (see _summed).
    """
    return _summed([_point_part(points, normals, weights, radar)], positions, freqs, method, radar, sums=sums)


def echo(tri: np.ndarray, visibility: np.ndarray, positions: np.ndarray | Aperture, freqs: np.ndarray,
         radar: RadarParams, method: str | None = None, points: np.ndarray | None = None,
         diffuse: tuple | None = None, diffuse_on: tuple | None = None, sums=None):
    """Noise-free echo s(m, n) of a mesh's facets under radar.facet (DESIGN section 4), complex128 (M, N).

    tri : (K, 3, 3) float mm, corners counter-clockwise seen from outside; visibility : (K,)
    float V_k in [0, 1]; positions : (M, 3) antennas, mm, or an Aperture; freqs : (N,) Hz.
    facet "po": each facet's physical-optics integral; "centroid" / "random": a point
    scatterer of the facet's area at points (K, 3) (default the centroids). diffuse :
    (points (P, 3), normals (P, 3), weights (P,) complex, pattern radar), point scatterers
    added to the echo (radar.diffuse: the radar of lambert()). method : "direct",
    "chebyshev" or "factorised": for the facet integral on an Aperture, the series on each
    30 mm cluster's Chebyshev grid of antennas, interpolated (relative L2 error 1e-5 to
    5e-5 against the direct sum; see _summed for the rest); default radar.echo_method.

    diffuse_on : (ix, iy, i_freq) int indices into an Aperture's axes and freqs: then returns
    (echo, the diffuse part alone on that sub-grid (len(ix) len(iy), len(i_freq)) complex128),
    the latter from the diffuse part's own sums on the same clusters, so it costs an
    interpolation onto the sub-grid, not an echo (its power where the shards keep the echo).

    sums : a device's direct sum for the grids' and antennas' sums (radar.gpu.echo), else the CPU's.
    """
    if diffuse_on is not None and diffuse is None:
        raise ValueError("diffuse_on: there is no diffuse part to return")
    tri = np.asarray(tri, dtype=np.float64).reshape(-1, 3, 3)
    centres, normals, areas = triangle_geometry(tri)
    weights = np.asarray(visibility, dtype=np.float64) * areas
    if radar.facet == "po":
        parts = [(centres, normals, weights, tri - centres[:, None, :], radar)]
    else:
        parts = [_point_part(centres if points is None else points, normals, weights, radar)]
    if diffuse is not None:
        parts.append(_point_part(*diffuse))
    return _summed(parts, positions, freqs, method, radar, diffuse_on, sums)
