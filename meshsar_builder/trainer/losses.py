"""SAR2Mesh training losses (DESIGN section 10), as plain functions of tensors.

Geometric losses take coordinates in any length unit; the trainer passes them
divided by fov/2 so that the squared-length terms are O(1e-3) and the default
weights [0.3, 0.05, 0.46, 0.16] (Chamfer, Laplacian, edge length, normal
consistency) balance. Topology helpers (edges, adjacent face pairs) are numpy,
computed once per template level.
"""

from __future__ import annotations

import warnings
from collections import OrderedDict

import numpy as np
import torch
from scipy.spatial import cKDTree

from meshsar_builder.radar.differentiable import aperture_probes, echo_torch
from meshsar_builder.radar.params import RadarParams

RADAR_MODES = ("focused", "depth", "raw", "profile")
# focused and depth: blurred, debiased power volumes (radar/focused.py), compared by cosine or by their
# depth maps (the volume distance focused_loss takes); raw and profile: L1 on the echo.
FOCUSED_MODES = {"focused": "cosine", "depth": "depth"}
ECHO_MODES = ("raw", "profile")


# ---------------------------------------------------------------- topology


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """(E, 2) int64 undirected edges of a triangle mesh, each once, smaller index first, sorted."""
    faces = np.asarray(faces, dtype=np.int64)
    pairs = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(pairs, axis=0)


def adjacent_face_pairs(faces: np.ndarray) -> np.ndarray:
    """(P, 2) int64 pairs of faces sharing an edge (edges with exactly two faces; boundary edges skipped)."""
    faces = np.asarray(faces, dtype=np.int64)
    pairs = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    owner = np.repeat(np.arange(len(faces)), 3)
    _, edge_id, counts = np.unique(pairs, axis=0, return_inverse=True, return_counts=True)
    edge_id = edge_id.reshape(-1)
    order = np.argsort(edge_id, kind="stable")
    shared = counts[edge_id[order]] == 2
    return owner[order][shared].reshape(-1, 2)


def neighbour_mean(values: torch.Tensor, edges: torch.Tensor, n_vertices: int) -> torch.Tensor:
    """Mean over each vertex's mesh neighbours: values (..., n, F) -> (..., n, F).

    edges : (E, 2) undirected edges. Isolated vertices get 0.
    """
    src = torch.cat([edges[:, 0], edges[:, 1]])  # (2E,)
    dst = torch.cat([edges[:, 1], edges[:, 0]])  # (2E,)
    summed = torch.zeros_like(values).index_add_(-2, dst, values.index_select(-2, src))  # (..., n, F)
    degree = torch.zeros(n_vertices, dtype=values.dtype, device=values.device).index_add_(
        0, dst, torch.ones_like(dst, dtype=values.dtype))  # (n,)
    return summed / degree.clamp_min(1)[:, None]


