"""The `meshsar` command line."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .errors import MeshsarError


def cmd_build(args: argparse.Namespace) -> int:
    from . import recipe as recipe_mod
    from .runner import build, format_summary

    recipe = recipe_mod.load(args.recipe)
    out = Path(args.out) if args.out else Path("build") / recipe.name
    results = build(recipe, out, workers=args.workers, until=args.until, force=tuple(args.force))
    print(format_summary(results))
    print(f"\noutput: {out}")
    return 1 if results.failures else 0


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="meshsar", description="Build the Cardiac Mesh-SAR dataset.")
    sub = p.add_subparsers(dest="command", required=True)
    b = sub.add_parser("build", help="run a recipe's stages (skips what is up to date)")
    b.add_argument("recipe", help="recipe TOML, e.g. manifests/demo.toml")
    b.add_argument("--out", help="output folder (default build/<recipe name>)")
    b.add_argument("--workers", type=int, default=1, help="local worker processes (default 1)")
    b.add_argument("--until", metavar="STAGE", help="stop after this stage")
    b.add_argument("--force", metavar="STAGE", action="append", default=[], help="rerun every item of STAGE (repeatable)")
    b.set_defaults(func=cmd_build)
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
