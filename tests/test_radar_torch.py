"""Differentiable echo: the production facet model, checked against plain loops, Embree occlusion and gradcheck."""

import numpy as np
import pytest
import trimesh

import meshsar_builder.radar.params as RP

torch = pytest.importorskip("torch")
import meshsar_builder.radar.differentiable as RT  # noqa: E402
from meshsar_builder.radar.differentiable import echo_torch, facet_phasor  # noqa: E402

C_MM = RP.SPEED_OF_LIGHT_M_PER_S * 1e3  # mm/s


def triangle_gauss(corners, order):
    """Points (order^2, 3) and weights (order^2,) summing to 1 of a triangle (3, 3).

    Gauss-Legendre on the square collapsed onto the triangle (Duffy: x = a + u (b - a) + v (1 - u)
    (c - a), Jacobian 1 - u): exact for polynomials of degree < order, so exponentially
    convergent for exp(j q.x) once order exceeds ~ the phase spread / 2.
    """
    nodes, w = np.polynomial.legendre.leggauss(order)
    nodes, w = (nodes + 1) / 2, w / 2
    u, v = (x.ravel() for x in np.meshgrid(nodes, nodes, indexing="ij"))
    weights = (w[:, None] * w[None, :]).ravel() * (1 - u) * 2
    a, b, c = np.asarray(corners, dtype=np.float64)
    return a + u[:, None] * (b - a) + (v * (1 - u))[:, None] * (c - a), weights


def reference_echo(verts, faces, visibility, positions, freqs, radar, order=48):
    """The model of DESIGN section 4 as a plain loop over facets and antennas, F_k by Gauss quadrature.

    visibility (F,): V_k. The facet integral uses the plane wave at the centroid, as the model does.
    """
    out = np.zeros((len(positions), len(freqs)), dtype=np.complex128)
    k = 2 * np.pi * freqs / C_MM  # rad/mm
    for corners, v in zip(verts[faces], visibility):
        if v == 0:
            continue
        centroid = corners.mean(0)
        cross = np.cross(corners[1] - corners[0], corners[2] - corners[0])
        area, normal = np.linalg.norm(cross) / 2, cross / np.linalg.norm(cross)
        points, weights = triangle_gauss(corners, order)
        offsets = points - centroid
        for m, a in enumerate(positions):
            r = np.linalg.norm(a - centroid)
            cos = max(normal @ (a - centroid) / r, 0.0)
            lobe = cos if radar.reflectivity == "po" else (1 - radar.kappa) * cos**radar.p + radar.kappa * cos
            tau = 2 * r / C_MM
            phase = 2 * np.pi * (freqs * tau - (0.5 * radar.slope_hz_per_s * tau**2 if radar.rvp else 0.0))
            q = 2 * k[:, None] * (centroid - a) / r  # (N, 3)
            integral = area * np.exp(1j * q @ offsets.T) @ weights if radar.facet == "po" else area
            scale = k / (2 * np.pi) if radar.reflectivity == "po" else 1.0
            out[m] += v * lobe / r**2 * scale * np.exp(1j * phase) * integral
    return out


def relative_error(got, expected):
    return float(np.linalg.norm(got - expected) / np.linalg.norm(expected))


