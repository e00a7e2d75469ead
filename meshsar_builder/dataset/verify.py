"""`meshsar verify`: check a built dataset against the data contract (DESIGN section 7).

Every problem is one line naming the file (relative to the build folder) and
what is wrong; an empty list means the dataset is sound.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from meshsar_builder.dataset.shards import INDEX_NAME, SHARD_DIR, read_index, structure_problems
from meshsar_builder.dataset.splits import GROUP_BY, RESERVED, describe_leaks, subject_leaks
from meshsar_builder.pipeline.errors import InputError
from meshsar_builder.pipeline.io import read_json, sha256_file


def _expected_shapes(index: dict) -> tuple[tuple, int | None]:
    """(V, C, H, W) of a sample's sar, and Ex * Ey * Ef of its echo per view (None if the grid is unusable)."""
    names = [v["name"] for v in index["views"]]
    sar = (len(names), len(index["channels"]), *index["image_size"])
    grid = index["echo_grid"]
    try:
        sizes = {len(grid["positions_mm"][n]) for n in names}
        echo = sizes.pop() * len(grid["frequencies_hz"]) if len(sizes) == 1 else None
    except (KeyError, TypeError):
        echo = None
    return sar, echo


def _loss_grid_size(index: dict) -> int | None:
    """Lx * Ly * Lf of echo_clean per view, from the index's loss_grid (None if the grid is unusable)."""
    try:
        grid = index["loss_grid"]
        sizes = {len(grid["positions_mm"][v["name"]]) for v in index["views"]}
        return sizes.pop() * len(grid["frequencies_hz"]) if len(sizes) == 1 else None
    except (KeyError, TypeError):
        return None


def content_problems(arrays: dict[str, np.ndarray], index: dict) -> list[str]:
    """Element-level checks of structurally sound shard arrays against the index."""
    problems = []
    sar_shape, echo_size = _expected_shapes(index)
    if arrays["sar"].shape[1:] != sar_shape:
        problems.append(f"sar has per-sample shape {arrays['sar'].shape[1:]}, index says (V, C, H, W) = {sar_shape}")
    echo = arrays["echo"].shape[1:]
    if echo[0] != sar_shape[0] or (echo_size is not None and int(np.prod(echo[1:])) != echo_size):
        problems.append(f"echo has per-sample shape {echo}, inconsistent with the index's views and echo_grid")
    clean, loss_size = arrays["echo_clean"].shape[1:], _loss_grid_size(index)
    if clean[0] != sar_shape[0] or (loss_size is not None and int(np.prod(clean[1:])) != loss_size):
        problems.append(f"echo_clean has per-sample shape {clean}, inconsistent with the index's views and loss_grid")
    if np.any(arrays["noise_sigma"] < 0):
        problems.append("noise_sigma has negative values")
    for key in ("verts", "center_mm", "sar", "echo", "echo_clean", "noise_sigma"):
        if not np.all(np.isfinite(arrays[key])):
            problems.append(f"{key} has NaN or infinite values")
    if "intensity" in index["channels"] and arrays["sar"].shape[1:] == sar_shape:
        intensity = arrays["sar"][:, :, index["channels"].index("intensity")]
        if intensity.size and not (np.nanmin(intensity) >= 0 and np.nanmax(intensity) <= 1):
            problems.append("sar intensity channel outside [0, 1]")
    n_verts = np.diff(arrays["vert_offsets"])
    owner = np.repeat(np.arange(len(n_verts)), np.diff(arrays["face_offsets"]))
    faces = arrays["faces"]
    bad = np.flatnonzero((faces < 0).any(axis=1) | (faces >= n_verts[owner][:, None]).any(axis=1))
    if bad.size:
        problems.append(f"{bad.size} face(s) index vertices outside their sample (first: face {bad[0]} of "
                        f"sample {arrays['sample_id'][owner[bad[0]]]})")
    for sid, text in zip(arrays["sample_id"], arrays["meta"]):
        try:
            ok = isinstance(json.loads(str(text)), dict)
        except ValueError:
            ok = False
        if not ok:
            problems.append(f"meta of sample {sid} is not a JSON object")
    return problems


