"""Differentiable echo: agrees with the reference echo and differentiates to the vertices."""

import numpy as np
import pytest
import trimesh

import meshsar_builder.radar.echo as RE
import meshsar_builder.radar.params as RP
import meshsar_builder.radar.visibility as RV

torch = pytest.importorskip("torch")
from meshsar_builder.radar.differentiable import echo_torch  # noqa: E402


def reference_with_soft_visibility(verts, faces, positions, freqs, radar, beta):
    """radar.echo (direct) given the soft visibility sigmoid(beta cos theta) as V_k."""
    centres, normals, areas = RV.facet_geometry(verts, faces)
    to_centre = positions.mean(axis=0) - centres
    cos = np.einsum("fc,fc->f", normals, to_centre) / np.linalg.norm(to_centre, axis=1)
    weights = areas / (1 + np.exp(-beta * cos))
    return RE.point_echo(centres, normals, weights, positions, freqs, radar, method="direct")


def test_matches_direct_echo_in_float32():
    mesh = trimesh.creation.icosphere(2, radius=1.0)
    verts32 = (mesh.vertices * [50.0, 40.0, 60.0]).astype(np.float32)
    radar = RP.RadarParams()
    grid = RP.echo_grid(radar)
    positions, freqs = grid["positions_mm"]["left"], grid["frequencies_hz"]
    got = echo_torch(torch.from_numpy(verts32), torch.from_numpy(mesh.faces), positions, freqs, radar, beta=8.0)
    assert got.dtype == torch.complex64 and got.shape == (256, 32)
    expected = reference_with_soft_visibility(verts32.astype(np.float64), mesh.faces, positions, freqs, radar, 8.0)
    error = np.linalg.norm(got.numpy() - expected) / np.linalg.norm(expected)
    assert error <= 1e-3


def test_batches_and_chunks_agree(monkeypatch):
    import meshsar_builder.radar.differentiable as RT

    mesh = trimesh.creation.icosphere(1, radius=40.0)
    radar = RP.RadarParams(rvp=False)
    grid = RP.echo_grid(radar)
    verts = torch.tensor(mesh.vertices)
    batch = torch.stack([verts, 1.1 * verts])
    whole = echo_torch(batch, torch.tensor(mesh.faces), grid["positions_mm"]["superior"], grid["frequencies_hz"], radar)
    monkeypatch.setattr(RT, "TERMS_PER_CHUNK", 5000)
    chunked = echo_torch(1.1 * verts, torch.tensor(mesh.faces), grid["positions_mm"]["superior"],
                         grid["frequencies_hz"], radar)
    assert whole.shape == (2, 256, 32)
    torch.testing.assert_close(whole[1], chunked)


def test_gradcheck_on_a_small_mesh():
    mesh = trimesh.creation.icosphere(0, radius=30.0)
    rng = np.random.default_rng(2)
    verts = torch.tensor(mesh.vertices + rng.normal(scale=2.0, size=mesh.vertices.shape), requires_grad=True)
    faces = torch.tensor(mesh.faces)
    radar = RP.RadarParams(aperture=(4, 4), step_mm=20.0, n_samples=8, echo_decimation=(1, 1, 1))
    positions = RP.aperture_positions(radar, "anterior")[[0, 5, 15]]
    freqs = RP.frequencies(radar)[[0, 3, 7]]
    assert torch.autograd.gradcheck(
        lambda v: echo_torch(v, faces, positions, freqs, radar, beta=5.0), (verts,), eps=1e-6, atol=1e-7, rtol=1e-4
    )


def test_gradient_reaches_every_visible_vertex():
    mesh = trimesh.creation.icosphere(2, radius=40.0)
    radar = RP.RadarParams()
    grid = RP.echo_grid(radar)
    verts = torch.tensor(mesh.vertices, dtype=torch.float32, requires_grad=True)
    target = torch.zeros(256, 32, dtype=torch.complex64)
    out = echo_torch(verts, torch.tensor(mesh.faces), grid["positions_mm"]["anterior"], grid["frequencies_hz"], radar)
    (out - target).abs().mean().backward()
    facing = mesh.vertex_normals @ RP.view_frame("anterior")[2] > 0.3
    assert torch.isfinite(verts.grad).all()
    assert (verts.grad[torch.from_numpy(facing)].norm(dim=1) > 0).all()
