"""The README's commands parse, its links resolve, and every `meshsar` command's help names its docs page.

Commands are the lines of the README's fenced `sh` blocks that start with `make` or `meshsar`
(after any VAR=value prefix). Nothing is built or run: a make line is checked with `make -n`
(and each VAR=value it passes must be a variable the Makefile defines), a meshsar line with the
CLI's own argparse parser. Paths into the repository that a command names (manifests/..., tests/...)
must exist.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import subprocess
from pathlib import Path

import pytest

from meshsar_builder.cli import parser

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
SHELL_LANGS = {"sh", "bash", "shell", "console"}
ASSIGNMENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")
REPO_PATH = re.compile(r"^(manifests|tests|docs|stages|meshsar_builder)/")


def fenced_blocks(text: str) -> list[tuple[str, list[str]]]:
    """(info string, lines) of every fenced ``` block."""
    blocks, lang, lines = [], None, []
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("```"):
            if lang is None:
                lang, lines = stripped[3:].strip().lower(), []
            else:
                blocks.append((lang, lines))
                lang = None
        elif lang is not None:
            lines.append(line)
    return blocks


def commands(text: str) -> list[list[str]]:
    """Each `make ...` / `meshsar ...` line of the shell blocks, as argv (comments and VAR= prefixes dropped)."""
    out = []
    for lang, lines in fenced_blocks(text):
        if lang not in SHELL_LANGS:
            continue
        for line in lines:
            argv = shlex.split(line, comments=True)
            while argv and ASSIGNMENT.match(argv[0]):
                argv = argv[1:]
            if argv and argv[0] in ("make", "meshsar"):
                out.append(argv)
    return out


def makefile_variables() -> set[str]:
    text = (ROOT / "Makefile").read_text(encoding="utf-8")
    return set(re.findall(r"^([A-Za-z_][A-Za-z0-9_]*)\s*[?:+]?=", text, flags=re.M))


def problems(argv: list[str]) -> list[str]:
    """Why a README command would not run as written; [] when it parses."""
    values = [a.split("=", 1)[1] if ASSIGNMENT.match(a) else a for a in argv[1:]]
    found = [f"{v}: no such path in the repository" for v in values if REPO_PATH.match(v) and not (ROOT / v).exists()]
    if argv[0] == "make":
        known = makefile_variables()
        found += [f"{a.split('=', 1)[0]}: not a Makefile variable" for a in argv[1:]
                  if ASSIGNMENT.match(a) and a.split("=", 1)[0] not in known]
        run = subprocess.run(["make", "-n", *argv[1:]], cwd=ROOT, capture_output=True, text=True,
                             env={**os.environ, "MAKEFLAGS": ""}, timeout=60)
        if run.returncode != 0:
            found.append(f"make -n failed: {run.stderr.strip()}")
    else:
        try:
            parser().parse_args(argv[1:])
        except SystemExit as e:
            found.append(f"argparse rejected it (exit {e.code})")
    return found


README_COMMANDS = commands(README.read_text(encoding="utf-8"))


def test_the_readme_has_commands_to_check():
    assert README_COMMANDS, "no make/meshsar lines found in README.md's ```sh blocks"
    lines = {" ".join(c) for c in README_COMMANDS}
    assert {"make dataset", "make test"} <= lines, "the two commands, `make dataset` and `make test`, must be there"
    assert any(c[0] == "meshsar" for c in README_COMMANDS)


@pytest.mark.parametrize("argv", README_COMMANDS, ids=[" ".join(c) for c in README_COMMANDS])
def test_a_readme_command_parses(argv):
    assert problems(argv) == [], f"{' '.join(argv)}: {problems(argv)}"


@pytest.mark.parametrize("line", [
    "meshsar build manifests/demo.toml --no-such-flag",
    "meshsar trian manifests/train/default.toml --data build/demo",
    "meshsar train manifests/train/default.toml",               # --data is required
    "meshsar build manifests/no_such_recipe.toml",
    "make no-such-target",
    "make dataset RECIPIE=manifests/smoke.toml",                # a misspelt variable
])
def test_a_broken_command_is_caught(line):
    assert problems(shlex.split(line))


def test_commands_are_found_in_sh_blocks_only():
    text = "```sh\nmake dataset   # comment\nX=1 meshsar verify build/demo\necho hi\n```\n" \
           "```python\nmeshsar = 1\n```\n"
    assert commands(text) == [["make", "dataset"], ["meshsar", "verify", "build/demo"]]


def slug(heading: str) -> str:
    """GitHub's anchor for a Markdown heading."""
    s = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return s.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = page.read_text(encoding="utf-8")
    return {slug(m) for m in re.findall(r"^#+\s+(.*)$", text, flags=re.M)}


PAGES = [README, *sorted(DOCS.glob("*.md"))]


@pytest.mark.parametrize("page", PAGES, ids=[p.relative_to(ROOT).as_posix() for p in PAGES])
def test_links_between_pages_resolve(page):
    text = page.read_text(encoding="utf-8")
    bad = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"^[a-z]+:", target):
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            bad.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            bad.append(f"{target}: no heading with that anchor")
    assert not bad, f"{page.relative_to(ROOT)}: {bad}"


def test_the_readme_stays_a_short_guide():
    assert len(README.read_text(encoding="utf-8").splitlines()) <= 300


def subcommands() -> dict[str, argparse.ArgumentParser]:
    p = parser()
    [sub] = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


def docs_pages_named(text: str) -> list[str]:
    return re.findall(r"docs/[\w\-]+\.md", text)


def test_meshsar_help_names_the_docs():
    named = docs_pages_named(parser().format_help())
    assert named, "`meshsar --help` names no docs/ page"
    assert all((ROOT / n).exists() for n in named), named


@pytest.mark.parametrize("name", sorted(subcommands()))
def test_each_subcommand_help_names_an_existing_docs_page(name):
    named = docs_pages_named(subcommands()[name].format_help())
    assert named, f"`meshsar {name} --help` names no docs/ page"
    missing = [n for n in named if not (ROOT / n).exists()]
    assert not missing, f"`meshsar {name} --help` names pages that do not exist: {missing}"
