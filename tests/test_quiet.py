"""A quiet console (issue 31 item 4): a build prints progress bars, a summary and real warnings only.

Every warning raised while a recipe builds is caught here with the line of the project's own
code (meshsar_builder/ or stages/) that led to it, and the test fails on any that is not
explained below. Items run in this process (workers=1), so warnings raised inside items are
caught as well; they are the same code paths that worker processes run.

Warnings the project raises on purpose for a user to act on (InputWarning for a label map
with odd values, SplitWarning for a sample-grouped split, ...) are recorded by the stages
into sidecars and the card; none is raised by the recipes built here.
"""

from __future__ import annotations

import contextlib
import os
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path

from meshsar_builder.pipeline import recipe as R
from meshsar_builder.pipeline.runner import build

from .conftest import ROOT

PROJECT = (str(ROOT / "meshsar_builder") + os.sep, str(ROOT / "stages") + os.sep)


@dataclass(frozen=True)
class Caught:
    category: str
    message: str
    where: str  # file:line that raised it (often a library's)
    caller: str  # the project's own line that led to it (file:line relative to the checkout), or "?"

    def __str__(self) -> str:
        return f"{self.category}: {self.message} (raised at {self.where}, from {self.caller})"


# Warnings that are expected, each with why, as (category, message start, project caller's file): the
# caller is compared by file so that an edit elsewhere in that file does not hide or reveal it.
EXPLAINED: dict[tuple[str, str, str], str] = {}

@contextlib.contextmanager
def caught_warnings():
    """Record every warning raised in the block (each occurrence, not once per place) as Caught."""
    caught: list[Caught] = []

    def show(message, category, filename, lineno, file=None, line=None):
        ours = [f for f in traceback.extract_stack()[:-1] if f.filename.startswith(PROJECT)]
        caller = f"{Path(ours[-1].filename).relative_to(ROOT)}:{ours[-1].lineno}" if ours else "?"
        where = filename.split("site-packages" + os.sep)[-1]
        caught.append(Caught(category.__name__, str(message), f"{where}:{lineno}", caller))

    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = show  # restored by catch_warnings on the way out
        yield caught


def _matches(c: Caught, table) -> bool:
    return any(c.category == cat and c.message.startswith(msg) and c.caller.split(":")[0] == path
               for cat, msg, path in table)


def unexplained(caught: list[Caught]) -> list[str]:
    """Each distinct warning not in EXPLAINED."""
    return sorted({str(c) for c in caught if not _matches(c, EXPLAINED)})


def test_the_recorder_names_the_project_line_behind_a_library_warning():
    import numpy as np

    with caught_warnings() as caught:
        np.array([0.0]) / np.array([0.0])  # noqa: B018 (the warning is the point)
    assert len(caught) == 1 and caught[0].category == "RuntimeWarning"
    assert caught[0].caller == "?"  # raised from the test, not from the project's code
    assert unexplained(caught) == [str(caught[0])]


def test_an_explained_warning_passes_and_any_other_fails(monkeypatch):
    expected = Caught("RuntimeWarning", "overflow", "numpy/x.py:1", "meshsar_builder/radar/echo.py:10")
    other = Caught("UserWarning", "something new", "x.py:1", "stages/radar.py:5")
    monkeypatch.setitem(EXPLAINED, ("RuntimeWarning", "overflow", "meshsar_builder/radar/echo.py"), "why")
    assert unexplained([expected]) == []
    assert unexplained([expected, other]) == [str(other)]


# The beating biventricular phantom meshed as `make dataset` (manifests/demo.toml) meshes it: 1 mm.
BEATING_AT_DEMO_RESOLUTION = """
name = "quiet-meshes"
seed = 0
[[sources]]
kind = "phantom"
anatomy = "biventricular"
subjects = 1
frames = 3
use = "direct"
[meshing]
spacing_mm = 1.0
"""


def test_meshing_at_the_demo_resolution_is_quiet(tmp_path):
    """The whole smoke recipe's build is checked in test_pipeline (one process, beside its bytes)."""
    recipe = tmp_path / "quiet-meshes.toml"
    recipe.write_text(BEATING_AT_DEMO_RESOLUTION)
    with caught_warnings() as caught:
        results = build(R.load(recipe), tmp_path / "out", until="meshes")
    assert results.failures == []
    assert unexplained(caught) == []
