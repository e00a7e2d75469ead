"""Stage `sources`: phantom label maps written (MM-WHS / ACDC layouts), real data folders indexed.

Outputs, per source `<name>`:
- phantom: `sources/<name>/ct_train_NNNN_label.nii.gz` (whole heart) or
  `sources/<name>/patientNNN/{Info.cfg, patientNNN_frameYY_gt.nii.gz}` (biventricular),
  one item per subject, indexed back through the same loaders as real data;
- real data: `sources/<name>.index.json`, the list of label maps found.
Each item's sidecar carries `label_items`, which the `meshes` stage meshes.
"""

from __future__ import annotations

import hashlib
import warnings
from pathlib import Path

from meshsar_builder.dataset.sources import (
    InputWarning,
    LabelItem,
    SourceSpec,
    index_acdc,
    index_mmwhs,
    index_nifti,
    warning_messages,
)
from meshsar_builder.geometry import phantom_beating, phantom_heart
from meshsar_builder.pipeline.io import write_json
from meshsar_builder.pipeline.runner import Context, Item, Results, Stage
from meshsar_builder.pipeline.seeding import item_rng

NAME = "sources"


def index_source(spec: SourceSpec, root: Path, provenance: str | None = None, subject: str = "*") -> list[LabelItem]:
    """The label maps of a source folder, through the loader of its layout."""
    limit = spec.subjects or None
    if spec.kind == "nifti":
        return index_nifti(root, spec.name, spec.labels, limit, pattern=spec.pattern)
    if spec.kind == "acdc" or spec.anatomy == "biventricular":
        return index_acdc(root, spec.name, limit, provenance=provenance, subject=subject)
    return index_mmwhs(root, spec.name, limit, provenance=provenance or "annotated", subject=subject)


def phantom_subjects(spec: SourceSpec) -> list[str]:
    """MM-WHS-like (ct_train_1001, ...) or ACDC-like (patient001, ...) subject names."""
    if spec.anatomy == "whole_heart":
        return [f"ct_train_{1001 + i}" for i in range(spec.subjects)]
    return [f"patient{i + 1:03d}" for i in range(spec.subjects)]


def listing_digest(root: Path) -> str:
    """Names, sizes and modification times of a data folder: cheap change detection for re-indexing."""
    h = hashlib.sha256()
    if root.is_dir():
        for p in sorted(root.rglob("*")):
            if p.is_file():
                st = p.stat()
                h.update(f"{p.relative_to(root)}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def plan(ctx: Context, results: Results) -> list[Item]:
    items = []
    for spec in ctx.recipe.sources:
        if spec.kind != "phantom":
            root = spec.data_path()
            params = {"kind": spec.kind, "root": str(root), "labels": spec.labels, "subjects": spec.subjects,
                      "pattern": spec.pattern, "listing": listing_digest(root)}
            items.append(Item(spec.name, (f"{spec.name}.index.json",), params=params, data=(spec, str(root), None)))
            continue
        params = {"anatomy": spec.anatomy, "voxel_mm": spec.voxel_mm, "frames": spec.frames, "seed": ctx.recipe.seed}
        for subject in phantom_subjects(spec):
            if spec.anatomy == "whole_heart":
                outputs = (f"{spec.name}/{subject}_label.nii.gz",)
            else:
                frames = tuple(f"{spec.name}/{subject}/{subject}_frame{f:02d}_gt.nii.gz" for f in range(1, spec.frames + 1))
                outputs = (f"{spec.name}/{subject}/Info.cfg", *frames)
            items.append(Item(f"{spec.name}-{subject}", outputs, params=params, data=(spec, None, subject)))
    return items


def run(ctx: Context, item: Item) -> dict:
    spec, root, subject = item.data
    if spec.kind != "phantom":
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", InputWarning)
            found = index_source(spec, Path(root))
        write_json(ctx.stage_dir(NAME) / f"{spec.name}.index.json", [li.to_json() for li in found])
        return {"label_items": [li.to_json() for li in found], "warnings": warning_messages(caught)}
    folder = ctx.stage_dir(NAME) / spec.name
    rng = item_rng(ctx.recipe.seed, NAME, item.id)
    if spec.anatomy == "whole_heart":
        phantom_heart.write_mmwhs_subject(folder, subject, rng, voxel_mm=spec.voxel_mm)
    else:
        phantom_beating.write_acdc_subject(folder, subject, rng, n_frames=spec.frames, voxel_mm=spec.voxel_mm)
    found = index_source(spec, folder, provenance="phantom", subject=subject)
    return {"label_items": [li.to_json() for li in found]}


STAGE = Stage(name=NAME, version=2, plan=plan, run=run)
