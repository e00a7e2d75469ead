"""One writer per build folder: a lock file, `<out>/build.lock`, held while a command writes there.

Two builds into one folder would race each other: each removes the temporaries it
believes stale (the other's files in flight), and which failures.json, index and shards
survive depends on who finishes last. So `meshsar build` holds the folder's lock for its
whole run, and `meshsar splits` and `meshsar preview` hold it while they write; a
command that finds it held by another process stops at once, naming the holder.

The lock file is created with O_CREAT | O_EXCL (atomic, also on NFS v3 and later) and
holds JSON: host, pid, the process's start time, when the lock was taken and the
command line. It is removed when the holder exits, normally or through an exception.
A lock left behind by a process that is gone (kill -9, a power cut) is taken over when
the holder ran on this host: the rerun resumes as after any crash. A lock held from
another host (a shared filesystem, a Dask driver elsewhere) cannot be checked from
here: the error says how to clear it (delete the file, or `--break-lock`).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shlex
import socket
import sys
import time
import uuid
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterator

from meshsar_builder.pipeline.errors import MeshsarError

LOCK_NAME = "build.lock"


class FolderLocked(MeshsarError):
    """The folder is held by another process (or by one this host cannot check)."""

    def __init__(self, message: str, holder: dict):
        super().__init__(message)
        self.holder = holder


def lock_path(out: str | os.PathLike) -> Path:
    return Path(out) / LOCK_NAME


def _process_start(pid: int) -> str | None:
    """The process's start time in clock ticks since boot (Linux /proc), or None where unknown.

    Recorded beside the pid so that a pid reused by an unrelated process after a crash
    is not taken for the build that held the lock.
    """
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    # Field 2 (the command name) may hold spaces and parentheses: split after its last ')'.
    fields = stat[stat.rfind(")") + 2:].split()
    return fields[19] if len(fields) > 19 else None


def _zombie(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rfind(")") + 2:].split()[:1] == ["Z"]


def process_alive(pid: int, start: str | None = None) -> bool:
    """Whether process `pid` of this host still runs (and, given its start time, is the same process)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: it exists
        pass
    if _zombie(pid):  # killed, not yet reaped by its parent: it writes nothing any more
        return False
    if start is not None:
        now = _process_start(pid)
        if now is not None and now != start:  # the pid was reused
            return False
    return True


def _describe(holder: dict) -> str:
    parts = [f"host {holder.get('host', '?')}", f"pid {holder.get('pid', '?')}",
             f"started {holder.get('started', '?')}"]
    if holder.get("command"):
        parts.append(f"command: {holder['command']}")
    return ", ".join(parts)


def read_holder(out: str | os.PathLike) -> dict | None:
    """The lock's record, None when the folder is not locked ({} for a file that is not a lock record)."""
    try:
        text = lock_path(out).read_text(encoding="utf-8")
    except (FileNotFoundError, NotADirectoryError):
        return None
    try:
        holder = json.loads(text)
    except ValueError:
        return {}
    return holder if isinstance(holder, dict) else {}


def holder_state(holder: dict) -> str:
    """'live' (a process of this host that runs), 'stale' (one of this host that is gone) or 'foreign'."""
    if holder.get("host") != socket.gethostname():
        return "foreign"
    try:
        pid = int(holder.get("pid"))
    except (TypeError, ValueError):
        return "stale"
    return "live" if process_alive(pid, holder.get("pid_start")) else "stale"


def _refusal(out: Path, holder: dict, state: str) -> FolderLocked:
    path = lock_path(out)
    if state == "live":
        return FolderLocked(
            f"{out} is being written by another meshsar process ({_describe(holder)}); one build per folder: "
            f"wait for it to finish, or stop it (kill {holder.get('pid')}) and rerun to resume, or build "
            f"into another folder (--out)", holder)
    return FolderLocked(
        f"{out} is locked by a meshsar process on another host ({_describe(holder)}), which this machine "
        f"cannot check. If it still runs, wait for it; if it has finished or died, clear the lock: delete "
        f"{path}, or pass --break-lock to meshsar build", holder)


def _record(command: str | None) -> dict:
    pid = os.getpid()
    return {
        "host": socket.gethostname(),
        "pid": pid,
        "pid_start": _process_start(pid),
        "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": command if command is not None else shlex.join(["meshsar", *sys.argv[1:]]),
        "token": uuid.uuid4().hex,  # which lock is ours, whatever pid and host say
    }


