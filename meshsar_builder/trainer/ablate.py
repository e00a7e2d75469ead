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

`meshsar ablate CONFIG --data OUT --radar` (radar_ablation) is the radar loss's own test:
the radar weight chosen on the validation part, then radar on against off over more seeds,
compared sample by sample on the test part with a paired test.
"""

from __future__ import annotations

import concurrent.futures
import copy
import csv
import multiprocessing
import os
from pathlib import Path

import numpy as np
import tomli_w
import torch
from scipy import stats
from tqdm import tqdm

from meshsar_builder.dataset.shards import read_index
from meshsar_builder.pipeline.errors import InputError
from meshsar_builder.pipeline.io import read_json, write_bytes, write_json
from meshsar_builder.pipeline.recipe import read_text, tomllib
from meshsar_builder.trainer.config import TrainConfig, parse_config
from meshsar_builder.trainer.evaluate import BASELINES, HIGHER_IS_BETTER, evaluate
from meshsar_builder.trainer.metrics import COLUMNS
from meshsar_builder.trainer.train import (
    BEST,
    CHECKPOINT,
    LOG,
    load_checkpoint,
    read_log,
    same_run,
    save_checkpoint,
    train,
)

VARIANTS = ("default", "no_radar", "max_only", "single_view")
RADAR_WEIGHTS = (0.03, 0.1, 0.3)
RADAR_SEEDS = (0, 1, 2, 3, 4)
# The paired test's metrics: the paper's table (Dice, ASSD, HD, ANE and the normalised distances).
PAIRED_COLUMNS = ("dice", "assd_mm", "hd_mm", "ane_rad", "assd_norm", "hd_norm")
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


def _setup(config, data, out, prefix: str, split: str, epochs: int | None) -> tuple[dict, Path, str, Path]:
    """The config's table (checked first: errors name the file before anything trains), the data
    folder, the build's first view and the ablation's folder (out, or
    DATA/ablations/<prefix><config name>-<split>[-e<epochs>])."""
    text = read_text(config, "trainer config")
    parse_config(text, str(config))
    base = tomllib.loads(text)
    data = Path(data)
    folder = Path(out) if out is not None else (
        data / "ablations" / f"{prefix}{base['name']}-{split}{'' if epochs is None else f'-e{epochs}'}")
    return base, data, read_index(data)["views"][0]["name"], folder


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
    base, data, first_view, folder = _setup(config, data, out, "", split, epochs)
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


def _radar_table(base: dict, name: str, seed: int, first_view: str, epochs: int | None, weight: float) -> dict:
    """The config table of the radar ablation's run `name` at this seed and radar weight."""
    table = variant_table(base, "default", seed, first_view, epochs)
    table["name"] = f"{base['name']}-{name}"
    table.setdefault("radar_loss", {})["weight"] = weight
    return table


def _finished(run: Path, epochs: int) -> bool:
    """Whether the run's log covers all its epochs (a committed result needs no checkpoint)."""
    return [row["epoch"] for row in read_log(run / LOG)] == list(range(epochs))


def _test_rows(run: Path, data: Path, split: str, device: str | None, samples: int, progress: bool) -> dict:
    """sample id -> the run's test metrics (float per COLUMNS) from its best validation checkpoint."""
    table = run / f"eval-{split}" / "metrics.csv"
    if not table.exists():
        evaluate(run, data, split, renders=0, device=device or "cpu", samples=samples, progress=progress,
                 baselines=False)
    with open(table, newline="", encoding="utf-8") as f:
        return {row["sample_id"]: {c: float(row[c]) for c in COLUMNS} for row in csv.DictReader(f)
                if row["method"] not in BASELINES}


def branch_run(source: Path, run: Path, config: TrainConfig) -> None:
    """Start `run`, a run of `config`, from the checkpoint in run folder `source`, which trained as
    `config` would up to its epoch (same_run with until); its log and best.pt come along. A run that
    has a checkpoint of its own is left as it is."""
    if (run / CHECKPOINT).exists():
        return
    state = load_checkpoint(source / CHECKPOINT)
    if not same_run(state["config_text"], config, until=state["epoch"]):
        raise InputError(f"{source}: its checkpoint (epoch {state['epoch']}) did not train as {config.name} "
                         f"would up to there; {run} cannot start from it")
    write_bytes(run / LOG, (source / LOG).read_bytes())
    # The checkpoint last: its presence marks a finished branch.
    for name in (BEST, CHECKPOINT):
        if (source / name).exists():
            save_checkpoint(run / name, {**load_checkpoint(source / name), "config_text": config.text})


def _radar_task(table: dict, run: Path, warm: Path | None, until: int | None, data: Path, split: str,
                device: str | None, samples: int | None, progress: bool) -> dict | None:
    """Train one run of the radar ablation (from the shared warm-up `warm`, or, with `until`, that
    warm-up itself) unless its log is complete; with `samples`, its test rows (_test_rows)."""
    config = parse_config(tomli_w.dumps(table), str(run / "config.toml"))
    if until is not None or not _finished(run, config.optim.epochs):
        if warm is not None:
            branch_run(warm, run, config)
        train(config, data, split, run, progress=progress, device=device, until=until)
    return None if samples is None else _test_rows(run, data, split, device, samples, progress)


