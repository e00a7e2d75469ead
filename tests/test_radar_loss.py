"""The radar loss points at the truth: a trainer-resolution mesh on the true surface, against the echo of a fine mesh.

The stored echo is simulated from the fine mesh with the production echo (the
physical-optics facet integral, Embree visibility); the prediction is the trainer's 2,562-vertex icosphere with its vertices on the same
ellipsoid. Scaling and shifting the prediction along each view axis must raise
every loss mode, and the profile loss must fall monotonically toward the truth.
"""

import numpy as np
import pytest
import trimesh

import meshsar_builder.radar.params as RP

torch = pytest.importorskip("torch")
from meshsar_builder.trainer.losses import ECHO_MODES as RADAR_MODES  # noqa: E402
from meshsar_builder.trainer.losses import radar_loss  # noqa: E402

AXES_MM = np.array([50.0, 40.0, 60.0])  # ellipsoid semi-axes, a heart-sized body
SCALES = (0.9, 0.95, 0.98, 0.99, 1.0, 1.01, 1.02, 1.05, 1.1)
SHIFTS_MM = (-5.0, -3.0, -2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0, 3.0, 5.0)


def production_echo(verts, faces, radar, positions):
    """(V, M, Ef) production echo (Embree visibility, the radar's facet model) of a mesh at positions (V, M, 3)."""
    import meshsar_builder.radar.echo as RE
    import meshsar_builder.radar.visibility as RV

    stored = []
    for view, pos in zip(radar.views, positions):
        vis, _ = RV.visibility(verts, faces, RP.probe_points(radar, view))
        seen = vis > 0
        stored.append(RE.echo(verts[faces][seen], vis[seen], pos, RP.echo_grid(radar)["frequencies_hz"], radar))
    return np.stack(stored)


@pytest.fixture(scope="module")
def scene():
    """Stored echo (1, V, M, Ef) of the fine ellipsoid on 4 x 4 antennas per view, and the loss's other inputs."""
    torch.set_num_threads(1)
    radar = RP.RadarParams()
    grid = RP.echo_grid(radar)
    antennas = np.arange(256).reshape(16, 16)[::5, ::5].ravel()  # 4 x 4 spread over the decimated aperture
    positions = np.stack([grid["positions_mm"][v][antennas] for v in radar.views])  # (V, 16, 3)
    centres = np.stack([radar.z0_mm * RP.view_frame(v)[2] for v in radar.views])  # (V, 3)
    fine = trimesh.creation.icosphere(7)  # edges <= 0.6 mm on the ellipsoid
    stored = production_echo(fine.vertices * AXES_MM, fine.faces, radar, positions)
    coarse = trimesh.creation.icosphere(4)  # the trainer's template level: 2,562 vertices, on the surface
    assert len(coarse.vertices) == 2562
    return dict(radar=radar, positions=positions, centres=centres, freqs=grid["frequencies_hz"],
                echo=torch.tensor(stored[None], dtype=torch.complex64),
                verts=coarse.vertices * AXES_MM, faces=torch.tensor(coarse.faces))


def losses(scene, verts):
    """{mode: loss} of one predicted mesh (n, 3) mm."""
    with torch.no_grad():
        batch = torch.tensor(verts, dtype=torch.float32)[None]
        return {mode: radar_loss(batch, scene["faces"], scene["echo"], scene["positions"], scene["centres"],
                                 scene["freqs"], scene["radar"], mode).item() for mode in RADAR_MODES}


@pytest.mark.slow
def test_every_mode_is_lowest_at_the_true_scale_and_position(scene):
    truth = losses(scene, scene["verts"])
    by_scale = {s: losses(scene, s * scene["verts"]) for s in SCALES if s != 1.0}
    for mode in RADAR_MODES:
        assert truth[mode] < min(value[mode] for value in by_scale.values()), (mode, truth, by_scale)
    for axis in range(3):  # x, y, z: the axes of the left, anterior and superior views
        curve = {d: truth if d == 0 else losses(scene, scene["verts"] + np.eye(3)[axis] * d) for d in SHIFTS_MM}
        for mode in RADAR_MODES:
            values = np.array([curve[d][mode] for d in SHIFTS_MM])
            assert SHIFTS_MM[int(np.argmin(values))] == 0.0, (mode, axis, values)
        profile = np.array([curve[d]["profile"] for d in SHIFTS_MM if abs(d) <= 3])  # -3 ... 3 mm
        centre = len(profile) // 2
        assert (np.diff(profile[: centre + 1]) < 0).all() and (np.diff(profile[centre:]) > 0).all(), (axis, profile)


def test_prediction_reproduces_the_production_echo_of_the_same_surface(scene):
    """DESIGN section 4: within 0.03 relative L2 of the production echo of the same mesh, and of a 4x finer
    midpoint subdivision of it (the same flat facets, edges <= 0.6 mm)."""
    from meshsar_builder.radar.differentiable import aperture_probes, echo_torch

    verts, faces = scene["verts"], scene["faces"].numpy()
    fine = trimesh.remesh.subdivide(*trimesh.remesh.subdivide(verts, faces))
    stored = [production_echo(*mesh, scene["radar"], scene["positions"]) for mesh in ((verts, faces), fine)]
    for v, (positions, centre) in enumerate(zip(scene["positions"], scene["centres"])):
        got = echo_torch(torch.tensor(verts), scene["faces"], positions, scene["freqs"], scene["radar"], centre=centre,
                         probes=aperture_probes(centre, scene["radar"])).numpy()
        for reference in stored:
            error = np.linalg.norm(got - reference[v]) / np.linalg.norm(reference[v])
            assert error <= 0.03, (scene["radar"].views[v], error)
