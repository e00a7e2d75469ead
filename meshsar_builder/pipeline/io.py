"""Atomic file writes, digests and JSON: a crash never leaves a half-written file under a real name."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from pathlib import Path
from typing import Any, Iterator

TMP_MARK = ".tmp-"


def _split_ext(name: str) -> tuple[str, str]:
    """('ct_1_label', '.nii.gz') for 'ct_1_label.nii.gz': writers pick the format from the extension."""
    for ext in (".nii.gz", ".tar.gz"):
        if name.endswith(ext):
            return name[: -len(ext)], ext
    stem, dot, ext = name.rpartition(".")
    return (stem, dot + ext) if stem else (name, "")


def tmp_name(path: Path) -> Path:
    """A temporary sibling of `path` (same folder, so os.replace is atomic), unique per process."""
    stem, ext = _split_ext(path.name)
    return path.with_name(f".{stem}{TMP_MARK}{os.getpid()}{ext}")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path to write; on success rename it to `path`, on error remove it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = tmp_name(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def dumps(obj: Any) -> str:
    """Canonical JSON (sorted keys, 1-space indent): same object, same bytes."""
    return json.dumps(obj, sort_keys=True, indent=1, allow_nan=True) + "\n"


def write_json(path: str | os.PathLike, obj: Any) -> None:
    write_bytes(path, dumps(obj).encode("utf-8"))


def read_json(path: str | os.PathLike) -> Any:
    with open(path, encoding="utf-8") as f:
        return json.load(f)


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def sha256_json(obj: Any) -> str:
    return hashlib.sha256(dumps(obj).encode("utf-8")).hexdigest()


def remove_stale_temporaries(folder: Path) -> int:
    """Delete temporaries a killed process left behind in `folder` (recursively); return how many."""
    n = 0
    if folder.is_dir():
        for p in folder.rglob(f".*{TMP_MARK}*"):
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
                n += 1
    return n
