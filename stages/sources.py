"""Stage `sources`: phantom label maps written (MM-WHS / ACDC layouts), real data folders indexed.

Outputs, per source `<name>`:
- phantom: `sources/<name>/ct_train_NNNN_label.nii.gz` (whole heart) or
  `sources/<name>/patientNNN/{Info.cfg, patientNNN_frameYY_gt.nii.gz}` (biventricular),
  one item per subject, indexed back through the same loaders as real data;
- real data: `sources/<name>.index.json`, the list of label maps found: one item per 3-D map,
  one per frame (T index) of a 4-D map, with subject, frame, phase and provenance from the
  source's layout (acdc: Info.cfg and predicted 4-D maps; nifti: regex, frame_table, phases);
- shape_model: `sources/<name>/<name>-smNNNNN.ply`, `samples` shapes drawn from the external
  PCA model as SSM samples are ([ssm] truncate_sigma, max_redraws; each from its own seed),
  one item per source (the model is read once).
Each item's sidecar carries `label_items`, which the `meshes` stage meshes; a shape_model's
carries `shape_samples` (coefficients, redraws) and `shape_model` (its files and their
digests), which the `radar` stage takes as dataset meshes.
"""

from __future__ import annotations

import hashlib
import warnings
from pathlib import Path

import numpy as np

from meshsar_builder.dataset.label_maps import InputWarning, LabelItem, warning_messages
from meshsar_builder.dataset.shape_models import load_shape_model
from meshsar_builder.dataset.sources import SourceSpec, index_acdc, index_mmwhs, index_nifti
from meshsar_builder.geometry import phantom_beating, phantom_heart
from meshsar_builder.geometry.meshfile import write_ply
from meshsar_builder.geometry.ssm import sample_valid
from meshsar_builder.pipeline.io import sha256_file, write_json
from meshsar_builder.pipeline.runner import Context, Item, Results, Stage
from meshsar_builder.pipeline.seeding import item_rng

NAME = "sources"
# [[sources]] keys that decide a real source's subjects and frames (sources.SourceSpec).
FRAME_KEYS = ("regex", "frame_table", "phases", "provenance", "predicted")


def index_source(spec: SourceSpec, root: Path, provenance: str | None = None, subject: str = "*") -> list[LabelItem]:
    """The label maps of a source folder, through the loader of its layout."""
    limit = spec.subjects or None
    if spec.kind == "nifti":
        return index_nifti(root, spec.name, spec.labels, limit, pattern=spec.pattern, regex=spec.regex,
                           frame_table=spec.frame_table, phases=spec.phases, provenance=spec.provenance)
    if spec.kind == "acdc" or spec.anatomy == "biventricular":
        return index_acdc(root, spec.name, limit, provenance=provenance, subject=subject,
                          predicted=spec.predicted if spec.kind == "acdc" else "")
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


def shape_sample_ids(spec: SourceSpec) -> list[str]:
    """Dataset sample ids of a shape_model source, unique across the recipe."""
    return [f"{spec.name}-sm{i:05d}" for i in range(spec.samples)]


def plan(ctx: Context, results: Results) -> list[Item]:
    items = []
    for spec in ctx.recipe.sources:
        if spec.kind == "shape_model":
            files = spec.model_files()
            params = {"n_modes": spec.n_modes, "labels": spec.labels, "structures": spec.structures,
                      "truncate_sigma": ctx.recipe.ssm.truncate_sigma, "max_redraws": ctx.recipe.ssm.max_redraws,
                      "seed": ctx.recipe.seed}
            outputs = tuple(f"{spec.name}/{sid}.ply" for sid in shape_sample_ids(spec))
            items.append(Item(spec.name, outputs, inputs=tuple(str(f) for f in files.values()), params=params,
                              data=(spec, None, None)))
            continue
        if spec.kind != "phantom":
            root = spec.data_path()
            params = {"kind": spec.kind, "root": str(root), "labels": spec.labels, "subjects": spec.subjects,
                      "pattern": spec.pattern, "listing": listing_digest(root)}
            # The subject / frame keys, where set (a recipe without them keeps its parameter hash).
            params.update({k: getattr(spec, k) for k in FRAME_KEYS if getattr(spec, k)})
            table = Path(spec.frame_table)
            inputs = (str(table),) if spec.frame_table and table.is_absolute() else ()  # else in the listing
            items.append(Item(spec.name, (f"{spec.name}.index.json",), inputs=inputs, params=params,
                              data=(spec, str(root), None)))
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
    if spec.kind == "shape_model":
        return draw_shape_samples(ctx, spec)
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


def draw_shape_samples(ctx: Context, spec: SourceSpec) -> dict:
    """Read the source's model once, draw and write its samples; the sidecar record."""
    files = spec.model_files()
    model = load_shape_model(files, spec.n_modes, spec.labels, spec.structures[0])
    samples = {}
    for sid in shape_sample_ids(spec):
        coeffs, verts, redraws = sample_valid(model, item_rng(ctx.recipe.seed, NAME, sid), ctx.recipe.ssm)
        write_ply(ctx.stage_dir(NAME) / spec.name / f"{sid}.ply", verts, model.faces, model.labels)
        samples[sid] = {"coeffs": np.round(coeffs, 6).tolist(), "redraws": redraws}
    provenance = {
        "files": {k: f.name for k, f in files.items()},
        "sha256": {k: sha256_file(f) for k, f in files.items()},
        "n_modes": len(model.variances),
        "variance_explained": round(float(model.variances.sum() / model.total_variance), 6),
    }
    return {"label_items": [], "shape_samples": samples, "shape_model": provenance}


# v3: 4-D label maps (one item per T index), acdc's predicted maps, nifti's regex / frame_table.
STAGE = Stage(name=NAME, version=4, plan=plan, run=run)
