"""FMCW mmWave radar echo of a surface mesh (DESIGN section 4).

Geometry is in millimetres in the heart frame; frequencies in Hz, delays in s.
Per view: Embree visibility of every facet from a few probe points on the
aperture, then the coherent sum over visible facets of

    s(m, n) = sum_k V_k A_k(m) exp(j 2 pi f_n tau_km) [exp(-j pi S tau_km^2)]

for every antenna m of the synthetic aperture and frequency sample n, then SAR
images (sar.py) and the echo decimated for the trainer's radar loss.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import trimesh

from .errors import MeshsarError
from .sar import ImageParams, image_metadata, invalid, phasor, view_images

SPEED_OF_LIGHT_M_PER_S = 299_792_458.0

# Rows u, v, w of each preset view (DESIGN section 3): w points from the heart to the radar.
VIEW_FRAMES = {
    "anterior": ((-1, 0, 0), (0, 0, 1), (0, 1, 0)),
    "posterior": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
    "left": ((0, -1, 0), (0, 0, 1), (-1, 0, 0)),
    "right": ((0, 1, 0), (0, 0, 1), (1, 0, 0)),
    "superior": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "inferior": ((-1, 0, 0), (0, 1, 0), (0, 0, -1)),
}
SCATTERERS = ("centroid", "random")
PROBES = ("corners", "centre")
ECHO_METHODS = ("blocked", "direct")

# Offset of a visibility ray's origin along the facet normal: ~100 float32 ulps at
# heart scale, so Embree never re-hits the facet it starts from.
RAY_OFFSET_MM = 1e-3
# Antenna-by-facet pairs per chunk: the blocked sum's working set (two complex64
# arrays of 8 x this) stays in cache; the direct sum multiplies it by n_samples.
PAIRS_PER_CHUNK = 1 << 14


def _as_float(obj, name: str) -> None:
    """Recipes may write 300 for 300.0: store floats so JSON output does not depend on it."""
    value = getattr(obj, name)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise invalid(name, "must be a number", value)
    object.__setattr__(obj, name, float(value))


def _int_tuple(obj, name: str, length: int, minimum: int) -> tuple[int, ...]:
    value = tuple(getattr(obj, name))
    if len(value) != length or any(isinstance(x, bool) or not isinstance(x, int) for x in value):
        raise invalid(name, f"must be {length} integers", value)
    if min(value) < minimum:
        raise invalid(name, f"entries must be >= {minimum}", value)
    object.__setattr__(obj, name, value)
    return value


@dataclass(frozen=True)
class RadarParams:
    """Echo model and scan of one sample (recipe section [radar]; DESIGN section 4)."""

    f0_hz: float = 77e9
    slope_hz_per_s: float = 100e12
    fs_hz: float = 1.6e6
    n_samples: int = 64
    t0_s: float = 0.0
    aperture: tuple[int, ...] = (80, 80)
    step_mm: float = 2.0
    z0_mm: float = 300.0
    views: tuple[str, ...] = ("anterior", "left", "superior")
    snr_db: float = 30.0
    rvp: bool = True
    p: float = 4.0
    kappa: float = 0.3
    scatterer: str = "centroid"
    probes: str = "corners"
    echo_decimation: tuple[int, ...] = (5, 5, 2)
    echo_method: str = "blocked"

    def __post_init__(self):
        for name in ("f0_hz", "slope_hz_per_s", "fs_hz", "t0_s", "step_mm", "z0_mm", "snr_db", "p", "kappa"):
            _as_float(self, name)
        for name in ("f0_hz", "slope_hz_per_s", "fs_hz", "step_mm", "z0_mm", "p"):
            if not (0 < getattr(self, name) < math.inf):
                raise invalid(name, "must be positive and finite", getattr(self, name))
        if not (0 <= self.t0_s < math.inf):
            raise invalid("t0_s", "must be >= 0 and finite", self.t0_s)
        if math.isnan(self.snr_db) or self.snr_db == -math.inf:
            raise invalid("snr_db", "must be a number or inf (no noise)", self.snr_db)
        if not 0 <= self.kappa <= 1:
            raise invalid("kappa", "must lie in [0, 1]", self.kappa)
        if isinstance(self.n_samples, bool) or not isinstance(self.n_samples, int) or self.n_samples < 2:
            raise invalid("n_samples", "must be an integer >= 2", self.n_samples)
        aperture = _int_tuple(self, "aperture", 2, 2)
        decimation = _int_tuple(self, "echo_decimation", 3, 1)
        for axis, (size, factor) in enumerate(zip((*aperture, self.n_samples), decimation)):
            if factor > size:
                raise invalid("echo_decimation", f"entry {axis} exceeds the grid size {size}", decimation)
        views = tuple(self.views)
        if not views or len(set(views)) != len(views):
            raise invalid("views", "must be a non-empty list without repeats", views)
        for view in views:
            if view not in VIEW_FRAMES:
                raise invalid("views", f"unknown view {view!r} (known: {', '.join(VIEW_FRAMES)})", views)
        object.__setattr__(self, "views", views)
        if not isinstance(self.rvp, bool):
            raise invalid("rvp", "must be true or false", self.rvp)
        for name, allowed in (("scatterer", SCATTERERS), ("probes", PROBES), ("echo_method", ECHO_METHODS)):
            if getattr(self, name) not in allowed:
                raise invalid(name, f"must be one of {', '.join(allowed)}", getattr(self, name))


# ---------------------------------------------------------------- views and apertures


def view_frame(name: str) -> np.ndarray:
    """(3, 3) float: rows u, v, w of a preset view (DESIGN section 3)."""
    try:
        return np.array(VIEW_FRAMES[name], dtype=np.float64)
    except KeyError:
        raise ValueError(f"view: unknown view, got {name!r}") from None


def aperture_axes(radar: RadarParams) -> tuple[np.ndarray, np.ndarray]:
    """Antenna coordinates along u (Nx,) and v (Ny,) in mm, centred on the view axis."""
    nx, ny = radar.aperture
    return ((np.arange(nx) - (nx - 1) / 2) * radar.step_mm, (np.arange(ny) - (ny - 1) / 2) * radar.step_mm)


def _plane_points(frame: np.ndarray, z0_mm: float, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
    """(len(x) * len(y), 3) points z0 w + x u + y v, row-major over (x, y)."""
    grid = x_mm[:, None, None] * frame[0] + y_mm[None, :, None] * frame[1] + z0_mm * frame[2]
    return grid.reshape(-1, 3)


def aperture_positions(radar: RadarParams, view: str) -> np.ndarray:
    """(Nx * Ny, 3) float: antenna positions (mm, heart frame), row-major over (Nx, Ny)."""
    return _plane_points(view_frame(view), radar.z0_mm, *aperture_axes(radar))


def frequencies(radar: RadarParams) -> np.ndarray:
    """(N,) float: frequency samples f_n = f0 + S (t0 + n / fs) in Hz."""
    n = np.arange(radar.n_samples)
    return radar.f0_hz + radar.slope_hz_per_s * (radar.t0_s + n / radar.fs_hz)


def probe_points(radar: RadarParams, view: str) -> np.ndarray:
    """(P, 3) float: visibility probes, the aperture centre (then its four corners for "corners")."""
    x, y = aperture_axes(radar)
    centre = _plane_points(view_frame(view), radar.z0_mm, np.zeros(1), np.zeros(1))
    if radar.probes == "centre":
        return centre
    corners = _plane_points(view_frame(view), radar.z0_mm, x[[0, -1]], y[[0, -1]])
    return np.concatenate([centre, corners])


def decimation_indices(size: int, factor: int) -> np.ndarray:
    """Indices kept when decimating an axis of `size` samples by `factor`.

    size // factor samples `factor` apart, placed so that their mean index is the
    axis centre (exactly when the parities allow, else half a sample low): the
    decimated aperture stays centred on the view axis. For frequencies 64 / 2 this
    keeps n = 0, 2, ..., 62.
    """
    count = size // factor
    start = ((size - 1) - factor * (count - 1)) // 2
    return start + factor * np.arange(count)


def echo_grid(radar: RadarParams) -> dict:
    """The decimated echo's grid: `frequencies_hz` (Ef,) and per view `positions_mm` (Ex * Ey, 3)."""
    (nx, ny), (dx, dy, df) = radar.aperture, radar.echo_decimation
    ix, iy = decimation_indices(nx, dx), decimation_indices(ny, dy)
    freqs = frequencies(radar)[decimation_indices(radar.n_samples, df)]
    positions = {
        view: aperture_positions(radar, view).reshape(nx, ny, 3)[np.ix_(ix, iy)].reshape(-1, 3)
        for view in radar.views
    }
    return {"frequencies_hz": freqs, "positions_mm": positions}


