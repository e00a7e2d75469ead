"""`meshsar evaluate RUN --data OUT [--split seed-0]`: metrics of a trained run on the test split.

Writes RUN/eval-<split>/:
    metrics.csv   one row per (sample, method): sample_id, source, subset, method, COLUMNS
    summary.md    mean ± std per source (and over all), methods as rows, COLUMNS in order
    summary.json  the same numbers as plain data
    renders.png   ground truth beside prediction in every view, for the first samples
Methods: "sar2mesh" (the run's final mesh) and "template" (the undeformed sphere
at the model's template radius: the baseline the network must beat).
"""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from meshsar_builder.dataset.card import plt, render_views, save_figure
from meshsar_builder.dataset.readers import MeshSARDataset
from meshsar_builder.dataset.shards import read_index
from meshsar_builder.pipeline.io import write_bytes, write_json
from meshsar_builder.trainer.metrics import COLUMNS, mesh_metrics
from meshsar_builder.trainer.model import icosphere_levels
from meshsar_builder.trainer.train import DatasetGeometry, load_run, split_seed

METHODS = ("sar2mesh", "template")
HIGHER_IS_BETTER = {"dice", "jaccard"}


def template_mesh(level: int, radius_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The undeformed template as a smooth icosphere of the final level: verts (n, 3) mm, faces (m, 3)."""
    verts, faces, _ = icosphere_levels(level)
    return verts[level] * radius_mm, faces[level]


def summarise(rows: list[dict]) -> dict:
    """{group: {method: {column: [mean, std, count]}}}, groups: every source, then "all"."""
    groups = sorted({r["source"] for r in rows}) + ["all"]
    out = {}
    for group in groups:
        chosen = [r for r in rows if group == "all" or r["source"] == group]
        out[group] = {}
        for method in METHODS:
            values = [r for r in chosen if r["method"] == method]
            if values:
                out[group][method] = {c: [float(np.mean([v[c] for v in values])), float(np.std([v[c] for v in values])),
                                          len(values)] for c in COLUMNS}
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


def render_pairs(pairs: list[tuple[str, tuple, tuple]], views: list[dict], fov_mm: float, path: Path) -> None:
    """Per sample a row: per view the ground truth, then the prediction. pairs: (id, (v, f) gt, (v, f) pred)."""
    cols = 2 * len(views)
    fig, axes = plt.subplots(len(pairs), cols, figsize=(1.8 * cols, 1.9 * len(pairs)), squeeze=False)
    for r, (sample_id, gt, pred) in enumerate(pairs):
        for c, (what, mesh) in enumerate((("truth", gt), ("prediction", pred))):
            for k, image in enumerate(render_views(*mesh, None, views, fov_mm)):
                ax = axes[r, 2 * k + c]
                ax.imshow(image)
                if r == 0:
                    ax.set_title(f"{views[k]['name']}\n{what}", fontsize=8)
        axes[r, 0].set_ylabel(sample_id, fontsize=7)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    save_figure(fig, path)


def evaluate(run: str | os.PathLike, data: str | os.PathLike | None = None, split: str = "seed-0",
             renders: int = 4, device: str = "cpu", samples: int = 20_000, progress: bool = True) -> dict:
    """Evaluate a run on the test split of `split`; returns the summary (see module docstring).

    data: the build folder (default: the one the run was trained on); renders: samples drawn.
    """
    run = Path(run)
    model, config, info = load_run(run, device)
    data = Path(data if data is not None else info["data"])
    index = read_index(data)
    geometry = DatasetGeometry.from_index(index, tuple(info["view_names"]))
    dataset = MeshSARDataset(data, "test", seed=split_seed(split), channels=list(info["channels"]))
    baseline = template_mesh(config.model.template_level, info["template_radius_mm"])
    faces = model.topology()["faces"].cpu().numpy()
    rows, pairs = [], []
    for i in tqdm(range(len(dataset)), desc="evaluate", disable=not progress):
        sample = dataset[i]
        with torch.no_grad():
            verts = model(sample["sar"][None, geometry.view_index].to(device))[-1][1][0].cpu().double().numpy()
        gt = (sample["verts"].double().numpy(), sample["faces"].numpy())
        for method, (pv, pf) in zip(METHODS, ((verts, faces), baseline)):
            metrics = mesh_metrics(pv, pf, *gt, samples=samples, seed=i)
            rows.append({"sample_id": sample["sample_id"], "source": sample["meta"].get("source", ""),
                         "subset": sample["meta"].get("subset", ""), "method": method, **metrics})
        if len(pairs) < renders:
            pairs.append((sample["sample_id"], gt, (verts, faces)))
    out = run / f"eval-{split}"
    summary = summarise(rows)
    write_csv(out / "metrics.csv", rows)
    write_bytes(out / "summary.md", (f"# {config.name} on {data.name} ({split}, test)\n\n" + markdown(summary)).encode())
    write_json(out / "summary.json", summary)
    if pairs:
        views = [index["views"][k] for k in geometry.view_index]
        render_pairs(pairs, views, geometry.fov_mm, out / "renders.png")
    return summary
