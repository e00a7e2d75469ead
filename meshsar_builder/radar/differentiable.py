"""Differentiable radar echo in PyTorch, for the trainer's radar loss (DESIGN section 4).

The same amplitude and phase as radar.echo, with the Embree visibility V_k
replaced by the soft visibility sigmoid(beta cos theta_k), cos theta_k the
cosine between the facet normal and the direction to the aperture centre (no
occlusion). Normals, areas and centroids are computed from the vertices inside
the graph, so gradients reach vertex positions. Runs on the device of `verts`.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch.utils.checkpoint import checkpoint

from meshsar_builder.radar.params import SPEED_OF_LIGHT_M_PER_S, RadarParams

# Antenna x facet x frequency terms held at once (complex): ~64 MB in complex64.
TERMS_PER_CHUNK = 1 << 23


def facet_geometry_torch(verts: torch.Tensor, faces: torch.Tensor):
    """Centroids (..., F, 3), unit normals (..., F, 3) and areas (..., F) from verts (..., V, 3)."""
    tri = verts[..., faces, :]
    cross = torch.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :], dim=-1)
    double_area = torch.linalg.vector_norm(cross, dim=-1)
    return tri.mean(dim=-2), cross / double_area.clamp_min(torch.finfo(verts.dtype).tiny)[..., None], double_area / 2


def soft_visibility(centroids: torch.Tensor, normals: torch.Tensor, centre: torch.Tensor, beta: float) -> torch.Tensor:
    """sigmoid(beta cos theta_k) (..., F), theta_k between n_k and the direction from c_k to `centre` (3,)."""
    to_centre = centre - centroids
    cos = (normals * to_centre).sum(-1) / torch.linalg.vector_norm(to_centre, dim=-1)
    return torch.sigmoid(beta * cos)


def _echo_chunk(centroids, normals, weights, positions, freqs, p, kappa, slope_hz_per_s):
    """sum_k w_k g(cos theta_km) / R^2 exp(j 2 pi (f_n tau - S tau^2 / 2)): (..., M, Ef)."""
    diff = positions[:, None, :] - centroids[..., None, :, :]  # (..., M, F, 3)
    r2 = (diff * diff).sum(-1)
    r = torch.sqrt(r2)
    cos = ((diff * normals[..., None, :, :]).sum(-1) / r).clamp_min(0)
    amplitude = weights[..., None, :] * ((1 - kappa) * cos**p + kappa * cos) / r2
    tau = r * (2e-3 / SPEED_OF_LIGHT_M_PER_S)
    cycles = tau[..., None] * freqs
    if slope_hz_per_s:
        cycles = cycles - (0.5 * slope_hz_per_s) * (tau * tau)[..., None]
    terms = torch.polar(amplitude[..., None].expand_as(cycles), (2 * math.pi) * cycles)
    return terms.sum(-2)


def echo_torch(verts: torch.Tensor, faces: torch.Tensor, positions, freqs, radar: RadarParams,
               beta: float = 10.0, centre=None) -> torch.Tensor:
    """Differentiable echo (..., M, Ef), complex of verts' precision.

    verts : (V, 3) or (B, V, 3) float tensor, mm, heart frame; faces : (F, 3) long;
    positions : (M, 3) antennas, mm (e.g. echo_grid(radar)["positions_mm"][view]);
    freqs : (Ef,) Hz; beta : steepness of the soft visibility; centre : (3,) aperture
    centre, mm (default: the mean of positions, the centre of a centred grid).
    Facet scatterers are the centroids. Antennas are processed in chunks, each
    recomputed in the backward pass when gradients are on (checkpointing), so
    memory stays near TERMS_PER_CHUNK terms whatever M.
    """
    dtype, device = verts.dtype, verts.device
    positions = torch.as_tensor(np.asarray(positions), dtype=dtype, device=device)
    freqs = torch.as_tensor(np.asarray(freqs), dtype=dtype, device=device)
    centre = positions.mean(0) if centre is None else torch.as_tensor(np.asarray(centre), dtype=dtype, device=device)
    faces = torch.as_tensor(faces, dtype=torch.long, device=device)
    centroids, normals, areas = facet_geometry_torch(verts, faces)
    weights = areas * soft_visibility(centroids, normals, centre, beta)
    slope = radar.slope_hz_per_s if radar.rvp else 0.0
    batch = int(np.prod(verts.shape[:-2], dtype=np.int64))
    chunk = max(1, TERMS_PER_CHUNK // (batch * len(faces) * len(freqs)))
    parts = []
    for start in range(0, len(positions), chunk):
        args = (centroids, normals, weights, positions[start : start + chunk], freqs, radar.p, radar.kappa, slope)
        if torch.is_grad_enabled() and verts.requires_grad:
            parts.append(checkpoint(_echo_chunk, *args, use_reentrant=False))
        else:
            parts.append(_echo_chunk(*args))
    return torch.cat(parts, dim=-2)