def index_metadata(radar: RadarParams, images: ImageParams) -> dict:
    """The index.json keys this module owns (DESIGN section 7), as plain JSON values.

    `views`, `fov_mm`, `image_size`, `channels`, `radar`, `echo_grid`. An infinite
    snr_db (no noise) is written as null, since JSON has no infinity.
    """
    grid = echo_grid(radar)
    radar_keys = ("f0_hz", "slope_hz_per_s", "fs_hz", "n_samples", "t0_s", "aperture", "step_mm",
                  "z0_mm", "snr_db", "rvp", "p", "kappa", "scatterer", "probes")
    radar_dict = {key: getattr(radar, key) for key in radar_keys}
    radar_dict["aperture"] = list(radar.aperture)
    radar_dict["snr_db"] = radar.snr_db if math.isfinite(radar.snr_db) else None
    return {
        "views": [
            {"name": view, **{axis: row.tolist() for axis, row in zip("uvw", view_frame(view))}}
            for view in radar.views
        ],
        **image_metadata(images),
        "radar": radar_dict,
        "echo_grid": {
            "frequencies_hz": grid["frequencies_hz"].tolist(),
            "positions_mm": {view: pos.tolist() for view, pos in grid["positions_mm"].items()},
        },
    }


# ---------------------------------------------------------------- facets and visibility


