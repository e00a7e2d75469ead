"""The radar of one view on a GPU: the echo's sums, and range-migration imaging.

The build's radar stage uses this for `[radar] device = "cuda"` (or `meshsar build
--device cuda`); the numba echo and numpy imaging stay the default (`device = "cpu"`).

- Echo: radar.echo's, by the recipe's echo_method, with its sums made here (device_sums)
  as the direct sum over (antenna, frequency, item) in float64. For the factorised echo
  (the default) those are the sums on each cluster's coarse grid of antennas; the
  clustering, the convergence checks and the interpolation stay the CPU's code, so a GPU
  build's echo follows a CPU build's to the CPU's per-pair series (~1e-9), not to the
  factorisation's 1-5e-5, and the GPU sums 6x fewer pairs than over the whole aperture
  (13 M against 82 M a view of the demo heart, its diffuse part included). "direct" sums
  every antenna. On a CUDA device a sum is one fused kernel (radar/cuda_sum.py,
  numba-cuda). On any other torch device (the tests run it on the CPU) it is
  differentiable.echo_chunk, the facet integral the trainer's radar loss differentiates,
  over chunks whose temporaries stay near CPU_CHUNK_BYTES; the kernel is tested against
  it. Facet geometry (centroids, normals, areas, corner offsets) comes from the same numpy
  code as the CPU echo, so all start from the same bits.
- Imaging: radar.imaging.focus in complex128 on a torch device: the same padded spectral
  grid (imaging.spectral_grid) and window, the 2-D FFT, each range slice's exp(-j kz d)
  computed exactly (no phasor recurrence), the explicit DFT onto the pixel centres.
  Returns complex64 like the numpy focus, and the channels (max over range, dB, depth)
  are made from it by imaging.volume_images on the CPU: 0.6 M values, the same code.

torch is an optional dependency (the `train` extra): render.view_functions imports this
module only for a CUDA device, so a CPU build needs no torch, and check_device names a
missing torch instead of failing on the import.
"""

from __future__ import annotations

import functools

import numpy as np

import meshsar_builder.radar.echo as RE
from meshsar_builder.pipeline.errors import MeshsarError
from meshsar_builder.radar.imaging import ImageParams, aperture_window, pixel_centres, range_slices, spectral_grid
from meshsar_builder.radar.params import RadarParams

try:
    import torch
except ImportError as _torch_error:  # optional: only a GPU radar needs it
    torch = None
    _TORCH_MISSING = (f"the GPU radar needs PyTorch with CUDA (pip install 'meshsar-builder[train]', or torch "
                      f"for your CUDA version); importing it failed: {_torch_error}")
else:
    _TORCH_MISSING = None
    from meshsar_builder.radar.differentiable import echo_chunk

# Bytes a chunk's temporaries may take. On a GPU, the imaging's range slices: 8 GiB, capped
# at a quarter of its free memory (chunk_bytes). On the CPU, the torch echo's chunks: 32 MiB,
# where chunks that stay in cache ran 3x faster than 2 GiB ones (1.4 s against 4.3 s for
# 12 M facet terms on one core). Peak bytes per (antenna, facet, frequency) term of one
# echo_chunk call, measured on the CPU (resident-set high-water mark, 4 M terms): 125 for
# the facet integral (~15 float64 arrays of the chunk's size inside facet_phasor), 51 for
# point scatterers.
DEVICE_CHUNK_BYTES = 8 << 30
CPU_CHUNK_BYTES = 32 << 20
BYTES_PER_TERM = 128
# The imaging's per-slice temporaries: the phases, the phasor and its product with the
# spectrum, float64 and complex128 of the padded spectrum's size.
BYTES_PER_SLICE_ELEMENT = 48
WHERE = 'radar device (recipe key [radar] device, or meshsar build --device)'


def check_device(device: str) -> torch.device:
    """The torch device for a radar `device` string, or MeshsarError saying why it cannot be used.

    Raised where the build starts (stages.radar's check), so a missing GPU is named before
    any item runs: torch missing, CUDA not available to this torch, or an index beyond the
    devices this process can see.
    """
    if _TORCH_MISSING:
        raise MeshsarError(f"{WHERE} = {device!r}: {_TORCH_MISSING}")
    dev = torch.device(device)
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            why = ("this torch is a CPU-only build: install one built for CUDA" if torch.version.cuda is None
                   else f"torch is built for CUDA {torch.version.cuda}, but no GPU or driver is visible")
            raise MeshsarError(f"{WHERE} = {device!r}: CUDA is not available here (torch.cuda.is_available() is "
                               f"false; torch {torch.__version__}: {why}); use device \"cpu\" or build on a "
                               f"machine with a GPU")
        count = torch.cuda.device_count()
        if dev.index is not None and dev.index >= count:
            raise MeshsarError(f"{WHERE} = {device!r}: this process sees {count} CUDA device(s), "
                               f"cuda:0 to cuda:{count - 1} (CUDA_VISIBLE_DEVICES renumbers them)")
    return dev


