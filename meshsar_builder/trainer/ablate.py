"""`meshsar ablate CONFIG --data OUT`: the radar-loss, pooling and view ablation over seeds.

Variants of one config:
    default      the config as given
    no_radar     [radar_loss] weight = 0
    max_only     [model] pooling = ["max"]
    single_view  [data] views = [the build's first view]
Each variant trains once per seed (TrainConfig.seed: initialisation, batch order and
the radar loss's antenna draws) on the same split and validation part, and is
evaluated on the test part from its best validation checkpoint. `epochs` shortens
every run alike: [optim] epochs, and the radar warm-up, ramp, validation and
checkpoint intervals scaled with it, so the radar term still acts for the same
share of training.

Writes OUT/ablations/<config name>-<split>[-e<epochs>]/:
    <variant>-seed-<S>/  the run folders (resumable: a finished run is not retrained,
                         an evaluated one not re-evaluated)
    ablation.json        per variant and seed the run's test means; per variant the
                         mean ± std over seeds; the template and mean-shape baselines
    ablation.md          the same as a table
"""

from __future__ import annotations

import copy
import os
from pathlib import Path

import numpy as np
import tomli_w

from meshsar_builder.dataset.shards import read_index
from meshsar_builder.pipeline.errors import InputError
from meshsar_builder.pipeline.io import read_json, write_bytes, write_json
from meshsar_builder.pipeline.recipe import read_text, tomllib
from meshsar_builder.trainer.config import parse_config
from meshsar_builder.trainer.evaluate import BASELINES, HIGHER_IS_BETTER, evaluate
from meshsar_builder.trainer.metrics import COLUMNS
from meshsar_builder.trainer.train import read_log, train

VARIANTS = ("default", "no_radar", "max_only", "single_view")
TABLE_COLUMNS = ("dice", "assd_mm", "hd_mm", "hd95_mm", "ane_rad")  # the table's subset of COLUMNS


def variant_table(base: dict, variant: str, seed: int, first_view: str, epochs: int | None) -> dict:
    """The config table (parsed TOML) of one run: `base` with the variant's change, the seed and the schedule."""
    table = copy.deepcopy(base)
    table["seed"] = seed
    table["name"] = f"{base['name']}-{variant}"
    if variant == "no_radar":
        table.setdefault("radar_loss", {})["weight"] = 0.0
    elif variant == "max_only":
        table.setdefault("model", {})["pooling"] = ["max"]
    elif variant == "single_view":
        table.setdefault("data", {})["views"] = [first_view]
    if epochs is not None:
        default = parse_config(tomli_w.dumps(base))  # the values the base config gets, defaults included
        scale = epochs / default.optim.epochs
        table.setdefault("optim", {})["epochs"] = epochs
        radar, run = table.setdefault("radar_loss", {}), table.setdefault("run", {})
        radar["warmup_epochs"] = round(default.radar_loss.warmup_epochs * scale)
        radar["ramp_epochs"] = round(default.radar_loss.ramp_epochs * scale)
        run["val_every"] = max(1, round(default.run.val_every * scale))
        run["checkpoint_every"] = max(1, round(default.run.checkpoint_every * scale))
    return table


def _means(summary: dict, method: str) -> dict[str, float]:
    return {c: summary["all"][method][c][0] for c in COLUMNS}


def ablate(config: str | os.PathLike, data: str | os.PathLike, split: str = "seed-0", seeds: tuple[int, ...] = (0, 1, 2),
           variants: tuple[str, ...] = VARIANTS, epochs: int | None = None, device: str | None = None,
           out: str | os.PathLike | None = None, samples: int = 20_000, progress: bool = True) -> dict:
    """Train and evaluate every (variant, seed); returns the ablation summary (also written, see module docstring).

    samples: surface points per mesh for the distance metrics (evaluate's `samples`); device:
    where runs train and are evaluated (overrides [run] device; not part of a run's config, so
    runs trained on a GPU are evaluated, or resumed, on a CPU and the reverse).
    """
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise InputError(f"unknown ablation variant {unknown[0]!r}; known: {', '.join(VARIANTS)}")
    text = read_text(config, "trainer config")
    parse_config(text, str(config))  # errors name the file before anything trains
    base = tomllib.loads(text)
    data = Path(data)
    first_view = read_index(data)["views"][0]["name"]
    folder = Path(out) if out is not None else (
        data / "ablations" / f"{base['name']}-{split}{'' if epochs is None else f'-e{epochs}'}")
    runs, baselines = {v: {} for v in variants}, {}
    # Seed by seed, every variant: an ablation stopped part-way has compared the variants on equal terms.
    for seed in seeds:
        for variant in variants:
            table = variant_table(base, variant, seed, first_view, epochs)
            run = folder / f"{variant}-seed-{seed}"
            parsed = parse_config(tomli_w.dumps(table), str(run / "config.toml"))
            train(parsed, data, split, run, progress=progress, device=device)
            summary_file = run / f"eval-{split}" / "summary.json"
            if not summary_file.exists():
                # The baselines see no images and every run has the same training ids: score them once.
                evaluate(run, data, split, renders=0, device=device or parsed.run.device, samples=samples,
                         progress=progress, baselines=not baselines)
            summary = read_json(summary_file)
            kind = next(m for m in summary["all"] if m not in BASELINES)
            baselines = baselines or {m: _means(summary, m) for m in BASELINES if m in summary["all"]}
            runs[variant][str(seed)] = {
                **_means(summary, kind),
                "train_seconds": float(sum(row["seconds"] for row in read_log(run / "log.csv"))),
            }
    result = {
        "config": str(config), "data": str(data), "split": split, "seeds": list(seeds), "epochs": epochs,
        "runs": runs, "baselines": baselines,
        "variants": {v: {c: [float(np.mean([r[c] for r in per.values()])), float(np.std([r[c] for r in per.values()]))]
                         for c in (*COLUMNS, "train_seconds")} for v, per in runs.items()},
    }
    write_json(folder / "ablation.json", result)
    write_bytes(folder / "ablation.md", markdown(result).encode())
    return result


def markdown(result: dict) -> str:
    """Mean ± std over seeds per variant, then the baselines (no images, so no spread)."""
    head = [f"{c} {'↑' if c in HIGHER_IS_BETTER else '↓'}" for c in TABLE_COLUMNS]
    lines = [f"# Ablation of {result['config']} on {result['data']} ({result['split']}, test; seeds "
             f"{', '.join(map(str, result['seeds']))}; {result['epochs'] or 'config'} epochs)", "",
             "| method | " + " | ".join(head) + " | train s |", "|---|" + "---|" * (len(TABLE_COLUMNS) + 1)]
    for variant, stats in result["variants"].items():
        cells = [f"{stats[c][0]:.4g} ± {stats[c][1]:.2g}" for c in TABLE_COLUMNS]
        lines.append(f"| {variant} | " + " | ".join(cells) + f" | {stats['train_seconds'][0]:.0f} |")
    for name, means in result["baselines"].items():
        lines.append(f"| {name} | " + " | ".join(f"{means[c]:.4g}" for c in TABLE_COLUMNS) + " | – |")
    return "\n".join(lines) + "\n"
