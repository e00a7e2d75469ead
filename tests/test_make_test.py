"""make test's own settings: a test process that crashes or hangs ends the run and is named, instead of a run that
waits until CI's time limit (pytest-xdist 3.8 under --dist loadfile can wait forever for a replacement's work)."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

BAD_TESTS = {
    "crash": "import ctypes\n\ndef test_bad():\n    ctypes.string_at(0)  # reads address 0: a segmentation fault\n",
    "hang": "import time\n\ndef test_bad():\n    time.sleep(120)\n",
}


def make_test_command() -> list[str]:
    """The pytest command line that `make test` runs (as `make -n` prints it), with this interpreter."""
    run = subprocess.run(["make", "-s", "-n", "-o", ".venv/.installed", "test"], cwd=ROOT, capture_output=True,
                         text=True, env={**os.environ, "MAKEFLAGS": ""}, timeout=60)
    line = next(line for line in run.stdout.splitlines() if " -m pytest " in line)
    return [sys.executable, *shlex.split(line)[1:]]


@pytest.mark.parametrize("kind", sorted(BAD_TESTS))
def test_a_test_process_that_crashes_or_hangs_ends_the_run_naming_its_test(tmp_path, kind):
    """Three files, the middle one with a test that crashes its process or sleeps past the hang timeout (lowered
    to 3 s; the project's pyproject.toml gives the rest of the settings): the run ends long before the sleep
    would, fails, names the test, and starts no replacement process."""
    (tmp_path / "test_a.py").write_text("def test_a1():\n    pass\n\n\ndef test_a2():\n    pass\n")
    (tmp_path / "test_b.py").write_text(BAD_TESTS[kind] + textwrap.dedent("""

        def test_after():
            pass
        """))
    (tmp_path / "test_c.py").write_text("def test_c():\n    pass\n")
    command = make_test_command() + ["-c", str(ROOT / "pyproject.toml"), "--rootdir", str(tmp_path),
                                     "-p", "no:cacheprovider", "-o", "faulthandler_timeout=3", str(tmp_path)]
    run = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=100)
    assert run.returncode != 0
    assert "crashed while running 'test_b.py::test_bad'" in run.stdout, run.stdout[-3000:]
    # not replaced: a replacement reruns the file's rest (here crashing in turn), and under loadfile it may wait
    # forever instead
    assert len(set(re.findall(r"worker '(gw\d+)' crashed", run.stdout))) == 1, run.stdout[-3000:]
