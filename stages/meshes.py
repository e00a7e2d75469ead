"""Stage `meshes`: each label map's union of structures to a closed genus-0 surface.

Outputs: `meshes/<item>.ply` (RAS mm, per-vertex canonical structure label) and
its sidecar `meshes/<item>.json` with size, area, volume, topology and provenance.
"""

from __future__ import annotations

import dataclasses
import warnings

import nibabel as nib
import numpy as np
import trimesh

from meshsar_builder.dataset.label_maps import InputWarning, LabelItem, read_label_map, warning_messages
from meshsar_builder.geometry.meshfile import write_ply
from meshsar_builder.geometry.meshing import labels_to_surface, long_axis_landmarks
from meshsar_builder.geometry.structures import STRUCTURES
from meshsar_builder.pipeline.errors import InputError
from meshsar_builder.pipeline.runner import Context, Item, Results, Stage

NAME = "meshes"


def plan(ctx: Context, results: Results) -> list[Item]:
    specs = {s.name: s for s in ctx.recipe.sources}
    meshing = dataclasses.asdict(ctx.recipe.meshing)
    items = []
    for rec in results.of("sources").values():
        for d in rec["label_items"]:
            li = LabelItem.from_json(d)
            spec = specs[li.source]
            params = {"meshing": meshing, "structures": list(spec.structures), "table": d["table"],
                      "require_affine": spec.require_affine}
            if li.t is not None:  # one frame (T index) of a 4-D label map
                params["t"] = li.t
            items.append(Item(li.item_id, (f"{li.item_id}.ply",), inputs=(li.path,), params=params,
                              data=(d, spec.structures, spec.use, spec.require_affine)))
    return items


def run(ctx: Context, item: Item) -> dict:
    d, structures, use, require_affine = item.data
    li = LabelItem.from_json(d)
    if "index_error" in li.extra:  # what the source's index could not use (label_maps.failed_item)
        raise InputError(li.extra["index_error"])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", InputWarning)
        labels, affine = read_label_map(li.path, li.table, require_affine, t=li.t)
    name = li.path if li.t is None else f"{li.path} (T index {li.t})"
    surf = labels_to_surface(labels, affine, list(structures), ctx.recipe.meshing, name=name)
    motion = {}
    if li.frame is not None and (labels == STRUCTURES["myo"]).any():
        # Frames of a cycle: apex and base plane along the stack's slice normal (the long axis
        # of a short-axis stack), for the card's cycle plot.
        apex, base = long_axis_landmarks(labels, affine, nib.load(li.path).affine[:3, 2])
        motion = {"apex_mm": [round(float(c), 3) for c in apex], "base_mm": round(base, 3)}
    write_ply(ctx.stage_dir(NAME) / f"{item.id}.ply", surf.verts, surf.faces, surf.labels)
    mesh = trimesh.Trimesh(surf.verts, surf.faces, process=False)
    lo, hi = surf.verts.min(axis=0), surf.verts.max(axis=0)
    voxel_ml = abs(np.linalg.det(affine[:3, :3])) / 1000.0
    counts = np.bincount(labels.ravel(), minlength=max(STRUCTURES.values()) + 1)
    return {
        "n_verts": len(surf.verts),
        "n_faces": len(surf.faces),
        "area_mm2": round(float(mesh.area), 3),
        "volume_ml": round(float(mesh.volume) / 1000.0, 4),
        "euler": int(mesh.euler_number),
        "watertight": bool(mesh.is_watertight),
        # The topology repair's record (empty when the union was genus 0 as it was): what each
        # step changed, the handles cut or filled and where, volume changes, surface shift.
        "repair": surf.repair,
        "spacing_mm": ctx.recipe.meshing.spacing_mm,
        "center_mm": [round(float(c), 4) for c in (lo + hi) / 2],
        # from voxel counts of the label map: chamber volumes over the cycle, for the dataset card
        "structure_volumes_ml": {s: round(float(counts[i] * voxel_ml), 3) for s, i in STRUCTURES.items() if counts[i]},
        "use": use,
        **motion,
        "warnings": warning_messages(caught),
        **{k: d[k] for k in ("source", "subject", "frame", "phase", "cycle_fraction", "provenance")},
    }


# Version 6: a voxel size from pixdim where the sform disagrees (label_maps.voxel_affine: real ACDC files).
# Version 7: a thick-slice stack that cuts the shape ends flat at its last slice's face (meshing._cut_flat).
# Version 8: that only with [meshing] flat_ends = true (default false: rounded, as version 6).
# Version 9: flat_ends on by default again: with track v15's ring points the flat bases track as well as rounded ones.
# Version 10: a structure missing from the map or lying apart from the rest fails the item (meshing._pieces_apart);
# the landmarks' long axis turned toward the apex by the ventricle's shape, not by the file's slice order.
# Version 11: a chamber cut by the map's border over more than max_border_mm2 fails the item (label_repair.
# check_border), and a 4-D frame's errors name its T index.
STAGE = Stage(name=NAME, version=11, plan=plan, run=run)
