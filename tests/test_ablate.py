"""`meshsar ablate`: every variant and seed trains its own config, the table is their mean ± std, reruns resume."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")
pytestmark = pytest.mark.slow  # eight tiny trainings and evaluations: ~40 s of CPU

from meshsar_builder.pipeline.errors import InputError  # noqa: E402
from meshsar_builder.pipeline.io import read_json  # noqa: E402
from meshsar_builder.trainer.ablate import VARIANTS, ablate  # noqa: E402
from meshsar_builder.trainer.config import load_config  # noqa: E402
from meshsar_builder.trainer.evaluate import BASELINES  # noqa: E402

from .test_train import TINY_CONFIG, make_dataset  # noqa: E402


def tiny_inputs(root):
    """A tiny build and a 4-epoch tiny config under root (the ablations shorten it to 2)."""
    data = make_dataset(root / "data")
    config = root / "tiny.toml"
    config.write_text(TINY_CONFIG.replace("epochs = 2", "epochs = 4"))
    return data, config


@pytest.fixture(scope="module")
def ablation(tmp_path_factory):
    data, config = tiny_inputs(tmp_path_factory.mktemp("ablate"))
    return data, config, ablate(config, data, seeds=(0, 1), epochs=2, samples=2000, progress=False)


def test_each_variant_trains_its_own_config(ablation):
    data, _, result = ablation
    folder = data / "ablations" / "tiny-seed-0-e2"
    configs = {(v, s): load_config(folder / f"{v}-seed-{s}" / "config.toml") for v in VARIANTS for s in (0, 1)}
    default = configs["default", 0]
    assert {c.seed for c in configs.values()} == {0, 1}
    # epochs 4 -> 2 halves the schedule: radar warm-up 1 -> round(0.5) = 0
    assert default.optim.epochs == 2 and default.radar_loss.warmup_epochs == 0
    assert default.radar_loss.weight > 0 and configs["no_radar", 0].radar_loss.weight == 0
    assert configs["max_only", 1].model.pooling == ("max",) and default.model.pooling != ("max",)
    first_view = read_json(data / "index.json")["views"][0]["name"]
    assert configs["single_view", 0].data.views == (first_view,) and default.data.views == ()
    assert read_json(folder / "single_view-seed-0" / "run.json")["view_names"] == [first_view]
    for (variant, seed), config in configs.items():  # nothing else differs from the default of that seed
        others = config.as_dict() | {"name": "", "seed": 0}
        reference = configs["default", seed].as_dict() | {"name": "", "seed": 0}
        changed = {k for k in others if others[k] != reference[k]}
        assert changed == {"default": set(), "no_radar": {"radar_loss"}, "max_only": {"model"},
                           "single_view": {"data"}}[variant]


def test_table_is_the_mean_and_spread_of_the_runs_test_scores(ablation):
    data, _, result = ablation
    folder = data / "ablations" / "tiny-seed-0-e2"
    for variant in VARIANTS:
        dice = [read_json(folder / f"{variant}-seed-{s}" / "eval-seed-0" / "summary.json")["all"]["sar2mesh"]["dice"][0]
                for s in (0, 1)]
        assert result["variants"][variant]["dice"] == pytest.approx([np.mean(dice), np.std(dice)])
        assert result["runs"][variant]["1"]["dice"] == pytest.approx(dice[1])
    assert set(result["baselines"]) == set(BASELINES)
    table = (folder / "ablation.md").read_text()
    assert all(f"| {name} |" in table for name in (*VARIANTS, *BASELINES))


def test_a_rerun_resumes_without_training(ablation, monkeypatch):
    data, config, result = ablation
    import meshsar_builder.trainer.ablate as A

    calls = []
    real = A.train
    monkeypatch.setattr(A, "train", lambda *a, **k: calls.append(a) or real(*a, **k))
    monkeypatch.setattr(A, "evaluate", lambda *a, **k: pytest.fail("evaluated again"))
    again = ablate(config, data, seeds=(0, 1), epochs=2, samples=2000, progress=False)
    assert again["variants"] == result["variants"] and len(calls) == 8
    for variant in VARIANTS:  # the finished runs' logs were not extended
        log = (data / "ablations" / "tiny-seed-0-e2" / f"{variant}-seed-0" / "log.csv").read_text().splitlines()
        assert len(log) == 1 + 2
    # Where runs train is not part of them: --device cpu finds the same finished runs.
    assert ablate(config, data, seeds=(0, 1), epochs=2, samples=2000, progress=False,
                  device="cpu")["variants"] == result["variants"]


def test_unknown_variant_is_refused_before_training(ablation, tmp_path):
    data, config, _ = ablation
    with pytest.raises(InputError, match="unknown ablation variant 'avg_only'"):
        ablate(config, data, variants=("default", "avg_only"), out=tmp_path)
    assert not list(tmp_path.iterdir())
