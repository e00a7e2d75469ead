"""Stage `shards`: the radar stage's samples packed into shards, then index.json and the default split.

Order: the radar stage's plan order (SSM samples in sample order, then the
direct meshes source by source as the recipe lists them, frames in order),
cut into runs of `shards.shard_size`; shard k is the item `shard-<k:05d>`,
written to `shards/shard-<k:05d>.npz`. Its inputs are each sample's radar npz
and mesh PLY; its params hold the sample ids and metas, so a changed sample
rewrites only its shard.

index.json needs every shard's sha256, so it cannot be an item of the same
stage (items run side by side, in no order). `finish` writes it, in the main
process, after the stage's items are all done or skipped (the runner calls it
once per build): from the items' sidecar records alone (digests, sample ids)
and the radar records (metas), so it reads no shard and is rewritten on every
build, byte-identical while nothing changed. It also writes the recipe's
default split and removes shard files of an earlier, larger plan.
"""

from __future__ import annotations

import numpy as np

from meshsar_builder.dataset.shards import FORMAT_VERSION, INDEX_NAME, SHARD_DIR, Sample, build_index, write_shard
from meshsar_builder.dataset.splits import make_split, write_split
from meshsar_builder.geometry.meshfile import read_ply
from meshsar_builder.pipeline.io import write_json
from meshsar_builder.pipeline.runner import Context, Item, Results, Stage, code_version
from meshsar_builder.radar.params import index_metadata

NAME = SHARD_DIR  # the stage folder is the index's shard folder


def plan(ctx: Context, results: Results) -> list[Item]:
    radar = ctx.stage_dir("radar")
    samples = [(sid, str(radar / f"{sid}.npz"), rec["mesh"], rec["meta"]) for sid, rec in results.of("radar").items()]
    size = ctx.recipe.shards.shard_size
    items = []
    for k in range(0, len(samples), size):
        chunk = samples[k : k + size]
        inputs = tuple(p for _, npz, mesh, _ in chunk for p in (npz, mesh))
        params = {"format_version": FORMAT_VERSION, "samples": [{"id": sid, "meta": meta} for sid, _, _, meta in chunk]}
        items.append(Item(f"shard-{k // size:05d}", (f"shard-{k // size:05d}.npz",), inputs=inputs, params=params))
    return items


def run(ctx: Context, item: Item) -> dict:
    samples = []
    for entry, (npz_path, mesh_path) in zip(item.params["samples"], zip(item.inputs[::2], item.inputs[1::2])):
        verts, faces, labels = read_ply(mesh_path)
        with np.load(npz_path, allow_pickle=False) as z:
            sar, echo, center = z["sar"], z["echo"], z["center_mm"]
            clean, seed, sigma = z["echo_clean"], z["noise_seed"], z["noise_sigma"]
        samples.append(Sample(
            sample_id=entry["id"],
            verts=verts - center.astype(np.float64),
            faces=faces,
            vert_labels=labels if labels is not None else np.zeros(len(verts), np.uint8),
            sar=sar, echo=echo, echo_clean=clean, noise_seed=seed, noise_sigma=sigma, center_mm=center,
            meta=entry["meta"],
        ))
    write_shard(ctx.stage_dir(NAME) / f"{item.id}.npz", samples)
    return {"n": len(samples), "sample_ids": [s.sample_id for s in samples]}


def finish(ctx: Context, results: Results) -> dict:
    """Write OUT/index.json and OUT/splits/seed-<S>.json from the done shard items; drop stale shard files.

    Shards whose item failed are left out of the index (the failure is in
    failures.json). Returns {"shards", "samples", "split"} for the log.
    """
    recipe, done = ctx.recipe, results.of(NAME)
    stage_dir = ctx.stage_dir(NAME)
    shards, metas = [], {}
    for item_id, rec in done.items():
        file = f"{item_id}.npz"
        shards.append({"file": f"{NAME}/{file}", "n": rec["n"], "sha256": rec["outputs"][file],
                       "sample_ids": rec["sample_ids"]})
    for rec in results.of("radar").values():
        metas[rec["item"]] = rec["meta"]
    for path in sorted(stage_dir.glob("shard-*")):
        if path.stem not in done:  # an earlier plan's shard, or one whose item failed now
            path.unlink()
    index = build_index(
        recipe=recipe.name, recipe_sha256=recipe.sha256, code_version=code_version(STAGE),
        metadata=index_metadata(recipe.radar, recipe.images), shard_size=recipe.shards.shard_size,
        shards=shards, metas=metas,
    )
    write_json(ctx.out / INDEX_NAME, index)
    split = make_split(index, recipe.splits.seed, recipe.splits.ratios, recipe.splits.group_by)
    path = write_split(ctx.out, split)
    return {"shards": len(shards), "samples": index["n_samples"], "split": str(path)}


# Version 2: format 2 (echo_clean, noise_seed, noise_sigma; loss_grid in the index).
STAGE = Stage(name=NAME, version=2, plan=plan, run=run, finish=finish)