def radar_ablation(config: str | os.PathLike, data: str | os.PathLike, split: str = "seed-0",
                   seeds: tuple[int, ...] = RADAR_SEEDS, weights: tuple[float, ...] = RADAR_WEIGHTS,
                   epochs: int | None = None, device: str | None = None, out: str | os.PathLike | None = None,
                   samples: int = 20_000, progress: bool = True, jobs: int = 1) -> dict:
    """Radar loss on against off: the weight chosen on validation, then a paired test on the test part.

    1. One run per radar weight in `weights` at the first seed; the weight whose run reached
       the lowest validation ASSD is chosen (the test part is never looked at).
    2. Arms `radar` (that weight) and `no_radar` (weight 0), one run per seed each, at the
       config's own schedule (warm-up and ramp; `epochs` scales them as in ablate).
    3. Each test sample's metrics are averaged over the seeds per arm, and the arms compared
       by a two-sided Wilcoxon signed-rank test over test samples, per metric in
       PAIRED_COLUMNS. The seeds' spread is given beside it (mean ± std of the per-seed means).

    The runs of one seed train alike until the radar warm-up ends (the weight is 0 there), so
    that part trains once per seed, in warmup-seed-<S>/, and every run of the seed starts from
    its checkpoint (branch_run): the same numbers as training each from scratch, in about
    a third less time at the default config. jobs: runs trained at once, in processes that share
    the machine's cores (torch threads = cores // jobs); runs start as what they need is done.

    Writes OUT/ablations/radar-<config name>-<split>[-e<epochs>]/ (resumable like ablate; a run
    whose log.csv is complete is not retrained, so the logs and eval folders alone resume it):
    radar_ablation.json (keys: `weights` (weight -> validation ASSD), `chosen_weight`,
    `arms` (arm -> per seed, the metrics' test means), `spread` (arm -> metric -> [mean, std]),
    `paired` (metric -> p), `paired_detail` (metric -> n, median difference radar - no_radar,
    the better arm)) and radar_ablation.md.
    """
    if not weights or any(not w > 0 for w in weights):
        raise InputError(f"radar weights: need positive values, got {list(weights)}")
    if len(seeds) < 2:
        raise InputError(f"seeds: a paired comparison over seeds needs at least 2, got {list(seeds)}")
    if jobs < 1:
        raise InputError(f"jobs: need at least 1, got {jobs}")
    base, data, first_view, folder = _setup(config, data, out, "radar-", split, epochs)
    first = parse_config(tomli_w.dumps(_radar_table(base, "no_radar", seeds[0], first_view, epochs, 0.0)))
    total, warmup = first.optim.epochs, min(first.radar_loss.warmup_epochs, first.optim.epochs)

    def name_of(key: tuple) -> str:
        return key[0] if key[0] in ("warmup", "no_radar") else f"radar-w{key[2] if key[0] == 'weight' else chosen:g}"

    def run_of(key: tuple) -> Path:
        return folder / f"{name_of(key)}-seed-{key[1]}"

    def validation_assd(weight: float) -> float:
        run = run_of(("weight", seeds[0], weight))
        values = [row["val_assd_mm"] for row in read_log(run / LOG) if row.get("val_assd_mm") is not None]
        if not values:
            raise InputError(f"{run}: no validation ASSD in its log; the radar weight is chosen on validation "
                             "([data] val_fraction > 0)")
        return float(min(values))

    def choose() -> tuple[dict, float] | tuple[None, None]:
        if not all(_finished(run_of(("weight", seeds[0], w)), total) for w in weights):
            return None, None
        validation = {f"{w:g}": validation_assd(w) for w in weights}
        return validation, float(min(validation, key=validation.get))

    # Keys: ("warmup", seed), ("weight", seed, w) the choice's runs at the first seed, and the arms
    # ("radar", seed) and ("no_radar", seed). The list is their order of priority: the choice first,
    # since every radar arm waits for it.
    shared = warmup > 0
    todo = ([("warmup", seeds[0])] if shared else []) + [("weight", seeds[0], w) for w in weights] + \
        ([("warmup", s) for s in seeds[1:]] if shared else []) + [("radar", s) for s in seeds] + \
        [("no_radar", s) for s in seeds]
    validation, chosen = choose()
    rows: dict[tuple, dict] = {}
    done: set = set()

    def needs(key: tuple) -> list[tuple]:
        """What a run waits for: its seed's warm-up, and for a radar arm the chosen weight."""
        wait = [("warmup", key[1])] if shared and key[0] != "warmup" else []
        return wait + ([("weight", seeds[0], w) for w in weights] if key[0] == "radar" else [])

    def warmup_needed(seed: int) -> bool:
        """False once every run that starts from the seed's warm-up has a complete log."""
        runs = [("no_radar", seed)] + ([("weight", seed, w) for w in weights] if seed == seeds[0] else
                                       [("radar", seed)] if chosen is not None else [])
        return len(runs) == 1 or not all(_finished(run_of(k), total) for k in runs)

    def arguments(key: tuple) -> tuple:
        weight = {"weight": key[-1], "radar": chosen}.get(key[0], 0.0)
        table = _radar_table(base, name_of(key), key[1], first_view, epochs, weight)
        return (table, run_of(key), run_of(("warmup", key[1])) if shared and key[0] != "warmup" else None,
                warmup if key[0] == "warmup" else None, data, split, device,
                samples if key[0] in ("radar", "no_radar") else None, progress and jobs == 1)

    pool = concurrent.futures.ProcessPoolExecutor(
        jobs, mp_context=multiprocessing.get_context("spawn"), initializer=torch.set_num_threads,
        initargs=(max(1, (os.cpu_count() or 1) // jobs),)) if jobs > 1 else None
    running: dict[concurrent.futures.Future, tuple] = {}
    bar = tqdm(total=len(todo), desc="radar ablation runs", unit="run", disable=not progress or jobs == 1)
    try:
        while todo or running:
            for key in [k for k in todo if all(n in done for n in needs(k))][:jobs - len(running)]:
                todo.remove(key)
                if key[0] == "warmup" and not warmup_needed(key[1]):
                    done.add(key)
                    bar.update()
                    continue
                if pool is not None:
                    running[pool.submit(_radar_task, *arguments(key))] = key
                else:
                    running[future := concurrent.futures.Future()] = key
                    future.set_result(_radar_task(*arguments(key)))
            finished, _ = concurrent.futures.wait(running, return_when=concurrent.futures.FIRST_COMPLETED)
            for future in finished:
                key = running.pop(future)
                done.add(key)
                if future.result() is not None:
                    rows[key] = future.result()
                bar.update()
            if chosen is None:
                validation, chosen = choose()
    finally:
        bar.close()
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    arms = {"radar": f"radar-w{chosen:g}", "no_radar": "no_radar"}
    per_seed = {arm: [{"seed": seed, **{c: float(np.mean([r[c] for r in rows[arm, seed].values()]))
                                        for c in COLUMNS}} for seed in seeds] for arm in arms}
    per_sample = {arm: [rows[arm, seed] for seed in seeds] for arm in arms}
    ids = sorted(per_sample["radar"][0])
    paired, detail = {}, {}
    for column in PAIRED_COLUMNS:
        # Each test sample's metric averaged over the seeds: the sample is the unit.
        radar, off = ([np.mean([seed_rows[i][column] for seed_rows in per_sample[arm]]) for i in ids] for arm in arms)
        difference = np.subtract(radar, off)
        p = float(stats.wilcoxon(radar, off).pvalue) if np.any(difference != 0) else 1.0
        paired[column] = p
        median = float(np.median(difference))
        better = "tie" if median == 0 else ("radar" if (median > 0) == (column in HIGHER_IS_BETTER) else "no_radar")
        detail[column] = {"n": len(ids), "median_difference": median, "better": better}
    result = {
        "config": str(config), "data": str(data), "split": split, "seeds": list(seeds), "epochs": epochs,
        "weights": validation, "chosen_weight": chosen, "arms": per_seed,
        "spread": {arm: {c: [float(np.mean([r[c] for r in rows])), float(np.std([r[c] for r in rows]))]
                         for c in COLUMNS} for arm, rows in per_seed.items()},
        "paired": paired, "paired_detail": detail,
    }
    write_json(folder / "radar_ablation.json", result)
    write_bytes(folder / "radar_ablation.md", radar_markdown(result).encode())
    return result


def radar_markdown(result: dict) -> str:
    """Per arm mean ± std over seeds, then the paired test per metric."""
    lines = [f"# Radar loss on against off: {result['config']} on {result['data']} ({result['split']}, test; "
             f"seeds {', '.join(map(str, result['seeds']))}; {result['epochs'] or 'config'} epochs)", "",
             "Radar weight chosen on validation (lowest ASSD): "
             + ", ".join(f"{w}: {a:.3f} mm" for w, a in result["weights"].items())
             + f" -> **{result['chosen_weight']:g}**.", "",
             "| metric | radar | no radar | Wilcoxon p (test samples, seed means) | better |", "|---|---|---|---|---|"]
    for column in PAIRED_COLUMNS:
        arms = [result["spread"][arm][column] for arm in ("radar", "no_radar")]
        detail = result["paired_detail"][column]
        lines.append(f"| {column} {'↑' if column in HIGHER_IS_BETTER else '↓'} | "
                     + " | ".join(f"{m:.4g} ± {s:.2g}" for m, s in arms)
                     + f" | {result['paired'][column]:.3g} (n = {detail['n']}) | {detail['better']} |")
    return "\n".join(lines) + "\n"
