"""Trainer: config validation, overfitting one sample, resuming, validation, DDP on CPU, evaluation of a run."""

from __future__ import annotations

import socket
from pathlib import Path

import numpy as np
import pytest
import trimesh

torch = pytest.importorskip("torch")

import meshsar_builder.radar.params as RP  # noqa: E402
from meshsar_builder.dataset.shards import INDEX_NAME, Sample, build_index, write_shard  # noqa: E402
from meshsar_builder.dataset.splits import make_split, write_split  # noqa: E402
from meshsar_builder.pipeline.errors import InputError, RecipeError  # noqa: E402
from meshsar_builder.pipeline.io import sha256_file, write_json  # noqa: E402
from meshsar_builder.radar.differentiable import echo_torch  # noqa: E402
from meshsar_builder.radar.imaging import ImageParams  # noqa: E402
from meshsar_builder.trainer import losses as L  # noqa: E402
from meshsar_builder.trainer import train as T  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TINY_RADAR = RP.RadarParams(aperture=(8, 8), step_mm=10.0, n_samples=8, echo_decimation=(2, 2, 2))
TINY_IMAGES = ImageParams(size=32)
TINY_CONFIG = """
name = "tiny"
seed = 3
[data]
batch_size = 2
val_fraction = 0.2
[model]
encoder_channels = [4, 8]
hidden = 16
blocks = 1
stage_scales = [[1], [1, 0], [0]]
template_level = 2
[loss]
chamfer_points = 300
[radar_loss]
warmup_epochs = 1
antennas = 4
[optim]
lr = 3e-3
epochs = 2
"""


def silhouettes(verts: np.ndarray, views: list[dict], fov_mm: float, size: int) -> np.ndarray:
    """(V, 2, size, size) images of a closed mesh's outline in each view, on the model's pixel grid
    (DESIGN section 3: column from p.u, row from -p.v): channel 0 the filled silhouette, 1 zero."""
    out = np.zeros((len(views), 2, size, size), np.float32)
    for k, view in enumerate(views):
        x, y = verts @ np.asarray(view["u"]) / (fov_mm / 2), -(verts @ np.asarray(view["v"])) / (fov_mm / 2)
        col, row = (np.floor((x + 1) / 2 * size).astype(int), np.floor((y + 1) / 2 * size).astype(int))
        keep = (col >= 0) & (col < size) & (row >= 0) & (row < size)
        out[k, 0, row[keep], col[keep]] = 1
    return out


