"""The recorded echo's noise: one generator for the build and for readers (DESIGN sections 4 and 7).

Each (sample, view) has its own uint64 `noise_seed`, drawn from the sample's generator
(seeding.item_rng(seed, "radar", sample_id)) after its random scatterers, and its noise
amplitude `noise_sigma` (echo units; 0 without noise). The view's unit noise is complex
white Gaussian of mean power 1 on the full (Nx, Ny, N) grid, drawn from
np.random.default_rng(noise_seed); the recorded echo at any sub-grid `keep` of the full
grid is

    recorded = complex64(complex128(clean) + sigma * unit_noise(full_shape, seed)[keep])

with clean the complex64 noise-free echo there. The build makes the stored `echo` (the
echo grid) this way and stores `echo_clean` (the loss grid) with the seeds and sigmas,
so a reader regenerates the recorded echo on the loss grid bit for bit. Numpy only: a
reader needs neither numba nor torch for it.
"""

from __future__ import annotations

import math

import numpy as np

SEED_DTYPE = np.dtype(np.uint64)


def draw_seeds(rng: np.random.Generator, count: int) -> np.ndarray:
    """(count,) uint64 noise seeds, one per view, from a sample's generator."""
    return rng.integers(0, 2**64, size=count, dtype=SEED_DTYPE, endpoint=False)


def unit_noise(shape: tuple[int, ...], seed: int | np.integer) -> np.ndarray:
    """Complex white Gaussian noise of mean power 1, complex128 of `shape`, from noise seed `seed`."""
    rng = np.random.default_rng(int(seed))
    # Pairs (real, imaginary) viewed as complex: the bytes of the product with [1, 1j] that it was, 2 ms faster.
    return rng.standard_normal((*shape, 2)).view(np.complex128)[..., 0] / math.sqrt(2)


def add_noise(clean: np.ndarray, sigma: float, unit: np.ndarray | None) -> np.ndarray:
    """complex64(complex128(complex64 clean) + sigma * unit): the recorded echo; clean itself when sigma is 0.

    clean and unit (the unit noise at the same samples) have the same shape; unit may be
    None when sigma is 0.
    """
    out = np.asarray(clean, dtype=np.complex64).astype(np.complex128)
    if sigma > 0:
        out += float(sigma) * unit
    return out.astype(np.complex64)


def recorded_echo(clean: np.ndarray, seed: int | np.integer, sigma: float, full_shape: tuple[int, int, int],
                  keep: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """The recorded (noisy) echo of one view on a sub-grid, complex64 of clean's shape.

    clean : (len(keep[0]), len(keep[1]), len(keep[2])) complex64, the noise-free echo on the
    sub-grid; keep : its indices (x, y, frequency) into the full grid of full_shape
    (Nx, Ny, N) (radar.params.grid_indices). The unit noise is regenerated on the full grid
    and sub-sampled, exactly as the build drew it.
    """
    if sigma <= 0:
        return add_noise(clean, 0.0, None)
    return add_noise(clean, sigma, unit_noise(full_shape, seed)[np.ix_(*keep)])
