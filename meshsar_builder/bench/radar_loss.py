"""`meshsar bench radar-loss`: the radar losses' landscapes on built samples (issue 28 item 2).

For each of N samples of a build (format 2: echo_clean on the loss grid), the truth is
re-meshed onto the network's output template (the icosphere of the trainer's final stage,
each vertex moved to the outermost point of the truth along its direction from the
truth's centre: what a prediction is, topologically), then moved along four families:
scale (+-10 %), shift along x, y, z (+-8 mm), a local bulge along the normals
(+-8 mm, Gaussian of BULGE_RADIUS_MM about the vertex nearest the anterior radar), and a
twist about the long axis (+-15 deg at the ends, linear along the axis). Each loss is
computed exactly as the trainer computes it, against the target from the full-resolution
truth's stored echo: "clean" (echo_clean) and "recorded" (the build's noisy echo).

Targets (each `met` holds for every sample; issue 28):
(a) minimum within 0.5 mm / 1 % / 1 deg of the truth, on a grid of 0.25 mm / 0.25 % / 0.5 deg;
(b) monotone rise from the truth out to 5 mm of shift, 8 % of scale and 5 mm of bulge, on
    0.5 mm (0.5 %) steps, each way, no dip larger than 1 % of the rise;
(c) cosine between minus the gradient (after the trainer's smoothing) and the per-vertex
    direction to the truth >= 0.3 at 2 and 4 mm of shift (each axis, each way), at
    +-4 % of scale and +-3 mm of bulge.

`focused` and `depth` are the trainer's losses of those modes (the same volumes, compared by cosine or
by depth maps). The raw L1 (the paper's) is measured with the trainer's code on a fixed subset of
RAW_ANTENNAS antennas per view (all its frequencies) to bound its cost: a dense echo per
evaluation is seconds a view on a CPU. `exact` (ExactEvaluator, entry exact_specular) is a
reference that no trainer runs: the production echo of each candidate, about 0.8 s an evaluation
on one core, so 3-4 minutes a sample.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from meshsar_builder.pipeline.errors import InputError
from meshsar_builder.pipeline.io import write_json
from meshsar_builder.trainer.losses import FOCUSED_MODES

TOLERANCE = {"shift": 0.5, "scale": 1.0, "bulge": 0.5, "twist": 1.0}  # mm, %, mm, deg
FINE = {"shift": (2.0, 0.25), "scale": (2.0, 0.25), "bulge": (2.0, 0.25), "twist": (3.0, 0.5)}
COARSE = {"shift": (8.0, 0.5), "scale": (10.0, 0.5), "bulge": (8.0, 0.5), "twist": (15.0, 1.0)}
MONOTONE_TO = {"shift": 5.0, "scale": 8.0, "bulge": 5.0}
COSINE_AT = {"shift": (2.0, 4.0), "scale": (4.0,), "bulge": (3.0,)}
COSINE_MIN = 0.3
DIP_FRACTION = 0.01
BULGE_RADIUS_MM = 15.0
RAW_ANTENNAS = 16
LOSSES = (*FOCUSED_MODES, "raw", "exact")


def remesh_onto_template(verts: np.ndarray, faces: np.ndarray, template: np.ndarray) -> np.ndarray:
    """(n, 3) the template's unit directions moved to the outermost truth point along each from its centre."""
    mesh = trimesh.Trimesh(verts, faces, process=False)
    centre = verts.mean(0)
    directions = template / np.linalg.norm(template, axis=1, keepdims=True)
    origins = np.repeat(centre[None], len(directions), 0)
    locations, ray_index, _ = mesh.ray.intersects_location(origins, directions, multiple_hits=True)
    reach = np.full(len(directions), np.nan)
    if len(locations):
        distance = ((locations - centre) * directions[ray_index]).sum(1)
        np.fmax.at(reach, ray_index, distance)
    missing = np.isnan(reach)
    if missing.any():  # rays that miss (numerical): the mean radius
        reach[missing] = np.linalg.norm(verts - centre, axis=1).mean()
    return centre + directions * reach[:, None]


def vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    return np.asarray(trimesh.Trimesh(verts, faces, process=False).vertex_normals)


