"""Stage `track`: the frames of every beating subject in correspondence (DESIGN section 6).

For each subject of `use = "direct"` sources with two or more frames, the reference frame's
remeshed surface (its ED frame, else its first) fits every other frame, warm-started from its
neighbour's fit (geometry/tracking.py), so all frames of the subject share the reference's
vertices, faces and labels: a motion field, and tissue that can be followed over the cycle.
The fits go outward from the reference both ways round the cycle; the two chains share only
the reference, so each is an item (`<reference>-cycle-forward`, which also writes the
reference, and `<reference>-cycle-backward`) and the two run side by side.

Outputs: `track/<frame>.ply` for every frame of the chain: the fitted reference mesh, or the
frame's own remeshed mesh where its fit was rejected (named in the sidecar); the sidecar
holds the subject's `reference` and `cycle` (all its frames) and per frame of the chain
whether it is in correspondence, the fit's figures and its seconds, and the per-vertex
displacement from the reference (mean, 95th percentile, per structure) of the frames in
correspondence. dataset.frames.merge_cycles joins a subject's chains.
"""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
from threadpoolctl import threadpool_limits

from meshsar_builder.dataset.frames import direct_meshes, source_cohorts, subject_series
from meshsar_builder.geometry.landmarks import structure_name
from meshsar_builder.geometry.meshfile import read_ply, write_ply
from meshsar_builder.geometry.tracking import track_frames, visit_chains
from meshsar_builder.pipeline.io import atomic_path
from meshsar_builder.pipeline.runner import Context, Item, Results, Stage
from meshsar_builder.pipeline.seeding import item_rng

NAME = "track"


def plan(ctx: Context, results: Results) -> list[Item]:
    params = dataclasses.asdict(ctx.recipe.registration)
    remeshed = ctx.stage_dir("remesh")
    items = []
    cohorts = source_cohorts(ctx.recipe.sources)
    for mids, reference in subject_series(direct_meshes(results.of("remesh"), cohorts), cohorts):
        if len(mids) < 2:
            continue
        ref = mids.index(reference)
        for name, chain in zip(("forward", "backward"), visit_chains(len(mids), ref)):
            writes = [ref] * (name == "forward") + [index for index, _ in chain]
            items.append(Item(f"{reference}-cycle-{name}", tuple(f"{mids[i]}.ply" for i in writes),
                              inputs=tuple(str(remeshed / f"{mid}.ply") for mid in mids), params=params,
                              data={"frames": mids, "reference": reference, "chain": chain, "writes": writes},
                              cost=len(chain)))  # a fit per frame of the chain
    return items


def run(ctx: Context, item: Item) -> dict:
    mids, reference, writes = item.data["frames"], item.data["reference"], item.data["writes"]
    frames = [read_ply(path) for path in item.inputs]
    ref = mids.index(reference)
    with threadpool_limits(limits=1):  # one core per item: items run side by side
        fits, reports = track_frames(frames, ref, ctx.recipe.registration,
                                     lambda i: item_rng(ctx.recipe.seed, NAME, mids[i]),
                                     order=[tuple(pair) for pair in item.data["chain"]])
    folder = ctx.stage_dir(NAME)
    _, ref_faces, ref_labels = frames[ref]
    per_frame = {}
    for index in writes:
        mid, path, fit, report = mids[index], item.inputs[index], fits[index], reports[index]
        if fit is None:  # rejected: the frame keeps its own mesh
            with atomic_path(folder / f"{mid}.ply") as tmp:
                shutil.copyfile(path, tmp)
        else:
            write_ply(folder / f"{mid}.ply", fit, ref_faces, ref_labels)
            report = {**report, **displacement(fit - fits[ref], ref_labels)}
        per_frame[mid] = report
    return {"reference": reference, "cycle": mids, "frames": per_frame,
            "in_correspondence": [mids[i] for i in writes if fits[i] is not None]}


def displacement(moved: np.ndarray, labels: np.ndarray) -> dict:
    """Per-vertex displacement (n, 3) mm from the reference -> its mean and 95th percentile, and
    its mean per structure (JSON-ready)."""
    length = np.linalg.norm(moved, axis=1)
    return {"displacement_mm": round(float(length.mean()), 3),
            "displacement_p95_mm": round(float(np.percentile(length, 95)), 3),
            "displacement_by_structure_mm": {structure_name(s): round(float(length[labels == s].mean()), 3)
                                             for s in np.unique(labels) if s != 0}}


# Version 7: label agreement and landmarks only for structures that form a region (register v12);
# version 8: flipped faces judged against their neighbourhood (register v13); version 9: a
# folding step keeps its fold-free part (register v14).
# Version 10: register v15's preconditioner.
# Version 11: register v17's preconditioner.
# Version 12: register v18's looser conjugate-gradient stop.
# Version 13: a frame fit's second soft step preconditioned by the first's factorisation (frame_carried_iterations).
# Version 14: register v19's preconditioner and tolerance; each step factorises its own matrix again (it costs less
# than the carried factor's extra iterations).
# Version 15: a frame's ring points counted in each ring's affine-normalised plane and turned to follow its
# neighbour's rings (landmarks.py).
# Version 16: a frame fit's spline start smoothed by frame_landmark_smoothing (100, not landmark_smoothing's 10).
STAGE = Stage(name=NAME, version=16, plan=plan, run=run, after=("remesh",))
