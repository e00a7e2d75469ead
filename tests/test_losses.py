"""Training losses equal naive loop implementations; the radar loss differentiates to the vertices."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import trimesh

torch = pytest.importorskip("torch")

import meshsar_builder.radar.params as RP  # noqa: E402
from meshsar_builder.radar.differentiable import aperture_probes, echo_torch  # noqa: E402
from meshsar_builder.trainer import losses as L  # noqa: E402


@pytest.fixture
def noisy_sphere():
    torch.set_num_threads(1)
    mesh = trimesh.creation.icosphere(1, radius=1.0)
    rng = np.random.default_rng(5)
    verts = mesh.vertices + rng.normal(scale=0.1, size=mesh.vertices.shape)
    reference = mesh.vertices + rng.normal(scale=0.1, size=mesh.vertices.shape)
    return torch.tensor(verts), torch.tensor(reference), mesh.faces


def neighbours(faces):
    adjacency = {}
    for face in faces.tolist():
        for a, b in itertools.permutations(face, 2):
            adjacency.setdefault(a, set()).add(b)
    return adjacency


@pytest.mark.parametrize("method", ["tree", "matrix"])
def test_chamfer_and_its_gradient_match_a_double_loop_and_it_vanishes_on_identical_sets(method):
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(17, 3)), rng.normal(size=(23, 3))
    forward = np.mean([min(np.sum((p - q) ** 2) for q in b) for p in a])
    backward = np.mean([min(np.sum((p - q) ** 2) for p in a) for q in b])
    got = L.chamfer(torch.tensor(a), torch.tensor(b), method).item()
    assert got == pytest.approx(forward + backward, rel=1e-10)
    assert L.chamfer(torch.tensor(a), torch.tensor(a[::-1].copy()), method).item() == pytest.approx(0, abs=1e-12)
    # the gradient on the points: each point pulled to its nearest target, each target's nearest point to it
    expected = np.zeros_like(a)
    for i, p in enumerate(a):
        expected[i] += 2 * (p - b[np.argmin(((b - p) ** 2).sum(1))]) / len(a)
    for q in b:
        i = np.argmin(((a - q) ** 2).sum(1))
        expected[i] += 2 * (a[i] - q) / len(b)
    points = torch.tensor(a, requires_grad=True)
    L.chamfer(points, torch.tensor(b), method).backward()
    np.testing.assert_allclose(points.grad.numpy(), expected, rtol=1e-10, atol=1e-14)


def test_nearest_pairs_agree_between_the_tree_and_the_matrix_on_float32_clouds():
    rng = np.random.default_rng(1)
    a, b = torch.tensor(rng.normal(size=(2000, 3)), dtype=torch.float32), torch.tensor(rng.normal(size=(1500, 3)),
                                                                                       dtype=torch.float32)
    for tree, matrix in zip(L.nearest_pairs(a, b, "tree"), L.nearest_pairs(a, b, "matrix")):
        assert tree.dtype == matrix.dtype == torch.long and torch.equal(tree, matrix)
    with pytest.raises(ValueError, match="method must be tree or matrix"):
        L.nearest_pairs(a, b, "brute")


def test_laplacian_loss_matches_a_loop(noisy_sphere):
    verts, reference, faces = noisy_sphere
    adjacency = neighbours(faces)
    v, r = verts.numpy(), reference.numpy()
    expected = np.mean([np.sum(((v[i] - v[list(n)].mean(0)) - (r[i] - r[list(n)].mean(0))) ** 2)
                        for i, n in sorted(adjacency.items())])
    edges = torch.from_numpy(L.mesh_edges(faces))
    assert L.laplacian_loss(verts, reference, edges).item() == pytest.approx(expected, rel=1e-10)


def test_edge_loss_matches_a_loop(noisy_sphere):
    verts, _, faces = noisy_sphere
    v = verts.numpy()
    edges = {tuple(sorted(e)) for f in faces.tolist() for e in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))}
    expected = np.mean([np.sum((v[a] - v[b]) ** 2) for a, b in edges])
    assert L.edge_loss(verts, torch.from_numpy(L.mesh_edges(faces))).item() == pytest.approx(expected, rel=1e-10)


def test_normal_consistency_matches_a_loop(noisy_sphere):
    verts, _, faces = noisy_sphere
    v = verts.numpy()
    by_edge = {}
    for k, f in enumerate(faces.tolist()):
        for e in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
            by_edge.setdefault(tuple(sorted(e)), []).append(k)

    def normal(k):
        a, b, c = v[faces[k]]
        n = np.cross(b - a, c - a)
        return n / np.linalg.norm(n)

    expected = np.mean([1 - normal(f) @ normal(g) for f, g in by_edge.values()])
    pairs = L.adjacent_face_pairs(faces)
    assert len(pairs) == 3 * len(faces) // 2
    got = L.normal_consistency(verts, torch.from_numpy(faces), torch.from_numpy(pairs)).item()
    assert got == pytest.approx(expected, rel=1e-10)


def test_losses_batch_like_single_meshes(noisy_sphere):
    verts, reference, faces = noisy_sphere
    edges = torch.from_numpy(L.mesh_edges(faces))
    batch = torch.stack([verts, 2 * verts])
    expected = (L.edge_loss(verts, edges) + L.edge_loss(2 * verts, edges)) / 2
    torch.testing.assert_close(L.edge_loss(batch, edges), expected)


def test_surface_samples_lie_on_the_mesh_with_area_density():
    # In the z = 0 plane: (0,0)-(1,0)-(0,1), area 1/2, and (1,0)-(3,0)-(0,3), area 3, beyond x + y = 1.
    verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [3, 0, 0], [0, 3, 0]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [1, 3, 4]])
    points = L.sample_surface(verts, faces, 20000, torch.Generator().manual_seed(0))
    assert torch.all(points[:, 2] == 0)
    in_first = (points[:, 0] + points[:, 1] <= 1).double().mean().item()
    assert in_first == pytest.approx(0.5 / 3.5, abs=0.01)


TINY = RP.RadarParams(aperture=(4, 4), step_mm=20.0, n_samples=8, echo_decimation=(1, 1, 1))


def tiny_radar_setup(dtype):
    mesh = trimesh.creation.icosphere(0, radius=30.0)
    rng = np.random.default_rng(2)
    verts = torch.tensor(mesh.vertices + rng.normal(scale=2.0, size=mesh.vertices.shape), dtype=dtype)
    faces = torch.tensor(mesh.faces)
    views = ("anterior", "left")
    positions = np.stack([RP.aperture_positions(TINY, v)[[0, 5, 15]] for v in views])
    centres = np.stack([TINY.z0_mm * RP.view_frame(v)[2] for v in views])
    freqs = RP.frequencies(TINY)[[0, 3, 7]]
    target = torch.stack([echo_torch(1.05 * verts, faces, positions[k], freqs, TINY, centre=centres[k])
                          for k in range(len(views))])[None]  # (1, V, M, Ef)
    return verts, faces, target, positions, centres, freqs


@pytest.mark.parametrize("mode", L.ECHO_MODES)
def test_radar_loss_gradcheck(mode):
    verts, faces, target, positions, centres, freqs = tiny_radar_setup(torch.float64)
    verts.requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda v: L.radar_loss(v[None], faces, target, positions, centres, freqs, TINY, mode, beta=5.0),
        (verts,), eps=1e-6, atol=1e-7, rtol=1e-4)


@pytest.mark.parametrize("mode", L.ECHO_MODES)
def test_radar_loss_vanishes_on_its_own_echo(mode):
    verts, faces, _, positions, centres, freqs = tiny_radar_setup(torch.float64)
    own = torch.stack([echo_torch(verts, faces, positions[k], freqs, TINY, centre=centres[k],
                                  probes=aperture_probes(centres[k], TINY)) for k in range(2)])[None]
    assert L.radar_loss(verts[None], faces, own, positions, centres, freqs, TINY, mode).item() == pytest.approx(0, abs=1e-12)
    with pytest.raises(ValueError, match="mode"):
        L.radar_loss(verts[None], faces, own, positions, centres, freqs, TINY, "phase")


@pytest.mark.parametrize("mode", L.ECHO_MODES)
def test_radar_loss_matches_a_loop_over_samples_and_views(mode):
    verts, faces, target, positions, centres, freqs = tiny_radar_setup(torch.float64)
    batch = torch.stack([verts, 0.97 * verts])  # (2, n, 3)
    stored = torch.cat([target, 3 * target.flip(-2)])  # (2, V, M, Ef): the second sample's echo is 3x stronger
    got = L.radar_loss(batch, faces, stored, positions, centres, freqs, TINY, mode).item()
    ratios = []
    for b in range(2):
        for v in range(len(positions)):
            p = echo_torch(batch[b], faces, positions[v], freqs, TINY, centre=centres[v],
                           probes=aperture_probes(centres[v], TINY)).numpy()  # (M, Ef)
            t = stored[b, v].numpy()
            if mode == "profile":
                p, t = np.abs(np.fft.ifft(p, axis=-1)), np.abs(np.fft.ifft(t, axis=-1))
            num = sum(abs(p[m, f] - t[m, f]) for m in range(p.shape[0]) for f in range(p.shape[1]))
            den = sum(abs(t[m, f]) for m in range(t.shape[0]) for f in range(t.shape[1]))
            ratios.append(num / den)  # per sample and view, each relative to its own stored signal
    assert got == pytest.approx(sum(ratios) / len(ratios), rel=1e-10)
