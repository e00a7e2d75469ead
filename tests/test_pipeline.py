"""The smoke recipe end to end: every stage, a verified dataset, the same bytes with 1 or 2 workers."""

from __future__ import annotations

import json

import numpy as np
import pytest

from meshsar_builder.dataset.readers import MeshSARDataset
from meshsar_builder.dataset.verify import verify
from meshsar_builder.pipeline import recipe as R
from meshsar_builder.pipeline.io import TMP_MARK, read_json, sha256_file
from meshsar_builder.pipeline.runner import STAGE_ORDER, build

from .conftest import MANIFESTS
from .test_quiet import caught_warnings, unexplained

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    out = tmp_path_factory.mktemp("smoke") / "w2"
    results = build(R.load(MANIFESTS / "smoke.toml"), out, workers=2)
    return out, results


def test_every_stage_runs_and_the_dataset_verifies(smoke):
    out, results = smoke
    assert results.failures == [] and [r["stage"] for r in results.summary] == list(STAGE_ORDER)
    assert verify(out) == []
    index = read_json(out / "index.json")
    assert index["counts"]["subset"] == {"ssm": 4, "direct": 4}
    assert [v["name"] for v in index["views"]] == ["anterior", "left", "superior"]
    groupwise = read_json(out / "register" / "groupwise.json")
    # The default 2 groupwise rounds after the reference subject's, each recorded with its movement.
    assert [r["round"] for r in groupwise["rounds"]] == [0, 1, 2] and groupwise["last_round"] == 2
    assert all(r["registered"] == 3 and r["movement_mm"] >= 0 for r in groupwise["rounds"][1:])
    assert (out / "register" / "template.ply").read_bytes() == (out / "register" / "template-2.ply").read_bytes()
    report = read_json(out / "ssm" / "report.json")
    assert {"compactness", "generalisation_mm", "specificity_mm"} <= set(report)
    assert report["self_intersection_redraws"] >= 0 and report["samples"] == 4
    # every part's specificity draws, each mode count's draws split across the parts
    assert report["specificity_draws"] == 1000 and len(report["specificity_curve_mm"]) == report["modes"]
    assert sorted(p.name for p in (out / "ssm" / "specificity").glob("*.npz")) == [f"{c}.npz" for c in range(4)]
    card = (out / "card" / "README.md").read_text()
    for section in ("## Samples", "## Speckle", "## Shape model", "## Dynamic subjects", "## Frames in correspondence",
                    "## Counts", "## Time per stage"):
        assert section in card
    for png in ("gallery.png", "speckle.png", "ssm_variance.png", "ssm_modes.png", "cycle.png", "motion.png"):
        assert (out / "card" / png).stat().st_size > 1000
    # diffuse scatterers: a shape-model sample draws its own; frames in correspondence share their reference's
    for sid in index["samples"]:
        meta = read_json(out / "radar" / f"{sid}.json")["meta"]
        shared = meta.get("correspondence") in ("reference", "tracked")
        assert meta["scatterers"] == (meta["reference_frame"] if shared else sid), sid
        assert len(meta["appearance"]) == 3 and 0 <= meta["appearance"][0]["speckle_share"] <= 1
    split = read_json(out / "splits" / "seed-0.json")
    assert sorted(split["train"] + split["test"]) == sorted(index["samples"])


def test_shape_model_samples_drawn_in_parts_are_the_same_bytes(smoke, tmp_path):
    """The 4 samples in parts of 3 (ssm.samples_per_item): the same files, both parts' redraws
    in the report, and the registration is not redone."""
    import shutil

    out, _ = smoke
    copy = tmp_path / "parts"
    shutil.copytree(out, copy)
    recipe = tmp_path / "smoke.toml"
    # Few specificity draws: they do not touch the samples, and the rerun stays short.
    split = "[ssm]\nsamples_per_item = 3\nspecificity_samples = 8\nspecificity_items = 2\n"
    recipe.write_text((MANIFESTS / "smoke.toml").read_text().replace("[ssm]\n", split))
    results = build(R.load(recipe), copy, workers=2, until="ssm")
    ran = {r["stage"]: r["ran"] for r in results.summary}
    assert results.failures == [] and ran["ssm"] > 0 and ran["remesh"] == ran["register"] == 0
    parts = sorted(p.name for p in (copy / "ssm" / "samples").glob("*.json"))
    assert parts == ["0.json", "1.json"]
    assert [len(read_json(copy / "ssm" / "samples" / p)["samples"]) for p in parts] == [3, 1]
    for ply in (out / "ssm" / "samples").glob("*.ply"):
        assert (copy / "ssm" / "samples" / ply.name).read_bytes() == ply.read_bytes(), ply.name
    report, before = read_json(copy / "ssm" / "report.json"), read_json(out / "ssm" / "report.json")
    assert report["samples"] == 4 and report["self_intersection_redraws"] == before["self_intersection_redraws"]


