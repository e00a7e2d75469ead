"""Splits: whole subjects per split, every sample once, seeded and machine-independent, ratios kept."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from meshsar_builder.dataset.splits import (
    SplitWarning,
    group_key,
    largest_remainder,
    make_split,
    parse_ratios,
    read_split,
    split_dataset,
    subject_leaks,
    write_split,
)
from meshsar_builder.dataset.verify import notes, verify
from meshsar_builder.pipeline.errors import InputError

from .test_shards import tiny_dataset


def index_of(groups: dict[str, list[int]]) -> dict:
    """A minimal index: per subset, one subject per entry with that many frames (no shards needed)."""
    samples, ids = {}, []
    for subset, sizes in groups.items():
        for g, size in enumerate(sizes):
            for f in range(size):
                sid = f"{subset}-{g:04d}-{f:03d}"
                samples[sid] = {"source": "src", "subject": f"{subset}{g}", "subset": subset}
                ids.append(sid)
    return {"samples": samples, "shards": [{"sample_ids": ids}]}


def names(split: dict) -> list[str]:
    return list(split["ratios"])


def check_partition(index: dict, split: dict) -> None:
    chosen = [sid for n in names(split) for sid in split[n]]
    assert sorted(chosen) == sorted(index["samples"])  # each sample exactly once
    where = {}
    for n in names(split):
        for sid in split[n]:
            s = index["samples"][sid]
            key = (s["source"], s["subject"])
            assert where.setdefault(key, n) == n, f"subject {key} in two splits"


def test_subjects_never_straddle_and_every_sample_once(tmp_path):
    index, _ = tiny_dataset(tmp_path, n_ssm=6, direct=(4, 4, 3, 5, 2))
    for seed in range(20):
        split = make_split(index, seed, {"train": 0.6, "val": 0.2, "test": 0.2})
        check_partition(index, split)
        assert set(split) == {"seed", "ratios", "group_by", "train", "val", "test"}


def test_same_seed_same_bytes_other_seed_differs(tmp_path):
    index, _ = tiny_dataset(tmp_path / "data", n_ssm=30, direct=(3,) * 10)
    a = write_split(tmp_path / "a", make_split(index, 7)).read_bytes()
    b = write_split(tmp_path / "b", make_split(index, 7)).read_bytes()
    c = write_split(tmp_path / "c", make_split(index, 8)).read_bytes()
    assert a == b and a != c
    assert (tmp_path / "a" / "splits" / "seed-7.json").is_file()


def test_split_ignores_the_order_of_the_index():
    index = index_of({"ssm": [1] * 20, "direct": [5, 3, 4, 6]})
    shuffled = dict(reversed(list(index["samples"].items())))
    assert make_split(index, 3) == make_split({**index, "samples": shuffled}, 3)


def test_known_split_is_pinned():
    # A fixed expectation: the split of a seed must not change across numpy versions or machines.
    split = make_split(index_of({"ssm": [1] * 10}), 0)
    assert split["test"] == ["ssm-0007-000", "ssm-0009-000"] and len(split["train"]) == 8
    # the ratios as a mapping decide, not the order they were written in
    assert make_split(index_of({"ssm": [1] * 10}), 0, {"test": 0.2, "train": 0.8})["test"] == split["test"]


def test_singleton_groups_meet_targets_exactly():
    index = index_of({"ssm": [1] * 101})
    split = make_split(index, 1, {"train": 0.7, "val": 0.15, "test": 0.15})
    # 70.7 / 15.15 / 15.15 -> 70 / 15 / 15 plus the remainder to the first largest fraction
    assert [len(split[n]) for n in names(split)] == [71, 15, 15]


@settings(max_examples=60, deadline=None)
@given(
    ssm=st.integers(0, 40),
    direct=st.lists(st.integers(1, 12), max_size=12),
    ratios=st.lists(st.floats(0, 1), min_size=1, max_size=3).filter(lambda r: sum(r) > 0.05),
    seed=st.integers(0, 2**31),
)
def test_ratios_respected_within_one_group_per_subset(ssm, direct, ratios, seed):
    groups = {"ssm": [1] * ssm, "direct": direct}
    index = index_of(groups)
    named = {f"s{i}": r for i, r in enumerate(ratios)}
    split = make_split(index, seed, named)
    check_partition(index, split)
    weights = np.array(ratios) / sum(ratios)
    for subset, sizes in groups.items():
        total, biggest = sum(sizes), max(sizes, default=0)
        for n, w in zip(names(split), weights):
            got = sum(index["samples"][sid]["subset"] == subset for sid in split[n])
            assert abs(got - w * total) < biggest + 1, (subset, n, got, w * total)


def test_group_by_sample_splits_frames():
    index = index_of({"direct": [50]})
    split = make_split(index, 0, group_by="sample")
    assert (len(split["train"]), len(split["test"])) == (40, 10)
    with pytest.warns(SplitWarning, match=r"the parts \['test'\] got no samples: 50 samples in 1 group\(s\) of \[50\]"):
        assert make_split(index, 0)["test"] == []  # one subject: all of it in one part


def test_largest_remainder():
    assert largest_remainder(np.array([0.7, 0.2, 0.1]), 10).tolist() == [7, 2, 1]
    assert largest_remainder(np.array([1.0, 1.0, 1.0]), 10).tolist() == [4, 3, 3]
    assert largest_remainder(np.array([0.8, 0.2]), 0).tolist() == [0, 0]


def test_parse_ratios():
    assert parse_ratios("train=0.8,test=0.2") == {"train": 0.8, "test": 0.2}
    assert parse_ratios(" train = 3 , val=1,test=1") == {"train": 3.0, "val": 1.0, "test": 1.0}
    for bad, match in [("train0.8", "NAME=NUMBER"), ("train=x", "NAME=NUMBER"), ("=1", "NAME=NUMBER"),
                       ("seed=1", "reserved"), ("a=-1,b=2", "non-negative"), ("a=0", "positive sum")]:
        with pytest.raises(ValueError, match=match):
            parse_ratios(bad)


def test_split_dataset_reads_only_the_index(tmp_path):
    index, _ = tiny_dataset(tmp_path)
    for shard in (tmp_path / "shards").iterdir():
        shard.unlink()  # splits never open shards
    path = split_dataset(tmp_path, 4, {"train": 0.5, "test": 0.5})
    assert path == tmp_path / "splits" / "seed-4.json"
    with pytest.raises(InputError, match="index.json"):
        split_dataset(tmp_path / "nowhere", 0)


# --- subjects grouped across sources (cohorts), and splits that leak refused ----------------------


def cohort_index(subjects: list[tuple[int, int, int]]) -> dict:
    """Per subject k: (annotated frames, predicted frames, frames of an unrelated source with the same
    names); sources "gt" and "pred" share cohort "c", "other" has none. Plus a few SSM samples."""
    samples, ids = {}, []

    def add(sid, **s):
        samples[sid] = s
        ids.append(sid)

    for k, (n_gt, n_pred, n_other) in enumerate(subjects):
        for f in range(n_gt):
            add(f"gt-p{k:02d}-f{f:02d}", source="gt", cohort="c", subject=f"p{k:02d}", subset="direct")
        for f in range(n_pred):
            add(f"pred-p{k:02d}-f{f:02d}", source="pred", cohort="c", subject=f"p{k:02d}", subset="direct")
        for f in range(n_other):
            add(f"other-p{k:02d}-f{f:02d}", source="other", subject=f"p{k:02d}", subset="direct")
    for i in range(3):
        add(f"ssm-{i:05d}", source="phantom_wh", subject=f"ssm-{i:05d}", subset="ssm")
    return {"samples": samples, "shards": [{"sample_ids": ids}]}


@settings(max_examples=80, deadline=None)
@given(
    subjects=st.lists(st.tuples(st.integers(0, 3), st.integers(0, 6), st.integers(0, 2)), min_size=2, max_size=9),
    ratios=st.sampled_from([{"train": 0.8, "test": 0.2}, {"train": 0.6, "val": 0.2, "test": 0.2},
                            {"a": 1.0, "b": 1.0}]),
    seed=st.integers(0, 2**31),
)
def test_frames_of_a_subject_never_leak_across_sources_of_a_cohort(subjects, ratios, seed):
    index = cohort_index(subjects)
    split = make_split(index, seed, ratios)
    check_partition(index, split)
    assert subject_leaks(split, index["samples"]) == {}
    where = {}
    for n in names(split):
        for sid in split[n]:
            s = index["samples"][sid]
            # annotated and predicted frames of one patient: one part, whichever source
            assert where.setdefault(group_key(s), n) == n, (group_key(s), n)
    assert {group_key(s) for s in index["samples"].values() if s["source"] == "pred"} <= {
        f"c/p{k:02d}" for k in range(len(subjects))}


def test_same_names_in_sources_without_a_cohort_are_different_subjects():
    index = cohort_index([(0, 0, 2)] * 6)
    for sid, s in list(index["samples"].items())[:12]:
        index["samples"][sid.replace("other", "else")] = {**s, "source": "else"}
        index["shards"][0]["sample_ids"].append(sid.replace("other", "else"))
    keys = {group_key(s) for s in index["samples"].values()}
    assert "other/p00" in keys and "else/p00" in keys
    # with one seed or another, some patient p0k of "other" and of "else" land apart: no cohort, no grouping
    assert any(subject_leaks(make_split(index, seed), {sid: {**s, "source": "x", "cohort": ""}
                                                        for sid, s in index["samples"].items()})
               for seed in range(10))


def test_a_group_spanning_subsets_goes_whole_to_one_part():
    index = cohort_index([(2, 2, 0)] * 5)
    for sid in [s for s in index["samples"] if s.startswith("pred-")]:
        index["samples"][sid]["subset"] = "zz"  # a cohort spread over two subsets
    for seed in range(30):
        assert subject_leaks(make_split(index, seed), index["samples"]) == {}


def test_reading_a_leaking_split_is_refused_naming_the_subject(tmp_path):
    index, _ = tiny_dataset(tmp_path, n_ssm=2, direct=(3, 3, 3, 3, 3))
    split = make_split(index, 0, {"train": 0.6, "test": 0.4})
    write_split(tmp_path, split)
    assert read_split(tmp_path, 0) == split  # a sound split reads as written
    moved = next(sid for sid in split["train"] if index["samples"][sid]["subset"] == "direct")
    subject = index["samples"][moved]["subject"]
    split["train"].remove(moved)
    split["test"].append(moved)
    write_split(tmp_path, split)
    with pytest.raises(InputError, match=rf"seed-0.json: a subject-grouped split with 1 subject\(s\) in two parts, "
                                         rf"which leaks them between parts: subject phantom_bv/{subject} in"):
        read_split(tmp_path, 0)
    (problem,) = verify(tmp_path)
    assert problem.startswith(f"splits/seed-0.json: subject-grouped split with 1 subject(s) in two parts: "
                              f"subject phantom_bv/{subject} in test (1) and train (2)")
    # the same split marked as grouped by sample, an opt-in: read with a warning that names it; verify notes it
    write_split(tmp_path, {**split, "group_by": "sample"})
    with pytest.warns(SplitWarning, match=rf'group_by = "sample" \(opt-in\): 1 subject\(s\) .* phantom_bv/{subject}'):
        read_split(tmp_path, 0)
    assert verify(tmp_path) == []
    (note,) = notes(tmp_path)
    assert note.startswith('splits/seed-0.json: group_by = "sample" (opt-in): not grouped by subject; 1 subject(s) in '
                           'several parts')
    write_split(tmp_path, {**split, "group_by": "visit"})
    with pytest.raises(InputError, match=r"group_by must be one of \('subject', 'sample'\), got 'visit'"):
        read_split(tmp_path, 0)
    assert any("group_by must be one of" in p for p in verify(tmp_path))


def test_a_built_sample_grouped_split_is_noted_without_leaks_when_none(tmp_path):
    index, _ = tiny_dataset(tmp_path, n_ssm=4, direct=())
    write_split(tmp_path, make_split(index, 0, group_by="sample"))
    assert notes(tmp_path) == ['splits/seed-0.json: group_by = "sample" (opt-in): not grouped by subject; '
                               'no subject is in two parts']


def test_a_cohort_travels_from_the_recipe_through_meta_and_index_to_the_split(tmp_path):
    """The radar stage puts a source's cohort in its samples' meta, the index keeps it, and the split
    groups a patient's annotated and predicted frames together."""
    from types import SimpleNamespace

    from meshsar_builder.dataset.shards import build_index
    from meshsar_builder.pipeline import recipe as R
    from stages.radar import dataset_meshes

    from .test_shards import METADATA

    recipe = R.parse('name = "c"\n'
                     '[[sources]]\nkind = "nifti"\nname = "gt"\npath = "a"\nlabels = { lv = 1 }\ncohort = "cine"\n'
                     '[[sources]]\nkind = "nifti"\nname = "pred"\npath = "b"\nlabels = { lv = 1 }\ncohort = "cine"\n'
                     '[[sources]]\nkind = "nifti"\nname = "other"\npath = "c"\nlabels = { lv = 1 }\n')
    remesh = {f"{src}-p{k}-f{f:02d}": {"use": "direct", "source": src, "subject": f"p{k}", "frame": f, "phase": "",
                                        "cycle_fraction": None,
                                        "provenance": "predicted" if src == "pred" else "annotated"}
              for src in ("gt", "pred", "other") for k in range(6) for f in range(3 if src == "pred" else 1)}
    results = SimpleNamespace(of=lambda stage: remesh if stage == "remesh" else {})
    ctx = SimpleNamespace(recipe=recipe, stage_dir=lambda name: tmp_path / name)
    metas = {sid: meta for sid, _, meta in dataset_meshes(ctx, results)}
    assert metas["gt-p0-f00"]["cohort"] == metas["pred-p0-f02"]["cohort"] == "cine"
    assert "cohort" not in metas["other-p0-f00"]  # no cohort: the meta is as it was
    # frame 0 of each patient, given by both: the annotated map, once
    assert metas["gt-p0-f00"]["replaces"] == ["pred-p0-f00"] and "pred-p0-f00" not in metas
    ids = list(metas)
    index = build_index(recipe="c", recipe_sha256="0" * 64, code_version="test", metadata=METADATA, shard_size=64,
                        shards=[{"file": "shards/shard-00000.npz", "n": len(ids), "sha256": "0" * 64, "sample_ids": ids}],
                        metas=metas)
    assert index["samples"]["pred-p3-f01"]["cohort"] == "cine" and "cohort" not in index["samples"]["other-p3-f00"]
    for seed in range(40):
        split = make_split(index, seed, {"train": 0.5, "test": 0.5})
        assert subject_leaks(split, index["samples"]) == {}
        part = {sid: n for n in names(split) for sid in split[n]}
        assert all(part[f"gt-p{k}-f00"] == part[f"pred-p{k}-f{f:02d}"] for k in range(6) for f in (1, 2))


def test_a_negative_seed_is_refused_by_the_command_line(tmp_path, capsys):
    """numpy's seed sequences take no negative seed: named at the argument (exit 2), not a traceback."""
    from meshsar_builder.cli import main

    with pytest.raises(SystemExit) as exit_:
        main(["splits", str(tmp_path), "--seed", "-1"])
    assert exit_.value.code == 2 and "argument --seed: a seed is an integer >= 0, got -1" in capsys.readouterr().err
