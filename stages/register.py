"""Stage `register`: a groupwise template fitted to every shape-model subject (DESIGN section 6).

Only sources with `use = "ssm"` are registered, in rounds, each a pass of the stage (one
item per subject, side by side; runner.Stage.again):

- round 0: the template is the remeshed surface of the reference subject
  (`registration.template`: the median-volume subject or a subject id), simplified to
  `registration.template_vertices`: `register/template-0.ply`;
- round r >= 1: the template is the Procrustes mean of round r-1's fits, smoothed clean
  if it folds, in its canonical frame, with round 0's faces and labels
  (geometry/groupwise.py): `register/template-<r>.ply`, its json with the movement from
  the previous template;
- the last round is round `groupwise_rounds`, or the first round r >= 1 whose template
  moved less than `groupwise_converge_mm`.

A template is made while planning its round, since every item of the round depends on
it, and is kept when its json still names the same inputs. Fits of earlier rounds are
`register/round<r>/<item>.ply` (with their sidecars); the last round's are
`register/<item>.ply`, the template's faces and labels on the fitted vertices, with a
sidecar holding the fit report (surface distances, per-structure label agreement, the
label landmarks used) and the round. `register/template.ply` is the template of the last
round (the model's frame, stages/ssm.py); `register/groupwise.json` records every round:
template movement, smoothing, fits accepted, their distances, label agreement and time.
A fit outside the thresholds (surface distance, folds, and in the last round per-structure
label agreement) is a named failure, not a silent bad shape. Version 3: groupwise
template; version 4: label agreement by face strip (landmarks.label_agreement), judged in
the last round only; version 5: second-order NRICP stiffness and its schedule (nricp.py).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from meshsar_builder.geometry.groupwise import final_round, mean_template
from meshsar_builder.geometry.meshfile import read_ply, write_ply
from meshsar_builder.geometry.meshing import transfer_labels
from meshsar_builder.geometry.registration import accept, choose_template, register
from meshsar_builder.geometry.remesh import simplify
from meshsar_builder.pipeline.errors import MeshError
from meshsar_builder.pipeline.io import read_json, sha256_file, write_bytes, write_json
from meshsar_builder.pipeline.runner import Context, Item, Results, Stage
from meshsar_builder.pipeline.seeding import item_rng

NAME = "register"
# These decide how many rounds run, not what one fit gives (the template's digest carries
# the smoothing), so a change does not redo the rounds already done.
ROUND_KEYS = ("groupwise_rounds", "groupwise_converge_mm", "groupwise_smoothing", "groupwise_max_distance_mm")


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


def _current(meta, want: dict) -> bool:
    return meta.exists() and {k: read_json(meta).get(k) for k in want} == want


def seed_template(ctx: Context, subjects: dict[str, dict]) -> str:
    """Write register/template-0.ply (the reference subject) unless it is up to date; return its path."""
    params = ctx.recipe.registration
    volumes = {i: rec["volume_ml"] for i, rec in subjects.items()}
    chosen = choose_template(volumes, resolve_template(params.template, subjects))
    source = ctx.stage_dir("remesh") / f"{chosen}.ply"
    folder = ctx.stage_dir(NAME)
    want = {"round": 0, "subject": chosen, "source_sha256": sha256_file(source),
            "template_vertices": params.template_vertices}
    path, meta = folder / "template-0.ply", folder / "template-0.json"
    if path.exists() and _current(meta, want):
        return str(path)
    verts, faces, labels = read_ply(source)
    t_verts, t_faces = simplify(verts, faces, params.template_vertices)
    write_ply(path, t_verts, t_faces, transfer_labels(verts, labels, t_verts))
    write_json(meta, {**want, "n_vertices": len(t_verts), "n_faces": len(t_faces), "volumes_ml": volumes})
    return str(path)


def groupwise_template(ctx: Context, round_: int, fits: dict[str, dict]) -> tuple[str, float]:
    """Write register/template-<round_>.ply, the mean of the previous round's fits (records by
    item id), unless it is up to date; return its path and its movement from the previous one (mm)."""
    folder = ctx.stage_dir(NAME)
    previous = folder / f"template-{round_ - 1}.ply"
    want = {"round": round_, "previous_sha256": sha256_file(previous),
            "fits": {i: rec["outputs"][f"{i}.ply"] for i, rec in fits.items()},
            "smoothing": ctx.recipe.registration.groupwise_smoothing,
            "max_distance_mm": ctx.recipe.registration.groupwise_max_distance_mm}
    path, meta = folder / f"template-{round_}.ply", folder / f"template-{round_}.json"
    if path.exists() and _current(meta, want):
        return str(path), read_json(meta)["movement_mm"]
    t_verts, t_faces, t_labels = read_ply(previous)
    shapes = np.stack([read_ply(folder / f"{i}.ply")[0] for i in fits])
    verts, report = mean_template(shapes, t_faces, t_verts, ctx.recipe.registration.groupwise_smoothing,
                                  ctx.recipe.registration.groupwise_max_distance_mm)
    ids = list(fits)
    report["left_out"] = [ids[k] for k in report["left_out"]]
    report["distance_to_fits_mm"] = dict(zip(ids, report["distance_to_fits_mm"]))
    write_ply(path, verts, t_faces, t_labels)
    write_json(meta, {**want, **report})
    return str(path), report["movement_mm"]


def publish(ctx: Context, template: str, round_: int) -> None:
    """register/template.ply: the last round's template (only rewritten when it changed)."""
    folder = ctx.stage_dir(NAME)
    data = Path(template).read_bytes()
    path = folder / "template.ply"
    if not path.exists() or path.read_bytes() != data:
        write_bytes(path, data)
    write_json(folder / "template.json", {**read_json(f"{template[:-4]}.json"), "round": round_,
                                          "template": f"template-{round_}.ply"})


