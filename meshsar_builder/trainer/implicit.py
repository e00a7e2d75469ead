"""The learned implicit baseline (DESIGN section 10): occupancy from pixel-aligned multi-view features.

The family of NeuS, VolSDF and Neuralangelo adapted, as the paper's retrained
baselines had to be, to feed-forward multi-view SAR input, PIFu-style: the same
UNet as SAR2Mesh encodes every view; a query point is projected into every view
(DESIGN section 3), its features sampled at the scales of [model] stage_scales
and pooled over views (max, mean, std), and an MLP maps [position, features] to
an occupancy logit. Trained with binary cross-entropy on points near the surface
and uniform in the field-of-view cube; the surface is the 0.5 level set of the
occupancy on a grid, by marching cubes. `[model] kind = "implicit"` in a trainer
config trains it with `meshsar train`; `meshsar evaluate` and `predict` use it
like SAR2Mesh.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from meshsar_builder.trainer.losses import sample_surface
from meshsar_builder.trainer.metrics import inside, occupancy_surface
from meshsar_builder.trainer.model import ModelConfig, UNet, encode, pool_views, project, sample_views

QUERY_CHUNK = 32_768  # grid queries per forward when extracting a surface (bounds memory)


class ImplicitSAR(nn.Module):
    """Occupancy network. frames (V, 3, 3) rows u, v, w of the views in sar order; fov_mm: the images'
    field of view; in_channels: C of the sar input. The query cube is [-fov/2, fov/2]^3 mm."""

    def __init__(self, config: ModelConfig, frames: np.ndarray, fov_mm: float, in_channels: int):
        super().__init__()
        self.config, self.half_fov = config, fov_mm / 2
        self.register_buffer("frames", torch.as_tensor(np.asarray(frames), dtype=torch.float32))
        self.encoder = UNet(in_channels, config.encoder_channels)
        self.scales = sorted({s for stage in config.stage_scales for s in stage})
        width = 3 + len(config.pooling) * sum(config.encoder_channels[s] for s in self.scales)
        layers: list[nn.Module] = [nn.Linear(width, config.hidden), nn.ReLU()]
        for _ in range(config.blocks):
            layers += [nn.Linear(config.hidden, config.hidden), nn.ReLU()]
        self.mlp = nn.Sequential(*layers, nn.Linear(config.hidden, 1))

    def query(self, features: list[torch.Tensor], points: torch.Tensor) -> torch.Tensor:
        """Occupancy logits (B, P) at points (B, P, 3) mm, given encode()'s feature maps of B samples."""
        pos = points / self.half_fov
        grid = project(pos, self.frames)
        pooled = [pool_views(sample_views(features[s], grid), self.config.pooling) for s in self.scales]
        return self.mlp(torch.cat([pos.to(pooled[0].dtype), *pooled], dim=-1))[..., 0]

    def forward(self, sar: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """sar (B, V, C, H, W), points (B, P, 3) mm -> occupancy logits (B, P)."""
        return self.query(encode(self.encoder, sar, self.config.input_pool), points)

    def predict_mesh(self, sar: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """The 0.5 occupancy surface of one sample: sar (V, C, H, W) -> verts (n, 3) float64 mm, faces (m, 3).

        A model that predicts no inside (or only inside) voxel gets a 1-voxel octahedron at the
        origin, so metrics still compare a closed mesh (and score it as the miss it is).
        """
        n = self.config.implicit_grid
        voxel = 2 * self.half_fov / n
        lo = np.full(3, -self.half_fov)
        axis = torch.linspace(-self.half_fov + voxel / 2, self.half_fov - voxel / 2, n, device=self.frames.device)
        points = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(1, -1, 3)
        with torch.no_grad():
            features = encode(self.encoder, sar[None].to(self.frames.device), self.config.input_pool)
            occupancy = torch.cat([torch.sigmoid(self.query(features, chunk))
                                   for chunk in points.split(QUERY_CHUNK, dim=1)], dim=1)
        occupancy = occupancy.reshape(n, n, n).cpu().double().numpy()
        if occupancy.max() <= 0.5 or occupancy.min() > 0.5:
            octahedron = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]) * voxel
            faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
            return octahedron.astype(np.float64), faces
        return occupancy_surface(occupancy, lo, voxel)


def occupancy_samples(verts: torch.Tensor, faces: torch.Tensor, count: int, noise_mm: float, half_fov: float,
                      generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Training queries of one mesh: points (count, 3) mm and labels (count,) float (1 inside).

    Half are surface points offset by N(0, noise_mm) (where the surface is decided), half uniform in
    the field-of-view cube (so empty space stays empty). verts (n, 3) mm, faces (m, 3).
    """
    near = count // 2
    surface = sample_surface(verts.double().cpu(), faces.cpu(), near, generator)
    points = torch.cat([surface + noise_mm * torch.randn(near, 3, generator=generator, dtype=torch.float64),
                        (2 * torch.rand(count - near, 3, generator=generator, dtype=torch.float64) - 1) * half_fov])
    labels = inside(points.numpy(), verts.double().cpu().numpy(), faces.cpu().numpy())
    return points.float(), torch.from_numpy(labels.astype(np.float32))


def occupancy_loss(net: nn.Module, model: ImplicitSAR, batch: dict, sar: torch.Tensor,
                   generators: list[torch.Generator]) -> dict[str, torch.Tensor]:
    """Binary cross-entropy of a batch's occupancy queries: {"occupancy", "total"} (scalars, means).

    net: the model or its DDP wrapper; sar (B, V, C, H, W) on the model's device; generators: one per sample.
    """
    c = model.config
    queries = [occupancy_samples(v, f, c.implicit_points, c.implicit_noise_mm, model.half_fov, g)
               for v, f, g in zip(batch["verts"], batch["faces"], generators)]
    points = torch.stack([p for p, _ in queries]).to(sar.device)  # (B, P, 3)
    labels = torch.stack([lab for _, lab in queries]).to(sar.device)  # (B, P)
    bce = F.binary_cross_entropy_with_logits(net(sar, points).float(), labels)
    return {"occupancy": bce, "total": bce}