def make_dataset(root: Path, n: int = 6, shard_size: int = 3, radii: tuple[float, float] = (30, 50),
                 images: str = "random", train: float = 2 / 3) -> Path:
    """A tiny build folder: ellipsoid meshes, images, the echo of each mesh, a seed-0 split.

    images: "random" (noise), "silhouette" (each mesh's outline per view) or "shuffled" (the
    silhouettes of another sample: a fixed derangement). The defaults give train s1 | s3 s4 s5
    by shard: ranks dealt whole shards would get 1 and 3 samples.
    """
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    sphere = trimesh.creation.icosphere(2)
    dense = trimesh.creation.icosphere(5).vertices  # fills the silhouettes at 32 px
    grid, loss = RP.echo_grid(TINY_RADAR), RP.loss_grid(TINY_RADAR)
    metadata = RP.index_metadata(TINY_RADAR, TINY_IMAGES)
    draws = [(rng.uniform(*radii, 3), rng.random((3, 2, 32, 32))) for _ in range(n)]  # (scale, noise) per sample
    scales = [scale for scale, _ in draws]
    outlines = [silhouettes(dense * scale, metadata["views"], metadata["fov_mm"], 32) for scale in scales]
    samples = []
    for i in range(n):
        verts = (sphere.vertices * scales[i]).astype(np.float32)
        echo = np.stack([echo_torch(torch.from_numpy(verts), torch.from_numpy(sphere.faces), grid["positions_mm"][v],
                                    grid["frequencies_hz"], TINY_RADAR).numpy().reshape(4, 4, 4)
                         for v in TINY_RADAR.views])
        clean = np.stack([echo_torch(torch.from_numpy(verts), torch.from_numpy(sphere.faces), loss["positions_mm"][v],
                                     loss["frequencies_hz"], TINY_RADAR).numpy().reshape(8, 8, 2)
                          for v in TINY_RADAR.views]).astype(np.complex64)  # the noise-free echo on the loss grid
        sar = {"random": draws[i][1], "silhouette": outlines[i], "shuffled": outlines[(i + 1) % n]}[images]
        samples.append(Sample(
            sample_id=f"s{i}", verts=verts, faces=sphere.faces, vert_labels=np.zeros(len(verts), np.uint8),
            sar=sar.astype(np.float16), echo=echo, echo_clean=clean, noise_seed=np.arange(3, dtype=np.uint64),
            noise_sigma=np.zeros(3), center_mm=np.zeros(3, np.float32),
            meta={"source": "toy", "subject": f"subj{i}", "subset": "direct"}))
    shards = []
    for k in range(0, n, shard_size):
        file = f"shards/shard-{k // shard_size:05d}.npz"
        write_shard(root / file, samples[k : k + shard_size])
        shards.append({"file": file, "n": len(samples[k : k + shard_size]), "sha256": sha256_file(root / file),
                       "sample_ids": [s.sample_id for s in samples[k : k + shard_size]]})
    index = build_index(recipe="tiny", recipe_sha256="0" * 64, code_version="test", metadata=metadata,
                        shard_size=shard_size, shards=shards, metas={s.sample_id: s.meta for s in samples})
    write_json(root / INDEX_NAME, index)
    write_split(root, make_split(index, 0, {"train": train, "test": 1 - train}, "sample"))
    return root


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("tiny"))


def test_shipped_configs_parse():
    default = T.load_config(ROOT / "manifests/train/default.toml")
    paper = T.load_config(ROOT / "manifests/train/paper.toml")
    assert paper.optim.lr == 1e-3 and paper.data.batch_size == 1 and paper.optim.epochs == 500
    assert paper.loss.weights == (0.3, 0.05, 0.46, 0.16)
    assert paper.radar_loss.weight == 0.1 and paper.radar_loss.warmup_epochs == 20
    assert paper.radar_loss.ramp_epochs == 0 and paper.radar_loss.mode == "raw" and paper.radar_loss.balance == "none"
    assert paper.model.norm == "batch" and paper.optim.schedule == "constant" and not paper.run.amp
    assert default.model.stages == paper.model.stages == 3
    # The radar loss chosen on validation (docs/trainer.md, "So default.toml uses it"): depth maps, 20 smoothing steps.
    rc = default.radar_loss
    assert (rc.mode, rc.smooth_iterations, rc.weight, rc.target) == ("depth", 20, 0.3, "clean")


@pytest.mark.parametrize("text, message", [
    ('name = "x"\n[model]\nhiden = 3\n', "unknown key 'hiden'"),
    ('name = "x"\n[optim]\nlr = "fast"\n', "[optim] lr: expected a number"),
    ('name = "x"\n[radar_loss]\nmode = "phase"\n', "mode: must be one of"),
    ('name = "x"\n[radar_loss]\nbalance = "magic"\n', "balance: must be one of"),
    ('name = "x"\n[optim]\nschedule = "step"\n', "schedule: must be one of"),
    ('name = "x"\nepochs = 3\n', "unknown key 'epochs'"),
    ('name = "x"\nseed = -3\n', "seed: must be >= 0"),
])
def test_bad_configs_name_the_file_and_key(text, message):
    with pytest.raises(RecipeError, match="cfg.toml") as info:
        T.parse_config(text, "cfg.toml")
    assert message in str(info.value)


