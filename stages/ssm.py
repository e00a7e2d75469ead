"""Stage `ssm`: the statistical shape model of the registered subjects, and its samples.

Item `model`: Procrustes + PCA over every registered subject, `ssm/model.npz` (mean, modes,
variances, template faces, per-vertex labels) and the model's compactness and
generalisation. Items `samples/<c>` (side by side with it) each use the same model (a worker
builds it once for its items) and draw `ssm.samples_per_item` consecutive samples of the
`ssm.samples` shapes: `ssm/samples/ssm-NNNNN.ply`. Items `specificity/<c>`
(`ssm.specificity_items` of them, listed first: the longest) use it too and make every
items-th of the `ssm.specificity_samples` specificity draws per mode count through the
samples' own sampler (redraws included), from their own seed: `ssm/specificity/<c>.npz`.
Once all are done, `ssm/report.json` (the stage's finish) holds compactness, generalisation
and specificity per number of modes (vertex to vertex), the samples' redraws and the
per-subject registration figures. Each sample is drawn from its own seed (recipe seed,
stage, sample id), so a sample does not change when the sample count or the split into items
does; self-intersecting draws are redrawn and counted. The model's frame is the template's
(register/template.ply: canonical pose), and its modes have a fixed sign, so the order of
the subjects changes nothing (version 3).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
from tqdm import tqdm

from meshsar_builder.geometry.meshfile import read_ply, write_ply
from meshsar_builder.geometry.ssm import (
    build_model, model_quality, sample_valid, save_model, specificity_draws, specificity_summary)
from meshsar_builder.pipeline.errors import MeshError
from meshsar_builder.pipeline.io import atomic_path, sha256_file, write_json
from meshsar_builder.pipeline.runner import Context, Item, Results, Stage
from meshsar_builder.pipeline.seeding import item_rng

NAME = "ssm"
MIN_SUBJECTS = 3  # a mean and one mode from two shapes is their difference: no model of a population


def sample_ids(ctx: Context) -> list[str]:
    return [f"ssm-{i:05d}" for i in range(ctx.recipe.ssm.samples)]


def plan(ctx: Context, results: Results) -> list[Item]:
    registered = results.of("register")
    if not registered:
        return []
    if len(registered) < MIN_SUBJECTS or not next(iter(registered.values()))["final"]:
        # Too few fits, or rounds that stopped short of their template: one failed item says why, not every item.
        why = (f"the shape model needs at least {MIN_SUBJECTS} registered subjects, and registration kept "
               f"{len(registered)} ({', '.join(sorted(registered))}); failures.json names the fits it rejected")
        return [Item("model", ("model.npz",), params=dataclasses.asdict(ctx.recipe.ssm), data={"refused": why})]
    template = str(ctx.stage_dir("register") / "template.ply")
    inputs = (template, *(str(ctx.stage_dir("register") / f"{i}.ply") for i in registered))
    params = dataclasses.asdict(ctx.recipe.ssm)
    fits = {i: rec["fit"] | {"subject": rec["subject"], "source": rec["source"]} for i, rec in registered.items()}
    sources = sorted({rec["source"] for rec in registered.values()})
    model = Item("model", ("model.npz",), inputs=inputs, params=params, data={"fits": fits})
    samples = [Item(part, tuple(f"samples/{sid}.ply" for sid in ids), inputs=inputs, params=params,
                    data={"sources": sources, "samples": ids}) for part, ids in sample_parts(ctx).items()]
    # Longest first, so that the short sample parts even out the workers' ends: scheduled from a paper-scale
    # build's item times, 61.1 s on two workers against 62.4 s with the model and the samples first.
    return [*(Item(part, (f"{part}.npz",), inputs=inputs, params=params, data={}) for part in specificity_parts(ctx)),
            model, *samples]


def sample_parts(ctx: Context) -> dict[str, list[str]]:
    """Item id -> the consecutive sample ids it draws, ssm.samples_per_item of them."""
    ids, size = sample_ids(ctx), ctx.recipe.ssm.samples_per_item
    return {f"samples/{c}": ids[start:start + size] for c, start in enumerate(range(0, len(ids), size))}


def specificity_parts(ctx: Context) -> list[str]:
    return [f"specificity/{c}" for c in range(ctx.recipe.ssm.specificity_items)]


def _model(ctx: Context, item: Item):
    """The shape model of the item's inputs (every item builds it alike) and the registered shapes."""
    params = ctx.recipe.ssm
    return _built_model(tuple((p, sha256_file(p)) for p in item.inputs), params.variance, params.procrustes_iterations)


