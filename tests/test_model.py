"""SAR2Mesh model: projection agrees with SAR imaging, template hierarchy, pooling, shapes."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import meshsar_builder.radar.echo as RE  # noqa: E402
import meshsar_builder.radar.params as RP  # noqa: E402
from meshsar_builder.radar import imaging as S  # noqa: E402
from meshsar_builder.trainer import model as Mo  # noqa: E402

RADAR = RP.RadarParams(snr_db=np.inf)
IMAGES = S.ImageParams(size=64, fov_mm=160.0, channels=("intensity",))
PIXEL_MM = IMAGES.fov_mm / IMAGES.size
# Off-centre in every view, within 0.2 pixel of a pixel centre whatever the view's signs.
POINT = np.array([9.5 * PIXEL_MM + 0.3, -13.5 * PIXEL_MM - 0.4, 6.5 * PIXEL_MM + 0.2])
FRAMES = np.stack([RP.view_frame(v) for v in RADAR.views])


@pytest.mark.parametrize("view", RADAR.views)
def test_projection_lands_on_the_sar_image_of_a_point_scatterer(view):
    torch.set_num_threads(1)
    frame = RP.view_frame(view)
    echo = RE.point_echo(POINT[None], frame[2][None], np.ones(1), RP.aperture_positions(RADAR, view),
                  RP.frequencies(RADAR), RADAR).reshape(*RADAR.aperture, RADAR.n_samples)
    image = S.view_images(echo, RP.frequencies(RADAR), *RP.aperture_axes(RADAR), RADAR.z0_mm, IMAGES)[0]
    brightest = np.unravel_index(np.argmax(image), image.shape)
    # The model's own projection and sampling, on a one-hot image of the brightest pixel.
    one_hot = torch.zeros(1, 1, IMAGES.size, IMAGES.size, dtype=torch.float64)
    one_hot[0, 0, brightest[0], brightest[1]] = 1
    grid = Mo.project(torch.tensor(POINT / (IMAGES.fov_mm / 2))[None, None], torch.tensor(frame)[None])
    sampled = Mo.sample_views(one_hot, grid)
    # Bilinear weight of the nearest pixel centre is >= 0.8^2 when the point is within 0.2 pixel of it.
    assert sampled.item() >= 0.6, (view, brightest)


def test_icosphere_hierarchy_and_unpooling():
    verts, faces, splits = Mo.icosphere_levels(4)
    assert [len(v) for v in verts] == [12, 42, 162, 642, 2562]
    assert [len(f) for f in faces] == [20, 80, 320, 1280, 5120]
    for level in range(4):
        up = Mo.unpool(torch.tensor(verts[level])[None], torch.tensor(splits[level]))[0].numpy()
        np.testing.assert_allclose(up / np.linalg.norm(up, axis=1, keepdims=True), verts[level + 1], atol=1e-12)
        # Faces stay outward (counter-clockwise seen from outside): positive volume.
        tri = verts[level + 1][faces[level + 1]]
        assert np.einsum("fc,fc->f", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), tri[:, 0]).min() > 0


def test_pool_views_concatenates_max_mean_std():
    x = torch.randn(2, 3, 5, 4, dtype=torch.float64)
    pooled = Mo.pool_views(x, ("max", "mean", "std"))
    assert pooled.shape == (2, 5, 12)
    torch.testing.assert_close(pooled[..., :4], x.max(1).values)
    torch.testing.assert_close(pooled[..., 4:8], x.mean(1))
    torch.testing.assert_close(pooled[..., 8:], (x.var(1, unbiased=False) + 1e-6).sqrt())


@pytest.mark.parametrize("norm", Mo.NORMS)
def test_default_model_shapes_and_untrained_output_is_the_template(norm):
    torch.set_num_threads(1)
    config = Mo.ModelConfig(encoder_channels=(4, 8, 8, 8), hidden=8, blocks=1, norm=norm)
    model = Mo.SAR2Mesh(config, FRAMES, 160.0, 2, 45.0)
    norms = [m for m in model.modules() if isinstance(m, Mo.VertexBatchNorm)]
    # The paper's GCN block: every graph convolution but the displacement output is followed by BatchNorm.
    assert len(norms) == (3 * (1 + 2 * config.blocks) if norm == "batch" else 0)
    meshes = model(torch.rand(2, 3, 2, 32, 32))
    assert [m[1].shape for m in meshes] == [(2, 162, 3), (2, 642, 3), (2, 2562, 3)]
    assert model.topology()["faces"].shape == (5120, 3)
    torch.testing.assert_close(meshes[0][1][0], model.initial_mesh())
    np.testing.assert_allclose(meshes[-1][1].norm(dim=-1).max().item(), 45.0, rtol=1e-5)
    meshes[-1][1].sum().backward()
    assert all(p.grad is not None for p in model.parameters())


def test_model_config_rejects_unknown_scales_and_pooling():
    with pytest.raises(ValueError, match="stage_scales"):
        Mo.ModelConfig(encoder_channels=(4, 8), stage_scales=((2,), (1,), (0,)))
    with pytest.raises(ValueError, match="pooling"):
        Mo.ModelConfig(pooling=("median",))
    with pytest.raises(ValueError, match="template_level"):
        Mo.ModelConfig(template_level=1)
    with pytest.raises(ValueError, match="norm"):
        Mo.ModelConfig(norm="layer")


def test_vertex_batch_norm_normalises_over_all_vertices_of_the_batch():
    x = torch.randn(2, 50, 4, dtype=torch.float64) * torch.tensor([1.0, 3.0, 0.5, 2.0], dtype=torch.float64) + 7
    y = Mo.VertexBatchNorm(4).double()(x)
    flat = y.reshape(-1, 4)
    torch.testing.assert_close(flat.mean(0), torch.zeros(4, dtype=torch.float64), atol=1e-12, rtol=0)
    torch.testing.assert_close(flat.var(0, unbiased=False), torch.ones(4, dtype=torch.float64), atol=1e-4, rtol=0)


def test_implicit_queries_are_labelled_by_the_mesh_and_the_model_maps_them_to_logits():
    import trimesh

    from meshsar_builder.trainer import implicit as I

    torch.set_num_threads(1)
    sphere = trimesh.creation.icosphere(4, radius=30.0)
    points, labels = I.occupancy_samples(torch.tensor(sphere.vertices), torch.tensor(sphere.faces), 1000, 5.0, 80.0,
                                         torch.Generator().manual_seed(0))
    radius = points.double().norm(dim=1)
    clear = (radius - 30).abs() > 0.1
    assert torch.equal(labels[clear] == 1, radius[clear] < 30)
    assert (radius[:500] - 30).abs().mean() < 8 and points[500:].abs().max() <= 80  # near-surface half, cube half
    config = Mo.ModelConfig(encoder_channels=(4, 8), hidden=8, blocks=1, stage_scales=((1,), (0,)), kind="implicit",
                            implicit_grid=16)
    model = I.ImplicitSAR(config, FRAMES, 160.0, 2)
    assert model(torch.rand(2, 3, 2, 32, 32), points[None].expand(2, -1, -1)).shape == (2, 1000)
    verts, faces = model.predict_mesh(torch.rand(3, 2, 32, 32))
    assert verts.shape[1] == 3 and faces.max() < len(verts) and trimesh.Trimesh(verts, faces).is_watertight