def test_radar_weight_ramps_in_and_lr_follows_the_schedule():
    config = T.parse_config('name = "x"\n[radar_loss]\nweight = 0.2\nwarmup_epochs = 3\nramp_epochs = 3\n'
                            '[optim]\nlr = 1e-3\nepochs = 11\nschedule = "cosine"\nfinal_lr = 0.1\n')
    assert [T.radar_weight_at(config, e) for e in range(8)] == pytest.approx([0, 0, 0, 0.05, 0.1, 0.15, 0.2, 0.2])
    assert T.lr_at(config, 0) == pytest.approx(1e-3) and T.lr_at(config, 10) == pytest.approx(1e-4)
    assert T.lr_at(config, 5) == pytest.approx(0.55e-3)
    constant = T.parse_config('name = "x"\n[optim]\nlr = 2e-3\nepochs = 4\n')
    assert [T.lr_at(constant, e) for e in range(4)] == [2e-3] * 4


def test_balanced_radar_term_has_the_geometric_gradient_norm():
    torch.manual_seed(0)
    leaf = torch.randn(2, 5, 3, dtype=torch.float64, requires_grad=True)
    verts = 2 * leaf  # not a leaf, as the model's output
    geometric = 1e-3 * verts.square().sum()
    radar = (verts.sin() * 40).abs().sum()
    g_geo, = torch.autograd.grad(geometric, verts, retain_graph=True)
    g_radar, = torch.autograd.grad(radar, verts, retain_graph=True)
    term = L.balanced(radar, geometric, verts)
    g_term, = torch.autograd.grad(term, verts, retain_graph=True)
    scale = g_geo.norm() / g_radar.norm()
    torch.testing.assert_close(g_term, scale * g_radar)
    assert g_term.norm().item() == pytest.approx(g_geo.norm().item())
    assert term.item() == pytest.approx((scale * radar).item())
    g_leaf, = torch.autograd.grad(geometric + term, leaf)  # reaches the parameters through the surrogate
    torch.testing.assert_close(g_leaf, 2 * (g_geo + scale * g_radar))


def test_resume_matches_an_uninterrupted_run(tiny_data, tmp_path):
    config = T.parse_config(TINY_CONFIG)
    whole = T.train(config, tiny_data, out=tmp_path / "whole", progress=False)
    first = T.train(T.parse_config(TINY_CONFIG.replace("epochs = 2", "epochs = 1")), tiny_data,
                    out=tmp_path / "part", progress=False)
    assert len(first.log) == 1
    # Same config text as the uninterrupted run, so the folder's checkpoint is accepted and resumed.
    state = T.load_checkpoint(tmp_path / "part" / T.CHECKPOINT)
    state["config_text"] = config.text
    T.save_checkpoint(tmp_path / "part" / T.CHECKPOINT, state)
    resumed = T.train(config, tiny_data, out=tmp_path / "part", progress=False)
    assert [row["epoch"] for row in resumed.log] == [0, 1]
    assert resumed.log[1]["radar"] > 0  # the radar term is on after the 1-epoch warm-up
    assert resumed.log[1]["total"] == pytest.approx(whole.log[1]["total"], rel=1e-6)
    for a, b in zip(whole.model.state_dict().values(), resumed.model.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)
    assert T.read_log(tmp_path / "part" / T.LOG) == resumed.log
    row = resumed.log[1]
    assert row["samples"] == 3  # 4 train samples, 1 held out for validation
    for name in T.LOSS_TERMS:  # the per-stage columns add up to the term
        assert sum(row[f"{name}_s{k}"] for k in range(3)) == pytest.approx(row[name], rel=1e-6)  # float32 terms
    assert 0 < row["val_dice"] <= 1 and row["val_assd_mm"] > 0 and row["val_total"] > 0
    best = T.load_checkpoint(tmp_path / "part" / T.BEST)
    assert best["val"]["dice"] == max(r["val_dice"] for r in resumed.log)
    assert best["epoch"] == 1 + max(resumed.log, key=lambda r: r["val_dice"])["epoch"]
    model, _, info = T.load_run(tmp_path / "part")
    assert info["checkpoint"] == T.BEST