def chunk_bytes(dev: torch.device) -> int:
    """The temporaries' budget of one chunk on dev (see DEVICE_CHUNK_BYTES), at most a quarter of a GPU's free memory."""
    if dev.type == "cpu":
        return CPU_CHUNK_BYTES
    if dev.type == "cuda":
        return min(DEVICE_CHUNK_BYTES, torch.cuda.mem_get_info(dev)[0] // 4)
    return DEVICE_CHUNK_BYTES


def _chunks(total: int, size: int):
    return ((start, min(start + size, total)) for start in range(0, total, size))


def echo(tri: np.ndarray, visibility: np.ndarray, positions, freqs: np.ndarray, radar: RadarParams,
         points: np.ndarray | None = None, diffuse: tuple | None = None, diffuse_on: tuple | None = None,
         device: str = "cuda", method: str | None = None):
    """radar.echo.echo with its sums on `device` (device_sums): the same arguments, method and result.

    tri (K, 3, 3) float mm, visibility (K,) float, positions (M, 3) mm or an Aperture, freqs
    (N,) Hz, points, diffuse and diffuse_on as there. The factorised echo (the default
    method) runs the CPU's clustering, checks and interpolation on the sums of its grids
    made here, so it follows the CPU's to the series' truncation, not to the factorisation's
    error; "direct" (and "chebyshev") sum every antenna here.
    """
    check_device(device)
    return RE.echo(tri, visibility, positions, freqs, radar, method=method, points=points, diffuse=diffuse,
                   diffuse_on=diffuse_on, sums=functools.partial(device_sums, device=device))


def point_echo(points: np.ndarray, normals: np.ndarray, weights: np.ndarray, positions, freqs: np.ndarray,
               radar: RadarParams, device: str = "cuda", method: str | None = None) -> np.ndarray:
    """radar.echo.point_echo on `device`: (M, N) complex128 of point scatterers with real or complex weights (K,)."""
    check_device(device)
    return RE.point_echo(points, normals, weights, positions, freqs, radar, method,
                         sums=functools.partial(device_sums, device=device))


def device_sums(points, normals, weights, offsets, positions, first, last, freqs, radar: RadarParams, out,
                tolerance=None, device: str = "cuda") -> bool:
    """radar.factorised.series_sums on `device`, by the direct sum: adds antenna m's sum over items first[m]:last[m]
    to out (M, N) complex128; always True (a direct sum has no terms to run out of; tolerance is the series').

    points, normals (K, 3); weights (K,) real or complex; offsets (K, 3, 3) corner offsets
    for the facet integral, or None for point scatterers; positions (M, 3) mm; first, last
    (M,) int. One CUDA kernel on a GPU (radar/cuda_sum.py); elsewhere echo_chunk's sum per run
    of antennas with the same items.
    """
    dev = check_device(device)
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    freqs = np.asarray(freqs, dtype=np.float64)
    first, last = np.asarray(first, dtype=np.int64), np.asarray(last, dtype=np.int64)
    if dev.type == "cuda":
        from meshsar_builder.radar.cuda_sum import direct_sum

        index = torch.cuda.current_device() if dev.index is None else dev.index
        out += direct_sum(points, normals, weights, offsets, positions, freqs, radar, index, first, last)
        return True
    runs = np.flatnonzero((np.diff(first) != 0) | (np.diff(last) != 0)) + 1
    for a0, a1 in zip(np.r_[0, runs], np.r_[runs, len(first)]):
        k0, k1 = (first[a0], last[a0]) if a1 > a0 else (0, 0)
        if k1 > k0:
            out[a0:a1] += _torch_sum(points[k0:k1], normals[k0:k1], weights[k0:k1],
                                     None if offsets is None else offsets[k0:k1], positions[a0:a1], freqs, radar, dev)
    return True


def _torch_sum(scatterers, normals, weights, edges, positions, freqs, radar: RadarParams, dev) -> np.ndarray:
    """The direct sum (M, N) complex128 by echo_chunk on a torch device, in chunks (the GPU's kernel's reference).

    scatterers, normals (K, 3); weights (K,) real or complex; edges (K, 3, 3) corner offsets
    for the facet integral, or None for point scatterers; positions (M, 3) mm; freqs (N,) Hz.
    """
    if np.iscomplexobj(weights):  # linear in the weights; echo_chunk takes real ones
        return (_torch_sum(scatterers, normals, weights.real, edges, positions, freqs, radar, dev)
                + 1j * _torch_sum(scatterers, normals, weights.imag, edges, positions, freqs, radar, dev))
    on = functools.partial(torch.as_tensor, dtype=torch.float64, device=dev)
    scatterers, normals, weights, positions_t, freqs_t = map(on, (scatterers, normals, weights, positions, freqs))
    edges = None if edges is None else on(edges)
    # Facets first, then antennas: a chunk spans whole facet ranges of as many antennas as
    # fit, and a mesh too large for one antenna per chunk (6,000 facets x 64 samples is
    # 0.4 M terms, a 32 MiB chunk 0.26 M) is split over its facets instead.
    terms = max(1, chunk_bytes(dev) // BYTES_PER_TERM)
    facet_step = max(1, min(len(weights), terms // len(freqs)))
    antenna_step = max(1, terms // (facet_step * len(freqs)))
    out = torch.zeros((len(positions), len(freqs)), dtype=torch.complex128, device=dev)
    with torch.no_grad():
        for a0, a1 in _chunks(len(positions), antenna_step):
            for f0, f1 in _chunks(len(weights), facet_step):
                out[a0:a1] += echo_chunk(scatterers[f0:f1], normals[f0:f1], weights[f0:f1],
                                         None if edges is None else edges[f0:f1], positions_t[a0:a1], freqs_t, radar)
    return out.cpu().numpy()


def focus(echo: np.ndarray, freqs: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray, u_mm: np.ndarray,
          v_mm: np.ndarray, d_mm: np.ndarray, window: str = "hann", device: str = "cuda") -> np.ndarray:
    """Complex reflectivity (S, H, W) complex64 by range migration on `device`: radar.imaging.focus in complex128.

    echo : (Nx, Ny, Nf) complex, antennas at x_mm (Nx,), y_mm (Ny,) along u, v, uniformly
    spaced; freqs : (Nf,) Hz; u_mm (W,), v_mm (H,): output points; d_mm (S,): range
    slices, distances from the aperture plane.
    """
    dev = check_device(device)
    nx, ny, nf = echo.shape
    px, py, kx, ky, k, _, _ = spectral_grid(nx, ny, freqs, x_mm, y_mm, u_mm, v_mm)  # the pixels by DFT here
    real = functools.partial(torch.as_tensor, dtype=torch.float64, device=dev)
    weighted = torch.as_tensor(np.asarray(echo), dtype=torch.complex128, device=dev) * real(aperture_window(nx, ny,
                                                                                                           window))
    with torch.no_grad():
        spectrum = torch.fft.fft2(weighted, s=(px, py), dim=(0, 1))  # (px, py, Nf)
        kx_t, ky_t, k_t = real(kx), real(ky), real(k)
        kz2 = 4 * k_t[None, None, :] ** 2 - kx_t[:, None, None] ** 2 - ky_t[None, :, None] ** 2
        spectrum = torch.where(kz2 > 0, spectrum, 0)  # evanescent: no propagating wave carries it
        kz = torch.sqrt(kz2.clamp_min(0))
        d = real(np.asarray(d_mm, dtype=np.float64))
        focused = torch.empty((len(d), px, py), dtype=torch.complex128, device=dev)
        step = max(1, chunk_bytes(dev) // (BYTES_PER_SLICE_ELEMENT * px * py * nf))
        one = real(np.ones(()))  # the phasors' modulus
        for s0, s1 in _chunks(len(d), step):  # exp(-j kz d), each slice's own exact phase
            focused[s0:s1] = (spectrum[None] * torch.polar(one, -kz[None] * d[s0:s1, None, None, None])).sum(-1)
        # The FFT's phase reference is antenna 0, hence the x_mm[0], y_mm[0] shifts.
        to_u = torch.polar(one, real(np.outer(np.asarray(u_mm) - x_mm[0], kx)))  # (W, px)
        to_v = torch.polar(one, real(np.outer(np.asarray(v_mm) - y_mm[0], ky)))  # (H, py)
        volume = to_v @ focused.transpose(1, 2) @ to_u.T
    return volume.to(torch.complex64).cpu().numpy()


def view_volume(echo: np.ndarray, freqs: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray, z0_mm: float,
                images: ImageParams, device: str = "cuda") -> np.ndarray:
    """radar.imaging.view_volume on `device`: complex reflectivity (S, H, W) complex64 of echo (Nx, Ny, Nf)."""
    u, v = pixel_centres(images.size, images.fov_mm)
    return focus(echo, freqs, x_mm, y_mm, u, v, range_slices(z0_mm, images.fov_mm, freqs), images.window, device)


def view_functions(device: str):
    """(echo, view_volume) bound to `device`, with the signatures render_sample calls the CPU ones with."""
    check_device(device)
    return functools.partial(echo, device=device), functools.partial(view_volume, device=device)
