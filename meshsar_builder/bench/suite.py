"""`meshsar bench` / `make bench`: speed and memory, as JSON under build/bench/.

Parts:
- radar: seconds per view (visibility, echo, imaging) on one core for a demo
  mesh, the production echo's speed-up over the direct sum in the same run,
  Embree rays per second (bench_radar);
- geometry: seconds per subject for meshing, remeshing and registration (all
  groupwise rounds, and each round on its own), and ms per SSM sample, at the demo recipe's settings on demo phantoms;
- pipeline: the demo recipe's settings with fewer items, built with 1 and 2
  workers on the local pool and on a Dask LocalCluster: seconds per sample
  per stage, samples per minute, peak memory, scaling efficiency;
- trainer: ms per training step on the CPU at the default and paper sizes (bench_trainer).
Every part runs its measurements with one BLAS thread, like the stages do.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from meshsar_builder.pipeline.io import read_json, write_json
from meshsar_builder.pipeline.recipe import load

DEMO = Path(__file__).resolve().parents[2] / "manifests" / "demo.toml"
PARTS = ("radar", "geometry", "pipeline", "trainer")


def demo_subject(index: int = 0):
    """The meshing-stage surface of the demo recipe's whole-heart phantom number `index`.

    Seeded and read back exactly as the sources and meshes stages do.
    """
    from meshsar_builder.dataset.sources import MMWHS_TABLE, read_label_map
    from meshsar_builder.geometry import phantom_heart
    from meshsar_builder.geometry.meshing import labels_to_surface
    from meshsar_builder.pipeline.seeding import item_rng

    recipe = load(DEMO)
    spec = recipe.sources[0]
    subject = f"ct_train_{1001 + index}"
    with tempfile.TemporaryDirectory() as tmp:
        rng = item_rng(recipe.seed, "sources", f"{spec.name}-{subject}")
        path = phantom_heart.write_mmwhs_subject(Path(tmp), subject, rng, voxel_mm=spec.voxel_mm)
        labels, affine = read_label_map(path, MMWHS_TABLE)
    return labels_to_surface(labels, affine, list(spec.structures), recipe.meshing)


def demo_mesh() -> tuple[np.ndarray, np.ndarray]:
    """A dataset-sized heart mesh: a demo subject remeshed and simplified to the template size, centred."""
    from meshsar_builder.geometry.remesh import remesh, simplify

    recipe = load(DEMO)
    surf = demo_subject(0)
    verts, faces = simplify(*remesh(surf.verts, surf.faces, recipe.remesh), recipe.registration.template_vertices)
    return verts - (verts.min(axis=0) + verts.max(axis=0)) / 2, faces


def bench_radar(out: Path) -> dict:
    from meshsar_builder.bench.radar import run

    return run(out, *demo_mesh())


def _timed(fn, *args):
    t0 = time.perf_counter()
    result = fn(*args)
    return time.perf_counter() - t0, result


def bench_geometry(out: Path, subjects: int = 3, samples: int = 20) -> dict:
    """Seconds per subject for meshing, remeshing and registration; ms per SSM sample (demo settings)."""
    from meshsar_builder.geometry.groupwise import register_groupwise
    from meshsar_builder.geometry.meshing import transfer_labels
    from meshsar_builder.geometry.remesh import remesh, simplify
    from meshsar_builder.geometry.ssm import build_model, sample_valid
    from meshsar_builder.pipeline.seeding import item_rng

    recipe = load(DEMO)
    timings = {"meshes": [], "remesh": [], "register": []}
    remeshed = []
    with threadpool_limits(limits=1):
        for i in range(subjects):
            t, surf = _timed(demo_subject, i)
            timings["meshes"].append(t)
            t, (v, f) = _timed(remesh, surf.verts, surf.faces, recipe.remesh)
            timings["remesh"].append(t)
            remeshed.append((v, f, transfer_labels(surf.verts, surf.labels, v)))
        t_verts, t_faces = simplify(*remeshed[0][:2], recipe.registration.template_vertices)
        t_labels = transfer_labels(remeshed[0][0], remeshed[0][2], t_verts)
        # With the vertex labels and the groupwise rounds, as the register stage runs it.
        t, (final, _, rounds) = _timed(register_groupwise, (t_verts, t_faces, t_labels), remeshed, recipe.registration,
                                       lambda r, i: item_rng(0, "bench", f"{r}-{i}"))
        timings["register"].append(t / subjects)
        for rec in rounds:
            timings[f"register_round{rec['round']}"] = [rec["seconds_per_subject"]]
        fits = [{k: report[k] for k in ("mean_mm", "p95_mm", "flipped_faces", "self_intersections",
                                        "label_agreement_by_structure")} for report in rounds[-1]["fits"]]
        model = build_model(final, t_faces, recipe.ssm.variance)
        rng = np.random.default_rng(0)
        t, _ = _timed(lambda: [sample_valid(model, rng, recipe.ssm) for _ in range(samples)])
    result = {
        "settings": {"recipe": str(DEMO.name), "subjects": subjects, "template_vertices": len(t_verts),
                     "edge_mm": recipe.remesh.edge_mm, "spacing_mm": recipe.meshing.spacing_mm},
        "seconds_per_subject": {k: float(np.mean(v)) for k, v in timings.items()},
        "seconds_each": timings,
        "ms_per_ssm_sample": 1000 * t / samples,
        "fits": fits,
        "groupwise_rounds": [{"round": rec["round"], "movement_mm": rec["movement_mm"],
                              "seconds_per_subject": rec["seconds_per_subject"]} for rec in rounds],
    }
    write_json(out / "geometry.json", result)
    return result


PIPELINE_RECIPE = """
name = "bench"
seed = 0
[[sources]]
kind = "phantom"
anatomy = "whole_heart"
subjects = 4
[[sources]]
kind = "phantom"
anatomy = "biventricular"
subjects = 1
frames = 4
[ssm]
samples = 8
"""


PEAK_RSS = (
    "import resource, subprocess, sys; "
    "subprocess.run(sys.argv[1:], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL); "
    "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)"
)


# (name, extra `meshsar build` arguments): the local pool and a Dask LocalCluster, 1 and 2 workers.
PIPELINE_RUNS = (
    ("local-1", ["--workers", "1"]), ("local-2", ["--workers", "2"]),
    ("dask-1", ["--scheduler", "local:1"]), ("dask-2", ["--scheduler", "local:2"]),
)


def bench_pipeline(out: Path, runs: tuple = PIPELINE_RUNS) -> dict:
    """The demo's settings on 4 whole-heart subjects, 8 SSM samples and 4 frames, local pool and Dask.

    Each build runs from scratch as its own `meshsar build` process; peak
    memory is the largest resident set among that process and its workers.
    Scaling efficiency of a backend = (1-worker time / 2-worker time) / 2.
    """
    measured = {}
    with tempfile.TemporaryDirectory() as tmp:
        recipe = Path(tmp) / "bench.toml"
        recipe.write_text(PIPELINE_RECIPE)
        for name, args in runs:
            build_dir = Path(tmp) / name
            build = [sys.executable, "-m", "meshsar_builder.cli", "build", str(recipe), "--out", str(build_dir), *args]
            t0 = time.perf_counter()
            # A wrapper process waits for the build, so its children's peak RSS is this build's alone.
            peak_kb = subprocess.run([sys.executable, "-c", PEAK_RSS, *build], check=True, capture_output=True,
                                     text=True).stdout.split()[-1]
            wall = time.perf_counter() - t0
            per_stage = {}
            for stage_dir in sorted(p for p in build_dir.iterdir() if p.is_dir()):
                secs = [rec["seconds"] for rec in map(read_json, stage_dir.glob("*.json")) if "seconds" in rec]
                if secs:
                    per_stage[stage_dir.name] = {"items": len(secs), "seconds_per_item": float(np.mean(secs))}
            samples = read_json(build_dir / "index.json")["n_samples"]
            measured[name] = {"wall_seconds": wall, "samples": samples, "seconds_per_sample": wall / samples,
                              "samples_per_minute": 60 * samples / wall,
                              "peak_rss_mb_largest_process": int(peak_kb) / 1024, "stages": per_stage}
    result = {"recipe": "demo settings; " + " ".join(PIPELINE_RECIPE.split()), "runs": measured, "scaling": {}}
    for backend in ("local", "dask"):
        one, two = measured.get(f"{backend}-1"), measured.get(f"{backend}-2")
        if one and two:
            speedup = one["wall_seconds"] / two["wall_seconds"]
            result["scaling"][backend] = {"speedup_2_workers": speedup, "efficiency_2_workers": speedup / 2}
    write_json(out / "pipeline.json", result)
    return result


def bench_trainer(out: Path) -> dict:
    from meshsar_builder.bench.trainer import run

    return run(out)


def run(parts: list[str], out: Path = Path("build/bench")) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    benches = {"radar": bench_radar, "geometry": bench_geometry, "pipeline": bench_pipeline, "trainer": bench_trainer}
    return {part: benches[part](out) for part in parts}