class Families:
    """The deformations of a base mesh: candidate(family, axis, t) -> (n, 3)."""

    def __init__(self, base: np.ndarray, faces: np.ndarray, anterior_w: np.ndarray):
        self.base, self.faces = base, faces
        self.centre = base.mean(0)
        self.normals = vertex_normals(base, faces)
        apex = int(np.argmax(base @ anterior_w))
        d2 = ((base - base[apex]) ** 2).sum(1)
        self.bump = np.exp(-d2 / (2 * BULGE_RADIUS_MM**2))[:, None] * self.normals
        centred = base - self.centre
        _, _, vt = np.linalg.svd(centred, full_matrices=False)
        self.axis = vt[0]
        along = centred @ self.axis
        self.along = along / np.abs(along).max()

    def candidate(self, family: str, axis: int, t: float) -> np.ndarray:
        if family == "shift":
            out = self.base.copy()
            out[:, axis] += t
            return out
        if family == "scale":
            return self.centre + (1 + t / 100) * (self.base - self.centre)
        if family == "bulge":
            return self.base + t * self.bump
        if family == "twist":
            angle = np.radians(t) * self.along  # (n,)
            p = self.base - self.centre
            k = self.axis
            cos, sin = np.cos(angle)[:, None], np.sin(angle)[:, None]
            rotated = p * cos + np.cross(k, p) * sin + k[None] * (p @ k)[:, None] * (1 - cos)
            return self.centre + rotated
        raise ValueError(family)


def grid(family: str) -> np.ndarray:
    fine_half, fine_step = FINE[family]
    coarse_half, coarse_step = COARSE[family]
    fine = np.arange(-fine_half, fine_half + 1e-9, fine_step)
    coarse = np.arange(-coarse_half, coarse_half + 1e-9, coarse_step)
    return np.unique(np.round(np.concatenate([fine, coarse]), 6))


def landscape_flags(family: str, ts: np.ndarray, values: np.ndarray) -> dict:
    """(a) and (b) of one family's curve."""
    fine_half, _ = FINE[family]
    near = np.abs(ts) <= fine_half + 1e-9
    t_min = float(ts[near][np.argmin(values[near])])
    out = {"argmin": t_min, "minimum_met": abs(t_min) <= TOLERANCE[family] + 1e-9}
    if family in MONOTONE_TO:
        step = COARSE[family][1]
        worst_dip, rises = 0.0, []
        for sign in (1, -1):
            path = np.arange(0, MONOTONE_TO[family] + 1e-9, step) * sign
            curve = np.array([values[np.argmin(np.abs(ts - p))] for p in path])
            rise = float(curve[-1] - curve[0])
            dips = np.maximum(curve[:-1] - curve[1:], 0)
            rises.append(rise)
            worst_dip = max(worst_dip, float(dips.max()) / rise if rise > 0 else math.inf)
        out.update(rise=rises, worst_dip_fraction=worst_dip, monotone_met=bool(min(rises) > 0 and
                                                                              worst_dip <= DIP_FRACTION))
    return out


class FocusedEvaluator:
    """The trainer's loss of a FOCUSED_MODES mode ("focused", "depth": its FocusedSetup, smoothing and target)
    for one sample."""

    def __init__(self, geometry, config, sample: dict, faces: torch.Tensor, target: str, edges, mode: str):
        from meshsar_builder.trainer.train import focused_params

        self.name = mode
        rc = config.radar_loss
        self.params, self.geometry, self.edges, self.iterations = focused_params(rc), geometry, edges, \
            rc.smooth_iterations
        self.setup = geometry.focused_setup(self.params)
        batch = {"sample_id": [sample["sample_id"]], "echo_clean": sample["echo_clean"][None],
                 "noise_sigma": sample["noise_sigma"][None]}
        if target == "recorded":
            batch["echo_noisy"] = sample["echo_noisy"][None]
        self.targets = geometry.focused_targets(batch, self.params, target)
        self.faces = faces

    def __call__(self, verts: torch.Tensor) -> torch.Tensor:
        from meshsar_builder.trainer import losses as L

        smoothed = L.smooth_gradient(verts, self.edges, self.iterations)
        return L.focused_radar_loss(smoothed, self.faces, self.targets, self.setup, mode=self.name)


class RawEvaluator:
    """The trainer's raw relative L1 (mode raw) on RAW_ANTENNAS fixed antennas a view.

    clean: against echo_clean on the loss grid; recorded: against the recorded echo there (echo_clean plus
    the build's noise), as the trainer reads them (DatasetGeometry.echo_targets). The trainer's raw mode
    applies no gradient smoothing.
    """

    name = "raw"

    def __init__(self, geometry, sample: dict, faces: torch.Tensor, target: str):
        rng = np.random.default_rng(0)
        batch = {key: sample[key][None] for key in ("echo_clean", "echo_noisy") if key in sample}
        positions, freqs, echo = geometry.positions, geometry.freqs, geometry.echo_targets(batch, target)[0]
        pick = rng.choice(positions.shape[1], RAW_ANTENNAS, replace=False)
        self.positions, self.echo, self.freqs = positions[:, pick], echo[:, pick][None], freqs
        self.geometry, self.faces = geometry, faces

    def __call__(self, verts: torch.Tensor) -> torch.Tensor:
        from meshsar_builder.trainer import losses as L

        return L.radar_loss(verts, self.faces, self.echo, self.positions, self.geometry.centres, self.freqs,
                            self.geometry.radar, "raw", 10.0)


