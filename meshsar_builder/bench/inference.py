"""`meshsar bench inference`: the cost of physics at inference (issue 30 item 3).

On N shape-model test samples of a build (format 2, with its shape model), each timed alone:
- fit: `meshsar fit`'s shape-model fit to the recorded echo (trainer/fit.py fit_corrected at
  the default FitParams, its model-bias corrections included), from the recorded echo's
  focused targets to the fitted mesh;
- refine: `--refine` on a prediction-like mesh (the truth re-meshed onto the trainer's output
  template and scaled by REFINE_SCALE about its centre, so the refinement has somewhere to
  go), with the default config's [refine], from the recorded echo to the refined mesh.
Targets on the 2-core machine: a fit <= FIT_TARGET_S, a refinement <= REFINE_TARGET_S a sample,
each a `met` flag on the median sample (the worst beside it). Torch uses its default threads
(all cores), as `meshsar fit` and `evaluate --refine` do.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from meshsar_builder.pipeline.errors import InputError
from meshsar_builder.pipeline.io import write_json

FIT_TARGET_S = 60.0
REFINE_TARGET_S = 30.0
REFINE_SCALE = 1.04


def run(out_dir: str | Path, data: str | Path, samples: int = 3, split: str = "seed-0",
        config_path: str | Path | None = None, params=None) -> dict:
    """Time `samples` fits and refinements; writes out_dir/inference.json and returns it.

    config_path: the trainer config whose [refine], [radar_loss] and output template refine
    (default manifests/train/default.toml); params: the fit's FitParams (default: as `meshsar fit`)."""
    from meshsar_builder.bench.radar_loss import remesh_onto_template
    from meshsar_builder.dataset.readers import MeshSARDataset
    from meshsar_builder.trainer import losses as L
    from meshsar_builder.trainer.config import load_config, split_seed
    from meshsar_builder.trainer.fit import FitParams, fit_corrected, shape_model_tensors, specular_simulator
    from meshsar_builder.trainer.model import icosphere_levels
    from meshsar_builder.trainer.refine import sample_refiner
    from meshsar_builder.trainer.dataset_geometry import DatasetGeometry

    data = Path(data)
    if not (data / "index.json").exists():
        raise InputError(f"bench inference: {data} holds no build (build the demo recipe there first: "
                         f"meshsar build manifests/demo.toml --out {data})")
    config = load_config(config_path or Path(__file__).resolve().parents[2] / "manifests" / "train" / "default.toml")
    dataset = MeshSARDataset(data, "test", seed=split_seed(split), noisy_loss_echo=True)
    if dataset.index.get("loss_grid") is None:
        raise InputError(f"bench inference: {data} is a format-1 build without a loss grid; rebuild it")
    model = shape_model_tensors(data / "ssm" / "model.npz")
    params = params or FitParams(modes=min(FitParams.modes, model["modes"].shape[0]))  # a small model: all it has
    setup = DatasetGeometry.from_index(dataset.index, ()).focused_setup(params.focused)
    simulate = specular_simulator(data, model["faces"].numpy())
    refine = sample_refiner(dataset.index, config)
    levels, level_faces, _ = icosphere_levels(config.model.template_level)
    template, tfaces = levels[-1], level_faces[-1]
    topology = {"faces": torch.as_tensor(tfaces, dtype=torch.long), "edges": torch.as_tensor(L.mesh_edges(tfaces))}

    rows = []
    for i in range(len(dataset)):
        if len(rows) == samples:
            break
        sample = dataset[i]
        if sample["meta"].get("provenance") != "ssm":
            continue
        began = time.perf_counter()
        # echo_noisy: the build's recording on the loss grid, as `meshsar fit` reads it
        targets = torch.from_numpy(setup.target(sample["echo_noisy"].numpy(), sample["noise_sigma"].numpy()))
        fitted = fit_corrected(model, targets, setup, params, simulate)
        fit_s = time.perf_counter() - began
        truth = sample["verts"].double().numpy()
        base = remesh_onto_template(truth, sample["faces"].numpy(), template)
        start = base.mean(0) + REFINE_SCALE * (base - base.mean(0))
        began = time.perf_counter()
        refined = refine(start, topology, sample)
        refine_s = time.perf_counter() - began
        rows.append({"sample_id": sample["sample_id"], "fit_seconds": fit_s, "refine_seconds": refine_s,
                     "fit_loss": [float(fitted["losses"][0]), float(fitted["losses"][-1])],
                     # mean vertex distance to the re-meshed truth, before and after refinement (mm)
                     "refine_distance_mm": [float(np.linalg.norm(start - base, axis=1).mean()),
                                            float(np.linalg.norm(refined - base, axis=1).mean())]})
        print(f"{sample['sample_id']}: fit {fit_s:.1f} s, refine {refine_s:.1f} s", flush=True)
    if not rows:
        raise InputError(f"bench inference: the test part of {split} in {data} has no shape-model samples")

    def target(key: str, limit: float) -> dict:
        values = [row[key] for row in rows]
        median = float(np.median(values))
        return {"target": f"<= {limit}", "measured": median, "worst": max(values), "met": median <= limit}

    result = {"data": str(data), "split": split, "config": config.name, "threads": torch.get_num_threads(),
              "fit": {"modes": params.modes, "iterations": params.iterations, "corrections": params.corrections,
                      "correction_iterations": params.correction_iterations},
              "refine": {"steps": config.refine.steps, "smooth_iterations": config.refine.smooth_iterations,
                         "template_vertices": len(template), "start_scale": REFINE_SCALE},
              "targets": {"fit_seconds_per_sample": target("fit_seconds", FIT_TARGET_S),
                          "refine_seconds_per_sample": target("refine_seconds", REFINE_TARGET_S)},
              "samples": rows}
    write_json(Path(out_dir) / "inference.json", result)
    return result
