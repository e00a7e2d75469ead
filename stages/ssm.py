"""Stage `ssm`: the statistical shape model of the registered subjects, and its samples.

One item, `model`, since every sample depends on the model: Procrustes + PCA
over every registered subject, `ssm/model.npz` (mean, modes, variances,
template faces, per-vertex labels), `ssm/report.json` (compactness,
generalisation and specificity per number of modes, vertex to vertex; specificity
from `ssm.specificity_samples` draws per mode count through the samples' own
sampler, redraws included; per-subject registration figures), and
`ssm/samples/<source>-ssmNNNNN.ply` for `ssm.samples` shapes. Each sample is
drawn from its own seed (recipe seed, stage, sample id), so a sample does not
change when the sample count does; self-intersecting draws are redrawn and
counted. The model's frame is the template's (register/template.ply: canonical pose),
and its modes have a fixed sign, so the order of the subjects changes nothing (version 3).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from meshsar_builder.geometry.meshfile import read_ply, write_ply
from meshsar_builder.geometry.ssm import build_model, quality_report, sample_valid, save_model
from meshsar_builder.pipeline.errors import MeshError
from meshsar_builder.pipeline.io import write_json
from meshsar_builder.pipeline.runner import Context, Item, Results, Stage
from meshsar_builder.pipeline.seeding import item_rng

NAME = "ssm"


def sample_ids(ctx: Context) -> list[str]:
    return [f"ssm-{i:05d}" for i in range(ctx.recipe.ssm.samples)]


def plan(ctx: Context, results: Results) -> list[Item]:
    registered = results.of("register")
    if not registered:
        return []
    template = str(ctx.stage_dir("register") / "template.ply")
    inputs = (template, *(str(ctx.stage_dir("register") / f"{i}.ply") for i in registered))
    outputs = ("model.npz", "report.json", *(f"samples/{s}.ply" for s in sample_ids(ctx)))
    fits = {i: rec["fit"] | {"subject": rec["subject"], "source": rec["source"]} for i, rec in registered.items()}
    sources = sorted({rec["source"] for rec in registered.values()})
    return [Item("model", outputs, inputs=inputs, params=dataclasses.asdict(ctx.recipe.ssm),
                 data={"fits": fits, "sources": sources})]


def run(ctx: Context, item: Item) -> dict:
    params = ctx.recipe.ssm
    template, faces, labels = read_ply(item.inputs[0])
    shapes = np.stack([read_ply(p)[0] for p in item.inputs[1:]])
    if len(shapes) < 3:
        raise MeshError(f"shape model: needs at least 3 registered subjects, got {len(shapes)}")
    # The template's frame (register: the groupwise template in its canonical pose), so the
    # model's pose does not follow whichever subject was listed first.
    model = build_model(shapes, faces, params.variance, params.procrustes_iterations, labels=labels, reference=template)
    folder = ctx.stage_dir(NAME)
    save_model(folder / "model.npz", model)
    samples, redraws = {}, 0
    for sid in sample_ids(ctx):
        coeffs, verts, n = sample_valid(model, item_rng(ctx.recipe.seed, NAME, sid), params)
        write_ply(folder / "samples" / f"{sid}.ply", verts, model.faces, model.labels)
        samples[sid] = {"coeffs": np.round(coeffs, 6).tolist(), "redraws": n}
        redraws += n
    quality = quality_report(model, shapes, item_rng(ctx.recipe.seed, NAME, "quality"), params)
    report = {
        **quality,
        "subjects": len(shapes),
        "n_vertices": int(len(model.mean)),
        "total_variance_mm2": model.total_variance,
        "samples": len(samples),
        "self_intersection_redraws": redraws,
        "registration": item.data["fits"],
    }
    write_json(folder / "report.json", report)
    return {"sources": item.data["sources"], "samples": samples, "modes": quality["modes"],
            "self_intersection_redraws": redraws}


STAGE = Stage(name=NAME, version=3, plan=plan, run=run)