class ExactEvaluator:
    """The production echo as the model: each candidate's specular echo on the loss grid
    (radar.render.specular_loss_echo, the factorised facet integral), focused, squared and blurred
    as the targets are (FocusedSetup.target), against the same of the full-resolution truth.

    A reference, not a training loss: what an image-domain model that reproduced the echo exactly
    would measure on the same template-resolution candidates. Specular part only on both sides
    (the diffuse part's random scatterers are not the candidate's). No gradient (the echo is numba),
    so (c) is not measured.
    """

    name = "exact"
    differentiable = False

    def __init__(self, setup, radar, view_index, truth_verts: np.ndarray, truth_faces: np.ndarray, faces: np.ndarray):
        self.setup, self.view_index, self.faces = setup, view_index, faces
        self.radar = dataclasses.replace(radar, diffuse=False)
        self.target = torch.from_numpy(self.volumes(truth_verts, truth_faces))

    def volumes(self, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """(V, S, H, W) the focused, blurred power of a mesh's specular echo in the views in use."""
        from meshsar_builder.radar.render import specular_loss_echo

        return self.setup.target(specular_loss_echo(verts, faces, self.radar)[self.view_index], 0.0)

    def __call__(self, verts: torch.Tensor) -> torch.Tensor:
        from meshsar_builder.radar.focused import cosine_distance

        predicted = torch.from_numpy(self.volumes(verts[0].double().numpy(), self.faces))
        return cosine_distance(predicted, self.target).mean()  # views as the batch: the mean over views


def measure_sample(evaluator, families: Families, faces_np) -> dict:
    out = {}
    for family in ("shift", "scale", "bulge", "twist"):
        for axis in ((0, 1, 2) if family == "shift" else (0,)):
            key = f"{family}_{'xyz'[axis]}" if family == "shift" else family
            ts = grid(family)
            values = []
            for t in ts:
                v = torch.as_tensor(families.candidate(family, axis, t), dtype=torch.float32)[None]
                with torch.no_grad():
                    values.append(float(evaluator(v)))
            values = np.array(values)
            entry = {"t": ts.tolist(), "loss": values.tolist(), **landscape_flags(family, ts, values)}
            if family in COSINE_AT and not getattr(evaluator, "differentiable", True):
                entry["cosine_met"] = None  # not measured (ExactEvaluator)
            elif family in COSINE_AT:
                cosines = {}
                for mag in COSINE_AT[family]:
                    for sign in (1, -1):
                        cand = families.candidate(family, axis, sign * mag)
                        v = torch.as_tensor(cand, dtype=torch.float32)[None].requires_grad_(True)
                        evaluator(v).backward()
                        g = -v.grad[0].double().numpy().ravel()
                        d = (families.base - cand).ravel()
                        cosines[str(sign * mag)] = float(g @ d / max(np.linalg.norm(g) * np.linalg.norm(d), 1e-30))
                entry["cosine"] = cosines
                entry["cosine_met"] = min(cosines.values()) >= COSINE_MIN
            out[key] = entry
    return out


def summarise(per_sample: list[dict]) -> dict:
    families = [f for f in per_sample[0] if isinstance(per_sample[0][f], dict)]
    minimum = all(s[f]["minimum_met"] for s in per_sample for f in families)
    monotone = all(s[f].get("monotone_met", True) for s in per_sample for f in families)
    flags = [s[f].get("cosine_met", True) for s in per_sample for f in families]
    cosine = None if None in flags else all(flags)  # None: not measured (a model without gradients)
    cosines = [min(s[f]["cosine"].values()) for s in per_sample for f in families if "cosine" in s[f]]
    return {"met": {"minimum": minimum, "monotone": monotone, "cosine": cosine,
                    "all": bool(minimum and monotone and cosine)},
            "worst_argmin": {f: max(abs(s[f]["argmin"]) for s in per_sample) for f in families},
            "worst_cosine": min(cosines) if cosines else None,
            "worst_dip_fraction": {f: max(s[f]["worst_dip_fraction"] for s in per_sample) for f in families
                                   if "worst_dip_fraction" in per_sample[0][f]}}


def run(out_dir: str | Path, data: str | Path, samples: int = 5, config_path: str | Path | None = None,
        losses: tuple[str, ...] = ("focused", "raw"), targets: tuple[str, ...] = ("clean", "recorded")) -> dict:
    """Measure, write out_dir/radar_loss.json (rewritten after each sample: a partial run keeps what finished)."""
    from meshsar_builder.dataset.readers import MeshSARDataset
    from meshsar_builder.trainer import losses as L
    from meshsar_builder.trainer.config import load_config
    from meshsar_builder.trainer.model import icosphere_levels
    from meshsar_builder.radar.focused import radar_from_index
    from meshsar_builder.trainer.dataset_geometry import DatasetGeometry
    from meshsar_builder.trainer.train import focused_params

    data = Path(data)
    unknown = sorted(set(losses) - set(LOSSES))
    if unknown:
        raise InputError(f"bench radar-loss: unknown losses {unknown}; choose from {list(LOSSES)}")
    if not (data / "index.json").exists():
        raise InputError(f"bench radar-loss: {data} holds no build (build the demo recipe there first: "
                         f"meshsar build manifests/demo.toml --out {data})")
    config = load_config(config_path or Path(__file__).resolve().parents[2] / "manifests" / "train" / "default.toml")
    dataset = MeshSARDataset(data, None, noisy_loss_echo=True)
    if "loss_grid" not in dataset.index:
        raise InputError(f"bench radar-loss: {data} is a format-1 build without a loss grid; rebuild it")
    geometry = DatasetGeometry.from_index(dataset.index, config.data.views)
    levels, level_faces, _ = icosphere_levels(config.model.template_level)
    template, tfaces = levels[-1], level_faces[-1]
    faces_t = torch.as_tensor(tfaces, dtype=torch.long)
    edges = torch.as_tensor(L.mesh_edges(tfaces))
    anterior_w = np.asarray(geometry.frames[0][2])
    default = f"{config.radar_loss.mode}_{config.radar_loss.target}"
    result = {"data": str(data), "samples": [], "default": default, "config": config.name,
              "template_vertices": len(template), "raw_antennas_per_view": RAW_ANTENNAS,
              "smooth_iterations": config.radar_loss.smooth_iterations,
              "focused": {"lateral_mm": config.radar_loss.focused_lateral_mm,
                          "range_mm": config.radar_loss.focused_range_mm,
                          "blur_mm": config.radar_loss.focused_blur_mm},
              "entries": {}}
    # The exact reference simulates its own specular target: one entry, exact_specular.
    pairs = [(loss, target) for loss in losses for target in (("specular",) if loss == "exact" else targets)]
    per = {f"{loss}_{target}": [] for loss, target in pairs}
    previous = Path(out_dir) / "radar_loss.json"
    if previous.exists():  # keep the entries of other losses measured earlier on the same build
        old = json.loads(previous.read_text())
        if old.get("data") == str(data):
            result["entries"] = {k: v for k, v in old.get("entries", {}).items() if k not in per}
    for i in range(min(samples, len(dataset))):
        sample = dataset[i]
        verts, faces = sample["verts"].double().numpy(), sample["faces"].numpy()
        base = remesh_onto_template(verts, faces, template)
        families = Families(base, tfaces, anterior_w)
        result["samples"].append(sample["sample_id"])
        for loss, target in pairs:
            start = time.perf_counter()
            if loss in FOCUSED_MODES:
                evaluator = FocusedEvaluator(geometry, config, sample, faces_t, target, edges, loss)
            elif loss == "exact":
                evaluator = ExactEvaluator(geometry.focused_setup(focused_params(config.radar_loss)),
                                           radar_from_index(dataset.index), geometry.view_index, verts, faces, tfaces)
            else:
                evaluator = RawEvaluator(geometry, sample, faces_t, target)
            measured = measure_sample(evaluator, families, tfaces)
            measured["seconds"] = time.perf_counter() - start
            per[f"{loss}_{target}"].append(measured)
            print(f"{sample['sample_id']} {loss}/{target}: {measured['seconds']:.0f} s", flush=True)
        for key, items in per.items():
            if items:
                result["entries"][key] = {**summarise(items), "per_sample": items}
        result["samples_done"] = i + 1
        write_json(Path(out_dir) / "radar_loss.json", result)
    write_json(Path(out_dir) / "radar_loss.json", result)
    return result
