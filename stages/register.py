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
the last round only; version 5: second-order NRICP stiffness and its schedule (nricp.py);
version 7: landmarks with a confidence and a robust check, a divergence monitor with a
retry, landmark residual judged, groupwise templates checked against their fits (issue 26);
version 10: the stiffest step on a coarse template, the landmark term left out of the
preconditioner (nricp.py; issue 32); version 11: exact closest points from libigl's AABB tree
(the coarse start's interpolation, the reports' distances, label agreement); version 12: a
structure that forms no region of the surface (landmarks.surface_regions) is neither judged
by label agreement nor landmarked; version 13: a flipped face is one turned over against its
neighbourhood, not a smooth turn past 90 degrees (measures.flipped_faces), and a retry that
the fold guard stopped too is kept where it lies closer to the subject; version 14: a step that
still folds after its repeats keeps its longest fold-free part, and the schedule goes on.
The rounds' files are made in geometry/groupwise.py; this stage is their plan and one call
per item.
"""

from __future__ import annotations

import dataclasses

from threadpoolctl import threadpool_limits

from meshsar_builder.geometry.groupwise import (
    final_round,
    fit_subject,
    groupwise_template,
    publish,
    seed_template,
    write_report,
)
from meshsar_builder.pipeline.runner import Context, Item, Results, Stage
from meshsar_builder.pipeline.seeding import item_rng

NAME = "register"
# These decide how many rounds run, not what one fit gives (the template's digest carries
# the smoothing and the distance check), so a change does not redo the rounds already done.
ROUND_KEYS = ("groupwise_rounds", "groupwise_converge_mm", "groupwise_smoothing", "groupwise_max_distance_mm")


def ssm_subjects(results: Results) -> dict[str, dict]:
    return {i: rec for i, rec in results.of("remesh").items() if rec["use"] == "ssm"}


def plan(ctx: Context, results: Results) -> list[Item]:
    subjects = ssm_subjects(results)
    if not subjects:
        return []
    params, folder = ctx.recipe.registration, ctx.stage_dir(NAME)
    round_ = results.passes.get(NAME, 0)
    # One BLAS thread, as in the items: the template must not depend on the machine's cores.
    with threadpool_limits(limits=1):
        if round_ == 0:
            template, moved = seed_template(folder, ctx.stage_dir("remesh"), subjects, params), None
        else:
            template, moved = groupwise_template(folder, round_, results.of(NAME), params)
    final = final_round(round_, moved, params)
    if final:
        publish(folder, template, round_)
    prefix = "" if final else f"round{round_}/"
    item_params = {k: v for k, v in dataclasses.asdict(params).items() if k not in ROUND_KEYS}
    # A subject's fit in the round before is the best guess of its cost in this one (the runner starts the
    # costliest first; each round waits for its last fit).
    before = {rec["item"].rsplit("/", 1)[-1]: rec["seconds"] for rec in results.of(NAME).values()} if round_ else {}
    return [
        Item(f"{prefix}{i}", (f"{prefix}{i}.ply",), inputs=(str(ctx.stage_dir("remesh") / f"{i}.ply"), template),
             params=item_params, data={"round": round_, "final": final,
                                       **{k: rec[k] for k in ("source", "subject", "frame", "phase", "provenance")}},
             cost=before.get(i, 0.0))
        for i, rec in subjects.items()
    ]


def run(ctx: Context, item: Item) -> dict:
    subject_path, template_path = item.inputs
    report = fit_subject(subject_path, template_path, ctx.stage_dir(NAME) / f"{item.id}.ply", ctx.recipe.registration,
                         item_rng(ctx.recipe.seed, NAME, item.id), item.data["final"])
    return {"fit": report, **item.data}


def again(ctx: Context, results: Results) -> bool:
    """Another round unless this one was the last, or left fewer than 2 fits to average."""
    records = list(results.of(NAME).values())
    return len(records) >= 2 and not records[0]["final"]


def finish(ctx: Context, results: Results) -> None:
    """After the last round: register/groupwise.json (geometry/groupwise.write_report)."""
    records = results.of(NAME)
    if records and next(iter(records.values()))["final"]:
        write_report(ctx.stage_dir(NAME), records, len(ssm_subjects(results)), ctx.recipe.registration)


# Version 9: a biventricular map's apex along its basal LV disc (v7: issue 26; v6: the fold guard
# adds the first-order term on folded regions).
# Version 15: the preconditioner's LU with relaxed supernodes (its rounding changes, so the fits' last bits do).
# Version 16: the rounds before the last run round_coarse_steps coarse (groupwise.round_params), so the templates
# and the last round's fits move within the rounds' tolerance.
# Version 17: SuperLU's default supernodes again (relaxed ones corrupted its heap), so the fits' last bits change.
# Version 18: the fits' conjugate gradients stop at a relative residual of 3e-4 (1e-4 before).
# Version 19: the preconditioner is CHOLMOD's Cholesky factor in double precision (SuperLU's single-precision LU
# before), and the conjugate gradients stop at 1e-4 again, so the fits move within their tolerance.
STAGE = Stage(name=NAME, version=19, plan=plan, run=run, finish=finish, again=again, after=("remesh",))
