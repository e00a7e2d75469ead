"""`meshsar evaluate RUN --data OUT [--split seed-0] [--with RUN2 ...] [--device D] [--renders N]`: test metrics.

Writes RUN/eval-<split>/:
    metrics.csv   one row per (sample, method): sample_id, source, subset, method, COLUMNS
    summary.md    mean ± std per source (and over all), methods as rows, COLUMNS in order
    summary.json  the same numbers as plain data
    renders.png   ground truth beside prediction in every view (every sample, or the first N)
Methods: the run's model, named by its [model] kind ("sar2mesh", or "implicit" for
the learned occupancy baseline), from its best validation checkpoint; the runs given
with --with beside it (kind, or kind-name when taken); and two baselines that see no
images: "template" (the undeformed sphere at the model's template radius) and
"mean_shape" (the mean of the training shapes, each centred at the heart frame's
origin: the check that the images help at all).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import os
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from meshsar_builder.dataset.card import plt, render_views, save_figure
from meshsar_builder.dataset.readers import MeshSARDataset
from meshsar_builder.dataset.shards import read_index
from meshsar_builder.pipeline.errors import InputError
from meshsar_builder.pipeline.io import read_json, write_bytes, write_json
from meshsar_builder.trainer.metrics import COLUMNS, mesh_metrics, occupancy_surface, voxelise
from meshsar_builder.trainer.model import icosphere_levels
from meshsar_builder.trainer.refine import sample_refiner
from meshsar_builder.trainer.dataset_geometry import DatasetGeometry
from meshsar_builder.trainer.train import Subset, load_run, pick_device, split_seed

BASELINES = ("template", "mean_shape")
HIGHER_IS_BETTER = {"dice", "jaccard"}


def template_mesh(level: int, radius_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The undeformed template as a smooth icosphere of the final level: verts (n, 3) mm, faces (m, 3)."""
    verts, faces, _ = icosphere_levels(level)
    return verts[level] * radius_mm, faces[level]


