"""Near-field range-migration SAR imaging of one view, and its images (DESIGN section 5).

The echo s(x_i, y_j, f_n) of a planar aperture at distance z0 from the heart
centre is focused to complex reflectivity on range slices d (distance from the
aperture plane along -w) and on any cross-range points (u, v):

    S(kx, ky, k)  = sum_ij win_i win_j s(x_i, y_j, k) exp(-j (kx x_i + ky y_j))  (zero-padded FFT)
    img(u, v, d)  = sum_{kx, ky, k} S exp(-j kz d) exp(j (kx u + ky v)),  kz = sqrt(4 k^2 - kx^2 - ky^2)

The forward model's exp(+j 2 k R) makes S of a point at (u', v', d') carry
exp(j (kz d' - kx u' - ky v')) (stationary phase), so the sum peaks there.
The last step evaluates the sum at the pixel centres exactly, so the DESIGN image grid
holds whatever the aperture step and fov: by an inverse FFT of the zero-inserted spectrum
where the padded size makes the FFT's samples fall a pixel apart (the defaults: 165 k
samples of 2 mm apertures, inverse FFTs of 264 give 1.25 mm pixels), else by a DFT matrix.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import scipy.fft
from scipy.fft import next_fast_len
from scipy.ndimage import gaussian_filter

from meshsar_builder.radar.jit import KERNEL_OPTIONS, njit

SPEED_OF_LIGHT_MM_PER_S = 299_792_458.0e3
CHANNELS = ("intensity", "depth")
WINDOWS = ("hann", "none")
# Range slices per range resolution c / 2B. The parabolic refinement of a sinc
# main lobe sampled at 1/8 of its width is biased by well under 1 % of the
# resolution (0.3 mm at the default 37.5 mm); at the defaults 35 slices cover z0 +- fov/2.
SLICES_PER_RESOLUTION = 8
# Depth is only meaningful where something was imaged (DESIGN section 5): above this
# intensity, and this many dB above the RMS of the noise's own image at the peak's range.
# That RMS is taken per range slice: a finite aperture's noise image is not stationary in
# range (0.80-1.27 of its whole RMS at the defaults, strongest near the radar), and against
# the whole RMS 1.75e-4 of pure noise's pixels passed (about 3 a 128 x 128 image), against
# 2.0e-6 per slice (one pixel in 30 images; 1e-7 a sample for an exponential |v|^2).
DEPTH_INTENSITY_FLOOR = 0.1
DETECTION_MARGIN_DB = 12.0


def invalid(field: str, problem: str, value) -> ValueError:
    """The error for a bad parameter value, in the form recipes report: "<field>: <problem>, got <value>"."""
    return ValueError(f"{field}: {problem}, got {value!r}")


@dataclass(frozen=True)
class ImageParams:
    """The images of each view (recipe section [images])."""

    size: int = 128
    fov_mm: float = 160.0
    channels: tuple[str, ...] = ("intensity", "depth")
    window: str = "hann"
    dynamic_range_db: float = 40.0
    depth_looks_mm: float = 3.0

    def __post_init__(self):
        if isinstance(self.size, bool) or not isinstance(self.size, int) or self.size < 2:
            raise invalid("size", "must be an integer >= 2", self.size)
        for name in ("fov_mm", "dynamic_range_db"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
                raise invalid(name, "must be positive and finite", value)
            object.__setattr__(self, name, float(value))
        channels = tuple(self.channels)
        if not channels or len(set(channels)) != len(channels) or not set(channels) <= set(CHANNELS):
            raise invalid("channels", f"must be distinct names from {', '.join(CHANNELS)}", channels)
        object.__setattr__(self, "channels", channels)
        if self.window not in WINDOWS:
            raise invalid("window", f"must be one of {', '.join(WINDOWS)}", self.window)
        looks = self.depth_looks_mm
        if isinstance(looks, bool) or not isinstance(looks, (int, float)) or not 0 <= looks < math.inf:
            raise invalid("depth_looks_mm", "must be >= 0 and finite (0: each pixel's own peak)", looks)
        object.__setattr__(self, "depth_looks_mm", float(looks))


def image_metadata(images: ImageParams) -> dict:
    """index.json's `fov_mm`, `image_size` [H, W] and `channels` (DESIGN section 7)."""
    return {"fov_mm": images.fov_mm, "image_size": [images.size, images.size], "channels": list(images.channels)}


