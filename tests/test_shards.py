"""Shards: exact round trips of ragged meshes, determinism, named errors, and the shards stage."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from meshsar_builder.dataset.shards import (
    ADDED_IN_FORMAT_2,
    SHARD_KEYS,
    Sample,
    Shard,
    build_index,
    read_index,
    read_shard,
    recorded_loss_echo,
    write_shard,
)
from meshsar_builder.dataset.splits import make_split, write_split
from meshsar_builder.dataset.verify import verify
from meshsar_builder.geometry.meshfile import write_ply
from meshsar_builder.pipeline import recipe as R
from meshsar_builder.pipeline.errors import InputError
from meshsar_builder.pipeline.io import sha256_file, write_json
from meshsar_builder.pipeline.runner import Context, Results, run_stage
from meshsar_builder.radar.params import echo_grid, loss_grid
from stages import shards as shards_stage

# A tiny dataset layout shared by the shard, split, verify and reader tests.
V, C, H, W = 2, 2, 4, 4
ECHO = (V, 2, 2, 3)
LOSS = (V, 2, 2, 2)  # the loss grid: decimation (2, 2, 2) of a 4 x 4 x 4 full grid
METADATA = {
    "views": [{"name": "anterior", "u": [-1, 0, 0], "v": [0, 0, 1], "w": [0, 1, 0]},
              {"name": "left", "u": [0, -1, 0], "v": [0, 0, 1], "w": [-1, 0, 0]}],
    "fov_mm": 160.0, "image_size": [H, W], "channels": ["intensity", "depth"],
    "radar": {"f0_hz": 77e9, "aperture": [4, 4], "n_samples": 4, "echo_decimation": [2, 2, 1],
              "loss_decimation": [2, 2, 2]},
    "echo_grid": {"frequencies_hz": [77e9, 78e9, 79e9],
                  "positions_mm": {v: [[0.0, 0.0, 300.0]] * 4 for v in ("anterior", "left")}},
    "loss_grid": {"frequencies_hz": [77e9, 79e9],
                  "positions_mm": {v: [[0.0, 0.0, 300.0]] * 4 for v in ("anterior", "left")}},
}


def random_sample(rng: np.random.Generator, sid: str, meta: dict, n_verts: int | None = None,
                  n_faces: int | None = None, sar_shape=(V, C, H, W), echo_shape=ECHO, loss_shape=LOSS) -> Sample:
    n = int(rng.integers(3, 30)) if n_verts is None else n_verts
    m = int(rng.integers(0, 40)) if n_faces is None else n_faces
    sar = rng.random(sar_shape)
    sar[:, 1:] = rng.normal(size=sar[:, 1:].shape)  # depth-like channels are signed
    return Sample(
        sample_id=sid,
        verts=rng.normal(0, 40, (n, 3)).astype(np.float32),
        faces=rng.integers(0, max(n, 1), (m if n else 0, 3)),
        vert_labels=rng.integers(0, 8, n).astype(np.uint8),
        sar=sar.astype(np.float16),
        echo=(rng.normal(size=echo_shape) + 1j * rng.normal(size=echo_shape)).astype(np.complex64),
        echo_clean=(rng.normal(size=loss_shape) + 1j * rng.normal(size=loss_shape)).astype(np.complex64),
        noise_seed=rng.integers(0, 2**64, size=loss_shape[0], dtype=np.uint64),
        noise_sigma=rng.uniform(0.01, 1.0, loss_shape[0]),
        center_mm=rng.normal(0, 100, 3).astype(np.float32),
        meta=meta,
    )


def tiny_dataset(root: Path, n_ssm: int = 5, direct: tuple[int, ...] = (4, 4, 3), shard_size: int = 4,
                 seed: int = 0, split_seed: int = 0) -> tuple[dict, dict[str, Sample]]:
    """Write shards, index.json and splits/seed-<split_seed>.json of random samples; return (index, samples).

    n_ssm SSM samples (one subject each), then one direct subject per entry of
    `direct` with that many frames.
    """
    rng = np.random.default_rng(seed)
    metas = {f"ssm-{i:05d}": {"source": "phantom_wh", "subject": f"ssm-{i:05d}", "subset": "ssm", "frame": None}
             for i in range(n_ssm)}
    for j, frames in enumerate(direct):
        for f in range(frames):
            metas[f"phantom_bv-patient{j:03d}-frame{f:02d}"] = {
                "source": "phantom_bv", "subject": f"patient{j:03d}", "subset": "direct", "frame": f + 1}
    samples = {sid: random_sample(rng, sid, meta) for sid, meta in metas.items()}
    ids = list(samples)
    shards = []
    for k in range(0, len(ids), shard_size):
        file = f"shards/shard-{k // shard_size:05d}.npz"
        write_shard(root / file, [samples[s] for s in ids[k : k + shard_size]])
        shards.append({"file": file, "n": len(ids[k : k + shard_size]), "sha256": sha256_file(root / file),
                       "sample_ids": ids[k : k + shard_size]})
    index = build_index(recipe="tiny", recipe_sha256="0" * 64, code_version="test", metadata=METADATA,
                        shard_size=shard_size, shards=shards, metas=metas)
    write_json(root / "index.json", index)
    write_split(root, make_split(index, split_seed))
    return index, samples


def assert_same(a: Sample, b: Sample) -> None:
    assert a.sample_id == b.sample_id and a.meta == b.meta
    for name in ("verts", "faces", "vert_labels", "sar", "echo", "echo_clean", "noise_seed", "noise_sigma",
                 "center_mm"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.shape == y.shape and np.array_equal(x, y), name
        assert name not in ("echo_clean", "noise_seed", "noise_sigma") or x.dtype == y.dtype, name


sizes = st.lists(st.tuples(st.integers(0, 50), st.integers(0, 60)), min_size=1, max_size=6)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(sizes=sizes, seed=st.integers(0, 2**32 - 1))
def test_ragged_round_trip_is_exact(tmp_path, sizes, seed):
    rng = np.random.default_rng(seed)
    samples = [random_sample(rng, f"s{i}", {"i": i, "x": [1.5, None, "é"]}, n, m) for i, (n, m) in enumerate(sizes)]
    path = tmp_path / f"rt-{seed}.npz"
    write_shard(path, samples)
    for got, want in zip(read_shard(path), samples, strict=True):
        assert_same(got, want)
    mapped = Shard(path)
    for i, want in enumerate(samples):
        assert_same(mapped[i], want)
    with np.load(path, allow_pickle=False) as z:
        assert z.files == list(SHARD_KEYS)
        assert z["sample_id"].dtype.kind == "U" and z["meta"].dtype.kind == "U"
        assert z["verts"].shape == (sum(n for n, _ in sizes), 3) and z["vert_offsets"].dtype == np.int64
        assert z["faces"].dtype == np.int32 and z["sar"].shape == (len(sizes), V, C, H, W)
        assert z["echo_clean"].shape == (len(sizes), *LOSS) and z["echo_clean"].dtype == np.complex64
        assert z["noise_seed"].shape == (len(sizes), V) and z["noise_seed"].dtype == np.uint64
        assert z["noise_sigma"].shape == (len(sizes), V) and z["noise_sigma"].dtype == np.float64
        assert json.loads(z["meta"][0]) == {"i": 0, "x": [1.5, None, "é"]}


def test_writes_are_byte_identical(tmp_path):
    samples = [random_sample(np.random.default_rng(1), f"s{i}", {}) for i in range(3)]
    write_shard(tmp_path / "a.npz", samples)
    write_shard(tmp_path / "b.npz", samples)
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "b.npz"]  # no temporaries left


@pytest.mark.parametrize("damage", ["truncate", "garbage", "empty", "object"])
def test_bad_shards_raise_input_error_naming_the_file(tmp_path, damage):
    path = tmp_path / "shard-00000.npz"
    write_shard(path, [random_sample(np.random.default_rng(2), "s0", {})])
    data = path.read_bytes()
    if damage == "truncate":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        path.write_bytes(b"not a zip file at all" * 10)
    elif damage == "empty":
        path.write_bytes(b"")
    else:
        with open(path, "wb") as f:
            np.savez(f, sample_id=np.array([{"a": 1}], dtype=object))
    for reader in (read_shard, Shard):
        with pytest.raises(InputError, match="shard-00000.npz"):
            reader(path)


def test_missing_array_is_named(tmp_path):
    path = tmp_path / "s.npz"
    with open(path, "wb") as f:
        np.savez(f, sample_id=np.array(["a"]), verts=np.zeros((0, 3), np.float32))
    with pytest.raises(InputError, match=r"s.npz: not a valid shard: missing array 'vert_offsets'"):
        Shard(path)


def test_pack_refuses_bad_samples(tmp_path):
    rng = np.random.default_rng(3)
    bad_faces = random_sample(rng, "bad", {}, n_verts=4, n_faces=2)
    bad_faces.faces[0, 0] = 4
    with pytest.raises(ValueError, match="bad: face indices out of range"):
        write_shard(tmp_path / "x.npz", [bad_faces])
    other_sar = random_sample(rng, "b", {}, sar_shape=(V, 1, H, W))
    with pytest.raises(ValueError, match="b: sar"):
        write_shard(tmp_path / "x.npz", [random_sample(rng, "a", {}), other_sar])
    with pytest.raises(ValueError, match="distinct"):
        write_shard(tmp_path / "x.npz", [random_sample(rng, "a", {}), random_sample(rng, "a", {})])
    with pytest.raises(ValueError, match="c: echo_clean"):
        write_shard(tmp_path / "x.npz", [random_sample(rng, "a", {}),
                                         random_sample(rng, "c", {}, loss_shape=(V, 2, 2, 3))])
    no_seeds = random_sample(rng, "d", {})
    no_seeds.noise_seed = no_seeds.noise_seed[:1]
    with pytest.raises(ValueError, match="d: need echo .* noise_seed"):
        write_shard(tmp_path / "x.npz", [no_seeds])
    with pytest.raises(ValueError, match="nan: meta is not plain JSON"):
        write_shard(tmp_path / "x.npz", [random_sample(rng, "nan", {"x": float("nan")})])
    assert not (tmp_path / "x.npz").exists()


# ---------------------------------------------------------------- the stage

STAGE_RECIPE = """\
name = "tiny"
seed = 3
[[sources]]
kind = "phantom"
subjects = 3
[radar]
aperture = [8, 8]
n_samples = 8
echo_decimation = [4, 4, 2]
views = ["anterior", "left"]
[images]
size = 8
[shards]
shard_size = {shard_size}
[splits]
seed = 5
ratios = {{ train = 0.5, val = 0.25, test = 0.25 }}
"""


def fake_radar_outputs(out: Path, recipe: R.Recipe, n_ssm: int = 3, frames: int = 3) -> Results:
    """What the radar stage leaves behind (meshes, npz files, sidecar records), from random arrays."""
    rng = np.random.default_rng(11)
    grid, loss = echo_grid(recipe.radar), loss_grid(recipe.radar)
    n_views, n_pos, n_freq = len(recipe.radar.views), len(grid["positions_mm"]["anterior"]), len(grid["frequencies_hz"])
    side = int(round(np.sqrt(n_pos)))
    loss_side = int(round(np.sqrt(len(loss["positions_mm"]["anterior"]))))
    records = {}
    metas = [(f"ssm-{i:05d}", {"source": "phantom_wh", "subject": f"ssm-{i:05d}", "subset": "ssm"}) for i in range(n_ssm)]
    metas += [(f"phantom_bv-patient001-frame{f:02d}", {"source": "phantom_bv", "subject": "patient001",
                                                        "subset": "direct", "frame": f}) for f in range(1, frames + 1)]
    for sid, meta in metas:
        s = random_sample(rng, sid, meta, n_verts=12, n_faces=20, sar_shape=(n_views, 2, 8, 8),
                          echo_shape=(n_views, side, side, n_freq),
                          loss_shape=(n_views, loss_side, loss_side, len(loss["frequencies_hz"])))
        mesh = out / "remesh" / f"{sid}.ply"
        write_ply(mesh, s.verts.astype(np.float64) + 500, s.faces, s.vert_labels)
        (out / "radar").mkdir(parents=True, exist_ok=True)
        with open(out / "radar" / f"{sid}.npz", "wb") as f:
            np.savez(f, sar=s.sar, echo=s.echo, echo_clean=s.echo_clean, noise_seed=s.noise_seed,
                     noise_sigma=s.noise_sigma, center_mm=np.full(3, 500, np.float32))
        records[sid] = {"item": sid, "inputs": {str(mesh): sha256_file(mesh)}, "mesh": str(mesh), "meta": meta}
    return Results(done={"radar": records})


def build_shards(out: Path, shard_size: int = 4) -> tuple[Context, Results]:
    recipe = R.parse(STAGE_RECIPE.format(shard_size=shard_size), "tiny.toml")
    ctx = Context(out=out, recipe=recipe)
    results = fake_radar_outputs(out, recipe)
    row = run_stage(ctx, shards_stage.STAGE, results, pool=None)
    assert row["failed"] == 0, results.failures
    shards_stage.finish(ctx, results)
    return ctx, results


def test_stage_writes_verified_shards_index_and_default_split(tmp_path):
    out = tmp_path / "build"
    ctx, results = build_shards(out, shard_size=4)
    assert verify(out) == []
    index = read_index(out)
    radar_order = list(results.of("radar"))
    assert [s["file"] for s in index["shards"]] == ["shards/shard-00000.npz", "shards/shard-00001.npz"]
    assert [sid for s in index["shards"] for sid in s["sample_ids"]] == radar_order
    assert [s["n"] for s in index["shards"]] == [4, 2]
    assert index["recipe"] == "tiny" and index["recipe_sha256"] == ctx.recipe.sha256
    assert [v["name"] for v in index["views"]] == ["anterior", "left"] and index["image_size"] == [8, 8]
    assert index["counts"]["subset"] == {"ssm": 3, "direct": 3} and index["counts"]["subjects"] == {"ssm": 3, "direct": 1}
    assert index["samples"]["phantom_bv-patient001-frame02"]["subject"] == "patient001"
    split = json.loads((out / "splits" / "seed-5.json").read_text())
    assert split["ratios"] == {"train": 0.5, "val": 0.25, "test": 0.25}
    assert sorted(split["train"] + split["val"] + split["test"]) == sorted(radar_order)
    first = read_shard(out / "shards" / "shard-00000.npz")[0]
    # Heart frame: the mesh was written at +500 mm with center_mm 500.
    assert np.allclose(first.center_mm, 500) and abs(first.verts.mean()) < 100
    assert first.meta == results.of("radar")["ssm-00000"]["meta"]


def test_rebuild_is_byte_identical_and_skips(tmp_path):
    build_shards(tmp_path / "a")
    build_shards(tmp_path / "b")
    a, b = read_index(tmp_path / "a"), read_index(tmp_path / "b")
    assert [s["sha256"] for s in a["shards"]] == [s["sha256"] for s in b["shards"]]
    assert (tmp_path / "a" / "index.json").read_bytes() == (tmp_path / "b" / "index.json").read_bytes()
    assert (tmp_path / "a/splits/seed-5.json").read_bytes() == (tmp_path / "b/splits/seed-5.json").read_bytes()
    ctx, results = build_shards(tmp_path / "a")
    assert results.summary[-1]["skipped"] == 2 and results.summary[-1]["ran"] == 0
    assert (tmp_path / "a" / "index.json").read_bytes() == (tmp_path / "b" / "index.json").read_bytes()


def test_larger_shards_replace_the_old_ones(tmp_path):
    out = tmp_path / "build"
    build_shards(out, shard_size=2)
    assert len(list((out / "shards").glob("*.npz"))) == 3
    build_shards(out, shard_size=5)
    assert sorted(p.name for p in (out / "shards").iterdir()) == [
        "shard-00000.json", "shard-00000.npz", "shard-00001.json", "shard-00001.npz"]
    assert verify(out) == []


# ---------------------------------------------------------------- format 2: the loss grid's target


def test_index_and_shards_carry_the_loss_grid(tmp_path):
    out = tmp_path / "build"
    ctx, results = build_shards(out)
    index = read_index(out)
    assert index["format_version"] == 2
    assert index["radar"]["loss_decimation"] == list(ctx.recipe.radar.loss_decimation) == [1, 1, 4]
    grid = index["loss_grid"]
    assert set(grid) == {"frequencies_hz", "positions_mm"} and len(grid["frequencies_hz"]) == 2
    assert {v: len(p) for v, p in grid["positions_mm"].items()} == {"anterior": 64, "left": 64}
    sample = read_shard(out / "shards" / "shard-00000.npz")[0]
    assert sample.echo_clean.shape == (2, 8, 8, 2) and sample.noise_seed.dtype == np.uint64
    with np.load(out / "shards" / "shard-00000.npz", allow_pickle=False) as z:
        assert z["echo_clean"].shape == (4, 2, 8, 8, 2) and z["noise_sigma"].shape == (4, 2)


def test_recorded_loss_echo_is_clean_plus_the_seeded_noise(tmp_path):
    from meshsar_builder.radar.noise import unit_noise

    sample = random_sample(np.random.default_rng(5), "s", {})
    noisy = recorded_loss_echo(sample, METADATA)
    assert noisy.shape == LOSS and noisy.dtype == np.complex64
    for v in range(V):
        unit = unit_noise((4, 4, 4), sample.noise_seed[v])[np.ix_([0, 2], [0, 2], [0, 2])]
        want = (sample.echo_clean[v].astype(np.complex128) + sample.noise_sigma[v] * unit).astype(np.complex64)
        assert np.array_equal(noisy[v], want)
    sample.noise_sigma[:] = 0
    assert np.array_equal(recorded_loss_echo(sample, METADATA), sample.echo_clean)


def write_format_1(root: Path) -> Path:
    """A format-1 build folder: shards without the loss grid's arrays, index format_version 1."""
    tiny_dataset(root)
    index = json.loads((root / "index.json").read_text())
    index["format_version"] = 1
    del index["loss_grid"]
    write_json(root / "index.json", index)
    path = root / index["shards"][0]["file"]
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k not in ADDED_IN_FORMAT_2}
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    return path


def test_old_format_is_refused_with_how_to_rebuild(tmp_path):
    root = tmp_path / "old"
    shard = write_format_1(root)
    with pytest.raises(InputError) as info:
        read_index(root)
    message = str(info.value)
    assert str(root / "index.json") in message and "format_version 1" in message and "format 2" in message
    assert f"meshsar build {root}/recipe.toml --out {root} --force radar" in message
    for reader in (Shard, read_shard):
        with pytest.raises(InputError) as info:
            reader(shard)
        message = str(info.value)
        assert str(shard) in message and "format-1 shard (no echo_clean, noise_seed, noise_sigma)" in message
        assert f"meshsar build {root}/recipe.toml --out {root} --force radar" in message
    problems = verify(root)
    assert len(problems) == 1 and "format_version 1" in problems[0] and "--force radar" in problems[0]