@pytest.mark.parametrize("mode", ["focused", "depth"])
def test_focused_modes_train_against_the_loss_grid_target(tiny_data, tmp_path, mode):
    text = TINY_CONFIG.replace("warmup_epochs = 1", f'warmup_epochs = 0\nmode = "{mode}"\nsmooth_iterations = 5\n'
                               'focused_lateral_mm = 10.0\nfocused_range_mm = 20.0')
    run = T.train(T.parse_config(text.replace("epochs = 2", "epochs = 1")), tiny_data, out=tmp_path, progress=False)
    row = run.log[0]
    assert row["radar"] > 0 and np.isfinite(row["radar_l1"]) and row["radar_l1"] > 0
    if mode == "focused":  # 1 - cosine; depth: millimetres
        assert row["radar_l1"] <= 2


def test_the_raw_radar_loss_reads_the_builds_radar_and_its_noise_free_echo():
    """A build at z0 250 mm, physical-optics reflectivity and centre-only probes (none of them the defaults): the
    raw and profile losses simulate with every radar key the index records and compare with echo_clean on the
    loss grid (DESIGN section 10), so the truth scores 0 and a 1 mm shift does not. With the defaults' radar
    (z0 300 mm) the loss found no aperture centre; with the stored decimated echo it compared with noise."""
    radar = RP.RadarParams(aperture=(8, 8), step_mm=10.0, n_samples=8, z0_mm=250.0, reflectivity="po",
                           probes="centre", p=2.0, echo_decimation=(2, 2, 2), loss_decimation=(1, 1, 2))
    index = RP.index_metadata(radar, TINY_IMAGES)
    geometry = T.DatasetGeometry.from_index(index)
    assert geometry.radar == T.DatasetGeometry.from_index(index).full_radar
    assert (geometry.radar.z0_mm, geometry.radar.reflectivity, geometry.radar.probes) == (250.0, "po", "centre")
    sphere = trimesh.creation.icosphere(2)
    verts, faces = torch.tensor(sphere.vertices * (35.0, 30.0, 25.0)), torch.tensor(sphere.faces)
    loss = RP.loss_grid(radar)
    clean = torch.stack([echo_torch(verts, faces, loss["positions_mm"][v], loss["frequencies_hz"], radar)
                         .reshape(8, 8, 4) for v in radar.views])[None]  # (1, V, Lx, Ly, Lf)
    batch = {"echo_clean": clean, "echo_noisy": clean + 0.5 * clean.abs().mean(), "echo": torch.zeros(1, 3, 4, 4, 4)}
    torch.testing.assert_close(geometry.echo_targets(batch, "clean"), clean.reshape(1, 3, 64, 4))
    torch.testing.assert_close(geometry.echo_targets(batch, "recorded"), batch["echo_noisy"].reshape(1, 3, 64, 4))
    for mode in ("raw", "profile"):
        def score(v):
            return L.radar_loss(v[None].float(), faces, geometry.echo_targets(batch, "clean"), geometry.positions,
                                geometry.centres, geometry.freqs, geometry.radar, mode).item()
        assert score(verts) < 1e-4 and score(verts + torch.tensor([0.0, 0.0, 1.0])) > 0.005, mode  # float32
    # a build without a loss grid holds no echo_clean: named, not read from the recorded echo
    old = {k: v for k, v in index.items() if k != "loss_grid"}
    with pytest.raises(InputError, match="loss grid"):
        T.DatasetGeometry.from_index(old).echo_targets(batch, "clean")
    assert T.DatasetGeometry.from_index(old).echo_targets(batch, "recorded").shape == (1, 3, 16, 4)


def test_validation_is_a_seeded_part_of_the_train_split(tiny_data):
    index = T.read_index(tiny_data)
    train = T.split_ids(tiny_data, index, "train", 0)
    test = T.split_ids(tiny_data, index, "test", 0)
    fit, val = T.validation_split(tiny_data, index, 0, 0.5)
    assert sorted(fit + val) == sorted(train) and len(val) == 2 and not set(val) & set(test)
    assert T.validation_split(tiny_data, index, 0, 0.5) == (fit, val)
    assert T.validation_split(tiny_data, index, 0, 0.0) == (train, [])