def test_facet_phasor_matches_quadrature_at_all_spreads():
    """Normal incidence (F = area), nearly coinciding corners (series), two equal corners and wide spreads."""
    k = np.array([1.6, 1.7])  # rad/mm
    betas = np.array([[0, 0, 0], [0.3, -0.1, -0.2], [0.27, 0.27, -0.54], [0.6, -0.3, -0.3], [1e-9, 0, -1e-9],
                      [4, 4, -8], [0.5, 0.5 + 1e-7, -1], [5, -2, -3], [2, -0.5, -1.5], [9, -4, -5]]) / 1.6
    re, im = facet_phasor(torch.full((len(betas), 2), 0.3, dtype=torch.float64), torch.tensor(betas),
                          torch.tensor(k))
    got = (re + 1j * im).numpy()
    assert got[0] == pytest.approx(np.exp(0.3j), abs=1e-15)
    # distinct corners (the last 3): the divided difference sum_i e^{z_i} / prod_{j != i} (z_i - z_j), z = j alpha
    distinct = np.arange(len(betas)) >= 7
    z = 1j * k[None, :, None] * betas[distinct, None, :]  # (3, 2, 3)
    generic = 2 * sum(np.exp(z[..., i]) / np.prod([z[..., i] - z[..., j] for j in range(3) if j != i], axis=0)
                      for i in range(3))
    np.testing.assert_allclose(got[distinct], np.exp(0.3j) * generic, rtol=0, atol=1e-12)
    # the others (the series, two equal corners): Gauss quadrature on the barycentric simplex (x.beta = alpha)
    points, weights = triangle_gauss(np.eye(3), 24)
    expected = np.exp(0.3j) * np.exp(1j * k[None, :, None] * (betas[:7] @ points.T)[:, None, :]) @ weights
    np.testing.assert_allclose(got[:7], expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("facet, reflectivity", [("po", "lobe"), ("centroid", "lobe"), ("po", "po")])
def test_matches_loop_reference(facet, reflectivity):
    mesh = trimesh.creation.icosphere(1, radius=1.0)
    verts = mesh.vertices * [30.0, 25.0, 35.0]
    radar = RP.RadarParams(facet=facet, reflectivity=reflectivity)
    grid = RP.echo_grid(radar)
    positions, freqs = grid["positions_mm"]["left"][::37], grid["frequencies_hz"][::5]
    centre = radar.z0_mm * RP.view_frame("left")[2]
    got = echo_torch(torch.tensor(verts), torch.tensor(mesh.faces), positions, freqs, radar, beta=8.0,
                     centre=centre).numpy()
    normals = trimesh.Trimesh(verts, mesh.faces).face_normals  # of the scaled mesh
    to_centre = centre - verts[mesh.faces].mean(1)
    cos = np.einsum("fc,fc->f", normals, to_centre) / np.linalg.norm(to_centre, axis=1)
    # a convex mesh: Embree occludes exactly the facets turned away from the centre
    expected = reference_echo(verts, mesh.faces, (cos > 0) / (1 + np.exp(-8.0 * cos)), positions, freqs, radar)
    assert relative_error(got, expected) <= 2e-5
    got32 = echo_torch(torch.tensor(verts, dtype=torch.float32), torch.tensor(mesh.faces), positions, freqs, radar,
                       beta=8.0, centre=centre)
    assert got32.dtype == torch.complex64
    assert relative_error(got32.numpy(), expected) <= 1e-3


def test_occlusion_hides_a_sphere_behind_another():
    """Two spheres on the anterior axis: facets whose ray to the aperture centre crosses the front one get 0."""
    front = trimesh.creation.icosphere(2, radius=20.0)
    back = trimesh.creation.icosphere(2, radius=30.0)
    verts = np.concatenate([front.vertices + [0, 40.0, 0], back.vertices])
    faces = np.concatenate([front.faces, back.faces + len(front.vertices)])
    centre = np.array([0.0, 300.0, 0.0])
    mask = RT.occlusion_mask(torch.tensor(verts), torch.tensor(faces), centre[None]).numpy()
    centroids = verts[faces].mean(1)[len(front.faces):]
    direction = (centre - centroids) / np.linalg.norm(centre - centroids, axis=1, keepdims=True)
    # ray-sphere test against the front sphere (centre (0, 40, 0), radius 20; facets lie inside by < 0.5 mm)
    offset = centroids - [0, 40.0, 0]
    along = np.einsum("fc,fc->f", offset, direction)
    miss = np.einsum("fc,fc->f", offset, offset) - along**2
    blocked = (along < 0) & (miss < 19.0**2)
    clear = (along > 0) | (miss > 21.0**2)
    facing = np.einsum("fc,fc->f", back.face_normals, direction) > 0
    assert blocked.sum() > 50 and (clear & facing).sum() > 50
    assert (mask[len(front.faces):][blocked] == 0).all()
    assert (mask[len(front.faces):][clear & facing] == 1).all()
    assert (mask[len(front.faces):][~facing] == 0).all()


def test_batches_and_chunks_agree(monkeypatch):
    mesh = trimesh.creation.icosphere(1, radius=40.0)
    radar = RP.RadarParams(rvp=False)
    grid = RP.echo_grid(radar)
    verts = torch.tensor(mesh.vertices)
    batch = torch.stack([verts, 1.1 * verts])
    positions = grid["positions_mm"]["superior"][::4]
    whole = echo_torch(batch, torch.tensor(mesh.faces), positions, grid["frequencies_hz"], radar)
    monkeypatch.setattr(RT, "TERMS_PER_CHUNK", 5000)
    chunked = echo_torch(1.1 * verts, torch.tensor(mesh.faces), positions, grid["frequencies_hz"], radar)
    assert whole.shape == (2, 64, 32)
    torch.testing.assert_close(whole[1], chunked)


def test_gradcheck_on_a_small_mesh():
    """A jittered icosahedron (wide corner spreads) and a 6 mm box whose top faces the central antenna (series)."""
    ico = trimesh.creation.icosphere(0, radius=30.0)
    box = trimesh.creation.box((6.0, 6.0, 6.0))
    rng = np.random.default_rng(2)
    verts = np.concatenate([ico.vertices + rng.normal(scale=2.0, size=ico.vertices.shape), box.vertices + [0, 40, 0]])
    faces = torch.tensor(np.concatenate([ico.faces, box.faces + len(ico.vertices)]))
    verts = torch.tensor(verts, requires_grad=True)
    radar = RP.RadarParams(aperture=(3, 3), step_mm=20.0, n_samples=8, echo_decimation=(1, 1, 1))
    positions = RP.aperture_positions(radar, "anterior")[[0, 4]]
    freqs = RP.frequencies(radar)[[0, 7]]
    top = box.vertices[box.faces[box.face_normals[:, 1] > 0.99]].mean(1) + [0, 40, 0]
    assert len(top) == 2 and np.abs((positions[1] - top)[:, [0, 2]]).max() < 2.0  # seen head-on by antenna 4
    assert torch.autograd.gradcheck(
        lambda v: echo_torch(v, faces, positions, freqs, radar, beta=5.0), (verts,), eps=1e-6, atol=1e-7, rtol=1e-4
    )


def test_gradient_reaches_every_visible_vertex():
    mesh = trimesh.creation.icosphere(2, radius=40.0)
    radar = RP.RadarParams()
    grid = RP.echo_grid(radar)
    verts = torch.tensor(mesh.vertices, dtype=torch.float32, requires_grad=True)
    target = torch.zeros(64, 32, dtype=torch.complex64)
    out = echo_torch(verts, torch.tensor(mesh.faces), grid["positions_mm"]["anterior"][::4], grid["frequencies_hz"],
                     radar)
    (out - target).abs().mean().backward()
    facing = mesh.vertex_normals @ RP.view_frame("anterior")[2] > 0.3
    assert torch.isfinite(verts.grad).all()
    assert (verts.grad[torch.from_numpy(facing)].norm(dim=1) > 0).all()


def test_occlusion_masks_of_several_views_share_a_scene_and_equal_each_views_own_mask():
    """A batch of two meshes (the two-sphere scene and it shifted) seen from the anterior and the left:
    one call for both views gives each view's occlusion_mask, (B, F) per view."""
    from meshsar_builder.radar.visibility import visibility

    front = trimesh.creation.icosphere(2, radius=20.0)
    back = trimesh.creation.icosphere(2, radius=30.0)
    verts = np.concatenate([front.vertices + [0, 40.0, 0], back.vertices])
    faces = np.concatenate([front.faces, back.faces + len(front.vertices)])
    batch = torch.tensor(np.stack([verts, verts + [5.0, 0, -3.0]]))
    probes = [np.array([[0.0, 300.0, 0.0]]), np.array([[300.0, 0.0, 0.0], [300.0, 20.0, 0.0]])]
    masks = RT.occlusion_masks(batch, torch.tensor(faces), probes)
    assert len(masks) == 2 and all(m.shape == (2, len(faces)) for m in masks)
    for view, probe in enumerate(probes):
        np.testing.assert_array_equal(masks[view].numpy(), RT.occlusion_mask(batch, torch.tensor(faces), probe).numpy())
        for b in range(2):  # and the production visibility of that mesh alone
            np.testing.assert_array_equal(masks[view][b].numpy(), visibility(batch[b].numpy(), faces, probe)[0])
    assert not torch.equal(masks[0], masks[1])  # the views see different facets
