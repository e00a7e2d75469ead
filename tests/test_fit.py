"""`meshsar fit` (trainer/fit.py): a shape model fitted to the radar alone.

A 2-mode shape model of a 642-vertex ellipsoid (stretch along x, stretch along z) on a
32 x 32 aperture at 5 mm: against its own image-domain model of a translated, stretched
truth the fit recovers the coefficients and the translation (the optimiser and the
parameterisation); against the production echo of that truth (the physics) it lands far
closer to the truth than its start.
"""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import meshsar_builder.radar.params as RP  # noqa: E402
from meshsar_builder.pipeline.errors import InputError  # noqa: E402
from meshsar_builder.radar.focused import FocusedParams, FocusedSetup  # noqa: E402
from meshsar_builder.trainer.fit import FitParams, fit_shape, noise_scale, shape_model_tensors  # noqa: E402
from meshsar_builder.trainer.model import icosphere_levels  # noqa: E402

from .test_focused_loss import _quiet  # noqa: E402

AXES_MM = np.array([50.0, 40.0, 35.0])
TRUE_Z = np.array([1.2, -0.8])
SHIFT_MM = np.array([3.0, -2.0, 1.5])


@pytest.fixture(scope="module")
def scene():
    torch.set_num_threads(1)
    import meshsar_builder.radar.echo as RE
    import meshsar_builder.radar.visibility as RV

    radar = RP.RadarParams(aperture=(32, 32), step_mm=5.0, loss_decimation=(1, 1, 4), diffuse=False)
    setup = FocusedSetup(radar, radar.views, FocusedParams())
    verts, faces, _ = icosphere_levels(3)
    mean = verts[3] * AXES_MM
    # Unit modes (as PCA gives them): a stretch along x and one along z; sd: 10 % of each axis at 1 sd.
    modes = np.stack([mean * np.eye(3)[0], mean * np.eye(3)[2]])
    norms = np.linalg.norm(modes.reshape(2, -1), axis=1)
    modes /= norms[:, None, None]
    model = {"mean": torch.from_numpy(mean), "modes": torch.from_numpy(modes),
             "sd": torch.from_numpy(0.1 * norms), "faces": torch.from_numpy(faces[3].astype(np.int64))}
    truth = mean + np.einsum("k,kvc->vc", TRUE_Z * 0.1 * norms, modes) + SHIFT_MM
    grid = RP.loss_grid(radar)
    echoes = []
    for view in radar.views:
        vis, _ = RV.visibility(truth, faces[3], RP.probe_points(radar, view))
        seen = vis > 0
        with _quiet():
            e = RE.echo(truth[faces[3]][seen], vis[seen], grid["positions_mm"][view], grid["frequencies_hz"], radar)
        echoes.append(e.reshape(32, 32, -1))
    return {"setup": setup, "model": model, "truth": truth, "echo": np.stack(echoes)}


def test_against_its_own_model_the_fit_recovers_the_coefficients_and_the_shift(scene):
    setup, model = scene["setup"], scene["model"]
    with torch.no_grad():
        v = torch.as_tensor(scene["truth"], dtype=torch.float32)[None]
        targets = torch.stack([setup.predicted(v, model["faces"], k)[0] for k in range(3)])
    result = fit_shape(model, targets, setup, FitParams(modes=2, iterations=200))
    assert np.abs(result["z"] - TRUE_Z).max() < 0.05
    assert np.abs(result["translation"] - SHIFT_MM).max() < 0.25
    assert np.linalg.norm(result["verts"] - scene["truth"], axis=1).mean() < 0.25
    assert result["losses"][-1] < 0.05 * result["losses"][0]


def test_against_the_production_echo_the_fit_lands_near_the_truth(scene):
    setup, model = scene["setup"], scene["model"]
    targets = torch.from_numpy(setup.target(scene["echo"], 0.0))
    start = fit_shape(model, targets, setup, FitParams(modes=2, iterations=0))
    result = fit_shape(model, targets, setup, FitParams(modes=2, iterations=200))
    before = np.linalg.norm(start["verts"] - scene["truth"], axis=1).mean()
    after = np.linalg.norm(result["verts"] - scene["truth"], axis=1).mean()
    # measured 5.04 -> 0.71 mm; the image-domain model's own bias (about -2 % on ellipsoids, docs/trainer.md)
    # is what remains
    assert before > 4.0 and after < 1.0, (before, after)
    assert np.abs(result["translation"] - SHIFT_MM).max() < 0.5


def test_no_modes_fits_the_translation_alone_and_too_many_are_refused(scene):
    setup, model = scene["setup"], scene["model"]
    targets = torch.from_numpy(setup.target(scene["echo"], 0.0))
    alone = fit_shape(model, targets, setup, FitParams(modes=0, iterations=100))
    assert alone["z"].shape == (0,) and np.abs(alone["translation"] - SHIFT_MM).max() < 1.0
    with pytest.raises(InputError, match="modes must be 0..2"):
        fit_shape(model, targets, setup, FitParams(modes=3))


def test_noise_scale_gives_the_asked_image_snr_and_a_missing_model_is_named(tmp_path):
    index = {"radar": {"image_snr_db": 30.0}}
    assert noise_scale(index, 30.0) == 1.0 and noise_scale(index, None) == 0.0
    assert noise_scale(index, 20.0) == pytest.approx(10 ** 0.5)  # 10 dB less SNR: sigma x sqrt(10)
    with pytest.raises(InputError, match="model.npz: no shape model"):
        shape_model_tensors(tmp_path / "ssm" / "model.npz")