@pytest.mark.parametrize("n, batch, world", [(5, 1, 2), (7, 2, 3), (4, 3, 2), (9, 4, 4), (3, 2, 1)])
def test_epoch_batches_see_every_sample_once_on_equal_step_counts(n, batch, world):
    ranks = [T.epoch_batches(n, batch, world, r, seed=1, epoch=2) for r in range(world)]
    assert len({len(r) for r in ranks}) == 1  # the same number of steps on every rank
    seen = sorted(i for r in ranks for b, w in r if w > 0 for i in b)
    assert seen == list(range(n))
    for step in zip(*ranks):
        # DDP averages over ranks: sum_r w_r mean_r / world is then the mean over the global batch.
        total = sum(len(b) for b, w in step if w > 0)
        assert sum(w * len(b) for b, w in step) / world == pytest.approx(sum(len(b) ** 2 / total for b, w in step if w > 0))
        assert all(w == pytest.approx(len(b) * world / total) for b, w in step if w > 0)
    assert T.epoch_batches(n, batch, world, 0, seed=1, epoch=2) == ranks[0]  # every rank can recompute it


def test_a_run_refuses_another_config_but_not_another_device(tiny_data, tmp_path):
    one_epoch = TINY_CONFIG.replace("epochs = 2", "epochs = 1")
    first = T.train(T.parse_config(one_epoch), tiny_data, out=tmp_path, progress=False)
    # A run trained on one device is the same run on another (a GPU run evaluated or resumed on a CPU).
    elsewhere = T.parse_config(one_epoch + '[run]\ndevice = "cuda"\n')
    assert T.train(elsewhere, tiny_data, out=tmp_path, progress=False, device="cpu").log == first.log
    assert T.train(T.parse_config(one_epoch), tiny_data, out=tmp_path, progress=False, device="cpu").log == first.log
    assert T.read_json(tmp_path / "run.json")["devices"] == ["cpu"]  # the resumes trained no epoch: not added
    assert (tmp_path / "config.toml").read_text() == one_epoch  # the run's first config, not the resumed one's
    with pytest.raises(T.InputError, match="different config"):
        T.train(T.parse_config(TINY_CONFIG), tiny_data, out=tmp_path, progress=False)


def _ddp_worker(rank: int, world: int, port: int, data: str, out: str, config_text: str) -> None:
    import os

    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port))
    torch.set_num_threads(1)
    result = T.train(T.parse_config(config_text), data, out=Path(out) / "run", progress=False)
    flat = torch.cat([p.detach().flatten() for p in result.model.parameters()])
    torch.save({"params": flat, "log": result.log}, Path(out) / f"rank{rank}.pt")
    torch.distributed.destroy_process_group()


@pytest.mark.slow
def test_two_process_ddp_sees_every_sample_of_uneven_shards(tiny_data, tmp_path):
    """2 ranks x batch 1 over 3 samples (2 + 1) equal one process with batch 2: the same global batches."""
    single = TINY_CONFIG.replace("epochs = 2", "epochs = 1")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    ddp = single.replace("batch_size = 2", "batch_size = 1")
    torch.multiprocessing.spawn(_ddp_worker, args=(2, port, str(tiny_data), str(tmp_path), ddp), nprocs=2)
    ranks = [torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in range(2)]
    assert ranks[0]["log"][0]["samples"] == 3 and ranks[0]["log"][0]["steps"] == 2
    assert ranks[0]["log"][0]["val_dice"] > 0  # rank 0 validated
    torch.testing.assert_close(ranks[0]["params"], ranks[1]["params"], rtol=0, atol=0)
    torch.set_num_threads(1)
    reference = T.train(T.parse_config(single), tiny_data, out=tmp_path / "single", progress=False)
    assert reference.log[0]["samples"] == 3
    assert ranks[0]["log"][0]["total"] == pytest.approx(reference.log[0]["total"], rel=1e-5)
    flat = torch.cat([p.detach().flatten() for p in reference.model.parameters()])
    # Adam moves each weight by ~lr per step whatever its gradient's size, so float noise on near-zero
    # gradients shows as up to a few % of one step (3e-3); a wrongly weighted or skipped sample moves
    # most weights by a whole step.
    assert (ranks[0]["params"] - flat).abs().max() < 3e-4
    assert (ranks[0]["params"] - flat).abs().median() < 1e-6


