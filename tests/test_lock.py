"""One build per folder (issue 31 item 5): the build folder's lock, lock.py.

Each case: a second writer refused at once naming host, pid and start time; a lock left by
a process that is gone taken over (kill -9, then a rerun that resumes); a lock from another
host reported with how to clear it; splits and preview refused while a build holds the
folder; the lock released on exit, normal or not.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from meshsar_builder import cli
from meshsar_builder.pipeline import recipe as R
from meshsar_builder.pipeline.errors import MeshsarError
from meshsar_builder.pipeline.io import TMP_MARK, read_json
from meshsar_builder.pipeline.lock import (
    LOCK_NAME,
    FolderLocked,
    _process_start,
    acquire,
    folder_lock,
    process_alive,
    read_holder,
)
from meshsar_builder.pipeline.runner import build

from .conftest import MANIFESTS, ROOT

SMOKE = MANIFESTS / "smoke.toml"
HOLD = ("import sys\nfrom meshsar_builder.pipeline.lock import folder_lock\n"
        "with folder_lock(sys.argv[1], command='meshsar build manifests/smoke.toml'):\n"
        "    print('held', flush=True)\n    sys.stdin.read()\n")


def _dead_pid() -> int:
    """The pid of a process of this host that has exited (and been reaped)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _plant(out: Path, **fields) -> dict:
    record = {"host": socket.gethostname(), "pid": os.getpid(), "pid_start": _process_start(os.getpid()),
              "started": "2026-01-01T00:00:00+00:00", "command": "meshsar build manifests/demo.toml",
              "token": "planted", **fields}
    out.mkdir(parents=True, exist_ok=True)
    (out / LOCK_NAME).write_text(json.dumps(record))
    return record


@pytest.fixture
def holder(tmp_path):
    """A real second process holding tmp_path/out's lock until the test ends; yields (out, process)."""
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(out)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            cwd=ROOT, text=True)
    assert proc.stdout.readline().strip() == "held"
    yield out, proc
    proc.stdin.close()
    proc.wait(timeout=30)


def test_the_lock_records_who_holds_it_and_goes_on_exit(tmp_path):
    out = tmp_path / "out"
    with folder_lock(out, command="meshsar build x.toml") as lock:
        rec = read_json(out / LOCK_NAME)
        assert rec["host"] == socket.gethostname() and rec["pid"] == os.getpid()
        assert rec["command"] == "meshsar build x.toml" and rec["started"].endswith("+00:00")
        assert lock.took_over is None
    assert not (out / LOCK_NAME).exists()
    with pytest.raises(ZeroDivisionError):
        with folder_lock(out):
            1 / 0
    assert not (out / LOCK_NAME).exists()


def test_a_second_build_is_refused_at_once_naming_the_holder(holder):
    out, proc = holder
    rec = read_holder(out)
    t0 = time.perf_counter()
    with pytest.raises(FolderLocked) as e:
        build(R.load(SMOKE), out)
    assert time.perf_counter() - t0 < 5
    msg = str(e.value)
    assert f"host {socket.gethostname()}" in msg and f"pid {proc.pid}" in msg and f"started {rec['started']}" in msg
    assert "one build per folder" in msg and "meshsar build manifests/smoke.toml" in msg
    assert not (out / "recipe.toml").exists() and not (out / "sources").exists()  # nothing written
    assert read_holder(out) == rec  # and the holder's lock untouched


def test_the_command_line_refuses_build_splits_preview_and_readers(holder, capsys):
    out, proc = holder
    for argv in (["build", str(SMOKE), "--out", str(out)], ["build", str(SMOKE), "--out", str(out), "--break-lock"],
                 ["splits", str(out), "--seed", "0"], ["preview", str(out)], ["verify", str(out)],
                 ["train", "cfg.toml", "--data", str(out)], ["evaluate", "run", "--data", str(out)],
                 ["predict", "run", "--data", str(out)]):
        assert cli.main(argv) == 2, argv
        err = capsys.readouterr().err
        assert f"pid {proc.pid}" in err and "being written by another meshsar process" in err, (argv, err)
    assert not (out / "splits").exists() and not (out / "card").exists()


def test_splits_and_preview_hold_the_lock_while_they_write_and_release_it(tmp_path, monkeypatch, capsys):
    from meshsar_builder.dataset import card, splits

    out = tmp_path / "out"
    out.mkdir()
    seen = []

    def writer(name):
        def write(out_dir, *args):
            seen.append((name, read_holder(out_dir)))
            return Path(out_dir) / name
        return write

    monkeypatch.setattr(splits, "split_dataset", writer("splits"))
    monkeypatch.setattr(card, "preview", writer("preview"))
    assert cli.main(["splits", str(out), "--seed", "3"]) == 0
    assert cli.main(["preview", str(out), "--n", "2"]) == 0
    assert [name for name, _ in seen] == ["splits", "preview"]
    assert all(h and h["pid"] == os.getpid() for _, h in seen), seen
    assert not (out / LOCK_NAME).exists()
    # a folder that does not exist is not created by the lock: the command's own error names it
    monkeypatch.undo()
    assert cli.main(["splits", str(tmp_path / "missing"), "--seed", "0"]) != 0
    capsys.readouterr()
    assert not (tmp_path / "missing").exists()


def test_a_lock_left_by_a_process_that_is_gone_is_taken_over(tmp_path, capsys):
    out = tmp_path / "out"
    _plant(out, pid=_dead_pid())
    results = build(R.load(SMOKE), out, until="sources")
    assert results.failures == [] and not (out / LOCK_NAME).exists()
    assert "took over the lock" in capsys.readouterr().err


