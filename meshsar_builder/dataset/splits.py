"""Seeded dataset splits made from the index alone (DESIGN section 7).

A split file `splits/seed-<S>.json` holds {"seed", "ratios", "group_by", and
per ratio name the list of sample ids}. Samples are grouped (group_by
"subject": the frames of one subject form a group, an SSM sample is its own
subject; "sample": every sample alone, an explicit opt-in) and whole groups go
to one split, so no subject leaks from train into test. A subject is named
within its source, or within its cohort where sources declare one (`cohort` in
[[sources]]: annotated and predicted frames of the same patients), so grouping
crosses those sources (group_key). Reading a subject-grouped split
(read_split, and `meshsar verify`) refuses one in which a subject is in two
parts, naming it; a sample-grouped one is read with a SplitWarning naming the
subjects it spreads over several parts.

Rule, per subset (ssm, direct, ...; so each subset is split in the given
ratios rather than only the total):
A group whose samples lie in several subsets (a cohort spanning them) is
allocated, whole, with the first of them in sorted order.
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
import warnings
from collections import Counter
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


class SplitWarning(UserWarning):
    """A split that may hold one subject in several parts (group_by = "sample", an opt-in), or that leaves a part
    empty."""


def group_key(sample: dict) -> str:
    """The subject a sample of the index belongs to: `<cohort or source>/<subject>`."""
    return f"{sample.get('cohort') or sample['source']}/{sample['subject']}"


def subject_leaks(split: dict, samples: dict) -> dict[str, dict[str, int]]:
    """Subjects whose samples lie in more than one part of `split`: {group_key: {part: n samples}}.

    samples : the index's "samples" (id -> source, subject, cohort where declared); ids it does not
    know are left out (verify reports them separately).
    """
    parts: dict[str, dict[str, int]] = {}
    for name in split.get("ratios", {}):
        ids = split.get(name)
        if name in RESERVED or not isinstance(ids, list):
            continue
        for sid in ids:
            if isinstance(sid, str) and sid in samples:
                counts = parts.setdefault(group_key(samples[sid]), {})
                counts[name] = counts.get(name, 0) + 1
    return {key: counts for key, counts in sorted(parts.items()) if len(counts) > 1}


def describe_leaks(leaks: dict[str, dict[str, int]], limit: int = 5) -> str:
    """'subject acdc/patient001 in train (1) and test (1); ...' for the first `limit` leaks."""
    text = "; ".join(f"subject {key} in " + " and ".join(f"{n} ({c})" for n, c in counts.items())
                     for key, counts in list(leaks.items())[:limit])
    return text + (f"; and {len(leaks) - limit} more" if len(leaks) > limit else "")


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
    groups_all: dict[str, list[str]] = {}
    for sid, s in index["samples"].items():
        groups_all.setdefault(group_key(s) if group_by == "subject" else sid, []).append(sid)
    by_subset: dict[str, dict[str, list[str]]] = {}
    for key, members in groups_all.items():
        subset = min(index["samples"][sid]["subset"] for sid in members)
        by_subset.setdefault(subset, {})[key] = members
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
    empty = [n for n in names if ratios[n] > 0 and not chosen[n]]
    if empty:
        sizes = sorted((len(g) for g in groups_all.values()), reverse=True)
        warnings.warn(f"split seed {seed}: the parts {empty} got no samples: {len(index['samples'])} samples in "
                      f"{len(groups_all)} group(s) of {sizes[:10]}{'...' if len(sizes) > 10 else ''} samples (a "
                      f"{group_by}'s samples stay in one part), too few for the ratios {ratios}", SplitWarning,
                      stacklevel=2)
    return {"seed": int(seed), "ratios": ratios, "group_by": group_by,
            **{n: sorted(ids, key=position.__getitem__) for n, ids in chosen.items()}}


def split_path(out_dir: str | os.PathLike, seed: int) -> Path:
    return Path(out_dir) / "splits" / f"seed-{seed}.json"


def write_split(out_dir: str | os.PathLike, split: dict) -> Path:
    """Write `split` atomically to OUT/splits/seed-<S>.json (canonical JSON: same split, same bytes)."""
    path = split_path(out_dir, split["seed"])
    write_json(path, split)
    return path


def read_split(out_dir: str | os.PathLike, seed: int, index: dict | None = None) -> dict:
    """OUT/splits/seed-<S>.json; InputError naming the file when missing or malformed, or when it
    groups by subject (the default) and a subject of the index (`index`, else OUT/index.json)
    has samples in two parts, naming the subjects. A split grouped by sample is read, with a
    SplitWarning naming the subjects in several parts."""
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
    group_by = split.get("group_by", "subject")
    if group_by not in GROUP_BY:
        raise InputError(f"{path}: group_by must be one of {GROUP_BY}, got {group_by!r}")
    repeated = repeated_ids(split)
    if repeated:
        raise InputError(f"{path}: {len(repeated)} id(s) listed more than once (a reader would serve them twice an "
                         f"epoch, or in two parts): {repeated[:5]}")
    leaks = subject_leaks(split, (index if index is not None else read_index(out_dir))["samples"])
    if leaks and group_by == "subject":
        raise InputError(f"{path}: a subject-grouped split with {len(leaks)} subject(s) in two parts, which leaks "
                         f"them between parts: {describe_leaks(leaks)}")
    if leaks:
        warnings.warn(f"{path}: group_by = \"sample\" (opt-in): {len(leaks)} subject(s) have samples in several "
                      f"parts, so its parts are not subject-independent: {describe_leaks(leaks)}", SplitWarning,
                      stacklevel=2)
    return split


def repeated_ids(split: dict) -> list[str]:
    """The ids a split file lists more than once, within one part or across its parts."""
    counts = Counter(sid for name in split["ratios"] if isinstance(split.get(name), list) for sid in split[name])
    return sorted(sid for sid, n in counts.items() if n > 1)


def split_dataset(out_dir: str | os.PathLike, seed: int, ratios: dict[str, float] | None = None,
                  group_by: str = "subject") -> Path:
    """`meshsar splits`: make the split of a built dataset from its index.json and write it; return its path."""
    return write_split(out_dir, make_split(read_index(out_dir), seed, ratios, group_by))