@pytest.mark.slow
def test_overfits_one_sample(tiny_data):
    torch.set_num_threads(1)
    torch.manual_seed(0)
    # Level 3 (42 -> 162 -> 642 vertices): on a 12-vertex first stage the edge-length term
    # (mean squared edge, ~R^2 / n) would outweigh the Chamfer distance.
    config = T.parse_config(TINY_CONFIG.replace("template_level = 2", "template_level = 3"))
    index = T.read_index(tiny_data)
    geometry = T.DatasetGeometry.from_index(index)
    dataset = T.MeshSARDataset(tiny_data, "train")
    sample = dataset[0]
    model = T.build_model(config, {"frames": geometry.frames, "fov_mm": geometry.fov_mm, "channels": ["intensity", "depth"],
                                   "template_radius_mm": 40.0})
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    batch = T.collate_meshes([sample])
    curve = []
    for step in range(300):
        meshes = model(batch["sar"])
        terms = T.batch_losses(meshes, model, batch, geometry, config, 0.0, T.sample_generators(0, step, ["s0"]))
        optimizer.zero_grad()
        terms["total"].backward()
        optimizer.step()
        if step % 25 and step != 299:
            continue
        with torch.no_grad():
            # Surface to surface, so the vertex spacing (~5 mm at 642 vertices) sets no floor.
            generator = torch.Generator().manual_seed(1)
            final = L.sample_surface(meshes[-1][1][0], model.topology()["faces"], 4000, generator)
            truth = L.sample_surface(batch["verts"][0], batch["faces"][0], 4000, generator)
            curve.append(L.chamfer(final, truth).item())
    assert max(curve[-3:]) < curve[0] / 10, curve


@pytest.mark.slow
def test_evaluate_writes_metrics_tables_and_renders(tiny_data, tmp_path):
    from meshsar_builder.trainer.evaluate import COLUMNS, evaluate

    T.train(T.parse_config(TINY_CONFIG.replace("epochs = 2", "epochs = 1")), tiny_data, out=tmp_path, progress=False)
    summary = evaluate(tmp_path, tiny_data, samples=2000, progress=False)
    out = tmp_path / "eval-seed-0"
    for name in ("metrics.csv", "summary.md", "summary.json", "renders.png"):
        assert (out / name).exists(), name
    assert set(summary) == {"toy", "all"} and set(summary["all"]) == {"sar2mesh", "template", "mean_shape"}
    assert "best.pt" in (out / "summary.md").read_text()
    table = (out / "summary.md").read_text()
    assert table.index("dice") < table.index("assd_mm") < table.index("hd_mm") < table.index("si_pct")
    assert all(np.isfinite(summary["all"]["sar2mesh"][c][0]) for c in COLUMNS)
    # A split whose test part is empty (too few subjects for its ratios) is named, not a StopIteration inside.
    import json

    from meshsar_builder.dataset.shards import read_index
    from meshsar_builder.pipeline.errors import InputError

    empty = tiny_data / "splits" / "seed-99.json"
    ids = list(read_index(tiny_data)["samples"])
    empty.write_text(json.dumps({"seed": 99, "ratios": {"train": 0.8, "test": 0.2}, "train": ids, "test": []}))
    try:
        with pytest.raises(InputError, match=r"seed-99.json: its test part holds no samples"):
            evaluate(tmp_path, tiny_data, split="seed-99", samples=2000, progress=False)
    finally:
        empty.unlink()