def plan(ctx: Context, results: Results) -> list[Item]:
    subjects = ssm_subjects(results)
    if not subjects:
        return []
    params = ctx.recipe.registration
    round_ = results.passes.get(NAME, 0)
    # One BLAS thread, as in the items: the template must not depend on the machine's cores.
    with threadpool_limits(limits=1):
        if round_ == 0:
            template, moved = seed_template(ctx, subjects), None
        else:
            template, moved = groupwise_template(ctx, round_, results.of(NAME))
    final = final_round(round_, moved, params)
    if final:
        publish(ctx, template, round_)
    prefix = "" if final else f"round{round_}/"
    item_params = {k: v for k, v in dataclasses.asdict(params).items() if k not in ROUND_KEYS}
    return [
        Item(f"{prefix}{i}", (f"{prefix}{i}.ply",), inputs=(str(ctx.stage_dir("remesh") / f"{i}.ply"), template),
             params=item_params, data={"round": round_, "final": final,
                                       **{k: rec[k] for k in ("source", "subject", "frame", "phase", "provenance")}})
        for i, rec in subjects.items()
    ]


def run(ctx: Context, item: Item) -> dict:
    subject_path, template_path = item.inputs
    s_verts, s_faces, s_labels = read_ply(subject_path)
    t_verts, t_faces, t_labels = read_ply(template_path)
    rng = item_rng(ctx.recipe.seed, NAME, item.id)
    fitted, report = register(t_verts, t_faces, s_verts, s_faces, ctx.recipe.registration, rng, t_labels, s_labels)
    accept(report, ctx.recipe.registration, correspondence=item.data["final"])
    write_ply(ctx.stage_dir(NAME) / f"{item.id}.ply", fitted, t_faces, t_labels)
    return {"fit": report, **item.data}


def again(ctx: Context, results: Results) -> bool:
    """Another round unless this one was the last, or left fewer than 2 fits to average."""
    records = list(results.of(NAME).values())
    return len(records) >= 2 and not records[0]["final"]


def _round_summary(records: list[dict], planned: int) -> dict:
    fits = [rec["fit"] for rec in records]
    structures = sorted({s for f in fits for s in f.get("label_agreement_by_structure", {})})
    by_structure = {s: [f["label_agreement_by_structure"][s] for f in fits if s in f.get("label_agreement_by_structure", {})]
                    for s in structures}
    return {
        "registered": len(records),
        "failed": planned - len(records),
        "fit_mean_mm": float(np.mean([f["mean_mm"] for f in fits])) if fits else None,
        "fit_p95_mm": float(np.mean([f["p95_mm"] for f in fits])) if fits else None,
        # Mean over subjects, and the worst subject, per structure.
        "label_agreement_by_structure": {s: float(np.mean(v)) for s, v in by_structure.items()},
        "least_label_agreement_by_structure": {s: float(np.min(v)) for s, v in by_structure.items()},
        "seconds_per_subject": float(np.mean([rec["seconds"] for rec in records])) if records else None,
    }


def finish(ctx: Context, results: Results) -> None:
    """After the last round: register/groupwise.json, one entry per round (see the module docstring).

    Also how far the last round's own mean lies from the template it was fitted to (the
    movement the next round would have had), so convergence can be judged.
    """
    records = results.of(NAME)
    if not records or not next(iter(records.values()))["final"]:
        return
    folder = ctx.stage_dir(NAME)
    last = next(iter(records.values()))["round"]
    planned, rounds = len(ssm_subjects(results)), []
    for r in range(last + 1):
        meta = read_json(folder / f"template-{r}.json")
        if r < last:  # the fits the next template was made of: this round's accepted ones
            done = [read_json(folder / f"{i}.json") for i in read_json(folder / f"template-{r + 1}.json")["fits"]]
        else:
            done = list(records.values())
        entry = {"round": r, "template": f"template-{r}.ply", "template_sha256": sha256_file(folder / f"template-{r}.ply")}
        if r:
            entry |= {k: meta[k] for k in ("movement_mm", "movement_max_mm", "smoothing_steps",
                                           "self_intersections", "flipped_faces")}
        rounds.append(entry | _round_summary(done, planned))
    residual = None
    if len(records) >= 2:
        t_verts, t_faces, _ = read_ply(folder / f"template-{last}.ply")
        try:
            with threadpool_limits(limits=1):
                _, report = mean_template(np.stack([read_ply(folder / f"{i}.ply")[0] for i in records]), t_faces,
                                          t_verts, ctx.recipe.registration.groupwise_smoothing)
            residual = {k: report[k] for k in ("movement_mm", "movement_max_mm")}
        except MeshError as e:  # a report only: the fits stand
            residual = {"error": str(e)}
    write_json(folder / "groupwise.json", {"rounds": rounds, "last_round": last, "next_round_movement": residual,
                                           "converge_mm": ctx.recipe.registration.groupwise_converge_mm,
                                           "max_rounds": ctx.recipe.registration.groupwise_rounds})


# Version 6: the fold guard adds the first-order term on folded regions (v5: the second-order stiffness).
STAGE = Stage(name=NAME, version=6, plan=plan, run=run, finish=finish, again=again)
