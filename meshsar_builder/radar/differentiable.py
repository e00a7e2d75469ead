"""Differentiable radar echo in PyTorch, for the trainer's radar loss (DESIGN section 4).

The production model: per visible facet, its physical-optics integral F_k(q) (facet
"po") or its area (facet "centroid"), the reflectivity pattern g and 1/R^2 at the
centroid, the round-trip phase [with rvp]. The visibility V_k is the Embree
visibility of the facet on the current mesh (radar.visibility, a mask without
gradient, cast on the detached vertices) times the soft facing sigmoid(beta cos
theta_k), theta_k between the facet normal and the direction to the aperture
centre, which carries the gradient. Normals, areas, centroids and corners come
from the vertices inside the graph, so gradients reach vertex positions. Runs on
the device of `verts`.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from torch.utils.checkpoint import checkpoint

from meshsar_builder.radar.params import DELAY_S_PER_MM, SPEED_OF_LIGHT_M_PER_S, VIEW_FRAMES, RadarParams, probe_points

# Antenna x facet x frequency terms per chunk: the facet integral holds ~40 real arrays
# of this size for the backward pass, ~170 MB in float32.
TERMS_PER_CHUNK = 1 << 20
# Corner phase spread (rad) below which the facet integral uses its series: there the
# series' terms fall below 1e-16 by SERIES_TERMS, and above it the closed form loses at
# most a factor 1 / SERIES_GAP of precision to cancellation.
SERIES_GAP = 1.0
SERIES_TERMS = 16
# The series' coefficients in k^2 for even p: (-1)^(p/2) 2 / (p + 2)! (real part, with h_p) and
# (-1)^(p/2) 2 / (p + 3)! (imaginary part, with h_{p+1}); radar/cuda_sum.py's kernel shares them.
SERIES_RE = np.array([(-1) ** (p // 2) * 2 / math.factorial(p + 2) for p in range(0, SERIES_TERMS, 2)])
SERIES_IM = np.array([(-1) ** (p // 2) * 2 / math.factorial(p + 3) for p in range(0, SERIES_TERMS, 2)])


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


def facet_phasor(phase: torch.Tensor, beta: torch.Tensor, wavenumber: torch.Tensor):
    """exp(j phase) F / area of flat facets, real and imaginary parts (..., M, F, Ef).

    phase (..., M, F, Ef) rad; beta (..., M, F, 3) mm: the corner phases are alpha_i = k beta_i,
    beta_i = 2 (c - a).(p_i - c) / R (corners p_i, centroid c, antenna a); wavenumber (Ef,) k rad/mm.
    F / area = 2 DD[exp](j alpha_0, j alpha_1, j alpha_2) (Hermite-Genocchi: the integral of
    exp(j q.(x - c)) over the triangle is 2 area times the second divided difference of exp),
    exactly 1 at normal incidence (all alpha 0). Two evaluations; the closed form gets a safe
    gap where the series is taken ("double where"), so that it gives no NaN gradient:
    - corner spread k_min (hi - lo) > SERIES_GAP, lo <= mid <= hi the sorted beta (the order
      is the same for every k > 0): with phi1(jx) = (e^{jx} - 1) / (jx) = e^{jx/2} sinc(x/2),
      DD = e^{j k mid} (phi1(j k (hi - mid)) - phi1(j k (lo - mid))) / (j k (hi - lo)); dividing
      by the largest gap keeps it well conditioned when two corners coincide.
    - else the series about the mean m: DD = e^{j k m} sum_p (j k)^p h_p(w) / (p + 2)!,
      w = beta - m, h_p the complete homogeneous symmetric polynomials, h_p = -e2 h_{p-2} +
      e3 h_{p-3} (e1 = sum w = 0); the powers of k by Horner's rule.
    """
    lo, hi = beta.amin(-1), beta.amax(-1)  # (..., M, F)
    mid = beta.sum(-1) - lo - hi
    gap = hi - lo
    far = gap * wavenumber.min() > SERIES_GAP
    safe_gap = torch.where(far, gap, torch.ones_like(gap))[..., None] * wavenumber  # (..., M, F, Ef)
    k = wavenumber / 2
    upper = torch.sinc((hi - mid)[..., None] * (k / math.pi))
    lower = torch.sinc((lo - mid)[..., None] * (k / math.pi))
    up_angle = phase + (mid + hi)[..., None] * k
    low_angle = phase + (mid + lo)[..., None] * k
    # 2 (e^{ja} U - e^{jb} L) / (j k gap) = 2 (U sin a - L sin b - j (U cos a - L cos b)) / (k gap)
    direct_re = 2 * (upper * torch.sin(up_angle) - lower * torch.sin(low_angle)) / safe_gap
    direct_im = -2 * (upper * torch.cos(up_angle) - lower * torch.cos(low_angle)) / safe_gap

    # The series only where it is used (few pairs: facets seen near normal incidence);
    # index_put routes no gradient to the direct values it replaces.
    near = (~far).nonzero(as_tuple=True)
    w = beta[near] - beta[near].mean(-1, keepdim=True)  # (P, 3)
    e2 = w[:, 0] * w[:, 1] + w[:, 0] * w[:, 2] + w[:, 1] * w[:, 2]
    e3 = w[:, 0] * w[:, 1] * w[:, 2]
    h = [torch.ones_like(e2), torch.zeros_like(e2), -e2]
    for p in range(3, SERIES_TERMS):
        h.append(-e2 * h[p - 2] + e3 * h[p - 3])
    k2 = wavenumber * wavenumber  # Horner in k^2
    series_re, series_im = 0, 0
    for p in range(SERIES_TERMS - 2, -1, -2):
        series_re = series_re * k2 + float(SERIES_RE[p // 2]) * h[p][:, None]
        series_im = series_im * k2 + float(SERIES_IM[p // 2]) * h[p + 1][:, None]
    series_im = series_im * wavenumber  # (P, Ef)
    angle = phase[near] + beta[near].mean(-1, keepdim=True) * wavenumber
    c, s = torch.cos(angle), torch.sin(angle)
    near_re, near_im = c * series_re - s * series_im, s * series_re + c * series_im
    return direct_re.index_put(near, near_re), direct_im.index_put(near, near_im)


def echo_chunk(centroids, normals, weights, edges, positions, freqs, radar: RadarParams):
    """sum_k w_k g(cos theta_km) / R^2 exp(j 2 pi (f_n tau - S tau^2 / 2)) F_k / A_k: (..., M, Ef).

    centroids, normals (..., F, 3) mm; weights (..., F) mm^2 (visibility times area);
    edges (..., F, 3, 3): corners minus centroid, or None for a point scatterer at each
    centroid (F_k = A_k); positions (M, 3) mm; freqs (Ef,) Hz. The direct sum of DESIGN
    section 4 for one chunk of antennas and facets, in the precision and on the device of
    its tensors: the trainer's loss differentiates it (echo_torch) and the build's GPU
    radar evaluates it in float64 without gradients (radar/gpu.py), so both share this
    one copy of the facet integral.
    """
    diff = positions[:, None, :] - centroids[..., None, :, :]  # (..., M, F, 3) a_m - c_k
    r2 = (diff * diff).sum(-1)
    r = torch.sqrt(r2)
    cos = ((diff * normals[..., None, :, :]).sum(-1) / r).clamp_min(0)
    lobe = cos if radar.reflectivity == "po" else (1 - radar.kappa) * cos**radar.p + radar.kappa * cos
    amplitude = weights[..., None, :] * lobe / r2  # (..., M, F)
    tau = r * DELAY_S_PER_MM
    cycles = tau[..., None] * freqs  # (..., M, F, Ef)
    if radar.rvp:
        cycles = cycles - (0.5 * radar.slope_hz_per_s) * (tau * tau)[..., None]
    phase = (2 * math.pi) * cycles
    wavenumber = freqs * (2e-3 * math.pi / SPEED_OF_LIGHT_M_PER_S)  # (Ef,) rad/mm
    if edges is None:
        re, im = torch.cos(phase), torch.sin(phase)
    else:
        beta = -2 * (diff[..., None, :] * edges[..., None, :, :, :]).sum(-1) / r[..., None]  # (..., M, F, 3)
        re, im = facet_phasor(phase, beta, wavenumber)
    out = torch.complex((amplitude[..., None] * re).sum(-2), (amplitude[..., None] * im).sum(-2))  # (..., M, Ef)
    # the physical-optics factor k / 2 pi
    return out * (wavenumber / (2 * math.pi)) if radar.reflectivity == "po" else out


def aperture_probes(centre, radar: RadarParams) -> np.ndarray:
    """(P, 3) production visibility probes (radar.probes) of the preset view whose aperture centre is `centre` (3,) mm."""
    centre = np.asarray(centre, dtype=np.float64)
    for view, frame in VIEW_FRAMES.items():
        if np.allclose(radar.z0_mm * np.asarray(frame[2], dtype=np.float64), centre, atol=1e-6 * radar.z0_mm):
            return probe_points(radar, view)
    raise ValueError(f"centre: {centre.tolist()} is no preset view's aperture centre at z0_mm = {radar.z0_mm}")


def occlusion_mask(verts: torch.Tensor, faces: torch.Tensor, probes) -> torch.Tensor:
    """Embree visibility (..., F) of each facet from probes (P, 3) mm, on the detached vertices (..., V, 3).

    radar.visibility.visibility per mesh of the batch: the fraction of probes a facet faces
    and sees unoccluded. No gradient (it is piecewise constant in the vertices).
    """
    return occlusion_masks(verts, faces, [probes])[0]


def occlusion_masks(verts: torch.Tensor, faces: torch.Tensor, probe_sets) -> list[torch.Tensor]:
    """occlusion_mask for each probe set (P_i, 3) (one per view): one Embree scene and one batch of rays per mesh.

    The meshes of a batch are traced in torch's intra-op thread count of threads (Embree
    and numpy release the GIL for most of it: 1.4x on 2 cores for a batch of 4).
    """
    from meshsar_builder.radar.visibility import visibilities  # Embree: only where asked

    flat = verts.detach().reshape(-1, *verts.shape[-2:]).to("cpu", torch.float64).numpy()
    faces_np = faces.cpu().numpy()
    probe_sets = [np.asarray(probes, dtype=np.float64) for probes in probe_sets]
    threads = min(len(flat), torch.get_num_threads())
    with ThreadPoolExecutor(max(threads, 1)) as pool:
        masks = list(pool.map(lambda v: visibilities(v, faces_np, probe_sets)[0], flat))  # per mesh, (views, F)
    stacked = torch.as_tensor(np.asarray(masks), dtype=verts.dtype, device=verts.device)  # (meshes, views, F)
    return [stacked[:, k].reshape(*verts.shape[:-2], -1) for k in range(len(probe_sets))]


def echo_torch(verts: torch.Tensor, faces: torch.Tensor, positions, freqs, radar: RadarParams,
               beta: float = 10.0, centre=None, probes=None) -> torch.Tensor:
    """Differentiable echo (..., M, Ef), complex of verts' precision.

    verts : (V, 3) or (B, V, 3) float tensor, mm, heart frame; faces : (F, 3) long;
    positions : (M, 3) antennas, mm (e.g. echo_grid(radar)["positions_mm"][view]);
    freqs : (Ef,) Hz; beta : steepness of the soft facing; centre : (3,) aperture
    centre, mm (default: the mean of positions, the centre of a centred grid);
    probes : (P, 3) mm, the Embree visibility probes (default: the centre alone; the
    production echo uses aperture_probes(centre, radar)). radar.facet "po" integrates
    each facet, "centroid" takes its area; "random" has no differentiable counterpart.
    Antennas are processed in chunks, each recomputed in the backward pass when
    gradients are on (checkpointing), so memory stays near TERMS_PER_CHUNK terms.
    """
    if radar.facet not in ("po", "centroid"):
        raise ValueError(f"facet: the differentiable echo supports 'po' and 'centroid', got {radar.facet!r}")
    dtype, device = verts.dtype, verts.device
    positions = torch.as_tensor(np.asarray(positions), dtype=dtype, device=device)
    freqs = torch.as_tensor(np.asarray(freqs), dtype=dtype, device=device)
    centre = positions.mean(0) if centre is None else torch.as_tensor(np.asarray(centre), dtype=dtype, device=device)
    probes = centre.detach().cpu().numpy()[None] if probes is None else probes
    faces = torch.as_tensor(faces, dtype=torch.long, device=device)
    mask = occlusion_mask(verts, faces, probes)  # (..., F)
    # Facets hidden in every mesh of the batch have weight 0 and no gradient: skip them (about half).
    seen = (mask > 0).reshape(-1, len(faces)).any(0)  # (F,)
    faces, mask = faces[seen], mask[..., seen]
    centroids, normals, areas = facet_geometry_torch(verts, faces)
    weights = areas * mask * soft_visibility(centroids, normals, centre, beta)
    edges = verts[..., faces, :] - centroids[..., None, :] if radar.facet == "po" else None
    batch = int(np.prod(verts.shape[:-2], dtype=np.int64))
    chunk = max(1, TERMS_PER_CHUNK // max(1, batch * len(faces) * len(freqs)))
    parts = []
    for start in range(0, len(positions), chunk):
        args = (centroids, normals, weights, edges, positions[start : start + chunk], freqs, radar)
        if torch.is_grad_enabled() and verts.requires_grad:
            parts.append(checkpoint(echo_chunk, *args, use_reentrant=False))
        else:
            parts.append(echo_chunk(*args))
    return torch.cat(parts, dim=-2)