def _create(path: Path, record: dict) -> bool:
    """Create the lock file holding `record`, atomically; False if it exists already."""
    try:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return False
    try:
        os.write(fd, (json.dumps(record, indent=1) + "\n").encode("utf-8"))
        os.fsync(fd)
    except BaseException:
        os.close(fd)
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
        raise
    os.close(fd)
    return True


def _remove_if_unchanged(path: Path, holder: dict) -> None:
    """Remove the lock file if it still holds `holder` (a stale or broken lock), else leave it.

    Two reruns may find the same stale lock: under an flock on the file, each checks that
    the path still names the file it opened and that the file still holds what it read, so
    only one removes it and neither removes the lock the other has taken since.
    """
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        try:
            same_file = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            return
        with os.fdopen(os.dup(fd), encoding="utf-8") as f:
            text = f.read()
        try:
            now = json.loads(text)
        except ValueError:
            now = {}
        if same_file and (now if isinstance(now, dict) else {}) == holder:
            path.unlink()
    finally:
        os.close(fd)  # releases the flock


class FolderLock:
    """The lock of one build folder, held by this process; `release` removes it (only if still ours)."""

    def __init__(self, out: Path, record: dict, took_over: dict | None):
        self.out = out
        self.record = record
        self.took_over = took_over  # the stale holder's record when this lock replaced one, else None

    def release(self) -> None:
        holder = read_holder(self.out)
        if holder and holder.get("token") == self.record["token"]:
            with contextlib.suppress(FileNotFoundError):
                lock_path(self.out).unlink()


def acquire(out: str | os.PathLike, command: str | None = None, break_lock: bool = False,
            wait_unreadable_s: float = 2.0) -> FolderLock:
    """Take `out`'s lock (creating the folder) or raise FolderLocked naming the holder.

    A lock of this host whose process is gone is taken over; with `break_lock`, so is one
    held from another host (the user says it is gone). A lock of a live process of this
    host is never broken. `command` is recorded (default: this process's command line).
    MeshsarError when the folder is not writable.
    """
    out = Path(out)
    path = lock_path(out)
    record = _record(command)
    took_over = None
    unreadable_since = None
    try:
        out.mkdir(parents=True, exist_ok=True)
        while True:
            if _create(path, record):
                return FolderLock(out, record, took_over)
            holder = read_holder(out)
            if holder is None:  # released between our attempt and the read: try again
                continue
            if not holder.get("host") or "pid" not in holder:
                # Created but not yet written by a process taking the lock right now, or a file
                # broken by a crash between the two: wait a moment, then treat it as stale.
                unreadable_since = unreadable_since or time.monotonic()
                if time.monotonic() - unreadable_since < wait_unreadable_s:
                    time.sleep(0.05)
                    continue
                _remove_if_unchanged(path, holder)
                continue
            state = holder_state(holder)
            if state == "live" or (state == "foreign" and not break_lock):
                raise _refusal(out, holder, state)
            _remove_if_unchanged(path, holder)
            took_over = holder
    except OSError as e:
        raise MeshsarError(f"{out}: output folder is not writable ({e.strerror})") from e


@contextlib.contextmanager
def folder_lock(out: str | os.PathLike, command: str | None = None, break_lock: bool = False,
                create: bool = True) -> Iterator[FolderLock | None]:
    """Hold `out`'s lock for the block: released on normal exit and on any exception.

    create=False (commands that write into a built folder: splits, preview): a missing
    folder is not created and not locked (None is yielded); the command then fails on it.
    """
    if not create and not Path(out).is_dir():
        yield None
        return
    lock = acquire(out, command, break_lock)
    try:
        if lock.took_over is not None:
            print(f"note: took over the lock of {out} left by a process that is gone "
                  f"({_describe(lock.took_over)})", file=sys.stderr)
        yield lock
    finally:
        lock.release()


def refuse_if_locked(out: str | os.PathLike) -> None:
    """Raise FolderLocked if another live process (or one on another host) holds `out`; for readers."""
    holder = read_holder(out)
    if holder is None or not holder.get("host"):
        return
    state = holder_state(holder)
    if state != "stale":
        raise _refusal(Path(out), holder, state)