def uniform_laplacian(verts: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Uniform Laplacian coordinates x_i - mean_{j in N(i)} x_j: verts (..., n, 3) -> (..., n, 3)."""
    return verts - neighbour_mean(verts, edges, verts.shape[-2])


def sample_surface(verts: torch.Tensor, faces: torch.Tensor, count: int,
                   generator: torch.Generator | None = None) -> torch.Tensor:
    """(count, 3) points uniform by area on a mesh: verts (n, 3), faces (m, 3) long.

    Random numbers are drawn on the CPU (`generator` must be a CPU generator).
    """
    tri = verts[faces]  # (m, 3, 3)
    area = torch.linalg.vector_norm(torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1), dim=-1)  # (m,)
    pick = torch.multinomial(area.detach().cpu().double(), count, replacement=True, generator=generator)  # (count,)
    r = torch.rand(count, 2, generator=generator, dtype=torch.float64)  # (count, 2)
    # Folding the unit square's upper triangle onto the lower keeps the density uniform.
    r = torch.where(r.sum(1, keepdim=True) > 1, 1 - r, r).to(verts)
    chosen = tri[pick.to(verts.device)]  # (count, 3, 3)
    return chosen[:, 0] + r[:, :1] * (chosen[:, 1] - chosen[:, 0]) + r[:, 1:] * (chosen[:, 2] - chosen[:, 0])


# ---------------------------------------------------------------- geometric losses


def nearest_pairs(points: torch.Tensor, target: torch.Tensor, method: str | None = None) -> tuple[torch.Tensor, ...]:
    """Index of each point's nearest target (N,) and of each target's nearest point (M,), long.

    points (N, 3), target (M, 3). method "tree" (a k-d tree: O((N + M) log) without the
    (N, M) distance matrix, 4-6x faster at the trainer's sizes on a CPU) or "matrix" (the
    distance matrix, one kernel on a GPU); default: tree on the CPU, matrix elsewhere.
    """
    method = method or ("tree" if points.device.type == "cpu" else "matrix")
    if method not in ("tree", "matrix"):
        raise ValueError(f"nearest_pairs: method must be tree or matrix, got {method!r}")
    with torch.no_grad():
        if method == "tree":
            p, t = points.detach().numpy(), target.detach().numpy()
            return (torch.from_numpy(cKDTree(t).query(p)[1]).to(points.device),
                    torch.from_numpy(cKDTree(p).query(t)[1]).to(points.device))
        d = torch.cdist(points, target)  # (N, M)
        return d.min(dim=1).indices, d.min(dim=0).indices


def chamfer(points: torch.Tensor, target: torch.Tensor, method: str | None = None) -> torch.Tensor:
    """Symmetric Chamfer distance, squared: mean_p min_q |p-q|^2 + mean_q min_p |p-q|^2.

    points (N, 3), target (M, 3) -> scalar. The nearest pairs are found without a graph
    (nearest_pairs, `method`) and the distances of those pairs alone are differentiated:
    the gradient of the min (its argmin's), at O(N + M) in the backward pass instead of
    through the (N, M) matrix.
    """
    to_target, to_points = nearest_pairs(points, target, method)  # (N,), (M,)
    return ((points - target[to_target]).square().sum(-1).mean()
            + (points[to_points] - target).square().sum(-1).mean())


def laplacian_loss(verts: torch.Tensor, reference: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """mean_i |L(verts)_i - L(reference)_i|^2, the change of uniform Laplacian coordinates (Pixel2Mesh).

    verts, reference (..., n, 3) (reference: the mesh before the deformation); edges (E, 2) -> scalar.
    """
    change = uniform_laplacian(verts, edges) - uniform_laplacian(reference, edges)  # (..., n, 3)
    return change.square().sum(-1).mean()


def edge_loss(verts: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Mean squared edge length: verts (..., n, 3), edges (E, 2) -> scalar."""
    vectors = verts[..., edges[:, 1], :] - verts[..., edges[:, 0], :]  # (..., E, 3)
    return vectors.square().sum(-1).mean()


def face_normals(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit face normals (..., m, 3) of verts (..., n, 3), faces (m, 3)."""
    tri = verts[..., faces, :]  # (..., m, 3, 3)
    cross = torch.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :], dim=-1)
    return cross / torch.linalg.vector_norm(cross, dim=-1, keepdim=True).clamp_min(1e-12)


def normal_consistency(verts: torch.Tensor, faces: torch.Tensor, face_pairs: torch.Tensor) -> torch.Tensor:
    """Mean over faces sharing an edge of 1 - cos(angle between their normals).

    verts (..., n, 3), faces (m, 3), face_pairs (P, 2) -> scalar.
    """
    normals = face_normals(verts, faces)  # (..., m, 3)
    cos = (normals[..., face_pairs[:, 0], :] * normals[..., face_pairs[:, 1], :]).sum(-1)  # (..., P)
    return (1 - cos).mean()


# ---------------------------------------------------------------- radar loss


def range_profile(echo: torch.Tensor) -> torch.Tensor:
    """|IFFT over frequency| of an echo (..., Ef) complex -> (..., Ef) real: reflectivity per range bin."""
    return torch.fft.ifft(echo, dim=-1).abs()


def radar_loss(verts: torch.Tensor, faces: torch.Tensor, echo: torch.Tensor, positions: np.ndarray,
               centres: np.ndarray, freqs: np.ndarray, radar: RadarParams, mode: str = "profile",
               beta: float = 10.0) -> torch.Tensor:
    """L1 between the differentiable echo of a mesh and a stored echo, relative to the stored one.

    verts (B, n, 3) mm, heart frame; faces (m, 3) long; echo (B, V, M, Ef) complex,
    the stored echo at `positions` (V, M, 3) mm; centres (V, 3) mm, each view's
    aperture centre (soft visibility looks there); freqs (Ef,) Hz. The arrays are
    numpy (echo_torch moves them to verts' device and precision).
    mode "raw": mean |s_pred - s| / mean |s| (the paper's loss; phases wrap every
    lambda/2 of range). "profile": the same on |IFFT_f s|, range profiles, which
    only move by a range bin (c/2B) per c/2B of displacement. Each sample and view is
    normalised by its own stored signal (so weak echoes weigh as much as strong
    ones); the loss is the mean over samples and views, 0 on a perfect match and
    about 0.5-1.2 for a sphere against a heart.
    """
    if mode not in ECHO_MODES:
        raise ValueError(f"mode: must be one of {', '.join(ECHO_MODES)}, got {mode!r}")
    terms = []
    for v in range(echo.shape[1]):
        predicted = echo_torch(verts, faces, positions[v], freqs, radar, beta=beta, centre=centres[v],
                               probes=aperture_probes(centres[v], radar))  # (B, M, Ef)
        target = echo[:, v]  # (B, M, Ef)
        if mode == "profile":
            predicted, target = range_profile(predicted), range_profile(target)
        error = (predicted - target).abs().flatten(1).mean(1)  # (B,)
        terms.append(error / target.abs().flatten(1).mean(1).clamp_min(1e-30))
    return torch.stack(terms).mean()


# ---------------------------------------------------------------- gradient smoothing


class _SmoothGradient(torch.autograd.Function):
    """Identity forward; backward diffuses the vertex gradient over the mesh (heat-kernel filter)."""

    @staticmethod
    def forward(ctx, verts, edges, iterations):
        ctx.save_for_backward(edges)
        ctx.iterations = iterations
        return verts.view_as(verts)

    @staticmethod
    def backward(ctx, grad):
        edges, = ctx.saved_tensors
        return smooth_on_mesh(grad, edges, ctx.iterations), None, None


# (edges' identity, n, device, dtype) -> sparse 0.5 (I + D^-1 A); with a number of steps, its dense power. The
# least recently used go first beyond DIFFUSION_CACHED entries (a dense one is up to 64 MB).
_DIFFUSION: OrderedDict = OrderedDict()
DIFFUSION_CACHED = 8
# Up to this many vertices the whole heat kernel is kept as one dense matrix (64 MB in float32 at the limit): the
# default template's (2,562 vertices, 100 steps) takes 2.4 ms a batch against 10.8 ms for its steps one sparse
# product at a time (2 threads), after a one-off 0.7-1.3 s to build it.
DENSE_HEAT_KERNEL_VERTICES = 4096


def _cached_operator(edges: torch.Tensor, n: int, dtype, device, iterations: int | None = None) -> torch.Tensor:
    """The diffusion operator of a topology (sparse CSR), or with `iterations` its dense power; built once."""
    key = (edges.data_ptr(), tuple(edges.shape), int(edges[:, 0].sum()), int(edges[:, 1].sum()), n, str(device), dtype,
           iterations)
    if key in _DIFFUSION:
        _DIFFUSION.move_to_end(key)
        return _DIFFUSION[key]
    if iterations is None:
        e = edges.to(device)
        src = torch.cat([e[:, 0], e[:, 1]])
        dst = torch.cat([e[:, 1], e[:, 0]])
        degree = torch.zeros(n, dtype=dtype, device=device).index_add_(0, dst, torch.ones_like(dst, dtype=dtype))
        rows = torch.cat([dst, torch.arange(n, device=device)])
        cols = torch.cat([src, torch.arange(n, device=device)])
        values = torch.cat([0.5 / degree.clamp_min(1)[dst], torch.full((n,), 0.5, dtype=dtype, device=device)])
        coo = torch.sparse_coo_tensor(torch.stack([rows, cols]), values, (n, n), check_invariants=True).coalesce()
        with warnings.catch_warnings():  # "Sparse CSR tensor support is in beta state": 10x faster than COO here
            warnings.simplefilter("ignore", UserWarning)
            operator = coo.to_sparse_csr()
    else:
        step, operator = _cached_operator(edges, n, dtype, device), torch.eye(n, dtype=dtype, device=device)
        for _ in range(iterations):
            operator = step @ operator
    _DIFFUSION[key] = operator
    while len(_DIFFUSION) > DIFFUSION_CACHED:
        _DIFFUSION.popitem(last=False)
    return operator


def smooth_on_mesh(values: torch.Tensor, edges: torch.Tensor, iterations: int) -> torch.Tensor:
    """`iterations` steps of v <- (v + mean of neighbours) / 2 over (..., n, F): a discrete heat kernel.

    A field's features narrower than about sqrt(iterations) edges are removed. One sparse
    product a step (the operator is built once per topology), or on a mesh of at most
    DENSE_HEAT_KERNEL_VERTICES one dense product with all the steps (built once too).
    """
    if iterations <= 0:
        return values
    n = values.shape[-2]
    flat = values.movedim(-2, 0).reshape(n, -1)  # (n, ... * F)
    if n <= DENSE_HEAT_KERNEL_VERTICES:
        flat = _cached_operator(edges, n, values.dtype, values.device, iterations) @ flat
    else:
        operator = _cached_operator(edges, n, values.dtype, values.device)
        for _ in range(iterations):
            flat = operator @ flat
    return flat.reshape(n, *values.movedim(-2, 0).shape[1:]).movedim(0, -2)


def smooth_gradient(verts: torch.Tensor, edges: torch.Tensor, iterations: int) -> torch.Tensor:
    """verts itself, through which gradients flow back smoothed on the mesh (smooth_on_mesh); 0: no-op."""
    if iterations <= 0 or not verts.requires_grad:
        return verts
    return _SmoothGradient.apply(verts, edges, iterations)


def focused_radar_loss(verts: torch.Tensor, faces: torch.Tensor, targets: torch.Tensor, setup,
                       masks: list[torch.Tensor] | None = None, mode: str = "focused") -> torch.Tensor:
    """A radar loss on blurred power volumes (radar/focused.py focused_loss), of a FOCUSED_MODES mode.

    verts (B, n, 3) mm; targets (B, V, S, H, W) float, setup.target of each sample's
    loss-grid echo (echo_clean, or the recorded echo with its noise_sigma); setup a
    FocusedSetup for the views in use; masks: the views' occlusion masks V x (B, m) when
    already traced (None: traced here). focused: 1 - cosine, 0 on a perfect match, up to 1
    (2 for anti-correlated); depth: the depth maps' weighted Charbonnier distance in mm.
    """
    from meshsar_builder.radar.focused import focused_loss

    return focused_loss(verts, faces, targets, setup, masks, FOCUSED_MODES[mode])


def balanced(radar: torch.Tensor, geometric: torch.Tensor, verts: torch.Tensor) -> torch.Tensor:
    """The radar term rescaled so that its gradient on `verts` has the norm of the geometric terms' there.

    Returns s * radar in value and gradient, s = |d geometric/d verts| / |d radar/d verts| held
    constant. The radar graph is walked once: its vertex gradient is carried into the network by
    a linear surrogate (zero in value), so backward does not recompute the echo.
    """
    g_radar, = torch.autograd.grad(radar, verts)
    g_geometric, = torch.autograd.grad(geometric, verts, retain_graph=True, allow_unused=True)
    if g_geometric is None:
        return radar.detach() * 0
    scale = g_geometric.norm() / g_radar.norm().clamp_min(1e-30)
    surrogate = (verts * (scale * g_radar).to(verts.dtype)).sum()
    return scale * radar.detach() + (surrogate - surrogate.detach())