def facet_geometry(verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroids (F, 3), outward unit normals (F, 3) and areas (F,) of a mesh.

    verts : (n, 3) float mm; faces : (F, 3) int, counter-clockwise seen from outside.
    Degenerate facets get a zero normal and area, so they never contribute.
    """
    tri = np.asarray(verts, dtype=np.float64)[np.asarray(faces)]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    double_area = np.linalg.norm(cross, axis=1)
    normals = np.divide(cross, double_area[:, None], out=np.zeros_like(cross), where=double_area[:, None] > 0)
    return tri.mean(axis=1), normals, double_area / 2


def scatterer_points(verts: np.ndarray, faces: np.ndarray, mode: str, rng: np.random.Generator | None) -> np.ndarray:
    """(F, 3) float: each facet's scatterer, its centroid or ("random") a seeded uniform point in it."""
    tri = np.asarray(verts, dtype=np.float64)[np.asarray(faces)]
    if mode == "centroid":
        return tri.mean(axis=1)
    if mode != "random":
        raise invalid("scatterer", f"must be one of {', '.join(SCATTERERS)}", mode)
    r = rng.random((len(tri), 2))
    # Folding the unit square's upper triangle onto the lower keeps the density uniform.
    outside = r.sum(axis=1) > 1
    r[outside] = 1 - r[outside]
    return tri[:, 0] + r[:, :1] * (tri[:, 1] - tri[:, 0]) + r[:, 1:] * (tri[:, 2] - tri[:, 0])


def embree_intersector(verts: np.ndarray, faces: np.ndarray):
    """trimesh's Embree ray intersector for a mesh; MeshsarError if embreex is missing.

    Never trimesh's pure-Python backend: 10^4 times slower, and it exhausts memory
    at 10^5 rays.
    """
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector
    except ImportError as exc:
        raise MeshsarError(
            "radar visibility needs the Embree ray backend: install embreex "
            f"(pip install embreex); importing it failed: {exc}"
        ) from exc
    mesh = trimesh.Trimesh(np.asarray(verts, dtype=np.float64), np.asarray(faces), process=False)
    return RayMeshIntersector(mesh)


def visibility(verts: np.ndarray, faces: np.ndarray, probes: np.ndarray, intersector=None) -> tuple[np.ndarray, int]:
    """Per facet, the fraction of probes it faces and sees without occlusion.

    verts : (n, 3) float mm; faces : (F, 3) int; probes : (P, 3) float mm.
    intersector : from embree_intersector(verts, faces), to reuse across views.
    Returns (F,) float in [0, 1] and the number of rays cast. A ray starts at the
    centroid lifted by RAY_OFFSET_MM along the normal and counts as blocked if it
    hits any facet (probes lie outside the mesh, so nothing lies beyond them).
    """
    if intersector is None:
        intersector = embree_intersector(verts, faces)
    centres, normals, _ = facet_geometry(verts, faces)
    to_probe = np.asarray(probes, dtype=np.float64)[None, :, :] - centres[:, None, :]
    facing = np.einsum("fc,fpc->fp", normals, to_probe) > 0
    facet, probe = np.nonzero(facing)
    directions = to_probe[facet, probe]
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    origins = centres[facet] + RAY_OFFSET_MM * normals[facet]
    blocked = intersector.intersects_any(origins, directions)
    seen = np.zeros(facing.shape)
    seen[facet[~blocked], probe[~blocked]] = 1.0
    return seen.mean(axis=1), len(facet)


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


def _phase_cycles(tau: np.ndarray, freq: float, radar: RadarParams) -> np.ndarray:
    """Phase / 2 pi of the echo at `freq`: f tau, less S tau^2 / 2 with the residual video phase."""
    if radar.rvp:
        return tau * (freq - 0.5 * radar.slope_hz_per_s * tau)
    return tau * freq


def _uniform_step(freqs: np.ndarray) -> float:
    step = (freqs[-1] - freqs[0]) / (len(freqs) - 1) if len(freqs) > 1 else 0.0
    if not np.allclose(np.diff(freqs), step, rtol=1e-9, atol=0):
        raise ValueError(f"freqs: the blocked echo needs uniformly spaced frequencies, got {freqs!r}")
    return step


def _sum_direct(amp, tau, freqs, radar):
    """Reference: every term's phase in float64 and its own complex exponential."""
    cycles = tau[:, :, None] * freqs[None, None, :]
    if radar.rvp:
        cycles -= (0.5 * radar.slope_hz_per_s * tau**2)[:, :, None]
    return np.einsum("mk,mkn->mn", amp, np.exp(2j * np.pi * cycles))


def _sum_blocked(amp, tau, freqs, radar):
    """Production: the sum over k of c_k z_k^n, n = nb a + b, as a batched matrix product.

    With c_k = A exp(j 2 pi f_0 tau) [rvp] and z_k = exp(j 2 pi df tau), baby steps
    c z^b (b < nb) and giant steps z^(nb a) (a < na) are complex64 chains of at most
    ~sqrt(N) multiplications (relative error ~1e-6); s(m, nb a + b) = sum_k
    giant[a, k] baby[b, k] is then a (na x K)(K x nb) product per antenna, which BLAS
    runs at ~85 GFlop/s. Measured on one core, 6,400 antennas x 2,850 facets x 64
    (default view of a 100 x 80 x 120 mm ellipsoid), sum only: this 0.38 s; FINUFFT
    1-D type 1 per antenna (plan reused, eps 1e-6) 0.52 s, mostly per-antenna
    overhead; FINUFFT 2-D type 1 with the antenna as an on-grid coordinate 0.78 s;
    Jacobi-Anger (Chebyshev in range, 19 terms, float32) 0.39-0.57 s; a complex64
    phasor recurrence with a reduction per step 0.57 s; the direct sum ~21 s.
    """
    n = len(freqs)
    df = _uniform_step(freqs)
    nb = math.isqrt(n - 1) + 1
    na = -(-n // nb)
    m, k = amp.shape
    baby = np.empty((m, nb, k), dtype=np.complex64)
    baby[:, 0] = phasor(_phase_cycles(tau, freqs[0], radar))
    baby[:, 0] *= amp.astype(np.float32)
    z = phasor(df * tau)
    for b in range(1, nb):
        np.multiply(baby[:, b - 1], z, out=baby[:, b])
    giant = np.empty((m, na, k), dtype=np.complex64)
    giant[:, 0] = 1
    if na > 1:
        giant[:, 1] = phasor((nb * df) * tau)
    for a in range(2, na):
        np.multiply(giant[:, a - 1], giant[:, 1], out=giant[:, a])
    return np.matmul(giant, baby.transpose(0, 2, 1)).reshape(m, na * nb)[:, :n]


def echo(points: np.ndarray, normals: np.ndarray, weights: np.ndarray, positions: np.ndarray,
         freqs: np.ndarray, radar: RadarParams, method: str | None = None) -> np.ndarray:
    """Noise-free echo s(m, n) of scatterers (DESIGN section 4), complex128 (M, N).

    points : (K, 3) float mm, one scatterer per facet; normals : (K, 3) float, unit;
    weights : (K,) float, visibility times facet area (mm^2);
    positions : (M, 3) float mm, antennas; freqs : (N,) float Hz (uniform for "blocked").
    method : "direct" (reference) or "blocked" (production, complex64 inside,
    relative L2 error ~1e-6); default radar.echo_method. Antennas are processed in
    chunks, so memory stays bounded for any M and K.
    """
    method = radar.echo_method if method is None else method
    if method not in ECHO_METHODS:
        raise invalid("method", f"must be one of {', '.join(ECHO_METHODS)}", method)
    summer = _sum_blocked if method == "blocked" else _sum_direct
    points, normals, positions = (np.asarray(x, dtype=np.float64).reshape(-1, 3) for x in (points, normals, positions))
    weights, freqs = np.asarray(weights, dtype=np.float64), np.asarray(freqs, dtype=np.float64)
    out = np.zeros((len(positions), len(freqs)), dtype=np.complex128)
    if len(points) == 0:
        return out
    pairs = PAIRS_PER_CHUNK if method == "blocked" else max(1, PAIRS_PER_CHUNK * 16 // len(freqs))
    chunk = max(1, pairs // len(points))
    for start in range(0, len(positions), chunk):
        amp, tau = _amplitude_and_delay(points, normals, weights, positions[start : start + chunk], radar)
        out[start : start + chunk] = summer(amp, tau, freqs, radar)
    return out


def add_noise(signal: np.ndarray, snr_db: float, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """signal plus complex white Gaussian noise `snr_db` below its mean power; and that noise power.

    inf adds nothing (and draws nothing from rng).
    """
    if math.isinf(snr_db):
        return signal, 0.0
    noise_power = float(np.mean(np.abs(signal) ** 2)) / 10 ** (snr_db / 10)
    noise = rng.standard_normal((*signal.shape, 2)) @ np.array([1.0, 1.0j])
    return signal + math.sqrt(noise_power / 2) * noise, noise_power


# ---------------------------------------------------------------- one sample


def render_sample(verts: np.ndarray, faces: np.ndarray, radar: RadarParams, images: ImageParams,
                  rng: np.random.Generator) -> dict:
    """SAR images and decimated echo of one mesh for every view of `radar`.

    verts : (n, 3) float mm, heart frame; faces : (F, 3) int; rng : the sample's
    generator (seeding.item_rng(seed, "radar", sample_id)). Random scatterers are
    drawn from rng first, then view i's noise comes from the i-th of
    rng.spawn(len(views)), so each (sample, view) has its own noise stream.

    Returns `sar` (V, C, H, W) float16, `echo` (V, Ex, Ey, Ef) complex64 on the grid
    of echo_grid(radar), and `views`: per view a dict of `name`, `visible_facets`
    (V_k > 0), `visible_area_mm2` (sum of V_k area_k), `signal_power`,
    `noise_power`, `rays`, and `seconds` for visibility, echo and imaging.
    """
    verts, faces = np.asarray(verts, dtype=np.float64), np.asarray(faces)
    _, normals, areas = facet_geometry(verts, faces)
    points = scatterer_points(verts, faces, radar.scatterer, rng)
    noise_rngs = rng.spawn(len(radar.views))
    intersector = embree_intersector(verts, faces)
    freqs = frequencies(radar)
    x_mm, y_mm = aperture_axes(radar)
    keep_x, keep_y, keep_f = (decimation_indices(size, factor) for size, factor
                              in zip((*radar.aperture, radar.n_samples), radar.echo_decimation))
    sar, decimated, stats = [], [], []
    for view, noise_rng in zip(radar.views, noise_rngs):
        t0 = time.perf_counter()
        vis, rays = visibility(verts, faces, probe_points(radar, view), intersector)
        t1 = time.perf_counter()
        seen = vis > 0
        signal = echo(points[seen], normals[seen], (vis * areas)[seen], aperture_positions(radar, view), freqs, radar)
        signal_power = float(np.mean(np.abs(signal) ** 2))
        signal, noise_power = add_noise(signal, radar.snr_db, noise_rng)
        signal = signal.reshape(*radar.aperture, radar.n_samples)
        t2 = time.perf_counter()
        sar.append(view_images(signal, freqs, x_mm, y_mm, radar.z0_mm, images))
        t3 = time.perf_counter()
        decimated.append(signal[np.ix_(keep_x, keep_y, keep_f)])
        stats.append({
            "name": view, "visible_facets": int(seen.sum()), "visible_area_mm2": float(vis @ areas),
            "signal_power": signal_power, "noise_power": noise_power, "rays": rays,
            "seconds": {"visibility": t1 - t0, "echo": t2 - t1, "imaging": t3 - t2},
        })
    return {
        "sar": np.stack(sar).astype(np.float16),
        "echo": np.stack(decimated).astype(np.complex64),
        "views": stats,
    }
