"""`meshsar ablate --radar`: the weight is chosen on validation, the arms differ only in the radar
weight, each seed's shared warm-up gives the numbers of training from scratch, and the paired test
is a Wilcoxon signed-rank over test samples of the seed means."""

from __future__ import annotations

import csv
import dataclasses
import shutil

import numpy as np
import pytest

pytest.importorskip("torch")
pytestmark = pytest.mark.slow  # seven tiny trainings and evaluations, then two more in processes: ~60 s of CPU

import torch  # noqa: E402
from scipy import stats  # noqa: E402

from meshsar_builder.pipeline.errors import InputError  # noqa: E402
from meshsar_builder.trainer.ablate import PAIRED_COLUMNS, radar_ablation  # noqa: E402
from meshsar_builder.trainer.config import load_config  # noqa: E402
from meshsar_builder.trainer.train import load_checkpoint, read_log, train  # noqa: E402

from .test_ablate import tiny_inputs  # noqa: E402

SEEDS, WEIGHTS = (0, 1), (0.03, 0.3)


@pytest.fixture(scope="module")
def ablation(tmp_path_factory):
    data, config = tiny_inputs(tmp_path_factory.mktemp("radar_ablate"))
    # A 2-epoch warm-up of 4 epochs: the ablation's 2 epochs keep 1 of them, which the runs of a seed share.
    config.write_text(config.read_text().replace("warmup_epochs = 1", "warmup_epochs = 2"))
    result = radar_ablation(config, data, seeds=SEEDS, weights=WEIGHTS, epochs=2, samples=2000, progress=False)
    return data, config, data / "ablations" / "radar-tiny-seed-0-e2", result


def test_the_weight_is_chosen_on_validation_and_the_arms_differ_only_in_it(ablation):
    data, _, folder, result = ablation
    best = {w: min(row["val_assd_mm"] for row in read_log(folder / f"radar-w{w:g}-seed-0" / "log.csv")
                   if row["val_assd_mm"] is not None) for w in WEIGHTS}
    assert result["weights"] == {f"{w:g}": pytest.approx(v) for w, v in best.items()}
    chosen = min(best, key=best.get)
    assert result["chosen_weight"] == chosen
    for seed in SEEDS:
        on = load_config(folder / f"radar-w{chosen:g}-seed-{seed}" / "config.toml").as_dict()
        off = load_config(folder / f"no_radar-seed-{seed}" / "config.toml").as_dict()
        assert on["seed"] == off["seed"] == seed
        assert on["radar_loss"]["weight"] == chosen and off["radar_loss"]["weight"] == 0
        assert {k for k in on if on[k] != off[k]} == {"name", "radar_loss"}
        assert {k for k in on["radar_loss"] if on["radar_loss"][k] != off["radar_loss"][k]} == {"weight"}


def test_each_seed_warms_up_once_and_its_runs_branch_from_there(ablation):
    _, _, folder, result = ablation
    runs = sorted(p.name for p in folder.iterdir() if p.is_dir())
    assert runs == sorted([f"warmup-seed-{s}" for s in SEEDS] + [f"radar-w{w:g}-seed-0" for w in WEIGHTS]
                          + [f"radar-w{result['chosen_weight']:g}-seed-1"] + [f"no_radar-seed-{s}" for s in SEEDS])
    for seed in SEEDS:
        warm = read_log(folder / f"warmup-seed-{seed}" / "log.csv")
        assert [row["epoch"] for row in warm] == [0]
        assert load_checkpoint(folder / f"warmup-seed-{seed}" / "checkpoint.pt")["epoch"] == 1


def test_a_branched_run_is_the_run_trained_from_scratch(ablation, tmp_path):
    """The radar arm at the second seed, retrained alone from its own config: the same log and weights."""
    data, _, folder, result = ablation
    branched = folder / f"radar-w{result['chosen_weight']:g}-seed-1"
    alone = train(load_config(branched / "config.toml"), data, "seed-0", tmp_path / "alone", progress=False)
    drop = ("seconds",)
    assert [{k: v for k, v in row.items() if k not in drop} for row in alone.log] == \
        [{k: v for k, v in row.items() if k not in drop} for row in read_log(branched / "log.csv")]
    assert alone.log[-1]["radar_weight"] > 0
    theirs = load_checkpoint(branched / "checkpoint.pt")["model"]
    for name, tensor in alone.model.state_dict().items():
        assert torch.equal(tensor, theirs[name]), name


def test_paired_test_is_over_test_samples_of_the_seed_means(ablation):
    """Recomputed from each run's metrics.csv with plain loops."""
    _, _, folder, result = ablation
    chosen = result["chosen_weight"]
    tables = {}
    for arm, name in (("radar", f"radar-w{chosen:g}"), ("no_radar", "no_radar")):
        for seed in SEEDS:
            with open(folder / f"{name}-seed-{seed}" / "eval-seed-0" / "metrics.csv", newline="") as f:
                tables[arm, seed] = {row["sample_id"]: row for row in csv.DictReader(f)}
    ids = sorted(tables["radar", 0])
    for k, seed in enumerate(SEEDS):
        for arm in ("radar", "no_radar"):
            assert result["arms"][arm][k]["seed"] == seed
            assert result["arms"][arm][k]["dice"] == pytest.approx(
                np.mean([float(tables[arm, seed][i]["dice"]) for i in ids]))
    for column in PAIRED_COLUMNS:
        means = {}
        for arm in ("radar", "no_radar"):
            means[arm] = []
            for i in ids:
                total = 0.0
                for seed in SEEDS:
                    total += float(tables[arm, seed][i][column])
                means[arm].append(total / len(SEEDS))
        if means["radar"] == means["no_radar"]:
            assert result["paired"][column] == 1.0
        else:
            assert result["paired"][column] == pytest.approx(stats.wilcoxon(means["radar"], means["no_radar"]).pvalue)
        assert result["paired_detail"][column]["n"] == len(ids)
    assert "| assd_mm ↓ |" in (folder / "radar_ablation.md").read_text()


