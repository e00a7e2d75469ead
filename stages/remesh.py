"""Stage `remesh`: Taubin smoothing and isotropic remeshing of every mesh (DESIGN section 6).

Outputs: `remesh/<item>.ply` with structure labels carried over from the nearest
marching-cubes vertex, and a sidecar with the surface checks (watertight, Euler
characteristic, self-intersections, area, volume) and `warnings` (a surface remeshed at
finer edges than the recipe's, and why).
"""

from __future__ import annotations

import dataclasses
import warnings

from meshsar_builder.dataset.label_maps import warning_messages
from meshsar_builder.geometry.intersections import compile_kernels
from meshsar_builder.geometry.meshfile import read_ply, write_ply
from meshsar_builder.geometry.meshing import transfer_labels
from meshsar_builder.geometry.remesh import RemeshWarning, mesh_checks, remesh
from meshsar_builder.pipeline.runner import Context, Item, Results, Stage

NAME = "remesh"
CARRIED = ("source", "subject", "frame", "phase", "cycle_fraction", "provenance", "use")


def plan(ctx: Context, results: Results) -> list[Item]:
    params = dataclasses.asdict(ctx.recipe.remesh)
    return [
        Item(i, (f"{i}.ply",), inputs=(str(ctx.stage_dir("meshes") / f"{i}.ply"),), params=params,
             data={k: rec[k] for k in CARRIED})
        for i, rec in results.of("meshes").items()
    ]


def run(ctx: Context, item: Item) -> dict:
    verts, faces, labels = read_ply(item.inputs[0])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RemeshWarning)
        new_verts, new_faces = remesh(verts, faces, ctx.recipe.remesh)
    new_labels = transfer_labels(verts, labels, new_verts)
    write_ply(ctx.stage_dir(NAME) / f"{item.id}.ply", new_verts, new_faces, new_labels)
    checks = mesh_checks(new_verts, new_faces)
    lo, hi = new_verts.min(axis=0), new_verts.max(axis=0)
    # a finer edge than the recipe's where the surface has parts too thin for it (remesh), said here
    return {**checks, "volume_ml": checks["volume_mm3"] / 1000, "center_mm": ((lo + hi) / 2).tolist(),
            "warnings": warning_messages(caught, RemeshWarning), **item.data}


def warm(ctx: Context) -> None:
    compile_kernels()  # the surface checks' self-intersection test


# Version 2: a dense input's first remeshing iteration runs unchecked, then its vertices go back onto the
# input (geometry/remesh.py _coarsen_onto).
# Version 3: a result that lost a part of its input (geometry/remesh.py max_lost_mm) is remeshed at finer edges.
STAGE = Stage(name=NAME, version=3, plan=plan, run=run, warm=warm)
