"""`meshsar evaluate / predict --refine`: a predicted mesh moved against its sample's recorded echo.

The network's prediction is the start; the focused radar loss (radar/focused.py) against the
sample's recorded echo on the loss grid, its gradient smoothed on the mesh as in training, moves
it, by a budget of small steps (the smoothing and the budget keep the fine shape the network gave;
the Laplacian term against the prediction is about 1e-4 of the radar term at the default weight,
docs/trainer.md). Only the recorded echo and the radar parameters enter ([refine] in the trainer
config)."""

from __future__ import annotations

import numpy as np
import torch

from meshsar_builder.radar.focused import focused_loss
from meshsar_builder.trainer import losses as L
from meshsar_builder.trainer.dataset_geometry import DatasetGeometry
from meshsar_builder.trainer.train import focused_params


def refine_mesh(verts: np.ndarray, faces: torch.Tensor, edges: torch.Tensor, targets: torch.Tensor, setup,
                refine, unit_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """A predicted mesh moved against focused targets of its sample's recorded echo ([refine], config.RefineConfig).

    verts (n, 3) float mm, faces (m, 3) long, edges (E, 2) long: the prediction and its topology;
    targets (V, S, H, W) float (setup.target of the recorded echo); unit_mm: the trainer's
    coordinate unit (half the field of view), in which the Laplacian term is taken as in
    training. Each step takes the gradient of the focused loss, smoothed on the mesh
    (losses.smooth_gradient), plus laplacian_weight times the Laplacian term against the
    prediction (in unit_mm units, squared: weak at weight 1), and moves every vertex along it,
    the one that moves most by step_mm: a normalised step keeps the smoothed gradient's shape,
    where Adam would rescale each coordinate on its own. Returns the refined verts (n, 3)
    float64 and the loss before each step and after the last.
    """
    reference = torch.as_tensor(verts, dtype=torch.float32)  # (n, 3)
    v = reference.clone().requires_grad_(True)
    losses = []
    for _ in range(refine.steps + 1):
        radar = focused_loss(L.smooth_gradient(v[None], edges, refine.smooth_iterations), faces, targets[None], setup)
        total = radar + refine.laplacian_weight * L.laplacian_loss(v[None] / unit_mm, reference[None] / unit_mm, edges)
        losses.append(total.item())
        if len(losses) > refine.steps:
            break
        grad, = torch.autograd.grad(total, v)  # (n, 3)
        with torch.no_grad():
            v -= refine.step_mm * grad / grad.norm(dim=1).max().clamp_min(1e-30)
    return v.detach().double().numpy(), np.asarray(losses)


def sample_refiner(index: dict, config):
    """refine(verts (n, 3), topology of the model's final stage, sample) -> refined verts (n, 3) float64:
    refine_mesh with a run config's [refine] against a dataset sample's recorded echo (echo_noisy and
    noise_sigma, MeshSARDataset(noisy_loss_echo=True)), focused as its [radar_loss] focuses; the radar
    sees every view of the build, whichever the network reads."""
    setup = DatasetGeometry.from_index(index, ()).focused_setup(focused_params(config.radar_loss))

    def refine(verts: np.ndarray, topology: dict, sample: dict) -> np.ndarray:
        targets = torch.from_numpy(setup.target(sample["echo_noisy"].numpy(), sample["noise_sigma"].numpy()))
        return refine_mesh(verts, topology["faces"].cpu(), topology["edges"].cpu(), targets, setup, config.refine,
                           float(index["fov_mm"]) / 2)[0]

    return refine
