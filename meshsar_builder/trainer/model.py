"""SAR2Mesh: multi-view SAR images -> heart surface mesh (DESIGN section 10).

A 2-D UNet shared across views gives multi-scale feature maps; every vertex is
projected into every view (DESIGN section 3: x = 2 p.u / fov, y = -2 p.v / fov,
grid_sample with align_corners=False) and the sampled features are pooled over
views (max, mean, std). K cascaded graph-convolution stages deform an icosphere
template, with optional midpoint unpooling between stages; stage k sees
[position, hidden feature of stage k-1, pooled features of its scales] and
predicts a displacement. Inside the network lengths are in units of fov/2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from torch import nn
from torch.nn import functional as F

from meshsar_builder.trainer.losses import adjacent_face_pairs, mesh_edges, neighbour_mean

POOLINGS = ("max", "mean", "std")
NORMS = ("none", "batch")
KINDS = ("sar2mesh", "implicit")


@dataclass(frozen=True)
class ModelConfig:
    """Trainer config table [model]."""

    # sar2mesh: the deforming-template network; implicit: the occupancy baseline (trainer.implicit),
    # which uses encoder_channels, hidden, blocks (MLP layers), the scales of stage_scales, pooling,
    # input_pool and the implicit_* keys.
    kind: str = "sar2mesh"
    encoder_channels: tuple[int, ...] = (16, 32, 64, 128)  # UNet width per scale, full resolution first
    hidden: int = 128  # graph-convolution width
    blocks: int = 2  # residual graph-convolution blocks per stage
    # Encoder scales each stage samples (0 = full resolution): early stages deep, later shallow.
    stage_scales: tuple[tuple[int, ...], ...] = ((3, 2), (2, 1), (1, 0))
    unpool: bool = True  # midpoint unpooling between stages (icosphere level +1 per stage)
    template_level: int = 4  # icosphere subdivisions of the final mesh (4: 2,562 vertices)
    template_radius_mm: float = 0.0  # 0: the mean vertex radius of the training meshes
    pooling: tuple[str, ...] = POOLINGS  # over views; ["max"] is the max-pooling-only ablation
    input_pool: int = 1  # average-pool the images by this factor first (2 halves 128 px: CPU configs)
    norm: str = "none"  # after each graph convolution: none | batch (the paper's graph conv + BatchNorm + ReLU)
    implicit_points: int = 2048  # occupancy queries per sample and step: half near the surface, half uniform
    implicit_noise_mm: float = 5.0  # std of the near-surface queries' offsets
    implicit_grid: int = 64  # marching-cubes grid per axis over the field of view

    def __post_init__(self):
        if not self.encoder_channels or min(self.encoder_channels) < 1:
            raise ValueError(f"encoder_channels: need positive widths, got {list(self.encoder_channels)}")
        if self.hidden < 1 or self.blocks < 0:
            raise ValueError(f"hidden/blocks: need hidden >= 1 and blocks >= 0, got {self.hidden}, {self.blocks}")
        scales = [s for stage in self.stage_scales for s in stage]
        if not self.stage_scales or any(not stage for stage in self.stage_scales):
            raise ValueError("stage_scales: need one non-empty list of scales per stage")
        if min(scales) < 0 or max(scales) >= len(self.encoder_channels):
            raise ValueError(f"stage_scales: scales must lie in [0, {len(self.encoder_channels)}), got {scales}")
        if self.template_level - (self.stages - 1 if self.unpool else 0) < 0:
            raise ValueError(f"template_level: {self.template_level} is too low for {self.stages} unpooled stages")
        if self.template_radius_mm < 0:
            raise ValueError(f"template_radius_mm: must be >= 0, got {self.template_radius_mm}")
        if not self.pooling or len(set(self.pooling)) != len(self.pooling) or not set(self.pooling) <= set(POOLINGS):
            raise ValueError(f"pooling: distinct names from {list(POOLINGS)}, got {list(self.pooling)}")
        if self.input_pool < 1:
            raise ValueError(f"input_pool: must be >= 1, got {self.input_pool}")
        if self.norm not in NORMS:
            raise ValueError(f"norm: must be one of {', '.join(NORMS)}, got {self.norm!r}")
        if self.kind not in KINDS:
            raise ValueError(f"kind: must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if self.implicit_points < 2 or self.implicit_noise_mm <= 0 or self.implicit_grid < 8:
            raise ValueError("implicit_points: need >= 2, implicit_noise_mm: > 0, implicit_grid: >= 8")

    @property
    def stages(self) -> int:
        return len(self.stage_scales)

    def stage_levels(self) -> list[int]:
        """Icosphere level of each stage's mesh."""
        if self.unpool:
            return list(range(self.template_level - self.stages + 1, self.template_level + 1))
        return [self.template_level] * self.stages