@functools.lru_cache(maxsize=1)
def _built_model(inputs: tuple[tuple[str, str], ...], variance: float, procrustes_iterations: int):
    """The model of these (path, content digest) inputs: built once per worker process, which runs several of
    the stage's items (0.2 s an item at paper scale). Its arrays are read-only, as the items share them."""
    template, faces, labels = read_ply(inputs[0][0])
    shapes = np.stack([read_ply(p)[0] for p, _ in inputs[1:]])
    if len(shapes) < MIN_SUBJECTS:
        raise MeshError(f"shape model: needs at least {MIN_SUBJECTS} registered subjects, got {len(shapes)}")
    # The template's frame (register: the groupwise template in its canonical pose), so the
    # model's pose does not follow whichever subject was listed first.
    model = build_model(shapes, faces, variance, procrustes_iterations, labels=labels, reference=template)
    for array in (model.mean, model.modes, model.variances, model.faces, model.labels, shapes):
        if array is not None:
            array.flags.writeable = False
    return model, shapes


def run(ctx: Context, item: Item) -> dict:
    params, folder = ctx.recipe.ssm, ctx.stage_dir(NAME)
    if "refused" in item.data:
        raise MeshError(item.data["refused"])
    model, shapes = _model(ctx, item)
    if item.id.startswith("specificity/"):  # a share of the draws: every items-th draw per mode count
        part = int(item.id.rsplit("/", 1)[1])
        count = len(range(part, params.specificity_samples, params.specificity_items))
        distances, redraws = specificity_draws(model, shapes, item_rng(ctx.recipe.seed, NAME, item.id), params, count)
        with atomic_path(folder / f"{item.id}.npz") as tmp:
            np.savez(tmp, distances=distances, redraws=redraws)
        return {"specificity_draws": count, "specificity_redraws": redraws}
    if item.id.startswith("samples/"):
        samples = {}
        for sid in tqdm(item.data["samples"], desc=item.id, leave=False, disable=len(item.data["samples"]) < 100):
            coeffs, verts, n = sample_valid(model, item_rng(ctx.recipe.seed, NAME, sid), params)
            write_ply(folder / "samples" / f"{sid}.ply", verts, model.faces, model.labels)
            samples[sid] = {"coeffs": np.round(coeffs, 6).tolist(), "redraws": n}
        return {"sources": item.data["sources"], "samples": samples}
    save_model(folder / "model.npz", model)
    report = {
        **model_quality(model, shapes, params),
        "subjects": len(shapes),
        "n_vertices": int(len(model.mean)),
        "total_variance_mm2": model.total_variance,
        "registration": item.data["fits"],
    }
    return {"modes": report["modes"], "report": report}


def finish(ctx: Context, results: Results) -> None:
    """ssm/report.json: the model item's figures and the specificity of every part's draws,
    once all of them are done (a failed part leaves no report)."""
    records = results.of(NAME)
    parts, sampled = specificity_parts(ctx), list(sample_parts(ctx))
    if "model" not in records or any(part not in records for part in parts + sampled):
        return
    folder = ctx.stage_dir(NAME)
    draws = [np.load(folder / f"{part}.npz") for part in parts]
    distances = np.concatenate([d["distances"] for d in draws], axis=1)
    summary = specificity_summary(distances, sum(int(d["redraws"]) for d in draws))
    drawn = [s for part in sampled for s in records[part]["samples"].values()]
    samples = {"samples": len(drawn), "self_intersection_redraws": sum(s["redraws"] for s in drawn)}
    write_json(folder / "report.json", {**records["model"]["report"], **samples, **summary})


# Version 5: the samples in parts of samples_per_item, side by side (v4: the specificity draws in
# specificity_items parts).
# Version 6: specificity distances summed in one numba pass (last-bit changes); the self-intersection test's
# shared-vertex shortcut and the array-speed PLY writer change no byte.
STAGE = Stage(name=NAME, version=6, plan=plan, run=run, finish=finish, after=("register",))
