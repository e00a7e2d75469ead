"""The radar of one view on a GPU: the echo as a direct sum, and range-migration imaging.

The build's radar stage uses this for `[radar] device = "cuda"` (or `meshsar build
--device cuda`); the numba echo and numpy imaging stay the default (`device = "cpu"`).

- Echo: the same model as radar.echo (DESIGN section 4), evaluated as the direct sum over
  (antenna, frequency, facet) in float64. On a CUDA device it is one fused kernel
  (radar/cuda_sum.py, numba-cuda). On any other torch device (the tests run it on the
  CPU) it is differentiable.echo_chunk, the facet integral the trainer's radar loss
  differentiates, over chunks whose temporaries stay near CPU_CHUNK_BYTES; the kernel is
  tested against it. Facet geometry (centroids, normals, areas, corner offsets) comes
  from the same numpy code as the CPU echo, so all start from the same bits. The direct
  sum is the model itself, not a series, so there is no tail to check.
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

from meshsar_builder.pipeline.errors import MeshsarError
from meshsar_builder.radar.imaging import ImageParams, aperture_window, pixel_centres, range_slices, spectral_grid
from meshsar_builder.radar.params import Aperture, RadarParams
from meshsar_builder.radar.visibility import triangle_geometry

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
         device: str = "cuda"):
    """Noise-free echo s(m, n) (M, N) complex128 of a mesh's facets under radar.facet, computed on `device`.

    The arguments and the result are those of radar.echo.echo: tri (K, 3, 3) float mm,
    visibility (K,) float, positions (M, 3) mm or an Aperture, freqs (N,) Hz, points (K, 3)
    mm the point scatterers of "centroid" / "random" (default the centroids), diffuse the
    diffuse part's (points, normals, weights, pattern radar) added, and with diffuse_on (ix,
    iy, i_freq) also that part alone on a sub-grid of the Aperture (taken from its own sum
    here). A direct sum in float64: the model itself, which the CPU's factorised echo
    follows to 1e-5 - 4e-4.
    """
    if diffuse_on is not None and (diffuse is None or not isinstance(positions, Aperture)):
        raise ValueError("diffuse_on: needs a diffuse part and the antennas as an Aperture")
    tri = np.asarray(tri, dtype=np.float64).reshape(-1, 3, 3)
    centres, normals, areas = triangle_geometry(tri)
    weights = np.asarray(visibility, dtype=np.float64) * areas
    if radar.facet == "po":
        out = _direct_sum(centres, normals, weights, tri - centres[:, None, :], positions, freqs, radar, device)
    else:
        scatterers = centres if points is None else np.asarray(points, dtype=np.float64)
        out = _direct_sum(scatterers, normals, weights, None, positions, freqs, radar, device)
    if diffuse is None:
        return out
    alone = point_echo(*diffuse[:3], positions, freqs, diffuse[3], device)
    if diffuse_on is None:
        return out + alone
    ix, iy, i_freq = diffuse_on
    kept = alone.reshape(len(positions.x_mm), len(positions.y_mm), len(freqs))[np.ix_(ix, iy, i_freq)]
    return out + alone, kept.reshape(len(ix) * len(iy), len(i_freq))


def point_echo(points: np.ndarray, normals: np.ndarray, weights: np.ndarray, positions: np.ndarray,
               freqs: np.ndarray, radar: RadarParams, device: str = "cuda") -> np.ndarray:
    """radar.echo.point_echo on `device`: (M, N) complex128 of point scatterers with real or complex weights (K,)."""
    return _direct_sum(points, normals, np.asarray(weights), None, positions, freqs, radar, device)


def _direct_sum(scatterers, normals, weights, edges, positions, freqs, radar: RadarParams, device: str) -> np.ndarray:
    """The direct sum on `device`: (M, N) complex128, one CUDA kernel on a GPU (radar/cuda_sum.py), else echo_chunk's.

    scatterers, normals (K, 3); weights (K,) real or complex; edges (K, 3, 3) corner offsets
    for the facet integral, or None for point scatterers; positions (M, 3) mm or an
    Aperture; freqs (N,) Hz.
    """
    dev = check_device(device)
    positions = positions.positions if isinstance(positions, Aperture) else positions  # no factorisation here
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    freqs = np.asarray(freqs, dtype=np.float64)
    if len(weights) == 0 or len(positions) == 0:
        return np.zeros((len(positions), len(freqs)), dtype=np.complex128)
    if dev.type == "cuda":
        from meshsar_builder.radar.cuda_sum import direct_sum

        index = torch.cuda.current_device() if dev.index is None else dev.index
        return direct_sum(scatterers, normals, weights, edges, positions, freqs, radar, index)
    if np.iscomplexobj(weights):  # linear in the weights; echo_chunk takes real ones
        return (_direct_sum(scatterers, normals, weights.real, edges, positions, freqs, radar, device)
                + 1j * _direct_sum(scatterers, normals, weights.imag, edges, positions, freqs, radar, device))
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
