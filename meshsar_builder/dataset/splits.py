"""Seeded dataset splits made from the index alone (DESIGN section 7).

A split file `splits/seed-<S>.json` holds {"seed", "ratios", "group_by", and
per ratio name the list of sample ids}. Samples are grouped (group_by
"subject": the frames of one subject of one source form a group, an SSM sample
is its own subject; "sample": every sample alone) and whole groups go to one
split, so no subject leaks from train into test.

Rule, per subset (ssm, direct, ...; so each subset is split in the given
ratios rather than only the total):
1. the subset's N samples get integer targets by the largest-remainder rule
   over the normalised ratios (ties to the name first in sorted order);
2. its groups, sorted by key, are permuted by a generator seeded from (seed,
   "splits", subset) only, and laid end to end; with the splits' target
   intervals laid out in name order, a group goes to the split whose interval
   holds the group's midpoint.
Names are taken in sorted order, so the split depends on the ratios as a
mapping, not on the order they were written in (split files sort their keys).
Each split then differs from its target by less than the largest group; with
single-sample groups the targets are met exactly. Ids are listed in dataset
(index) order.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from meshsar_builder.dataset.shards import read_index
from meshsar_builder.pipeline.errors import InputError
from meshsar_builder.pipeline.io import read_json, write_json
from meshsar_builder.pipeline.seeding import item_rng


@dataclass(frozen=True)
class SplitParams:
    seed: int = 0
    ratios: dict[str, float] = field(default_factory=lambda: {"train": 0.8, "test": 0.2})
    group_by: str = "subject"

    def __post_init__(self):
        check_ratios(self.ratios)
        if self.group_by not in GROUP_BY:
            raise ValueError(f"group_by: must be one of {GROUP_BY}, got {self.group_by!r}")

RESERVED = ("seed", "ratios", "group_by")
GROUP_BY = ("subject", "sample")


def parse_ratios(text: str) -> dict[str, float]:
    """'train=0.8,test=0.2' -> {'train': 0.8, 'test': 0.2}; ValueError naming the bad entry."""
    ratios = {}
    for entry in text.split(","):
        name, eq, value = entry.partition("=")
        name = name.strip()
        try:
            ratios[name] = float(value)
        except ValueError:
            raise ValueError(f"ratios: expected NAME=NUMBER, got {entry.strip()!r}") from None
        if not eq or not name:
            raise ValueError(f"ratios: expected NAME=NUMBER, got {entry.strip()!r}")
    check_ratios(ratios)
    return ratios


def check_ratios(ratios: dict[str, float]) -> None:
    """ValueError unless the names are usable split names and the values non-negative with a positive sum."""
    bad = [n for n in ratios if n in RESERVED or not n]
    if bad:
        raise ValueError(f"ratios: split names {bad} are not allowed (reserved: {', '.join(RESERVED)})")
    if not ratios or any(not (0 <= v < np.inf) for v in ratios.values()) or sum(ratios.values()) <= 0:
        raise ValueError(f"ratios: need finite non-negative values with a positive sum, got {ratios}")


def largest_remainder(weights: np.ndarray, total: int) -> np.ndarray:
    """Integers summing to `total`, proportional to `weights` (K,), by the largest-remainder rule."""
    # Rounded first, so 0.7 * 10 = 7.000000000000001 does not win a remainder it does not have.
    quotas = np.round(weights / weights.sum() * total, 9)
    counts = np.floor(quotas).astype(np.int64)
    order = np.argsort(-(quotas - counts), kind="stable")
    counts[order[: total - counts.sum()]] += 1
    return counts


def make_split(index: dict, seed: int, ratios: dict[str, float] | None = None, group_by: str = "subject") -> dict:
    """A split of every sample of `index` (never opening shards); see the module docstring for the rule.

    Returns {"seed", "ratios", "group_by", name: [sample ids] for each ratio name}.
    """
    ratios = dict(ratios if ratios is not None else {"train": 0.8, "test": 0.2})
    check_ratios(ratios)
    if group_by not in GROUP_BY:
        raise ValueError(f"group_by: must be one of {GROUP_BY}, got {group_by!r}")
    names = sorted(ratios)
    weights = np.array([ratios[n] for n in names], dtype=np.float64)
    position = {sid: k for k, sid in enumerate(sid for shard in index["shards"] for sid in shard["sample_ids"])}
    chosen: dict[str, list[str]] = {n: [] for n in names}
    by_subset: dict[str, dict[str, list[str]]] = {}
    for sid, s in index["samples"].items():
        key = f"{s['source']}/{s['subject']}" if group_by == "subject" else sid
        by_subset.setdefault(s["subset"], {}).setdefault(key, []).append(sid)
    for subset in sorted(by_subset):
        groups = by_subset[subset]
        keys = sorted(groups)
        bounds = np.cumsum(largest_remainder(weights, sum(len(g) for g in groups.values())))
        start = 0
        for i in item_rng(seed, "splits", subset).permutation(len(keys)):
            members = groups[keys[i]]
            k = min(int(np.searchsorted(bounds, start + len(members) / 2, side="right")), len(names) - 1)
            chosen[names[k]].extend(members)
            start += len(members)
    return {"seed": int(seed), "ratios": ratios, "group_by": group_by,
            **{n: sorted(ids, key=position.__getitem__) for n, ids in chosen.items()}}


def split_path(out_dir: str | os.PathLike, seed: int) -> Path:
    return Path(out_dir) / "splits" / f"seed-{seed}.json"


def write_split(out_dir: str | os.PathLike, split: dict) -> Path:
    """Write `split` atomically to OUT/splits/seed-<S>.json (canonical JSON: same split, same bytes)."""
    path = split_path(out_dir, split["seed"])
    write_json(path, split)
    return path


def read_split(out_dir: str | os.PathLike, seed: int) -> dict:
    """OUT/splits/seed-<S>.json; InputError naming the file when missing or malformed."""
    path = split_path(out_dir, seed)
    try:
        split = read_json(path)
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: cannot read the split ({type(e).__name__}: {e}); "
                         f"make it with `meshsar splits {out_dir} --seed {seed}`") from e
    if not isinstance(split, dict) or not isinstance(split.get("ratios"), dict):
        raise InputError(f"{path}: not a split file (needs 'ratios' and one id list per ratio name)")
    bad = [n for n in split["ratios"] if not isinstance(split.get(n), list)]
    if bad:
        raise InputError(f"{path}: no id list for splits {bad}")
    return split


def split_dataset(out_dir: str | os.PathLike, seed: int, ratios: dict[str, float] | None = None,
                  group_by: str = "subject") -> Path:
    """`meshsar splits`: make the split of a built dataset from its index.json and write it; return its path."""
    return write_split(out_dir, make_split(read_index(out_dir), seed, ratios, group_by))