def pixel_centres(size: int, fov_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """u (W,) of the columns and v (H,) of the rows, mm: u = (col + 0.5 - W/2) fov/W, v = (H/2 - row - 0.5) fov/H."""
    index = np.arange(size)
    return (index + 0.5 - size / 2) * fov_mm / size, (size / 2 - index - 0.5) * fov_mm / size


def range_resolution_mm(freqs: np.ndarray) -> float:
    """c / 2B with B = N df, the swept bandwidth of N samples (37.5 mm at the defaults)."""
    bandwidth = len(freqs) * (freqs[-1] - freqs[0]) / (len(freqs) - 1)
    return SPEED_OF_LIGHT_MM_PER_S / (2 * bandwidth)


def range_slices(z0_mm: float, fov_mm: float, freqs: np.ndarray) -> np.ndarray:
    """Distances from the aperture plane (mm) covering z0 +- fov/2, SLICES_PER_RESOLUTION per c/2B."""
    count = math.ceil(fov_mm * SLICES_PER_RESOLUTION / range_resolution_mm(freqs)) + 1
    return np.linspace(z0_mm - fov_mm / 2, z0_mm + fov_mm / 2, count)


def _window(size: int, kind: str) -> np.ndarray:
    return np.hanning(size) if kind == "hann" else np.ones(size)


def phasor(cycles: np.ndarray) -> np.ndarray:
    """complex64 exp(j 2 pi cycles): reduced to [-1/2, 1/2] in float64, then float32 cos/sin.

    numpy's float32 sin/cos are SIMD (~0.4 ns) where float64's are scalar libm
    (~15 ns); after the reduction float32 keeps the phase to ~2e-7 rad.
    """
    reduced = (cycles - np.rint(cycles)).astype(np.float32) * np.float32(2 * np.pi)
    out = np.empty(cycles.shape, dtype=np.complex64)
    out.real = np.cos(reduced)
    out.imag = np.sin(reduced)
    return out


def aperture_window(nx: int, ny: int, kind: str) -> np.ndarray:
    """(Nx, Ny, 1) float: the separable aperture window the echo is weighted by before its FFT."""
    return _window(nx, kind)[:, None, None] * _window(ny, kind)[None, :, None]


# How much larger than the least fast size a padded axis may grow so that its inverse FFT lands on the pixels: the
# range slices cost the padded area, and at the defaults 165 against 162 (4 % more area) halves the pixel sums.
PIXEL_FFT_GROWTH = 1.1


def _padded_size(least: int, step_mm: float, pixels_mm: np.ndarray) -> tuple[int, int | None]:
    """(size, length): an FFT size >= least for an axis sampled every step_mm, and the length of the FFT that
    puts its samples exactly a pixel of pixels_mm (uniform) apart (not shorter than the size: pixels no finer than
    the FFT's samples, so its spectrum fits with zeros inserted), or None where no fast size up to
    PIXEL_FFT_GROWTH times the least fast one has a whole, fast such length (then the pixels take a DFT)."""
    fast = next_fast_len(least)
    if len(pixels_mm) > 1:
        pixel = abs(pixels_mm[-1] - pixels_mm[0]) / (len(pixels_mm) - 1)
        for size in range(least, int(fast * PIXEL_FFT_GROWTH) + 1):
            length = round(size * step_mm / pixel)
            fast_pair = next_fast_len(size) == size and next_fast_len(length) == length
            if (fast_pair and length >= max(size, len(pixels_mm))
                    and abs(length * pixel - size * step_mm) <= 1e-9 * size * step_mm):
                return size, length
    return fast, None


def spectral_grid(nx: int, ny: int, freqs: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray, u_mm: np.ndarray,
                  v_mm: np.ndarray) -> tuple[int, int, np.ndarray, np.ndarray, np.ndarray, int | None, int | None]:
    """(px, py, kx (px,), ky (py,), k (Nf,), length_u, length_v): the zero-padded FFT sizes and wavenumbers
    (rad/mm) of focus, and each axis's FFT length onto the pixels, or None for a DFT (_padded_size).

    Shared by the numpy focus and the torch one (radar/gpu.py), so both pad and sample
    the spectrum alike.
    """
    dx, dy = x_mm[1] - x_mm[0], y_mm[1] - y_mm[0]
    # Zero-padding to twice the larger of aperture and image extent keeps the
    # periodic images of the scene and of its sidelobes out of the pixels.
    extent = 2 * max(np.ptp(u_mm) + dx, np.ptp(v_mm) + dy, nx * dx, ny * dy)
    px, length_u = _padded_size(max(nx, math.ceil(extent / dx)), dx, np.asarray(u_mm))
    py, length_v = _padded_size(max(ny, math.ceil(extent / dy)), dy, np.asarray(v_mm))
    kx = 2 * np.pi * np.fft.fftfreq(px, dx)
    ky = 2 * np.pi * np.fft.fftfreq(py, dy)
    k = 2 * np.pi * np.asarray(freqs) / SPEED_OF_LIGHT_MM_PER_S
    return px, py, kx, ky, k, length_u, length_v


@njit(**KERNEL_OPTIONS)
def _slices(term, advance, out):
    """out[s] = sum_n term * advance^s over frequencies n, for each range slice s.

    term, advance : (px, Nf, py) complex64, term advanced in place; out : (S, px, py)
    complex64. One kx row at a time (its ~80 kB stay in cache for all slices), the loops
    over ky innermost: contiguous, vectorized, each ky its own sum in frequency order.
    """
    px, nf, py = term.shape
    acc = np.empty(py, dtype=np.complex64)
    for ix in range(px):
        row, step = term[ix], advance[ix]
        for s in range(out.shape[0]):
            acc[:] = 0
            for n in range(nf):
                t, a = row[n], step[n]
                for iy in range(py):
                    acc[iy] += t[iy]
                    t[iy] *= a[iy]
            out[s, ix] = acc


def focus(echo: np.ndarray, freqs: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray,
          u_mm: np.ndarray, v_mm: np.ndarray, d_mm: np.ndarray, window: str = "hann") -> np.ndarray:
    """Complex reflectivity (S, H, W) complex64 by range migration.

    echo : (Nx, Ny, Nf) complex, antenna (x_i, y_j) at x_mm (Nx,), y_mm (Ny,) along u, v,
    both uniformly spaced; freqs : (Nf,) Hz; u_mm (W,), v_mm (H,): output points;
    d_mm (S,): range slices, uniformly spaced distances from the aperture plane.
    """
    nx, ny, _ = echo.shape
    plan = _focus_plan(nx, ny, *(tuple(np.asarray(a, dtype=np.float64).tolist())
                                 for a in (freqs, x_mm, y_mm, u_mm, v_mm, d_mm)))
    weighted = (echo * aperture_window(nx, ny, window)).astype(np.complex64).transpose(0, 2, 1)  # (Nx, Nf, Ny)
    # Single precision: the spectrum is kept in complex64 either way. One axis at a time, x first (fft2's own order:
    # the same bytes), on the (x, frequency, y) layout the slices read, so no transposed copy of the padded
    # spectrum is made: 9 ms a volume against fft2's 15.
    spectrum = scipy.fft.fft(scipy.fft.fft(weighted, n=plan.padded[0], axis=0), n=plan.padded[1], axis=2)
    spectrum[plan.evanescent] = 0  # no propagating wave carries it
    spectrum *= plan.first
    focused = np.empty((plan.slices, *plan.padded), dtype=np.complex64)
    _slices(spectrum, plan.advance, focused)
    along_v = _onto_pixels(focused, 2, plan.to_v)  # (S, px, H)
    return np.ascontiguousarray(_onto_pixels(along_v, 1, plan.to_u).transpose(0, 2, 1))


def _onto_pixels(spectrum: np.ndarray, axis: int, transform) -> np.ndarray:
    """The sum over spectrum's k axis (1 or 2 of a 3-D array, in the FFT's order) of exp(j k (pixel - pixel_0))
    times it, onto the pixels of that axis. transform : (pixels, length, sign), an inverse FFT of that length of the
    spectrum with zeros inserted between its positive and negative wavenumbers, its first `pixels` samples; or
    the (pixels, k) DFT matrix. With pixels running against the axis (sign -1, the rows' v), a forward FFT.
    """
    if isinstance(transform, np.ndarray):
        return spectrum @ transform.T if axis == 2 else transform @ spectrum
    pixels, length, sign = transform
    size, positive = spectrum.shape[axis], (spectrum.shape[axis] + 1) // 2  # fftfreq's order: 0 .. positive - 1
    inserted = np.zeros(spectrum.shape[:axis] + (length,) + spectrum.shape[axis + 1:], dtype=spectrum.dtype)
    into, source = np.moveaxis(inserted, axis, 0), np.moveaxis(spectrum, axis, 0)  # views
    into[:positive] = source[:positive]
    into[length - (size - positive):] = source[positive:]  # the negative wavenumbers
    transformed = (scipy.fft.ifft(inserted, axis=axis, norm="forward", overwrite_x=True) if sign > 0
                   else scipy.fft.fft(inserted, axis=axis, overwrite_x=True))  # neither divides by the length
    return np.moveaxis(np.moveaxis(transformed, axis, 0)[:pixels], 0, axis)


@dataclass(frozen=True)
class _FocusPlan:
    """What focus needs besides the echo, read-only: the same for every view and sample of a build."""

    padded: tuple[int, int]  # (px, py), the zero-padded FFT sizes
    slices: int
    evanescent: np.ndarray  # (px, Nf, py) bool, 4 k^2 <= kx^2 + ky^2
    first: np.ndarray  # (px, Nf, py) complex64, exp(-j kz d_0) exp(j (kx (u_0 - x_0) + ky (v_0 - y_0)))
    advance: np.ndarray  # (px, Nf, py) complex64, exp(-j kz (d_1 - d_0)), a slice's step
    to_u: np.ndarray | tuple[int, int, int]  # onto the pixel columns: (W, length, sign) or the (W, px) DFT matrix
    to_v: np.ndarray | tuple[int, int, int]  # onto the pixel rows: (H, length, sign) or (H, py) (_onto_pixels)


@functools.lru_cache(maxsize=4)
def _focus_plan(nx: int, ny: int, freqs: tuple, x_mm: tuple, y_mm: tuple, u_mm: tuple, v_mm: tuple,
                d_mm: tuple) -> _FocusPlan:
    """focus's plan for one grid (arguments as tuples of floats, to be hashable): a third of focus's time,
    computed once per process and grid (~30 MB at the defaults)."""
    freqs, x_mm, y_mm, u_mm, v_mm, d_mm = map(np.asarray, (freqs, x_mm, y_mm, u_mm, v_mm, d_mm))
    px, py, kx, ky, k, length_u, length_v = spectral_grid(nx, ny, freqs, x_mm, y_mm, u_mm, v_mm)
    kz2 = 4 * k[None, :, None] ** 2 - kx[:, None, None] ** 2 - ky[None, None, :] ** 2  # (px, Nf, py)
    kz_cycles = np.sqrt(np.maximum(kz2, 0)) / (2 * np.pi)
    # exp(-j kz d) slice by slice: one exact phasor at the first slice, then a
    # complex64 step per slice (error ~S * 6e-8, far below the 40 dB range).
    step = d_mm[1] - d_mm[0] if len(d_mm) > 1 else 0.0
    # The FFT's phase reference is antenna 0 and the pixel sums' is the first pixel: the shift between them is
    # one more phase per wavenumber, put into the first slice's.
    shift_cycles = (kx[:, None, None] * (u_mm[0] - x_mm[0]) + ky * (v_mm[0] - y_mm[0])) / (2 * np.pi)  # (px, 1, py)
    to_pixels = [(len(pixels), length, int(np.sign(pixels[-1] - pixels[0]))) if length is not None
                 else np.exp(1j * np.outer(pixels - pixels[0], wavenumbers)).astype(np.complex64)
                 for pixels, wavenumbers, length in ((u_mm, kx, length_u), (v_mm, ky, length_v))]
    plan = _FocusPlan((px, py), len(d_mm), kz2 <= 0, phasor(shift_cycles - kz_cycles * d_mm[0]),
                      phasor(-kz_cycles * step), *to_pixels)
    for array in (plan.evanescent, plan.first, plan.advance, *to_pixels):
        if isinstance(array, np.ndarray):
            array.flags.writeable = False
    return plan


def peak_range(magnitude: np.ndarray, d_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the maximum over slices of magnitude (S, H, W) and its distance (mm).

    The distance is refined by the vertex of the parabola through the maximum and
    its two neighbours (the maximum's own slice at the ends of the range).
    """
    best = np.argmax(magnitude, axis=0)
    peak = np.take_along_axis(magnitude, best[None], axis=0)[0]
    before = np.take_along_axis(magnitude, np.maximum(best - 1, 0)[None], axis=0)[0]
    after = np.take_along_axis(magnitude, np.minimum(best + 1, len(d_mm) - 1)[None], axis=0)[0]
    curvature = before - 2 * peak + after
    inner = (best > 0) & (best < len(d_mm) - 1) & (curvature < 0)
    offset = np.divide(0.5 * (before - after), curvature, out=np.zeros_like(peak), where=inner)
    step = d_mm[1] - d_mm[0] if len(d_mm) > 1 else 0.0
    return peak, d_mm[best] + offset * step


def multilook_depth(distance: np.ndarray, power: np.ndarray, sigma_px: float) -> np.ndarray:
    """Power-weighted Gaussian mean (H, W) of per-pixel peak distances (H, W) over neighbours.

    power : (H, W) float, each pixel's peak power, 0 where nothing is detected (those pixels
    get no weight); sigma_px : the Gaussian's std in pixels. Where no detected pixel is
    near, the pixel's own distance is kept.
    """
    weight = gaussian_filter(power, sigma_px, mode="constant")
    looked = gaussian_filter(power * distance, sigma_px, mode="constant")
    return np.divide(looked, weight, out=np.array(distance, dtype=np.float64), where=weight > 0)


def view_volume(echo: np.ndarray, freqs: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray, z0_mm: float,
                images: ImageParams) -> np.ndarray:
    """Complex reflectivity (S, H, W) complex64 of a view on the DESIGN image grid and its range slices.

    echo : (Nx, Ny, Nf) complex with antennas at x_mm, y_mm (mm along u, v) at distance
    z0_mm from the heart centre. Linear in echo: the image of signal plus noise is the
    sum of their images.
    """
    u, v = pixel_centres(images.size, images.fov_mm)
    return focus(echo, freqs, x_mm, y_mm, u, v, range_slices(z0_mm, images.fov_mm, freqs), images.window)


def volume_images(volume: np.ndarray, freqs: np.ndarray, z0_mm: float, images: ImageParams,
                  noise_rms: float | np.ndarray = 0.0) -> np.ndarray:
    """The view's channels (C, H, W) float32 from its complex volume (S, H, W) (view_volume).

    `intensity`: max over range of |image| in dB below the view's maximum, clipped to the
    dynamic range, scaled to [0, 1]. `depth`: the w coordinate of that maximum over
    fov/2, 0 where intensity < 0.1 or the maximum is less than DETECTION_MARGIN_DB above
    noise_rms, the RMS of the noise's image (same units as volume; 0 without noise): one
    value, or (S,) per range slice, then taken at the maximum's range.
    """
    d = range_slices(z0_mm, images.fov_mm, freqs)
    peak, distance = peak_range(np.abs(volume).astype(np.float64), d)
    top = peak.max()
    if top > 0:
        decibels = 20 * np.log10(np.maximum(peak / top, 1e-300))
        intensity = np.clip(1 + decibels / images.dynamic_range_db, 0, 1)
    else:
        intensity = np.zeros_like(peak)
    floor = np.interp(distance, d, noise_rms) if np.ndim(noise_rms) else noise_rms
    detected = (intensity >= DEPTH_INTENSITY_FLOOR) & (peak >= floor * 10 ** (DETECTION_MARGIN_DB / 20))
    if images.depth_looks_mm > 0:
        distance = multilook_depth(distance, np.where(detected, peak**2, 0.0),
                                   images.depth_looks_mm * images.size / images.fov_mm)
    depth = np.where(detected, (z0_mm - distance) / (images.fov_mm / 2), 0.0)
    channels = {"intensity": intensity, "depth": depth}
    return np.stack([channels[name] for name in images.channels]).astype(np.float32)


def view_images(echo: np.ndarray, freqs: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray, z0_mm: float,
                images: ImageParams) -> np.ndarray:
    """The view's channels (C, H, W) float32 of an echo (Nx, Ny, Nf): volume_images of view_volume."""
    return volume_images(view_volume(echo, freqs, x_mm, y_mm, z0_mm, images), freqs, z0_mm, images)