def test_a_rerun_resumes_without_training_or_evaluating(ablation, monkeypatch):
    data, config, folder, result = ablation
    import meshsar_builder.trainer.ablate as A

    monkeypatch.setattr(A, "evaluate", lambda *a, **k: pytest.fail("evaluated again"))
    again = radar_ablation(config, data, seeds=SEEDS, weights=WEIGHTS, epochs=2, samples=2000, progress=False)
    assert again["paired"] == result["paired"] and again["arms"] == result["arms"]
    log = (folder / "no_radar-seed-1" / "log.csv").read_text().splitlines()
    assert len(log) == 1 + 2  # not extended


def test_runs_in_processes_retrain_only_what_is_missing(ablation, tmp_path):
    """jobs = 2: a copy with one arm's run and the choice's weight runs' checkpoints gone retrains that arm
    alone, from its warm-up, and leaves the complete logs as they are."""
    data, config, folder, result = ablation
    copy = tmp_path / "copy"
    shutil.copytree(folder, copy)
    shutil.rmtree(copy / "no_radar-seed-1")
    for w in WEIGHTS:
        (copy / f"radar-w{w:g}-seed-0" / "checkpoint.pt").unlink()
    kept = {p: p.read_bytes() for p in copy.glob("*/log.csv")}
    again = radar_ablation(config, data, seeds=SEEDS, weights=WEIGHTS, epochs=2, samples=2000, progress=False,
                           out=copy, jobs=2)
    assert {p: p.read_bytes() for p in kept} == kept
    assert [row["epoch"] for row in read_log(copy / "no_radar-seed-1" / "log.csv")] == [0, 1]
    assert again["chosen_weight"] == result["chosen_weight"] and again["arms"]["radar"] == result["arms"]["radar"]
    assert again["arms"]["no_radar"][0] == result["arms"]["no_radar"][0]


@pytest.mark.parametrize("weights, seeds, message", [((0.1, 0.0), (0, 1), "need positive values"),
                                                     ((0.1,), (0,), "needs at least 2")])
def test_bad_weights_or_one_seed_are_refused_before_training(ablation, tmp_path, weights, seeds, message):
    data, config, _, _ = ablation
    with pytest.raises(InputError, match=message):
        radar_ablation(config, data, seeds=seeds, weights=weights, out=tmp_path)
    assert not list(tmp_path.iterdir())


def test_a_checkpoint_that_trained_otherwise_is_not_branched_from(ablation, tmp_path):
    """After the warm-up the arms differ: a radar run cannot start from the no-radar arm's last epoch."""
    from meshsar_builder.trainer.ablate import branch_run

    _, _, folder, result = ablation
    config = load_config(folder / f"radar-w{result['chosen_weight']:g}-seed-1" / "config.toml")
    with pytest.raises(InputError, match="did not train as"):
        branch_run(folder / "no_radar-seed-1", tmp_path / "run", config)
    assert not (tmp_path / "run").exists()


def test_another_radar_loss_reuses_the_warm_ups_and_the_no_radar_arm(ablation, tmp_path):
    """The warm-up never computes the radar term, so an ablation of another radar loss (here the depth loss,
    smoothed otherwise) starts from the same warm-ups and keeps the no-radar arm: only its radar runs train."""
    from meshsar_builder.trainer.train import same_run

    data, config, folder, _ = ablation
    for run in folder.iterdir():
        if run.name.startswith(("warmup-", "no_radar-")):
            shutil.copytree(run, tmp_path / run.name)
    kept = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    other = tmp_path / "other.toml"
    other.write_text(config.read_text().replace("[radar_loss]", '[radar_loss]\nmode = "depth"\nsmooth_iterations = 7'))
    result = radar_ablation(other, data, seeds=SEEDS, weights=WEIGHTS, epochs=2, samples=2000, progress=False,
                            out=tmp_path)
    assert {p: p.read_bytes() for p in kept} == kept  # neither retrained nor re-evaluated
    branched = load_config(tmp_path / f"radar-w{result['chosen_weight']:g}-seed-1" / "config.toml")
    assert (branched.radar_loss.mode, branched.radar_loss.smooth_iterations) == ("depth", 7)
    warm_text = load_checkpoint(tmp_path / "warmup-seed-1" / "checkpoint.pt")["config_text"]
    assert same_run(warm_text, branched, until=1)  # the shared epoch: radar weight 0 in both
    # Where the radar term acts, its settings are part of the run: the same weights, another smoothing.
    smoother = dataclasses.replace(branched, radar_loss=dataclasses.replace(branched.radar_loss, smooth_iterations=8))
    assert same_run(branched.text, smoother, until=1) and not same_run(branched.text, smoother, until=2)