# ---------------------------------------------------------------- icosphere hierarchy


def subdivide(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Split each triangle into four at its edge midpoints.

    faces (m, 3) -> (new faces (4m, 3), edges (E, 2)): midpoint of edge e is the new
    vertex n_vertices + e, so unpooling appends the mean of each edge's two ends.
    """
    edges = mesh_edges(faces)
    key = {tuple(e): n_vertices + i for i, e in enumerate(edges.tolist())}
    mid = np.array([[key[tuple(sorted((f[a], f[b])))] for a, b in ((0, 1), (1, 2), (2, 0))] for f in faces.tolist()])
    a, b, c = faces.T
    ab, bc, ca = mid.T
    new = np.stack([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1), np.stack([ca, bc, c], 1),
                    np.stack([ab, bc, ca], 1)], 1).reshape(-1, 3)
    return new, edges


def icosphere_levels(level: int) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Unit icospheres of levels 0..level: vertices (n_l, 3), faces (m_l, 3), and the
    subdivided edges (E_l, 2) that take level l to l + 1 (one fewer than levels)."""
    base = trimesh.creation.icosahedron()
    verts, faces = [np.asarray(base.vertices, dtype=np.float64)], [np.asarray(base.faces, dtype=np.int64)]
    splits = []
    for _ in range(level):
        new_faces, edges = subdivide(faces[-1], len(verts[-1]))
        mids = verts[-1][edges].mean(1)
        verts.append(np.concatenate([verts[-1], mids / np.linalg.norm(mids, axis=1, keepdims=True)]))
        faces.append(new_faces)
        splits.append(edges)
    return verts, faces, splits


def unpool(values: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Append each edge's midpoint value: values (B, n, F), edges (E, 2) -> (B, n + E, F)."""
    return torch.cat([values, 0.5 * (values[:, edges[:, 0]] + values[:, edges[:, 1]])], dim=1)


# ---------------------------------------------------------------- image encoder


def conv_block(cin: int, cout: int) -> nn.Sequential:
    """Two 3x3 convolutions with GroupNorm (batch-size independent) and ReLU."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1), nn.GroupNorm(min(8, cout), cout), nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1), nn.GroupNorm(min(8, cout), cout), nn.ReLU(inplace=True),
    )


class UNet(nn.Module):
    """UNet returning a feature map per scale: [(N, c_0, H, W), (N, c_1, H/2, W/2), ...].

    Scale s < L-1 is the decoder output at resolution H/2^s (skip-connected), scale L-1 the bottleneck.
    """

    def __init__(self, in_channels: int, channels: tuple[int, ...]):
        super().__init__()
        self.down = nn.ModuleList(conv_block(cin, cout) for cin, cout in zip((in_channels, *channels[:-1]), channels))
        self.up = nn.ModuleList(nn.ConvTranspose2d(channels[s + 1], channels[s], 2, stride=2)
                                for s in range(len(channels) - 1))
        self.merge = nn.ModuleList(conv_block(2 * channels[s], channels[s]) for s in range(len(channels) - 1))

    def forward(self, images: torch.Tensor) -> list[torch.Tensor]:
        skips = []
        x = images
        for s, block in enumerate(self.down):
            x = block(x if s == 0 else F.max_pool2d(x, 2))
            skips.append(x)
        features = [x]
        for s in reversed(range(len(self.up))):
            up = self.up[s](x)
            # Odd sizes lose a row/column to pooling: pad back to the skip's size.
            skip = skips[s]
            up = F.pad(up, (0, skip.shape[-1] - up.shape[-1], 0, skip.shape[-2] - up.shape[-2]))
            x = self.merge[s](torch.cat([up, skip], dim=1))
            features.insert(0, x)
        return features


# ---------------------------------------------------------------- projection and pooling


def project(points: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
    """grid_sample coordinates of points in every view: points (B, n, 3) in fov/2 units,
    frames (V, 3, 3) rows u, v, w -> (B, V, n, 2) with x = p.u, y = -p.v (DESIGN section 3)."""
    uv = torch.einsum("bnc,vkc->bvnk", points, frames[:, :2])  # (B, V, n, 2)
    return uv * torch.tensor([1.0, -1.0], dtype=uv.dtype, device=uv.device)


def sample_views(features: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """Bilinear features at projected points: features (B*V, F, h, w), grid (B, V, n, 2) -> (B, V, n, F)."""
    b, v, n, _ = grid.shape
    sampled = F.grid_sample(features, grid.reshape(b * v, n, 1, 2).to(features.dtype),
                            mode="bilinear", padding_mode="zeros", align_corners=False)  # (B*V, F, n, 1)
    return sampled.reshape(b, v, -1, n).transpose(2, 3)


def encode(encoder: "UNet", sar: torch.Tensor, input_pool: int) -> list[torch.Tensor]:
    """Feature maps per scale of every view: sar (B, V, C, H, W) -> [(B*V, c_s, h_s, w_s)]."""
    images = sar.flatten(0, 1)
    if input_pool > 1:
        # Pooling whole pixel blocks keeps the DESIGN pixel grid: normalised coordinates still match.
        images = F.avg_pool2d(images, input_pool)
    return encoder(images)


def pool_views(per_view: torch.Tensor, modes: tuple[str, ...]) -> torch.Tensor:
    """Pool over the view axis and concatenate: (B, V, n, F) -> (B, n, F * len(modes))."""
    pooled = []
    for mode in modes:
        if mode == "max":
            pooled.append(per_view.max(dim=1).values)
        elif mode == "mean":
            pooled.append(per_view.mean(dim=1))
        else:
            # eps keeps the gradient of sqrt finite where the views agree (always for one view).
            pooled.append((per_view.var(dim=1, unbiased=False) + 1e-6).sqrt())
    return torch.cat(pooled, dim=-1)


# ---------------------------------------------------------------- graph decoder


class GraphConv(nn.Module):
    """y_i = W0 x_i + W1 mean_{j in N(i)} x_j + b: (B, n, Fin) -> (B, n, Fout)."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.own = nn.Linear(cin, cout)
        self.neighbours = nn.Linear(cin, cout, bias=False)

    def forward(self, x: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
        return self.own(x) + self.neighbours(neighbour_mean(x, edges, x.shape[1]))


class VertexBatchNorm(nn.BatchNorm1d):
    """BatchNorm over every vertex of every mesh of the batch: (B, n, F) -> (B, n, F)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return super().forward(x.reshape(-1, x.shape[-1])).reshape(x.shape)


def graph_norm(norm: str, width: int) -> nn.Module:
    """The normalisation after a graph convolution: none (identity, no parameters) or batch."""
    return VertexBatchNorm(width) if norm == "batch" else nn.Identity()


class GraphResBlock(nn.Module):
    """Pixel2Mesh residual block: (x + relu(n2(gc2(relu(n1(gc1(x))))))) / 2, n: the chosen normalisation."""

    def __init__(self, width: int, norm: str = "none"):
        super().__init__()
        self.first, self.second = GraphConv(width, width), GraphConv(width, width)
        self.norm_first, self.norm_second = graph_norm(norm, width), graph_norm(norm, width)

    def forward(self, x: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
        h = F.relu(self.norm_first(self.first(x, edges)))
        return 0.5 * (x + F.relu(self.norm_second(self.second(h, edges))))


class DeformStage(nn.Module):
    """Input features (B, n, Fin) -> (hidden (B, n, H), displacement (B, n, 3))."""

    def __init__(self, cin: int, hidden: int, blocks: int, norm: str = "none"):
        super().__init__()
        self.inp = GraphConv(cin, hidden)
        self.norm = graph_norm(norm, hidden)
        self.blocks = nn.ModuleList(GraphResBlock(hidden, norm) for _ in range(blocks))
        self.out = GraphConv(hidden, 3)
        # Zero displacement at initialisation: the untrained model returns the template.
        for layer in (self.out.own, self.out.neighbours):
            nn.init.zeros_(layer.weight)
        nn.init.zeros_(self.out.own.bias)

    def forward(self, x: torch.Tensor, edges: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = F.relu(self.norm(self.inp(x, edges)))
        for block in self.blocks:
            h = block(h, edges)
        return h, self.out(h, edges)


class SAR2Mesh(nn.Module):
    """The network. frames (V, 3, 3): rows u, v, w of the views in the order of the sar view axis;
    fov_mm: the images' field of view; in_channels: C of the sar input."""

    def __init__(self, config: ModelConfig, frames: np.ndarray, fov_mm: float, in_channels: int,
                 template_radius_mm: float):
        super().__init__()
        self.config, self.half_fov = config, fov_mm / 2
        self.register_buffer("frames", torch.as_tensor(np.asarray(frames), dtype=torch.float32))
        self.encoder = UNet(in_channels, config.encoder_channels)
        levels = config.stage_levels()
        verts, faces, splits = icosphere_levels(max(levels))
        self.register_buffer("template", torch.as_tensor(verts[levels[0]] * template_radius_mm / self.half_fov,
                                                         dtype=torch.float32))
        self.faces, self.edges, self.face_pairs, self.splits = [], [], [], []
        for k, level in enumerate(levels):
            # Buffers (not lists of tensors) so .to(device) moves the topology with the weights.
            for name, array in (("faces", faces[level]), ("edges", mesh_edges(faces[level])),
                                ("face_pairs", adjacent_face_pairs(faces[level]))):
                self.register_buffer(f"{name}_{k}", torch.as_tensor(array), persistent=False)
                getattr(self, name).append(f"{name}_{k}")
            if k > 0 and config.unpool:
                self.register_buffer(f"splits_{k}", torch.as_tensor(splits[level - 1]), persistent=False)
        pooled = len(config.pooling)
        self.stages = nn.ModuleList(
            DeformStage(3 + (config.hidden if k else 0) + pooled * sum(config.encoder_channels[s] for s in scales),
                        config.hidden, config.blocks, config.norm)
            for k, scales in enumerate(config.stage_scales))

    def topology(self, stage: int = -1) -> dict[str, torch.Tensor]:
        """faces (m, 3), edges (E, 2), face_pairs (P, 2) of a stage's mesh."""
        stage = stage % len(self.stages)
        return {name: getattr(self, getattr(self, name)[stage]) for name in ("faces", "edges", "face_pairs")}

    def initial_mesh(self) -> torch.Tensor:
        """The template scaled to template_radius_mm, as the first stage sees it: (n_0, 3) mm."""
        return self.template * self.half_fov

    def predict_mesh(self, sar: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """The final mesh of one sample: sar (V, C, H, W) -> verts (n, 3) float64 mm, faces (m, 3)."""
        with torch.no_grad():
            verts = self(sar[None].to(self.template.device))[-1][1][0]
        return verts.cpu().double().numpy(), self.topology()["faces"].cpu().numpy()

    def forward(self, sar: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """sar (B, V, C, H, W) -> per stage (input vertices, output vertices), each (B, n_k, 3) mm.

        The input of stage k is the output of stage k-1 (unpooled): the Laplacian loss
        compares against it.
        """
        b = sar.shape[0]
        features = encode(self.encoder, sar, self.config.input_pool)
        pos = self.template.expand(b, -1, -1)
        hidden = None
        meshes = []
        for k, stage in enumerate(self.stages):
            if k > 0 and self.config.unpool:
                split = getattr(self, f"splits_{k}")
                pos, hidden = unpool(pos, split), unpool(hidden, split)
            grid = project(pos, self.frames)
            pooled = [pool_views(sample_views(features[s], grid), self.config.pooling) for s in self.config.stage_scales[k]]
            parts = [pos] + ([hidden] if hidden is not None else []) + pooled
            hidden, delta = stage(torch.cat([p.to(pooled[0].dtype) for p in parts], dim=-1),
                                  getattr(self, self.edges[k]))
            new = pos + delta.to(pos.dtype)
            meshes.append((pos * self.half_fov, new * self.half_fov))
            pos = new
        return meshes
