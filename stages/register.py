"""Stage `register`: the template fitted to every shape-model subject (DESIGN section 6).

Only sources with `use = "ssm"` are registered. The template is the remeshed
surface of the reference subject (`registration.template`: the median-volume
subject or a subject id), simplified to `registration.template_vertices`; it is
made while planning, since every item depends on it, and written as
`register/template.ply` with `register/template.json`.

Outputs: `register/<item>.ply`, the template's faces and labels on the fitted
vertices, and a sidecar with the fit report (surface distances, per-structure
label agreement, the label landmarks used). A fit outside the thresholds
(surface distance, folds, per-structure label agreement) is a named failure,
not a silent bad shape. Version 2: label-aware matches and label landmarks.
"""

from __future__ import annotations

import dataclasses

from meshsar_builder.geometry.meshfile import read_ply, write_ply
from meshsar_builder.geometry.meshing import transfer_labels
from meshsar_builder.geometry.registration import accept, choose_template, register
from meshsar_builder.geometry.remesh import simplify
from meshsar_builder.pipeline.errors import MeshError
from meshsar_builder.pipeline.io import read_json, sha256_file, write_json
from meshsar_builder.pipeline.runner import Context, Item, Results, Stage
from meshsar_builder.pipeline.seeding import item_rng

NAME = "register"


def ssm_subjects(results: Results) -> dict[str, dict]:
    return {i: rec for i, rec in results.of("remesh").items() if rec["use"] == "ssm"}


def resolve_template(name: str, subjects: dict[str, dict]) -> str:
    """`median`, an item id, or a subject name (as in the source) -> item id."""
    if name == "median" or name in subjects:
        return name
    matches = [i for i, rec in subjects.items() if rec["subject"] == name]
    if len(matches) != 1:
        raise MeshError(f"registration.template: {name!r} names {len(matches)} of the registered subjects")
    return matches[0]


def ensure_template(ctx: Context, subjects: dict[str, dict]) -> str:
    """Write register/template.ply unless it is up to date; return its path."""
    params = ctx.recipe.registration
    volumes = {i: rec["volume_ml"] for i, rec in subjects.items()}
    chosen = choose_template(volumes, resolve_template(params.template, subjects))
    source = ctx.stage_dir("remesh") / f"{chosen}.ply"
    folder = ctx.stage_dir(NAME)
    want = {"subject": chosen, "source_sha256": sha256_file(source), "template_vertices": params.template_vertices}
    path, meta = folder / "template.ply", folder / "template.json"
    if path.exists() and meta.exists() and {k: read_json(meta).get(k) for k in want} == want:
        return str(path)
    verts, faces, labels = read_ply(source)
    t_verts, t_faces = simplify(verts, faces, params.template_vertices)
    write_ply(path, t_verts, t_faces, transfer_labels(verts, labels, t_verts))
    write_json(meta, {**want, "n_vertices": len(t_verts), "n_faces": len(t_faces), "volumes_ml": volumes})
    return str(path)


def plan(ctx: Context, results: Results) -> list[Item]:
    subjects = ssm_subjects(results)
    if not subjects:
        return []
    template = ensure_template(ctx, subjects)
    params = dataclasses.asdict(ctx.recipe.registration)
    return [
        Item(i, (f"{i}.ply",), inputs=(str(ctx.stage_dir("remesh") / f"{i}.ply"), template), params=params,
             data={k: rec[k] for k in ("source", "subject", "frame", "phase", "provenance")})
        for i, rec in subjects.items()
    ]


def run(ctx: Context, item: Item) -> dict:
    subject_path, template_path = item.inputs
    s_verts, s_faces, s_labels = read_ply(subject_path)
    t_verts, t_faces, t_labels = read_ply(template_path)
    rng = item_rng(ctx.recipe.seed, NAME, item.id)
    fitted, report = register(t_verts, t_faces, s_verts, s_faces, ctx.recipe.registration, rng, t_labels, s_labels)
    accept(report, ctx.recipe.registration)
    write_ply(ctx.stage_dir(NAME) / f"{item.id}.ply", fitted, t_faces, t_labels)
    return {"fit": report, **item.data}


STAGE = Stage(name=NAME, version=2, plan=plan, run=run)
