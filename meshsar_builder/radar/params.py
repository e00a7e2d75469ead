"""Radar parameters, view frames, the synthetic aperture and the echo grid (DESIGN sections 3-4).

Geometry is in millimetres in the heart frame; frequencies in Hz, delays in s.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from meshsar_builder.radar.imaging import ImageParams, image_metadata, invalid

SPEED_OF_LIGHT_M_PER_S = 299_792_458.0
DELAY_S_PER_MM = 2e-3 / SPEED_OF_LIGHT_M_PER_S  # round trip

# Rows u, v, w of each preset view (DESIGN section 3): w points from the heart to the radar.
VIEW_FRAMES = {
    "anterior": ((-1, 0, 0), (0, 0, 1), (0, 1, 0)),
    "posterior": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
    "left": ((0, -1, 0), (0, 0, 1), (-1, 0, 0)),
    "right": ((0, 1, 0), (0, 0, 1), (1, 0, 0)),
    "superior": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "inferior": ((-1, 0, 0), (0, 1, 0), (0, 0, -1)),
}
# How a facet scatters (DESIGN section 4): "po" its physical-optics integral over the
# triangle; "centroid" one point scatterer of the facet's area at its centroid; "random"
# that point drawn uniformly in the facet (seeded per sample).
FACET_MODELS = ("po", "centroid", "random")
# Reflectivity pattern g: "lobe" (1 - kappa) x^p + kappa x; "po" x with the physical-optics
# factor k_n / 2 pi, the textbook monostatic PO model (plate sigma = 4 pi A^2 / lambda^2).
REFLECTIVITIES = ("lobe", "po")
PROBES = ("corners", "centre")
# Noise: the image-domain noise floor's RMS this many dB below the noise-free image's peak,
# unless the recipe sets snr_db (per raw sample). 30 dB puts the noise floor inside the
# 40 dB display (a raw SNR of 30 dB left it ~62 dB down, invisible) and leaves the glints
# within 18 dB of the peak detected for the depth channel (DETECTION_MARGIN_DB).
DEFAULT_IMAGE_SNR_DB = 30.0
ECHO_METHODS = ("factorised", "chebyshev", "direct")
# The radar loss's stored target, echo_clean, is the noise-free echo on this decimation
# (ax, ay, af) of the full grid (issue 28, DESIGN section 7). Chosen by measurement
# (radar.ghosts, point targets at the field of view's edges and corners, +-60 mm deep):
# every 4th frequency of the full 2 mm aperture (80 x 80 x 16 at the defaults) adds
# ghosts at most -52 dB below the peak; every 8th -38 dB; every 16th -10 dB (range
# aliases 150 mm apart); any 4 mm aperture (2, 2, *) 0 dB: an edge target's grating lobe
# (about lambda R / 2d = 139 mm away) is as strong as the target. The limit is -25 dB.
DEFAULT_LOSS_DECIMATION = (1, 1, 4)
# The diffuse (speckle) part of the echo (radar.diffuse): the backscattering coefficient
# sigma0 at normal incidence (Lambert's law) and the scatterers per mm^2 of the reference
# surface. Chosen by measurement (docs/radar.md, Speckle): see the constants' use there.
DEFAULT_DIFFUSE_SIGMA0_DB = 6.0
DEFAULT_DIFFUSE_DENSITY_PER_MM2 = 0.25
# Beyond this the echo's cost (linear in the scatterers) is out of proportion: 20 per mm^2
# is ~300 per resolution cell of the default scan.
MAX_DIFFUSE_DENSITY_PER_MM2 = 20.0
# Where the echo and imaging of a view run: "cpu" (the numba echo and numpy imaging, the
# default, whose bytes the demo shards pin) or a CUDA device through torch (radar/gpu.py).
DEVICE_RE = re.compile(r"^(cpu|cuda|cuda:[0-9]+)$")

# Offset of a visibility ray's origin along the facet normal: ~100 float32 ulps at
# heart scale, so Embree never re-hits the facet it starts from.
RAY_OFFSET_MM = 1e-3
# Antenna-by-facet-by-frequency terms per chunk of the direct (reference) sum: 4 MiB of
# complex128 exponentials.
DIRECT_TERMS_PER_CHUNK = 1 << 18


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
    snr_db: float | None = None
    image_snr_db: float | None = None
    rvp: bool = True
    p: float = 4.0
    kappa: float = 0.3
    facet: str = "po"
    reflectivity: str = "lobe"
    probes: str = "corners"
    echo_decimation: tuple[int, ...] = (5, 5, 2)
    loss_decimation: tuple[int, ...] = DEFAULT_LOSS_DECIMATION
    echo_method: str = "factorised"
    device: str = "cpu"
    diffuse: bool = True
    diffuse_sigma0_db: float = DEFAULT_DIFFUSE_SIGMA0_DB
    diffuse_density_per_mm2: float = DEFAULT_DIFFUSE_DENSITY_PER_MM2

    def __post_init__(self):
        for name in ("f0_hz", "slope_hz_per_s", "fs_hz", "t0_s", "step_mm", "z0_mm", "p", "kappa"):
            _as_float(self, name)
        if self.snr_db is not None and self.image_snr_db is not None:
            raise invalid("snr_db", "set one of snr_db (per raw sample) and image_snr_db (image noise floor), not both",
                          self.snr_db)
        if self.snr_db is None and self.image_snr_db is None:
            object.__setattr__(self, "image_snr_db", DEFAULT_IMAGE_SNR_DB)
        for name in ("snr_db", "image_snr_db"):
            if getattr(self, name) is not None:
                _as_float(self, name)
                if math.isnan(getattr(self, name)) or getattr(self, name) == -math.inf:
                    raise invalid(name, "must be a number or inf (no noise)", getattr(self, name))
        for name in ("f0_hz", "slope_hz_per_s", "fs_hz", "step_mm", "z0_mm", "p"):
            if not (0 < getattr(self, name) < math.inf):
                raise invalid(name, "must be positive and finite", getattr(self, name))
        if not (0 <= self.t0_s < math.inf):
            raise invalid("t0_s", "must be >= 0 and finite", self.t0_s)
        if not 0 <= self.kappa <= 1:
            raise invalid("kappa", "must lie in [0, 1]", self.kappa)
        if isinstance(self.n_samples, bool) or not isinstance(self.n_samples, int) or self.n_samples < 2:
            raise invalid("n_samples", "must be an integer >= 2", self.n_samples)
        aperture = _int_tuple(self, "aperture", 2, 2)
        for key in ("echo_decimation", "loss_decimation"):
            decimation = _int_tuple(self, key, 3, 1)
            for axis, (size, factor) in enumerate(zip((*aperture, self.n_samples), decimation)):
                if factor > size:
                    raise invalid(key, f"entry {axis} exceeds the grid size {size}", decimation)
        views = tuple(self.views)
        if not views or len(set(views)) != len(views):
            raise invalid("views", "must be a non-empty list without repeats", views)
        for view in views:
            if view not in VIEW_FRAMES:
                raise invalid("views", f"unknown view {view!r} (known: {', '.join(VIEW_FRAMES)})", views)
        object.__setattr__(self, "views", views)
        for name in ("rvp", "diffuse"):
            if not isinstance(getattr(self, name), bool):
                raise invalid(name, "must be true or false", getattr(self, name))
        for name in ("diffuse_sigma0_db", "diffuse_density_per_mm2"):
            _as_float(self, name)
        if not math.isfinite(self.diffuse_sigma0_db):
            raise invalid("diffuse_sigma0_db", "must be finite (diffuse = false turns the diffuse part off)",
                          self.diffuse_sigma0_db)
        if not 0 < self.diffuse_density_per_mm2 <= MAX_DIFFUSE_DENSITY_PER_MM2:
            raise invalid("diffuse_density_per_mm2", f"must lie in (0, {MAX_DIFFUSE_DENSITY_PER_MM2:g}]",
                          self.diffuse_density_per_mm2)
        for name, allowed in (("facet", FACET_MODELS), ("reflectivity", REFLECTIVITIES), ("probes", PROBES),
                              ("echo_method", ECHO_METHODS)):
            if getattr(self, name) not in allowed:
                raise invalid(name, f"must be one of {', '.join(allowed)}", getattr(self, name))
        if not isinstance(self.device, str) or not DEVICE_RE.match(self.device):
            raise invalid("device", 'must be "cpu", "cuda" or "cuda:N" (N a device index)', self.device)


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


@dataclass(frozen=True)
class Aperture:
    """A view's planar antenna grid: antenna (i, j) at z0 w + x_i u + y_j v, rows u, v, w of frame.

    frame : (3, 3) float; x_mm : (Nx,) and y_mm : (Ny,) float, increasing. The factorised
    echo needs this structure; everything else takes `positions`.
    """

    frame: np.ndarray
    z0_mm: float
    x_mm: np.ndarray
    y_mm: np.ndarray

    @property
    def positions(self) -> np.ndarray:
        """(Nx * Ny, 3) float: antenna positions (mm, heart frame), row-major over (Nx, Ny)."""
        return _plane_points(self.frame, self.z0_mm, self.x_mm, self.y_mm)


def aperture(radar: RadarParams, view: str) -> Aperture:
    """The synthetic aperture of a view."""
    return Aperture(view_frame(view), radar.z0_mm, *aperture_axes(radar))


def aperture_positions(radar: RadarParams, view: str) -> np.ndarray:
    """(Nx * Ny, 3) float: antenna positions (mm, heart frame), row-major over (Nx, Ny)."""
    return aperture(radar, view).positions


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


def grid_indices(radar: RadarParams, decimation: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices (x, y, frequency) into the full (Nx, Ny, N) grid kept by decimation (ax, ay, af)."""
    sizes = (*radar.aperture, radar.n_samples)
    return tuple(decimation_indices(size, factor) for size, factor in zip(sizes, decimation))


