"""The `meshsar` command line."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from meshsar_builder.pipeline.errors import MeshsarError
from meshsar_builder.pipeline.lock import folder_lock, refuse_if_locked


def cmd_build(args: argparse.Namespace) -> int:
    from meshsar_builder.pipeline import recipe as recipe_mod
    from meshsar_builder.pipeline.pools import server_modules, start_worker_server
    from meshsar_builder.pipeline.runner import build, format_summary, stage_modules

    preload = server_modules(args.workers, args.scheduler, stage_modules())
    if preload:  # the workers' imports beside the recipe's (1 s of numpy, numba...)
        start_worker_server(preload)
    recipe = recipe_mod.load(args.recipe)
    if args.device is not None:
        recipe = recipe_mod.override(recipe, "radar", "device", args.device, "--device")
    out = Path(args.out) if args.out else Path("build") / recipe.name
    results = build(recipe, out, workers=args.workers, until=args.until, force=tuple(args.force),
                    scheduler=args.scheduler, break_lock=args.break_lock)
    print(format_summary(results))
    print(f"\noutput: {out}")
    return 1 if results.failures else 0


def cmd_splits(args: argparse.Namespace) -> int:
    from meshsar_builder.dataset.splits import parse_ratios, split_dataset

    try:
        ratios = parse_ratios(args.ratios) if args.ratios else None
    except ValueError as e:
        print(f"error: --ratios: {e}", file=sys.stderr)
        return 2
    with folder_lock(args.out, create=False):  # never beside a build writing the index
        print(split_dataset(Path(args.out), args.seed, ratios))
    return 0


def cmd_verify(args: argparse.Namespace) -> int:
    from meshsar_builder.dataset.verify import notes, verify

    refuse_if_locked(args.out)  # a build in progress rewrites what would be checked
    problems = verify(Path(args.out))
    for p in problems:
        print(p)
    for n in notes(Path(args.out)):  # e.g. a split grouped by sample, an opt-in
        print(f"note: {n}")
    print(f"{len(problems)} problem(s)" if problems else f"{args.out}: dataset verified")
    return 1 if problems else 0


def cmd_preview(args: argparse.Namespace) -> int:
    from meshsar_builder.dataset.card import preview

    with folder_lock(args.out, create=False):  # card/ is the build's card stage's folder too
        print(preview(Path(args.out), args.n))
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from meshsar_builder.bench.suite import PARTS, run

    if args.recipe:
        if args.part != "pipeline":
            print("error: --recipe goes with the pipeline part (meshsar bench pipeline --recipe R)", file=sys.stderr)
            return 2
        from meshsar_builder.bench.suite import bench_pipeline, bench_recipe

        if args.scaling:
            print(json.dumps(bench_pipeline(Path(args.out), recipe=Path(args.recipe))["scaling"]))
            return 0
        result = bench_recipe(Path(args.out), Path(args.recipe), args.workers, args.device)
        print(json.dumps({k: result[k] for k in ("wall_seconds", "target_met", "samples", "samples_per_minute",
                                                  "failures")}))
        return 1 if result["failures"] else 0
    parts = list(PARTS) if args.part == "all" else [args.part]
    from meshsar_builder.bench import result_name

    device = args.device or "cpu"
    for part in run(parts, Path(args.out), device):
        print(f"{part}: {Path(args.out) / result_name(part, device)}")
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from meshsar_builder.trainer.train import train

    refuse_if_locked(args.data)  # a build in progress rewrites the index and shards
    print(train(args.config, args.data, args.split, args.out, device=args.device).run)
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from meshsar_builder.trainer.evaluate import eval_folder, evaluate

    refuse_if_locked(args.data)
    refine = args.refine or args.refine_echo is not None
    evaluate(args.run, args.data, args.split, renders=args.renders, device=args.device, checkpoint=args.checkpoint,
             compare=tuple(args.compare), samples=args.samples, refine=refine, refine_echo=args.refine_echo)
    print((Path(args.run) / eval_folder(args.split, refine, args.refine_echo) / "summary.md").read_text())
    return 0


def cmd_fit(args: argparse.Namespace) -> int:
    from meshsar_builder.pipeline.io import write_bytes
    from meshsar_builder.trainer.fit import FitParams, fit_held_out, fit_split, sweep_table

    try:
        modes = [int(k) for k in args.modes.split(",")]
        noises = ["build" if n == "build" else None if n == "off" else float(n) for n in args.snr_db.split(",")]
    except ValueError:
        print(f"error: --modes takes comma-separated integers and --snr-db numbers, build or off; got "
              f"{args.modes!r} and {args.snr_db!r}", file=sys.stderr)
        return 2
    refuse_if_locked(args.data)
    for k in modes:
        for noise in noises:
            params = FitParams(modes=k, iterations=args.iterations, rotation_lr=args.rotation_lr,
                               **({} if args.corrections is None else {"corrections": args.corrections}))
            if args.held_out:
                fit_held_out(args.data, params, snr_db=noise, samples=args.samples, limit=args.limit)
            else:
                fit_split(args.data, args.split, params, snr_db=noise, run=args.run, samples=args.samples,
                          limit=args.limit)
    table = sweep_table(args.data, args.split)
    write_bytes(Path(args.data) / "fits" / f"{args.split}.md", table.encode())
    print(table)
    return 0


def cmd_ablate(args: argparse.Namespace) -> int:
    from meshsar_builder.trainer.ablate import (
        RADAR_SEEDS,
        RADAR_WEIGHTS,
        VARIANTS,
        ablate,
        markdown,
        radar_ablation,
        radar_markdown,
    )

    try:
        seeds = tuple(seed_number(s) for s in args.seeds.split(",")) if args.seeds else (
            RADAR_SEEDS if args.radar else (0, 1, 2))
    except (ValueError, argparse.ArgumentTypeError):
        print(f"error: --seeds: expected comma-separated integers >= 0, got {args.seeds!r}", file=sys.stderr)
        return 2
    try:
        weights = tuple(float(w) for w in args.radar_weights.split(",")) if args.radar_weights else RADAR_WEIGHTS
    except ValueError:
        print(f"error: --radar-weights: expected comma-separated numbers, got {args.radar_weights!r}", file=sys.stderr)
        return 2
    refuse_if_locked(args.data)
    if args.radar:
        print(radar_markdown(radar_ablation(args.config, args.data, args.split, seeds, weights, args.epochs,
                                            args.device, args.out, args.samples, jobs=args.jobs)))
        return 0
    variants = tuple(args.variants.split(",")) if args.variants else VARIANTS
    print(markdown(ablate(args.config, args.data, args.split, seeds, variants, args.epochs, args.device, args.out,
                          args.samples)))
    return 0


def cmd_predict(args: argparse.Namespace) -> int:
    from meshsar_builder.trainer.predict import predict

    if args.data:
        refuse_if_locked(args.data)
    print(predict(args.run, args.data, args.split, args.subset, args.images, args.device, args.out, args.checkpoint,
                  args.gallery, refine=args.refine))
    return 0


def seed_number(text: str) -> int:
    """A seed argument: an integer >= 0 (numpy's seed sequences take no negative one)."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"a seed is an integer >= 0, got {value}")
    return value


def add_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda", "auto"], help="default cpu")
    p.add_argument("--checkpoint", default="best", choices=["best", "last"],
                   help="best validation Dice (default; the last epoch when the run had no validation) or last")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="meshsar", description="Build the Cardiac Mesh-SAR dataset and train SAR2Mesh on it.",
        epilog="docs: README.md to start; docs/data.md (building and reading the data), docs/trainer.md "
               "(training), docs/results.md (results beside the paper). Each command's --help names its page.")
    sub = p.add_subparsers(dest="command", required=True)
    b = sub.add_parser("build", help="run a recipe's stages (skips what is up to date)",
                       epilog="docs: docs/data.md (stages, recipes, Dask); the radar on a GPU: docs/radar.md")
    b.add_argument("recipe", help="recipe TOML, e.g. manifests/demo.toml")
    b.add_argument("--out", help="output folder (default build/<recipe name>)")
    b.add_argument("--workers", type=int, default=1, help="local worker processes (default 1)")
    b.add_argument("--scheduler", metavar="ADDR", default=os.environ.get("MESHSAR_SCHEDULER") or None,
                   help="run items on a Dask cluster: tcp://HOST:PORT, or local:N for a LocalCluster of N "
                        "worker processes (default $MESHSAR_SCHEDULER; unset: local processes)")
    b.add_argument("--until", metavar="STAGE", help="stop after this stage")
    b.add_argument("--force", metavar="STAGE", action="append", default=[], help="rerun every item of STAGE (repeatable)")
    b.add_argument("--device", metavar="DEVICE", help="where the radar stage's echo and imaging run: cpu, cuda or "
                                                      "cuda:N (sets [radar] device; default: the recipe's, cpu)")
    b.add_argument("--break-lock", action="store_true",
                   help="take over the output folder's lock even when it was taken on another host (a shared "
                        "filesystem): only once that build has stopped. A lock left by a build of this host "
                        "that is gone is taken over without it")
    b.set_defaults(func=cmd_build)
    s = sub.add_parser("splits", help="write splits/seed-S.json from the index (shards are not read)",
                       epilog="docs: docs/data.md (splits)")
    s.add_argument("out", help="built dataset folder")
    s.add_argument("--seed", type=seed_number, required=True)
    s.add_argument("--ratios", help="e.g. train=0.8,test=0.2 (default)")
    s.set_defaults(func=cmd_splits)
    v = sub.add_parser("verify", help="check every shard's digest and arrays, the index and the splits",
                       epilog="docs: docs/data.md (the data contract)")
    v.add_argument("out", help="built dataset folder")
    v.set_defaults(func=cmd_verify)
    pv = sub.add_parser("preview", help="render a gallery of samples (meshes beside their SAR images) to "
                                         "card/preview.png", epilog="docs: docs/data.md")
    pv.add_argument("out", help="built dataset folder")
    pv.add_argument("--n", type=int, default=8, help="samples to show (default 8)")
    pv.set_defaults(func=cmd_preview)
    t = sub.add_parser("train", help="train the reference SAR2Mesh model on a built dataset (resumes a run)",
                       epilog="docs: docs/trainer.md")
    t.add_argument("config", help="trainer config TOML, e.g. manifests/train/default.toml")
    t.add_argument("--data", required=True, help="built dataset folder")
    t.add_argument("--split", default="seed-0")
    t.add_argument("--out", help="run folder (default DATA/runs/<config name>-<split>)")
    t.add_argument("--device", choices=["cpu", "cuda", "auto"], help="override [run] device")
    t.set_defaults(func=cmd_train)
    e = sub.add_parser("evaluate", help="metrics, tables and renders of a trained run on a split",
                       epilog="docs: docs/trainer.md (evaluation); measured results: docs/results.md")
    e.add_argument("run", help="run folder")
    e.add_argument("--data", required=True, help="built dataset folder")
    e.add_argument("--split", default="seed-0")
    e.add_argument("--renders", type=int, help="samples drawn in renders.png (default all)")
    e.add_argument("--samples", type=int, default=20_000,
                   help="surface points per mesh and direction for ASSD / HD / HD95 (default 20000)")
    e.add_argument("--with", dest="compare", metavar="RUN", action="append", default=[],
                   help="another run evaluated beside it in the same table, e.g. an implicit baseline (repeatable)")
    e.add_argument("--refine", action="store_true",
                   help="also refine each predicted mesh against the sample's recorded echo (the run's [refine]); "
                        "writes RUN/eval-<split>-refine with a paired test, before against after")
    e.add_argument("--refine-echo", metavar="DATA2",
                   help="refine against the recorded echo of the same sample in build DATA2 (the same recipe with "
                        "other radar settings, e.g. diffuse = false); implies --refine; writes "
                        "RUN/eval-<split>-refine-<DATA2 name>")
    add_run_options(e)
    e.set_defaults(func=cmd_evaluate)
    fi = sub.add_parser("fit", help="fit the build's shape model to each test sample's recorded echo alone "
                                    "(no network): metrics against the truth",
                        epilog="docs: docs/trainer.md (physics at inference)")
    fi.add_argument("data", help="built dataset folder")
    fi.add_argument("--split", default="seed-0")
    fi.add_argument("--modes", default="7", help="comma-separated numbers of leading modes fitted (default 7)")
    fi.add_argument("--snr-db", default="build",
                    help="comma-separated noise levels: build (the recorded echo), an image SNR in dB (the noise "
                         "redrawn from the same seeds at that level) or off (default build)")
    fi.add_argument("--iterations", type=int, default=150, help="Adam steps per sample (default 150)")
    fi.add_argument("--rotation-lr", type=float, default=0.0,
                    help="Adam step of the rotation (rad); 0 (default) keeps the model's orientation")
    fi.add_argument("--corrections", type=int,
                    help="rounds of model-bias correction after the first fit: the production echo of the fit's "
                         "mesh re-simulated, the model's bias taken off the target (default 2, FitParams; 0: the "
                         "image-domain model alone)")
    fi.add_argument("--held-out", action="store_true",
                    help="fit each registered subject with a shape model of the others (leave-subject-out) "
                         "instead of the split's shape-model test samples")
    fi.add_argument("--run", help="a trained run whose evaluation on the split is tabled beside the fit")
    fi.add_argument("--limit", type=int, help="fit the first N shape-model test samples only")
    fi.add_argument("--samples", type=int, default=20_000,
                    help="surface points per mesh and direction for ASSD / HD / HD95 (default 20000)")
    fi.set_defaults(func=cmd_fit)
    pr = sub.add_parser("predict", help="meshes (PLY) and a gallery from a trained run, for a split or an images file",
                        epilog="docs: docs/trainer.md (prediction)")
    pr.add_argument("run", help="run folder")
    source = pr.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", help="built dataset folder")
    source.add_argument("--images", help="images file (.npz: sar (n, V, C, H, W) and the index's view metadata)")
    pr.add_argument("--split", default="seed-0", help="with --data (default seed-0)")
    pr.add_argument("--subset", default="test", help="with --data: which part of the split (default test)")
    pr.add_argument("--out", help="output folder (default RUN/predict-<split>-<subset> or RUN/predict-<file stem>)")
    pr.add_argument("--gallery", type=int, help="samples drawn in gallery.png (default all)")
    pr.add_argument("--refine", action="store_true",
                    help="refine each mesh against its sample's recorded echo (the run's [refine]; needs --data)")
    add_run_options(pr)
    pr.set_defaults(func=cmd_predict)
    ab = sub.add_parser("ablate", help="train and evaluate a config's ablation variants over seeds: mean ± std table",
                        epilog="docs: docs/trainer.md (ablation)")
    ab.add_argument("config", help="trainer config TOML, e.g. manifests/train/default.toml")
    ab.add_argument("--data", required=True, help="built dataset folder")
    ab.add_argument("--split", default="seed-0")
    ab.add_argument("--seeds", help="comma-separated trainer seeds (default 0,1,2; with --radar 0,1,2,3,4)")
    ab.add_argument("--radar", action="store_true",
                    help="radar loss on against off: the weight chosen on validation, a paired test on test samples")
    ab.add_argument("--radar-weights", help="with --radar: comma-separated weights to choose from (default 0.03,0.1,0.3)")
    ab.add_argument("--variants", help="comma-separated subset of default,no_radar,max_only,single_view (default all)")
    ab.add_argument("--epochs", type=int, help="shorten every run to this many epochs (warm-up, ramp and "
                                               "intervals scale with it; default: the config's)")
    ab.add_argument("--device", choices=["cpu", "cuda", "auto"], help="override [run] device")
    ab.add_argument("--samples", type=int, default=20_000,
                    help="surface points per mesh for the distance metrics (default 20000, as evaluate)")
    ab.add_argument("--jobs", type=int, default=1,
                    help="with --radar: runs trained at once, sharing the cores (default 1)")
    ab.add_argument("--out", help="folder (default DATA/ablations/<config name>-<split>[-e<epochs>])")
    ab.set_defaults(func=cmd_ablate)
    from meshsar_builder.bench.suite import PARTS

    be = sub.add_parser("bench", help="speed and memory benchmarks, JSON under build/bench/",
                        epilog="docs: docs/benchmarks.md (measured figures and the hardware)")
    be.add_argument("part", nargs="?", default="all", choices=[*PARTS, "all"])
    be.add_argument("--out", default="build/bench")
    be.add_argument("--recipe", help="pipeline only: build this recipe from scratch and time it against the "
                                     "paper-scale target (writes pipeline-<name>.json)")
    be.add_argument("--workers", type=int, default=2, help="with --recipe: local worker processes (default 2)")
    be.add_argument("--scaling", action="store_true",
                    help="with --recipe: its 1 -> 2 worker scaling on the local pool and Dask, four builds "
                         "(writes pipeline-scaling-<name>.json), instead of one build")
    be.add_argument("--device", choices=["cpu", "cuda"],
                    help="radar part: cuda times the GPU radar against one core of the same run (radar-cuda.json); "
                         "pipeline --recipe: the build's [radar] device (default: the recipe's); "
                         "trainer part: where steps are timed (cuda: fp32 and mixed precision); radar-throughput "
                         "part: where the workers render (default cpu)")
    be.set_defaults(func=cmd_bench)
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        return args.func(args)
    except MeshsarError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: finished items are kept; rerun the same command to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