def test_a_reused_pid_is_not_taken_for_the_holder(tmp_path):
    out = tmp_path / "out"
    # a live pid (this process) recorded with another start time: the holder is gone, its pid reused
    _plant(out, pid_start="1")
    lock = acquire(out)
    assert lock.took_over["token"] == "planted"
    lock.release()
    assert process_alive(os.getpid(), _process_start(os.getpid())) and not process_alive(_dead_pid())


def test_a_live_process_of_this_host_is_never_taken_over(tmp_path):
    out = tmp_path / "out"
    _plant(out)  # this very process, alive
    with pytest.raises(FolderLocked, match=f"pid {os.getpid()}, started 2026-01-01T00:00:00"):
        acquire(out, break_lock=True)
    assert read_holder(out)["token"] == "planted"


def test_a_lock_from_another_host_says_how_to_clear_it(tmp_path, capsys):
    out = tmp_path / "out"
    _plant(out, host="node17.cluster", pid=4242)
    with pytest.raises(FolderLocked) as e:
        build(R.load(SMOKE), out, until="sources")
    msg = str(e.value)
    assert "another host (host node17.cluster, pid 4242, started 2026-01-01T00:00:00+00:00" in msg
    assert f"delete {out / LOCK_NAME}" in msg and "--break-lock" in msg
    assert cli.main(["splits", str(out), "--seed", "0"]) == 2 and "--break-lock" in capsys.readouterr().err
    # the user says it is gone: --break-lock takes it over, the build runs and releases it
    assert cli.main(["build", str(SMOKE), "--out", str(out), "--until", "sources", "--break-lock"]) == 0
    assert not (out / LOCK_NAME).exists()


def test_a_lock_file_broken_by_a_crash_is_taken_over_after_a_moment(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK_NAME).write_text("")  # created, never written: the taker died between the two
    t0 = time.perf_counter()
    acquire(out, wait_unreadable_s=0.3).release()
    assert 0.25 < time.perf_counter() - t0 < 5


def test_racing_takers_of_a_stale_lock_get_it_once(tmp_path):
    out = tmp_path / "out"
    _plant(out, pid=_dead_pid())
    got, refused, go = [], [], threading.Barrier(8)

    def take():
        go.wait()
        try:
            got.append(acquire(out))
        except FolderLocked:
            refused.append(1)

    threads = [threading.Thread(target=take) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(got) == 1 and len(refused) == 7
    assert read_holder(out)["token"] == got[0].record["token"]
    got[0].release()


def test_an_unwritable_folder_is_named(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(MeshsarError, match="output folder is not writable"):
        acquire(blocker / "out")


def _meshsar(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "meshsar_builder.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, cwd=ROOT, text=True, **kw)


@pytest.fixture
def many(tmp_path) -> Path:
    """The smoke recipe with 40 whole-heart phantoms: its sources stage alone runs a few seconds, long
    enough for a second build to meet the first, and writes temporaries as every stage does."""
    path = tmp_path / "many.toml"
    path.write_text(SMOKE.read_text().replace("subjects = 3\n", "subjects = 40\n", 1))
    return path


@pytest.mark.slow
def test_two_builds_started_together_one_runs_one_is_refused(tmp_path, many):
    """The issue's race: `make dataset` in two terminals. Before the lock, one build failed an item
    on the other's temporary file (each removes the temporaries it finds when a stage starts) and
    which failures.json survived was a race."""
    out = tmp_path / "out"
    procs = [_meshsar("build", str(many), "--out", str(out), "--until", "sources") for _ in range(2)]
    outcomes = sorted((p.wait(timeout=300), *p.communicate()) for p in procs)
    (ok, ok_out, ok_err), (refused, _, refused_err) = outcomes
    assert ok == 0 and "FAILED" not in ok_err, ok_err[-2000:]
    assert refused == 2 and "being written by another meshsar process" in refused_err, refused_err[-2000:]
    assert read_json(out / "failures.json") == [] and not (out / LOCK_NAME).exists()
    assert len(list((out / "sources").glob("*.json"))) == 41
    assert not [p for p in out.rglob("*") if TMP_MARK in p.name]


@pytest.mark.slow
def test_a_build_killed_with_sigkill_leaves_a_lock_the_rerun_takes_over_and_resumes(tmp_path, many):
    out = tmp_path / "out"
    proc = _meshsar("build", str(many), "--out", str(out), "--until", "sources")
    deadline = time.time() + 120
    while len(list((out / "sources").glob("*.json"))) < 2 and time.time() < deadline and proc.poll() is None:
        time.sleep(0.01)
    assert proc.poll() is None, "build finished before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=60)
    assert read_holder(out)["pid"] == proc.pid  # the lock stays behind
    rerun = _meshsar("build", str(many), "--out", str(out), "--until", "sources")
    stdout, err = rerun.communicate(timeout=300)
    assert rerun.returncode == 0, err[-2000:]
    assert f"took over the lock of {out} left by a process that is gone" in err and f"pid {proc.pid}" in err
    assert not (out / LOCK_NAME).exists()
    items, ran, skipped, failed = next(line.split()[1:5] for line in stdout.splitlines() if line.startswith("sources"))
    assert items == "41" and int(skipped) >= 2 and int(ran) == 41 - int(skipped) and failed == "0", (stdout, err[-3000:])
