"""`meshsar bench radar-loss`'s exact reference (bench/radar_loss.py ExactEvaluator) on a tiny scan.

The reference scans each candidate with the production echo and focuses it as the targets
are: a coarser mesh of a surface must find its minimum where the fine mesh of the truth is,
and its echo must be the echo_clean that render_sample writes for the same mesh.
"""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import meshsar_builder.radar.params as RP  # noqa: E402
from meshsar_builder.bench.radar_loss import ExactEvaluator, run, summarise  # noqa: E402
from meshsar_builder.pipeline.errors import InputError  # noqa: E402
from meshsar_builder.radar.focused import FocusedParams, FocusedSetup  # noqa: E402
from meshsar_builder.radar.imaging import ImageParams  # noqa: E402
from meshsar_builder.radar.render import render_sample, specular_loss_echo  # noqa: E402
from meshsar_builder.trainer.model import icosphere_levels  # noqa: E402

AXES_MM = np.array([50.0, 40.0, 35.0])
SCAN = RP.RadarParams(aperture=(32, 32), step_mm=5.0, loss_decimation=(2, 2, 4), diffuse=False)


@pytest.fixture(scope="module")
def meshes():
    verts, faces, _ = icosphere_levels(4)
    fine = (verts[4] * AXES_MM, faces[4])  # 2,562 vertices: the truth
    coarse = (verts[3] * AXES_MM, faces[3])  # 642 vertices on the same surface: the candidate
    return fine, coarse


def test_specular_loss_echo_is_render_samples_echo_clean_without_the_diffuse_part(meshes):
    (verts, faces), _ = meshes
    images = ImageParams(size=32)
    clean = render_sample(verts, faces, SCAN, images, np.random.default_rng(3))["echo_clean"]
    echo = specular_loss_echo(verts, faces, SCAN)
    assert echo.dtype == np.complex64 and echo.shape == clean.shape == (3, 16, 16, 16)
    assert np.array_equal(echo, clean)


def test_exact_reference_puts_a_coarser_mesh_at_the_truth(meshes):
    (fine_v, fine_f), (verts, faces) = meshes
    setup = FocusedSetup(SCAN, SCAN.views, FocusedParams())
    exact = ExactEvaluator(setup, SCAN, [0, 1, 2], fine_v, fine_f, faces)
    assert not exact.differentiable

    def loss(v):
        return float(exact(torch.as_tensor(v)[None]))

    shifts = np.arange(-1.5, 1.51, 0.5)
    for axis in range(3):
        values = [loss(verts + np.eye(3)[axis] * s) for s in shifts]
        assert abs(shifts[int(np.argmin(values))]) <= 0.5, (axis, values)
        assert values[0] > values[3] < values[-1]
    scales = np.array([-3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0])
    values = [loss(verts * (1 + s / 100)) for s in scales]
    assert abs(scales[int(np.argmin(values))]) <= 1.0, values
    assert values[0] > values[3] < values[-1]


def test_a_model_without_gradients_leaves_the_cosine_unmeasured_not_met():
    measured = {"argmin": 0.0, "minimum_met": True, "worst_dip_fraction": 0.0, "monotone_met": True,
                "cosine_met": None}
    summary = summarise([{"shift_x": measured, "seconds": 1.0}])
    assert summary["met"] == {"minimum": True, "monotone": True, "cosine": None, "all": False}
    assert summary["worst_cosine"] is None


def test_an_unknown_loss_is_refused_by_name(tmp_path):
    with pytest.raises(InputError, match="unknown losses \\['exactly'\\]"):
        run(tmp_path, tmp_path, losses=("exact", "exactly"))