IMAGES_CONFIG = """
name = "images"
seed = 0
[data]
batch_size = 2
val_fraction = 0.0
[model]
encoder_channels = [4, 8]
hidden = 16
blocks = 1
stage_scales = [[1], [1, 0], [0]]
template_level = 3
[loss]
chamfer_points = 300
[radar_loss]
weight = 0.0
[optim]
lr = 3e-3
epochs = 12
"""


@pytest.fixture(scope="module")
def silhouette_runs(tmp_path_factory):
    """The same 16 ellipsoids (12 train, 4 test) with their outlines as images, or another sample's
    outlines ("shuffled"), and the IMAGES_CONFIG run trained on each: {images: (data, run)}."""
    root = tmp_path_factory.mktemp("silhouettes")
    runs = {}
    for images in ("silhouette", "shuffled"):
        data = make_dataset(root / images, 16, 8, radii=(25, 55), images=images, train=0.75)
        runs[images] = data, T.train(T.parse_config(IMAGES_CONFIG), data, out=root / f"run-{images}", progress=False).run
    return runs


def held_out_scores(data: Path, run: Path) -> dict[str, float]:
    """Mean Dice and ASSD of a run's best model on the test samples."""
    from meshsar_builder.trainer.metrics import mesh_metrics

    model = T.load_run(run)[0]
    test = T.MeshSARDataset(data, "test")
    metrics = [mesh_metrics(*model.predict_mesh(test[i]["sar"]), test[i]["verts"].double().numpy(),
                            test[i]["faces"].numpy(), samples=2000) for i in range(len(test))]
    return {k: float(np.mean([m[k] for m in metrics])) for k in ("dice", "assd_mm")}


@pytest.mark.slow
def test_the_network_uses_its_images(silhouette_runs):
    """Same meshes, steps and seeds; images that show each mesh's outline, or another sample's:
    on the 4 held-out samples the true images must score clearly better (measured: ASSD 3.2 vs 9.8 mm,
    Dice 0.89 vs 0.63)."""
    scores = {images: held_out_scores(*silhouette_runs[images]) for images in ("silhouette", "shuffled")}
    assert scores["shuffled"]["assd_mm"] > 1.5 * scores["silhouette"]["assd_mm"], scores
    assert scores["silhouette"]["dice"] > scores["shuffled"]["dice"] + 0.1, scores


@pytest.mark.slow
def test_implicit_baseline_trains_by_the_same_cli_and_joins_the_table(silhouette_runs, tmp_path):
    from meshsar_builder.cli import main
    from meshsar_builder.pipeline.io import read_json
    from meshsar_builder.trainer.evaluate import evaluate

    data, mesh_run = silhouette_runs["silhouette"]
    config = tmp_path / "implicit.toml"
    config.write_text(IMAGES_CONFIG.replace("template_level = 3", 'template_level = 3\nkind = "implicit"\n'
                                            "implicit_grid = 24\nimplicit_points = 256")
                      .replace("val_fraction = 0.0", "val_fraction = 0.2").replace("epochs = 12", "epochs = 8")
                      + "[run]\nval_every = 4\nval_samples = 1000\n")
    assert main(["train", str(config), "--data", str(data), "--out", str(tmp_path / "implicit")]) == 0
    log = T.read_log(tmp_path / "implicit" / T.LOG)
    assert log[-1]["occupancy"] < 0.5 * log[0]["occupancy"] and log[-1]["val_dice"] > 0.8
    summary = evaluate(mesh_run, data, renders=1, samples=2000, progress=False, compare=(tmp_path / "implicit",))["all"]
    assert list(summary) == ["sar2mesh", "implicit", "template", "mean_shape"]
    assert set(read_json(mesh_run / "eval-seed-0" / "summary.json")["all"]) == set(summary)
    # Outlines determine these ellipsoids (their visual hull), so the learned methods beat the image-blind ones.
    for learned in ("sar2mesh", "implicit"):
        assert summary[learned]["dice"][0] > summary["mean_shape"]["dice"][0] + 0.1, summary