def sub_aperture(radar: RadarParams, view: str, decimation: tuple[int, ...]) -> Aperture:
    """The antennas of a view's aperture that decimation (ax, ay, af) keeps, as an Aperture."""
    (ix, iy, _), (x_mm, y_mm) = grid_indices(radar, decimation), aperture_axes(radar)
    return Aperture(view_frame(view), radar.z0_mm, x_mm[ix], y_mm[iy])


def _sub_grid(radar: RadarParams, decimation: tuple[int, ...]) -> dict:
    positions = {view: sub_aperture(radar, view, decimation).positions for view in radar.views}
    return {"frequencies_hz": frequencies(radar)[grid_indices(radar, decimation)[2]], "positions_mm": positions}


def echo_grid(radar: RadarParams) -> dict:
    """The decimated echo's grid: `frequencies_hz` (Ef,) and per view `positions_mm` (Ex * Ey, 3)."""
    return _sub_grid(radar, radar.echo_decimation)


def loss_grid(radar: RadarParams) -> dict:
    """The grid of echo_clean (the radar loss's target), laid out like echo_grid: (Lf,) and (Lx * Ly, 3) per view."""
    return _sub_grid(radar, radar.loss_decimation)


def index_metadata(radar: RadarParams, images: ImageParams) -> dict:
    """The index.json keys this module owns (DESIGN section 7), as plain JSON values.

    `views`, `fov_mm`, `image_size`, `channels`, `radar`, `echo_grid`, `loss_grid`. The
    noise key not in use, or an infinite one (no noise), is written as null, since JSON has
    no infinity. `radar` carries both decimations: with `aperture` and `n_samples` they
    place each grid in the full one, where the recorded noise is drawn (radar.noise).
    """
    radar_keys = ("f0_hz", "slope_hz_per_s", "fs_hz", "n_samples", "t0_s", "aperture", "step_mm",
                  "z0_mm", "snr_db", "image_snr_db", "rvp", "p", "kappa", "facet", "reflectivity", "probes",
                  "echo_decimation", "loss_decimation", "diffuse", "diffuse_sigma0_db", "diffuse_density_per_mm2")
    radar_dict = {key: getattr(radar, key) for key in radar_keys}
    for key in ("aperture", "echo_decimation", "loss_decimation"):
        radar_dict[key] = list(radar_dict[key])
    for key in ("snr_db", "image_snr_db"):
        radar_dict[key] = radar_dict[key] if radar_dict[key] is not None and math.isfinite(radar_dict[key]) else None
    return {
        "views": [
            {"name": view, **{axis: row.tolist() for axis, row in zip("uvw", view_frame(view))}}
            for view in radar.views
        ],
        **image_metadata(images),
        "radar": radar_dict,
        **{
            key: {
                "frequencies_hz": grid["frequencies_hz"].tolist(),
                "positions_mm": {view: pos.tolist() for view, pos in grid["positions_mm"].items()},
            }
            for key, grid in (("echo_grid", echo_grid(radar)), ("loss_grid", loss_grid(radar)))
        },
    }