def _shard_problems(root: Path, entry: dict, index: dict) -> list[str]:
    """Problems of one shard listed in the index (presence, digest, loading, arrays, ids)."""
    path = root / entry["file"]
    if not path.is_file():
        return ["missing"]
    problems = []
    if sha256_file(path) != entry["sha256"]:
        problems.append("sha256 differs from the index (file changed or corrupt)")
    try:
        with np.load(path, allow_pickle=False) as z:  # reading every member checks the zip CRCs
            arrays = {k: z[k] for k in z.files}
    except Exception as e:  # any failure to load is the finding, whatever numpy or zipfile raise
        return [*problems, f"does not load with np.load(allow_pickle=False): {type(e).__name__}: {e}"]
    structure = structure_problems(arrays)
    if structure:
        return problems + structure
    problems += content_problems(arrays, index)
    ids = [str(s) for s in arrays["sample_id"]]
    if ids != list(entry["sample_ids"]) or len(ids) != entry["n"]:
        problems.append(f"sample ids {ids[:3]}... (n={len(ids)}) differ from the index's (n={entry['n']})")
    return problems


def _split_problems(path: Path, known: set[str], samples: dict | None = None) -> list[str]:
    try:
        split = read_json(path)
        names = list(split["ratios"])
    except (OSError, ValueError, KeyError, TypeError) as e:
        return [f"not a readable split file ({type(e).__name__}: {e})"]
    problems, seen = [], {}
    group_by = split.get("group_by", "subject")
    if group_by not in GROUP_BY:
        problems.append(f"group_by must be one of {GROUP_BY}, got {group_by!r}")
    for name in names:
        if name in RESERVED or not isinstance(split.get(name), list):
            problems.append(f"split '{name}' has no id list")
            continue
        unknown = [s for s in split[name] if s not in known]
        if unknown:
            problems.append(f"split '{name}' names {len(unknown)} id(s) not in the index: {unknown[:5]}")
        for sid in split[name]:
            if sid in seen:
                problems.append(f"sample {sid} is in both '{seen[sid]}' and '{name}'" if seen[sid] != name
                                else f"sample {sid} is listed twice in '{name}'")
            seen[sid] = name
    leaks = subject_leaks(split, samples or {}) if group_by == "subject" else {}
    if leaks:
        problems.append(f"subject-grouped split with {len(leaks)} subject(s) in two parts: {describe_leaks(leaks)}")
    return problems


def verify(out_dir: str | os.PathLike) -> list[str]:
    """Every problem of the dataset in `out_dir`, each 'FILE: what'; [] when it is sound.

    Checks: index.json readable with the contract keys; each listed shard present,
    matching its sha256, loading without pickles, with the contract's arrays (keys,
    dtypes, shapes, monotone offsets, face indices in range, finite values, sar
    intensity in [0, 1], JSON meta) and the index's sample ids; ids unique over
    shards; no unlisted shard files; every split file's ids known to the index
    and in one split only, and in a subject-grouped split no subject (splits.group_key:
    cohort or source, and subject) in two parts.
    """
    root = Path(out_dir)
    try:
        index = read_index(root)
    except InputError as e:
        return [str(e)]
    problems = []
    listed, owner = set(), {}
    for entry in index["shards"]:
        listed.add(entry["file"])
        problems += [f"{entry['file']}: {p}" for p in _shard_problems(root, entry, index)]
        for sid in entry["sample_ids"]:
            if sid in owner:
                problems.append(f"{entry['file']}: sample id {sid} also in {owner[sid]}")
            owner[sid] = entry["file"]
    if set(owner) != set(index["samples"]):
        problems.append(f"{INDEX_NAME}: 'samples' and the shards' sample_ids differ "
                        f"({len(set(owner) ^ set(index['samples']))} id(s))")
    if index["counts"].get("total") != len(owner):
        problems.append(f"{INDEX_NAME}: counts.total {index['counts'].get('total')} but the shards hold {len(owner)}")
    for path in sorted((root / SHARD_DIR).glob("*.npz")):
        rel = path.relative_to(root).as_posix()
        if rel not in listed:
            problems.append(f"{rel}: shard file not listed in {INDEX_NAME}")
    for path in sorted((root / "splits").glob("*.json")):
        problems += [f"{path.relative_to(root).as_posix()}: {p}" for p in _split_problems(path, set(owner), index["samples"])]
    return problems


def notes(out_dir: str | os.PathLike) -> list[str]:
    """What `meshsar verify` reports besides problems: each split grouped by sample (an explicit
    opt-in), and how many subjects it spreads over several parts."""
    root = Path(out_dir)
    try:
        samples = read_index(root)["samples"]
    except InputError:
        return []
    out = []
    for path in sorted((root / "splits").glob("*.json")):
        try:
            split = read_json(path)
        except (OSError, ValueError):
            continue
        if isinstance(split, dict) and split.get("group_by") == "sample":
            leaks = subject_leaks(split, samples)
            out.append(f"{path.relative_to(root).as_posix()}: group_by = \"sample\" (opt-in): not grouped by subject; "
                       + (f"{len(leaks)} subject(s) in several parts: {describe_leaks(leaks, 3)}" if leaks
                          else "no subject is in two parts"))
    return out
