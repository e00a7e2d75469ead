"""`meshsar fit DATA --split seed-0`: the build's shape model fitted to each test sample's radar alone.

Analysis by synthesis, no network: the shape model (DATA/ssm/model.npz) with its K leading
modes, placed by a translation (and a rotation if asked), starts at its mean on the
heart-frame origin and moves so
that the focused radar loss's image-domain model of it (radar/focused.py, as the trainer
uses it) matches the focused recorded echo. The shape model keeps the shape smooth, which
the per-vertex radar gradient is not.

The image-domain model is biased: it splats each facet where it lies, while range migration
images a curved specular surface where its curvature puts it, so the fit alone stops about a
millimetre from a truth drawn from the model itself, at a loss below the truth's. The fit
therefore corrects the model's bias (defect correction): the production physics simulates
the echo of the fit's own mesh (radar.render, specular part), and the difference between its
focused power and the model's prediction of that mesh is taken off the target; the fit goes
on from where it stopped. At the fixed point the production echo of the fit, not the model's,
matches the recording. Simulating the estimate uses the radar parameters only.

Only what a scanner gives enters the fit: the recorded echo on the loss grid (the build's
echo_clean plus its noise, regenerated as the build drew it; the fit never separates the
two) and the radar parameters with the receiver's noise power (noise_sigma, which debiases
the target's power). With `snr_db` the noise is redrawn from the same seed at that image SNR
(sigma scaled from the build's image_snr_db); "off" fits the noise-free echo, the known-truth
check. The truth is read only to score the fit afterwards.

A whole-heart model fits whole-heart samples only: the test samples fitted are the build's
own shape-model samples (provenance "ssm"), drawn from the very model being fitted, so there
is no model error (an upper bound on what the radar gives). fit_held_out gives the honest
figure: each registered subject fitted by a model of the others.

Writes DATA/fits/<split>-k<K>-<noise>[-rot]/: fits.json (per sample: the fitted and true
standardised coefficients, the pose, the loss at the start, the end and the truth,
the per-vertex correspondence error, seconds), metrics.csv and summary.json / summary.md
as `meshsar evaluate` writes them (methods `radar_fit`, `ssm_mean`: the start, and the rows
of a trained run's evaluation on the same samples when `run` is given).
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import math
import os
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from meshsar_builder.dataset.readers import MeshSARDataset
from meshsar_builder.dataset.shards import loss_grid_indices, read_index
from meshsar_builder.pipeline.errors import InputError, MeshsarError
from meshsar_builder.pipeline.io import read_json, write_bytes, write_json
from meshsar_builder.radar.focused import FocusedParams, focused_loss
from meshsar_builder.radar.noise import recorded_echo
from meshsar_builder.trainer.config import split_seed
from meshsar_builder.trainer.evaluate import BASELINES, markdown, summarise, write_csv
from meshsar_builder.trainer.metrics import COLUMNS, mesh_metrics
from meshsar_builder.trainer.dataset_geometry import DatasetGeometry


@dataclasses.dataclass(frozen=True)
class FitParams:
    """How the fit moves: Adam on the standardised coefficients (coefficient / mode sd), the
    translation (mm) and, with rotation_lr > 0, the rotation (axis-angle, rad, about the mean's
    centre), each with its own step, for a fixed number of iterations.

    rotation_lr is 0 by default: the build places every shape-model sample in the model's own
    orientation, and a free rotation lets the fit trade the image-domain model's bias for a
    turn (measured: ASSD 1.51 mm against 1.05 mm on the demo's test samples, docs/trainer.md).
    Held-out subjects and scans lie 6-12 degrees off the model's frame and need it.

    corrections: rounds of model-bias (defect) correction after the first fit, each going on
    for correction_iterations steps (fit_corrected). 0 fits the image-domain model alone."""

    modes: int = 7
    iterations: int = 150
    corrections: int = 2
    correction_iterations: int = 75
    coefficient_lr: float = 0.05
    rotation_lr: float = 0.0
    translation_lr_mm: float = 0.5
    focused: FocusedParams = dataclasses.field(default_factory=FocusedParams)


def model_tensors(mean: np.ndarray, modes: np.ndarray, variances: np.ndarray, faces: np.ndarray) -> dict:
    """A shape model as float64 tensors: mean (n, 3), modes (K, n, 3), sd (K,), faces (m, 3) int64."""
    return {"mean": torch.from_numpy(np.asarray(mean, np.float64)), "modes": torch.from_numpy(np.asarray(modes, np.float64)),
            "sd": torch.from_numpy(np.sqrt(np.asarray(variances, np.float64))),
            "faces": torch.from_numpy(np.asarray(faces, np.int64))}


def shape_model_tensors(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """The build's shape model (ssm/model.npz) as model_tensors."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no shape model; the build has no ssm stage output")
    with np.load(path) as model:
        return model_tensors(model["mean"], model["modes"], model["variances"], model["faces"])


def fit_shape(model: dict[str, torch.Tensor], targets: torch.Tensor, setup, params: FitParams,
              start: dict | None = None) -> dict:
    """Fit the model's `params.modes` leading modes and its pose to focused targets.

    model: shape_model_tensors; targets (V, S, H, W) float, setup.target of the recorded
    echo of each view in setup.views. Starts at the mean, its bounding-box centre on the
    origin (the heart frame centres every sample there). Returns z (K,) the standardised
    coefficients, rotation (3,) axis-angle rad, translation (3,) mm (where the mean's centre
    goes), verts (n, 3) float64 mm, losses (iterations + 1,) the loss before each step and
    after the last. start: a result of fit_shape (its z, rotation, translation) to go on from
    instead of the mean.
    """
    k = params.modes
    if not 0 <= k <= model["modes"].shape[0]:
        raise InputError(f"fit: modes must be 0..{model['modes'].shape[0]} (the model's), got {k}")
    mean, modes, sd, faces = model["mean"], model["modes"][:k], model["sd"][:k], model["faces"]
    centre = (mean.max(0).values + mean.min(0).values) / 2
    start = start or {"z": np.zeros(k), "rotation": np.zeros(3), "translation": np.zeros(3)}
    z, rotation, translation = (torch.tensor(np.asarray(start[key], dtype=np.float64), requires_grad=True)
                                for key in ("z", "rotation", "translation"))
    groups = [{"params": [z], "lr": params.coefficient_lr}, {"params": [translation], "lr": params.translation_lr_mm}]
    optimiser = torch.optim.Adam(groups + ([{"params": [rotation], "lr": params.rotation_lr}]
                                           if params.rotation_lr > 0 else []))
    zero = torch.zeros((), dtype=torch.float64)

    def verts() -> torch.Tensor:
        x, y, w = rotation
        skew = torch.stack([torch.stack([zero, -w, y]), torch.stack([w, zero, -x]), torch.stack([-y, x, zero])])
        shape = mean + torch.einsum("k,kvc->vc", z * sd, modes) - centre  # (n, 3)
        return shape @ torch.linalg.matrix_exp(skew).T + translation  # (n, 3)

    losses = []
    for _ in range(params.iterations):
        optimiser.zero_grad()
        loss = focused_loss(verts()[None].float(), faces, targets[None], setup)
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
    with torch.no_grad():
        final = verts()
        losses.append(float(focused_loss(final[None].float(), faces, targets[None], setup)))
    return {"z": z.detach().numpy(), "rotation": rotation.detach().numpy(), "translation": translation.detach().numpy(),
            "verts": final.numpy(), "losses": np.asarray(losses)}


def model_bias(verts: np.ndarray, faces: torch.Tensor, setup, simulate) -> np.ndarray:
    """(V, S, H, W) float32: the production physics' focused power of a mesh less the image-domain
    model's specular prediction of it, scaled to it (least squares per view: the model has no
    absolute echo scale).

    verts (n, 3) mm; faces (m, 3) long; simulate: verts (n, 3) -> the mesh's noise-free
    specular echo on the loss grid (V, Lx, Ly, Lf), as the radar stage simulates it.
    """
    production = setup.target(simulate(verts))
    with torch.no_grad():
        model = np.stack([setup.predicted(torch.from_numpy(verts)[None].float(), faces, view, parts=("specular",))[0]
                          .numpy() for view in range(len(production))])  # (V, S, H, W)
    scale = (model * production).sum(axis=(1, 2, 3)) / np.maximum((model * model).sum(axis=(1, 2, 3)), 1e-30)
    return (production - scale[:, None, None, None] * model).astype(np.float32)


def fit_corrected(model: dict[str, torch.Tensor], targets: torch.Tensor, setup, params: FitParams,
                  simulate=None) -> dict:
    """fit_shape, then params.corrections rounds of defect correction (module docstring): each
    takes model_bias of the fit's mesh off the targets and goes on from the fit for
    params.correction_iterations steps. simulate: as model_bias's (needed only with corrections).
    Returns fit_shape's result of the last round with
    `rounds`: per correction round, the mean vertex move (mm) and the loss at its end,
    `targets` (V, S, H, W), the corrected targets the last round fitted, and `loss_start`, the
    loss at the start (before the first round's first step; `losses` are the last round's)."""
    if params.corrections and simulate is None:
        raise InputError("fit: model-bias corrections need a simulator of the production echo (simulate)")
    result = fit_shape(model, targets, setup, params)
    rounds, corrected, start = [], targets, float(result["losses"][0])
    for _ in range(params.corrections):
        corrected = targets - torch.from_numpy(model_bias(result["verts"], model["faces"], setup, simulate))
        previous = result["verts"]
        result = fit_shape(model, corrected, setup, dataclasses.replace(params, iterations=params.correction_iterations),
                           start=result)
        rounds.append({"moved_mm": float(np.linalg.norm(result["verts"] - previous, axis=1).mean()),
                       "loss_end": float(result["losses"][-1])})
    return {**result, "rounds": rounds, "targets": corrected, "loss_start": start}


def specular_simulator(data: Path, faces: np.ndarray):
    """verts (n, 3) -> the noise-free specular echo (V, Lx, Ly, Lf) on the loss grid of a mesh with
    these faces, simulated as the build's radar stage simulates a sample (its recipe's radar
    parameters, diffuse part off: its scatterers are the sample's own, which no scanner gives;
    noise off, so that no view images a noise volume echo_clean never holds). The recipe is
    read at the first call: a fit without corrections never makes one."""
    from meshsar_builder.pipeline import recipe as recipe_mod
    from meshsar_builder.radar.render import render_sample

    @functools.cache
    def setting():
        recipe = recipe_mod.load(data / "recipe.toml")
        return dataclasses.replace(recipe.radar, diffuse=False, snr_db=None, image_snr_db=math.inf), recipe.images

    return lambda verts: render_sample(verts, faces, *setting(), np.random.default_rng(0))["echo_clean"]


def recorded_loss_echo_at(sample: dict, index: dict, scale: float) -> np.ndarray:
    """(V, Lx, Ly, Lf) complex64: the recorded echo on the loss grid with the build's noise scaled
    by `scale` (1: the build's recording bit for bit; 0: noise-free), from the same seeds.

    sample: echo_clean (V, Lx, Ly, Lf), noise_seed (V,) and noise_sigma (V,), arrays or tensors."""
    full, keep = loss_grid_indices(index)
    return np.stack([recorded_echo(clean, seed, float(sigma) * scale, full, keep)
                     for clean, seed, sigma in zip(np.asarray(sample["echo_clean"]), sample["noise_seed"],
                                                   np.asarray(sample["noise_sigma"]))])


def noise_scale(index: dict, snr_db: float | None) -> float:
    """The factor on the build's noise sigma that gives image SNR `snr_db` (None: noise off). InputError
    for a build whose noise is not set by image_snr_db: its per-sample snr_db, or no noise (sigma 0,
    which no factor scales)."""
    if snr_db is None:
        return 0.0
    build = index["radar"].get("image_snr_db")
    if build is None:
        raw = index["radar"].get("snr_db")
        raise InputError(f"--snr-db {snr_db:g}: redraws the noise at an image SNR, which needs a build whose noise "
                         f"is set by [radar] image_snr_db; this build's is "
                         f"{'off' if raw is None else f'set by snr_db = {raw:g} (per sample)'}: fit its noise as "
                         "built (--snr-db build) or none (off)")
    return 10 ** ((float(build) - snr_db) / 20)


def _noise(index: dict, snr_db: float | None | str) -> tuple[float, str]:
    """(noise_scale, folder label) of a fit's snr_db: "build", a number in dB, or None (off)."""
    if snr_db == "build":
        return 1.0, "build"
    return noise_scale(index, snr_db), "off" if snr_db is None else f"{snr_db:g}db"


def fit_split(data: str | os.PathLike, split: str = "seed-0", params: FitParams = FitParams(),
              snr_db: float | None | str = "build", run: str | os.PathLike | None = None, samples: int = 20_000,
              limit: int | None = None, out: str | os.PathLike | None = None, progress: bool = True) -> dict:
    """Fit every shape-model test sample of `split` (module docstring); returns the summary.

    snr_db: "build" (the recorded echo as built), a number (the noise redrawn at that image
    SNR) or None (noise off); run: a trained run whose evaluation on this split
    (RUN/eval-<split>/metrics.csv) adds its rows for the same samples; limit: the first
    `limit` samples only.
    """
    data = Path(data)
    index = read_index(data)
    if index.get("loss_grid") is None:
        raise InputError(f"{data}: has no loss grid (shards format 2); rebuild it to fit the radar")
    model = shape_model_tensors(data / "ssm" / "model.npz")
    # a model has as many modes as its variance kept (the demo's 6): fit them all, as fit_held_out does
    params = dataclasses.replace(params, modes=min(params.modes, model["modes"].shape[0]))
    scale, label = _noise(index, snr_db)
    out = Path(out) if out is not None else data / "fits" / f"{split}-{_name(params, label)}"
    network = _run_rows(Path(run), split) if run is not None else {}
    geometry = DatasetGeometry.from_index(index, ())
    setup = geometry.focused_setup(params.focused)
    dataset = MeshSARDataset(data, "test", seed=split_seed(split))
    chosen = [(i, sample["sample_id"]) for i in range(len(dataset))
              if (sample := dataset[i])["meta"].get("provenance") == "ssm"][:limit]
    if not chosen:
        raise InputError(f"{data}: the test part of {split} has no shape-model samples to fit")
    record = {"data": str(data), "split": split, "snr_db": label, "params": _plain(params)}
    items = [(sid, i, lambda i=i: (dataset[i], model, params)) for i, sid in chosen]
    title = f"{data.name} ({split}, test, shape-model samples; {params.modes} modes, noise {label})"
    return _fit_items(out, record, items, index, scale, setup, specular_simulator(data, model["faces"].numpy()),
                      samples, network, title, progress)


def fit_held_out(data: str | os.PathLike, params: FitParams = FitParams(), snr_db: float | None | str = "build",
                 samples: int = 20_000, limit: int | None = None, out: str | os.PathLike | None = None,
                 progress: bool = True) -> dict:
    """Leave-subject-out: each registered subject of the build's shape model, fitted by a model of
    the others; returns the summary.

    The model of the others is built as the ssm stage builds the build's (the recipe's
    variance and Procrustes iterations, the groupwise template's frame), so it has not seen the
    subject: the fit's error includes the model's. The subject's echo is simulated as the
    radar stage simulates a sample (radar.render.render_sample on its registered mesh, centred
    on its bounding box; diffuse part and noise seeded by the recipe seed and the subject),
    then fitted as fit_split fits a test sample. Writes DATA/fits/held-out-k<K>-<noise>[-rot]/ alike.
    """
    from meshsar_builder.geometry.meshfile import read_ply
    from meshsar_builder.geometry.ssm import build_model
    from meshsar_builder.pipeline import recipe as recipe_mod
    from meshsar_builder.pipeline.seeding import item_rng
    from meshsar_builder.radar.render import render_sample

    data = Path(data)
    index = read_index(data)
    recipe = recipe_mod.load(data / "recipe.toml")
    record_file = data / "ssm" / "model.json"
    if not record_file.exists():
        raise InputError(f"{record_file}: not found; the build has no shape model to leave subjects out of")
    inputs = sorted(p for p in read_json(record_file)["inputs"] if p.startswith("register/"))
    subjects = [Path(p).stem for p in inputs if Path(p).stem != "template"]
    if len(subjects) < 4:
        raise InputError(f"{record_file}: {len(subjects)} registered subjects; leaving one out needs at least 4 "
                         "(a model of 3 or more)")
    template, faces, labels = read_ply(data / "register" / "template.ply")
    shapes = {sid: read_ply(data / "register" / f"{sid}.ply")[0] for sid in subjects}
    scale, label = _noise(index, snr_db)
    out = Path(out) if out is not None else data / "fits" / f"held-out-{_name(params, label)}"
    setup = DatasetGeometry.from_index(index, ()).focused_setup(params.focused)

    def subject(sid: str) -> tuple[dict, dict, FitParams]:
        others = np.stack([v for other, v in shapes.items() if other != sid])
        loo = build_model(others, faces, recipe.ssm.variance, recipe.ssm.procrustes_iterations, labels=labels,
                          reference=template)
        verts = shapes[sid] - (shapes[sid].max(0) + shapes[sid].min(0)) / 2
        echo = render_sample(verts, faces, recipe.radar, recipe.images, item_rng(recipe.seed, "fit-held-out", sid))
        source = read_json(data / "register" / f"{sid}.json").get("source", "")
        sample = {"sample_id": sid, "verts": torch.from_numpy(verts), "faces": torch.from_numpy(faces.astype(np.int64)),
                  "meta": {"source": source, "subset": "held_out"}, **{k: echo[k] for k in
                                                                        ("echo_clean", "noise_seed", "noise_sigma")}}
        # a model of s - 1 subjects has at most s - 2 modes
        return (sample, model_tensors(loo.mean, loo.modes, loo.variances, loo.faces),
                dataclasses.replace(params, modes=min(params.modes, len(loo.variances))))

    record = {"data": str(data), "split": "held-out", "snr_db": label, "params": _plain(params)}
    items = [(sid, n, lambda sid=sid: subject(sid)) for n, sid in enumerate(subjects[:limit])]
    title = f"{data.name} (held-out subjects, leave-one-out models; {params.modes} modes, noise {label})"
    return _fit_items(out, record, items, index, scale, setup, specular_simulator(data, faces), samples, {}, title,
                      progress)


def _fit_items(out: Path, record: dict, items: list, index: dict, scale: float, setup, simulate, samples: int,
               extra: dict, title: str, progress: bool) -> dict:
    """Fit each (id, metric seed, load -> (sample, model tensors, its FitParams)) item, keeping the fits that
    out/fits.json already holds with these settings (a rerun adds a run's rows or resumes);
    writes fits.json, metrics.csv and summary.json / .md; returns the summary. A sample whose fit fails (the
    radar refuses to simulate a correction round's mesh: one that drifted out of the images) is named in
    fits.json's `failed` and summary.md, and the others go on; a rerun tries it again."""
    previous = read_json(out / "fits.json") if (out / "fits.json").exists() else {}
    kept = previous.get("samples", {}) if all(previous.get(k) == v for k, v in record.items()) else {}
    rows, fits, failed = [], {}, {}
    for sid, seed, load in tqdm(items, desc=f"fit {out.name}", disable=not progress):
        try:
            fits[sid] = kept.get(sid) or _fit_sample(*load(), seed, index, scale, setup, simulate, samples)
            rows += fits[sid]["rows"] + extra.get(sid, [])
        except (MeshsarError, ValueError) as e:
            failed[sid] = f"{type(e).__name__}: {e}"
        write_json(out / "fits.json", {**record, "samples": fits, "failed": failed})
    if not fits:
        raise InputError(f"{out}: every sample's fit failed: {failed}")
    summary = summarise(rows)
    write_csv(out / "metrics.csv", rows)
    write_json(out / "summary.json", summary)
    failures = "".join(f"\n- {sid} failed: {message}" for sid, message in failed.items())
    write_bytes(out / "summary.md", f"# Shape model fitted to the radar alone: {title}\n\n{markdown(summary)}"
                                    f"{failures}".encode())
    return summary


def _fit_sample(sample: dict, model: dict, params: FitParams, seed: int, index: dict, scale: float, setup, simulate,
                samples: int) -> dict:
    """One test sample's fit record: coefficients, translation, losses, correspondence, seconds and
    its metric rows (`radar_fit` and the start, `ssm_mean`); the truth enters only the scores."""
    echo = recorded_loss_echo_at(sample, index, scale)
    targets = torch.from_numpy(setup.target(echo, np.asarray(sample["noise_sigma"]) * scale))  # (V, S, H, W)
    began = time.perf_counter()
    result = fit_corrected(model, targets, setup, params, simulate)
    seconds = time.perf_counter() - began
    start = fit_shape(model, targets, setup, dataclasses.replace(params, iterations=0))
    gt = (sample["verts"].double().numpy(), sample["faces"].numpy())
    k = params.modes
    rows = [{"sample_id": sample["sample_id"], "source": sample["meta"].get("source", ""),
             "subset": sample["meta"].get("subset", ""), "method": method,
             **mesh_metrics(verts, model["faces"].numpy(), *gt, samples=samples, seed=seed)}
            for method, verts in (("radar_fit", result["verts"]), ("ssm_mean", start["verts"]))]
    # against the targets the last round fitted (corrected for the model's bias at the fit)
    truth = focused_loss(torch.from_numpy(gt[0])[None].float(), torch.from_numpy(gt[1]), result["targets"][None], setup)
    return {
        "z": result["z"].tolist(),
        "z_true": (np.asarray(sample["meta"]["ssm_coeffs"][:k]) / model["sd"][:k].numpy()).tolist()
        if "ssm_coeffs" in sample["meta"] else None,
        "rotation_deg": np.degrees(result["rotation"]).tolist(), "translation_mm": result["translation"].tolist(),
        "loss_start": result["loss_start"], "loss_end": float(result["losses"][-1]), "loss_truth": float(truth),
        "corrections": result["rounds"],
        # the samples share the model's topology: vertex i of the fit against vertex i of the truth
        "correspondence_mm": float(np.linalg.norm(result["verts"] - gt[0], axis=1).mean()),
        "seconds": seconds, "rows": rows,
    }


def _run_rows(run: Path, split: str) -> dict[str, list[dict]]:
    """sample id -> a run's evaluation rows (its own methods, not the baselines), COLUMNS as floats."""
    table = run / f"eval-{split}" / "metrics.csv"
    if not table.exists():
        raise InputError(f"{table}: not found; run `meshsar evaluate {run} --split {split}` first")
    out: dict[str, list[dict]] = {}
    with open(table, newline="", encoding="utf-8") as f:
        for row in csv.DictReader(f):
            if row["method"] not in BASELINES:
                out.setdefault(row["sample_id"], []).append({**row, **{c: float(row[c]) for c in COLUMNS}})
    return out


def _name(params: FitParams, noise: str) -> str:
    """A fit folder's name after the split: k<modes>-<noise>[-rot]-c<corrections>."""
    return f"k{params.modes}-{noise}{'-rot' if params.rotation_lr > 0 else ''}-c{params.corrections}"


def _plain(params: FitParams) -> dict:
    return {**dataclasses.asdict(params), "focused": dataclasses.asdict(params.focused)}


def sweep_table(data: str | os.PathLike, split: str = "seed-0") -> str:
    """A markdown table of the fit folders under DATA/fits, the split's shape-model samples and the
    held-out subjects: mean ± std of ASSD, HD and Dice, the start's ASSD, the correspondence error."""
    lines = [("| samples | modes | noise | rotation | corrections | n | ASSD mm (fit) | ASSD mm (start) | HD mm (fit) | "
              "Dice (fit) | correspondence mm | s a fit |"), "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    fits_dir = Path(data) / "fits"
    for folder in sorted(fits_dir.glob(f"{split}-k*")) + sorted(fits_dir.glob("held-out-k*")):
        if not (folder / "summary.json").exists():
            continue
        summary, fits = read_json(folder / "summary.json")["all"], read_json(folder / "fits.json")
        fit, start = summary["radar_fit"], summary["ssm_mean"]
        records = list(fits["samples"].values())
        lines.append(f"| {fits['split']} | {fits['params']['modes']} | {fits['snr_db']} | "
                     f"{'free' if fits['params']['rotation_lr'] > 0 else 'fixed'} | "
                     f"{fits['params'].get('corrections', 0)} | {fit['assd_mm'][2]} | "
                     f"{fit['assd_mm'][0]:.2f} ± {fit['assd_mm'][1]:.2f} | {start['assd_mm'][0]:.2f} | "
                     f"{fit['hd_mm'][0]:.2f} ± {fit['hd_mm'][1]:.2f} | {fit['dice'][0]:.4f} | "
                     f"{np.mean([r['correspondence_mm'] for r in records]):.2f} | "
                     f"{np.mean([r['seconds'] for r in records]):.0f} |")
    return "\n".join(lines) + "\n"