def mean_shape(meshes: list[tuple[np.ndarray, np.ndarray]], voxel_mm: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The mean of closed meshes (verts (n_i, 3) mm, faces (m_i, 3)) of any topologies: each is centred at
    the origin (its vertex mean) and voxelised, and the surface where the fraction inside is 1/2 is
    extracted by marching cubes. Returns verts (n, 3) mm, faces (m, 3), outward."""
    centred = [(v - v.mean(0), f) for v, f in meshes]
    extent = max(np.abs(v).max() for v, _ in centred) + 2 * voxel_mm
    n = int(np.ceil(2 * extent / voxel_mm))
    lo = np.full(3, -n * voxel_mm / 2)
    occupancy = np.mean([voxelise(v, f, lo, (n, n, n), voxel_mm) for v, f in centred], axis=0)
    return occupancy_surface(occupancy, lo, voxel_mm)


def summarise(rows: list[dict]) -> dict:
    """{group: {method: {column: [mean, std, count]}}}, groups: every source, then "all"."""
    groups = sorted({r["source"] for r in rows}) + ["all"]
    out = {}
    for group in groups:
        chosen = [r for r in rows if group == "all" or r["source"] == group]
        out[group] = {}
        for method in dict.fromkeys(r["method"] for r in rows):
            values = [r for r in chosen if r["method"] == method]
            if values:
                out[group][method] = {c: [float(np.mean([v[c] for v in values])), float(np.std([v[c] for v in values])),
                                          len(values)] for c in COLUMNS}
    return out


def refine_paired(rows: list[dict]) -> dict:
    """method -> metric -> n, the Wilcoxon signed-rank p over samples of `<method>+refine`
    against `<method>`, the median difference (after - before) and the better of the two."""
    from scipy import stats

    by = {(r["method"], r["sample_id"]): r for r in rows}
    out = {}
    for method in dict.fromkeys(r["method"][: -len("+refine")] for r in rows if r["method"].endswith("+refine")):
        ids = [sid for m, sid in by if m == method]
        out[method] = {}
        for column in COLUMNS:
            before = np.array([by[method, i][column] for i in ids])
            after = np.array([by[f"{method}+refine", i][column] for i in ids])
            difference = after - before
            p = float(stats.wilcoxon(after, before).pvalue) if np.any(difference != 0) else 1.0
            median = float(np.median(difference))
            better = "tie" if median == 0 else ("refine" if (median > 0) == (column in HIGHER_IS_BETTER) else "before")
            out[method][column] = {"n": len(ids), "p": p, "median_difference": median, "better": better}
    return out


def markdown(summary: dict) -> str:
    """Mean ± std tables, one per source group, columns in COLUMNS order (arrows: better direction)."""
    head = [f"{c} {'↑' if c in HIGHER_IS_BETTER else '↓'}" for c in COLUMNS]
    lines = []
    for group, methods in summary.items():
        n = next(iter(methods.values()))[COLUMNS[0]][2]
        lines += [f"### {group} (n = {n})", "", "| method | " + " | ".join(head) + " |",
                  "|---|" + "---|" * len(COLUMNS)]
        for method, stats in methods.items():
            lines.append(f"| {method} | " + " | ".join(f"{stats[c][0]:.4g} ± {stats[c][1]:.2g}" for c in COLUMNS) + " |")
        lines.append("")
    return "\n".join(lines)


def write_csv(path: Path, rows: list[dict]) -> None:
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=["sample_id", "source", "subset", "method", *COLUMNS])
    writer.writeheader()
    writer.writerows(rows)
    write_bytes(path, text.getvalue().encode("utf-8"))


def render_gallery(rows: list[tuple[str, list[tuple[str, tuple]]]], views: list[dict], fov_mm: float,
                   path: Path) -> None:
    """Per sample a row: per view each of its meshes. rows: (sample id, [(label, (verts, faces)), ...])."""
    per = len(rows[0][1])
    cols = per * len(views)
    fig, axes = plt.subplots(len(rows), cols, figsize=(1.8 * cols, 1.9 * len(rows)), squeeze=False)
    for r, (sample_id, meshes) in enumerate(rows):
        for c, (what, mesh) in enumerate(meshes):
            for k, image in enumerate(render_views(*mesh, None, views, fov_mm)):
                ax = axes[r, per * k + c]
                ax.imshow(image)
                if r == 0:
                    ax.set_title(f"{views[k]['name']}\n{what}", fontsize=8)
        axes[r, 0].set_ylabel(sample_id, fontsize=7)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    save_figure(fig, path)


def training_shapes(run: Path, data: Path, split: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """The ground-truth meshes the run trained on (run.json's train_ids; else the split's train part)."""
    dataset = MeshSARDataset(data, "train", seed=split_seed(split))
    ids = read_json(run / "run.json").get("train_ids", dataset.ids) if (run / "run.json").exists() else dataset.ids
    chosen = Subset(dataset, ids)
    return [(chosen[i]["verts"].double().numpy(), chosen[i]["faces"].numpy()) for i in range(len(chosen))]


def evaluate(run: str | os.PathLike, data: str | os.PathLike | None = None, split: str = "seed-0",
             renders: int | None = None, device: str = "cpu", samples: int = 20_000, progress: bool = True,
             checkpoint: str = "best", compare: tuple[str | os.PathLike, ...] = (), baselines: bool = True,
             refine: bool = False, refine_echo: str | os.PathLike | None = None) -> dict:
    """Evaluate a run (and the runs in `compare`) on the test split of `split`; returns the summary
    (see module docstring), written under RUN/eval-<split>.

    data: the build folder (default: the one the run was trained on); renders: samples drawn
    (None: all); checkpoint: "best" (validation) or "last"; baselines: False leaves out the
    template and mean-shape rows (an ablation scores them once for all its runs); refine: also
    each mesh model's prediction refined against the sample's recorded echo (refine.refine_mesh,
    the run's [refine]), as method `<method>+refine`, with a Wilcoxon signed-rank test per
    metric over the test samples, before against after, in refine.json; written under
    RUN/eval-<split>-refine instead. refine_echo: with refine, the recorded echo comes from this
    build's sample of the same id instead (the same recipe's samples with other radar settings,
    e.g. `diffuse = false`), while the network still reads `data`'s images; written under
    RUN/eval-<split>-refine-<its folder name>.
    """
    run = Path(run)
    device = pick_device(device, 0)
    model, config, info = load_run(run, device, checkpoint)
    data = Path(data if data is not None else info["data"])
    index = read_index(data)
    learned = []  # (method, model, view positions, channel positions)
    configs = {}  # method -> its run's config ([refine], [radar_loss])
    for path, (net, cfg, inf) in [(run, (model, config, info)), *((p, load_run(p, device, checkpoint)) for p in compare)]:
        taken = [m for m, *_ in learned]
        method = cfg.model.kind if cfg.model.kind not in taken else f"{cfg.model.kind}-{cfg.name}"
        missing = [c for c in inf["channels"] if c not in index["channels"]]
        if missing:
            raise InputError(f"{data}: lacks the channels {missing} that run {path} uses")
        views = DatasetGeometry.from_index(index, tuple(inf["view_names"])).view_index
        learned.append((method, net, views, [index["channels"].index(c) for c in inf["channels"]]))
        configs[method] = cfg
    dataset = MeshSARDataset(data, "test", seed=split_seed(split), noisy_loss_echo=refine)
    if not len(dataset):
        raise InputError(f"{data}/splits/{split}.json: its test part holds no samples (too few subjects for its "
                         f"ratios: each subject's samples stay in one part); nothing to evaluate")
    if refine:
        echoes = _echo_source(data, index, refine_echo)
        # mesh models only: an implicit model's surface has no topology to move
        refiners = {method: (net.topology(), sample_refiner(index, configs[method])) for method, net, *_ in learned
                    if hasattr(net, "topology")}
    baselines = {"template": template_mesh(config.model.template_level, info["template_radius_mm"]),
                 "mean_shape": mean_shape(training_shapes(run, data, split))} if baselines else {}
    rows, pairs = [], []
    for i in tqdm(range(len(dataset)), desc="evaluate", disable=not progress):
        sample = dataset[i]
        meshes = {method: net.predict_mesh(sample["sar"][views][:, channels]) for method, net, views, channels in learned}
        gt = (sample["verts"].double().numpy(), sample["faces"].numpy())
        if refine:
            for method, (topology, refined) in refiners.items():
                meshes[f"{method}+refine"] = (refined(meshes[method][0], topology, echoes(sample)), meshes[method][1])
        for method, (pv, pf) in {**meshes, **baselines}.items():
            metrics = mesh_metrics(pv, pf, *gt, samples=samples, seed=i)
            rows.append({"sample_id": sample["sample_id"], "source": sample["meta"].get("source", ""),
                         "subset": sample["meta"].get("subset", ""), "method": method, **metrics})
        if renders is None or len(pairs) < renders:
            pairs.append((sample["sample_id"], [("truth", gt), *meshes.items()]))
    out = run / eval_folder(split, refine, refine_echo)
    summary = summarise(rows)
    if refine:
        write_json(out / "refine.json", refine_paired(rows))
    write_csv(out / "metrics.csv", rows)
    echo_note = f"; refined against {Path(refine_echo).name}'s echo" if refine and refine_echo else ""
    if refine:  # the [refine] each refined method ran with, since RUN/config.toml may change it after training
        echo_note += "; [refine] " + ", ".join(
            f"{method}: " + ", ".join(f"{k} = {v}" for k, v in dataclasses.asdict(configs[method].refine).items())
            for method in refiners)
    title = f"# {config.name} on {data.name} ({split}, test; {info['checkpoint']}, epoch {info['epoch']}{echo_note})\n\n"
    write_bytes(out / "summary.md", (title + markdown(summary)).encode())
    write_json(out / "summary.json", summary)
    if pairs:
        render_gallery(pairs, [index["views"][k] for k in learned[0][2]], float(index["fov_mm"]), out / "renders.png")
    return summary


def eval_folder(split: str, refine: bool = False, refine_echo: str | os.PathLike | None = None) -> str:
    """The folder under RUN that evaluate writes: eval-<split>[-refine[-<refine_echo's name>]]."""
    return f"eval-{split}{'-refine' if refine else ''}{f'-{Path(refine_echo).name}' if refine and refine_echo else ''}"


def _echo_source(data: Path, index: dict, other: str | os.PathLike | None):
    """sample -> the sample whose recorded echo refinement reads: itself, or (other given) the
    sample of the same id in build `other`, checked to hold the same mesh on the same loss grid."""
    if other is None:
        return lambda sample: sample
    other = Path(other)
    echoes = MeshSARDataset(other, None, noisy_loss_echo=True)
    if echoes.index.get("loss_grid") != index.get("loss_grid"):
        raise InputError(f"{other}: its loss grid differs from {data}'s; refinement needs the same grid")
    position = {sid: i for i, sid in enumerate(echoes.ids)}

    def echo_sample(sample: dict) -> dict:
        sid = sample["sample_id"]
        if sid not in position:
            raise InputError(f"{other}: has no sample {sid} (of {data}); build the same recipe there")
        found = echoes[position[sid]]
        if not torch.equal(found["verts"], sample["verts"]):
            raise InputError(f"{other}: sample {sid}'s mesh differs from {data}'s: not the same recipe's samples")
        return found

    return echo_sample