def test_reader_returns_the_meshes_and_images(smoke):
    out, _ = smoke
    ds = MeshSARDataset(out, split=None)
    s = ds[0]
    assert s["sar"].shape == (3, 2, 64, 64) and s["echo"].shape == (3, 8, 8, 16)
    verts = s["verts"].numpy()
    # heart-centred: the bounding box is centred on the origin
    np.testing.assert_allclose((verts.min(axis=0) + verts.max(axis=0)) / 2, 0, atol=1e-3)
    assert json.dumps(s["meta"])


def test_one_worker_gives_the_same_bytes_and_a_quiet_console(smoke, tmp_path):
    """Every stage in this process (workers=1): the bytes of two workers, and no warning nobody explained (test_quiet)."""
    out, _ = smoke
    one = tmp_path / "w1"
    with caught_warnings() as caught:
        results = build(R.load(MANIFESTS / "smoke.toml"), one, workers=1)
    assert results.failures == [], [f"{f['stage']}/{f['item']}: {f['message']}" for f in results.failures]
    assert unexplained(caught) == []
    for shard in sorted((out / "shards").glob("*.npz")):
        assert sha256_file(shard) == sha256_file(one / "shards" / shard.name), shard.name
    assert (out / "index.json").read_bytes() == (one / "index.json").read_bytes()
    assert (out / "splits" / "seed-0.json").read_bytes() == (one / "splits" / "seed-0.json").read_bytes()


def test_rerun_skips_everything(smoke):
    out, _ = smoke
    again = build(R.load(MANIFESTS / "smoke.toml"), out, workers=1)
    assert again.failures == [] and all(r["ran"] == 0 for r in again.summary)


def test_dask_local_cluster_gives_the_same_bytes(smoke, tmp_path):
    """scheduler "local:N" starts its own cluster; the meshes match (the shards on Dask: the next test)."""
    out, _ = smoke
    dask = tmp_path / "dask"
    assert build(R.load(MANIFESTS / "smoke.toml"), dask, until="remesh", scheduler="local:2").failures == []
    meshes = sorted(p.relative_to(out) for p in (out / "remesh").glob("*.ply"))
    assert meshes
    for name in meshes:
        assert (dask / name).read_bytes() == (out / name).read_bytes(), name


def test_sigkilled_dask_worker_is_retried_without_duplicates(smoke, tmp_path):
    """Kill a worker while it meshes; Dask reruns its task elsewhere; outputs equal a clean build."""
    import os
    import signal
    import threading
    import time

    import dask
    from distributed import Client, LocalCluster

    from meshsar_builder.pipeline.pools import SCHEDULE_WHEN_FREE

    out, _ = smoke
    killed = tmp_path / "killed"
    with dask.config.set(SCHEDULE_WHEN_FREE), \
            LocalCluster(n_workers=2, threads_per_worker=1, host="127.0.0.1", dashboard_address=None) as cluster, \
            Client(cluster) as client:
        pids = list(client.run(os.getpid).values())
        box = {}
        worker = threading.Thread(target=lambda: box.update(r=build(
            R.load(MANIFESTS / "smoke.toml"), killed, until="shards", scheduler=cluster.scheduler_address)))
        worker.start()
        deadline = time.time() + 300
        while not list((killed / "remesh").glob("*.json")) and time.time() < deadline:
            time.sleep(0.05)
        os.kill(pids[0], signal.SIGKILL)  # mid-stage: remesh items are in flight on both workers
        worker.join(timeout=600)
    assert box["r"].failures == []
    for name in [*(p.relative_to(out) for p in (out / "shards").glob("*.npz")), "index.json", "splits/seed-0.json"]:
        assert (killed / name).read_bytes() == (out / name).read_bytes(), name
    assert not [p for p in killed.rglob("*") if TMP_MARK in p.name]
