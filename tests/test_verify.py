"""verify: a sound dataset passes; each kind of damage is reported naming the file and the fault."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from meshsar_builder.dataset.shards import pack
from meshsar_builder.dataset.verify import verify
from meshsar_builder.pipeline.io import sha256_file, write_json

from .test_shards import tiny_dataset

SHARD = "shards/shard-00001.npz"


@pytest.fixture
def dataset(tmp_path):
    index, samples = tiny_dataset(tmp_path)
    return tmp_path, index, samples


def rewrite_arrays(root, index, file, change) -> None:
    """Rewrite a shard with `change(arrays)` applied and re-record its sha256, so only the content is wrong."""
    entry = next(s for s in index["shards"] if s["file"] == file)
    with np.load(root / file, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    change(arrays)
    with open(root / file, "wb") as f:
        np.savez(f, **arrays)
    entry["sha256"] = sha256_file(root / file)
    write_json(root / "index.json", index)


def test_sound_dataset_has_no_problems(dataset):
    root, _, _ = dataset
    assert verify(root) == []


def test_flipped_byte_is_reported(dataset):
    root, _, _ = dataset
    data = bytearray((root / SHARD).read_bytes())
    data[len(data) // 2] ^= 0x01
    (root / SHARD).write_bytes(bytes(data))
    problems = verify(root)
    assert any(p.startswith(f"{SHARD}: sha256 differs") for p in problems), problems
    assert all(p.startswith(SHARD) for p in problems)


def test_truncated_shard_is_reported(dataset):
    root, _, _ = dataset
    data = (root / SHARD).read_bytes()
    (root / SHARD).write_bytes(data[: len(data) - 100])
    problems = verify(root)
    assert f"{SHARD}: sha256 differs from the index (file changed or corrupt)" in problems
    assert any(p.startswith(f"{SHARD}: does not load with np.load(allow_pickle=False)") for p in problems), problems


def test_missing_shard_is_reported(dataset):
    root, _, _ = dataset
    (root / SHARD).unlink()
    assert verify(root) == [f"{SHARD}: missing"]


def test_split_naming_unknown_id_is_reported(dataset):
    root, _, _ = dataset
    path = root / "splits" / "seed-0.json"
    split = json.loads(path.read_text())
    split["test"].append("ghost-00001")
    split["test"].append(split["train"][0])
    write_json(path, split)
    problems = verify(root)
    assert problems[0] == "splits/seed-0.json: split 'test' names 1 id(s) not in the index: ['ghost-00001']"
    # the file's keys are sorted (canonical JSON), so 'test' is read first
    assert problems[1] == f"splits/seed-0.json: sample {split['train'][0]} is in both 'test' and 'train'"
    # and its subject is then in two parts of a subject-grouped split
    s = json.loads((root / "index.json").read_text())["samples"][split["train"][0]]
    assert problems[2] == (f"splits/seed-0.json: subject-grouped split with 1 subject(s) in two parts: "
                           f"subject {s['source']}/{s['subject']} in test (1) and train (1)")
    assert len(problems) == 3


def test_missing_index_is_reported(tmp_path):
    assert len(verify(tmp_path)) == 1 and "index.json" in verify(tmp_path)[0]


def test_unlisted_shard_file_is_reported(dataset):
    root, _, _ = dataset
    (root / "shards" / "shard-00099.npz").write_bytes((root / SHARD).read_bytes())
    assert verify(root) == ["shards/shard-00099.npz: shard file not listed in index.json"]


@pytest.mark.parametrize("fault, change, message", [
    ("face out of range", lambda a: a["faces"].__setitem__((0, 0), 10_000), "face(s) index vertices outside their sample"),
    ("nan vertex", lambda a: a["verts"].__setitem__((0, 1), np.nan), "verts has NaN or infinite values"),
    ("bright intensity", lambda a: a["sar"].__setitem__((0, 0, 0, 0, 0), 1.5), "sar intensity channel outside [0, 1]"),
    ("meta not json", lambda a: a.__setitem__("meta", np.array(["{", *a["meta"][1:]])), "is not a JSON object"),
    ("offsets", lambda a: a["vert_offsets"].__setitem__(1, 10**6), "'vert_offsets' must rise from 0"),
    ("dtype", lambda a: a.__setitem__("verts", a["verts"].astype(np.float64)), "'verts' has dtype float64"),
    ("ids", lambda a: a.__setitem__("sample_id", a["sample_id"][::-1].copy()), "differ from the index's"),
    ("views", lambda a: a.__setitem__("sar", a["sar"][:, :1].copy()), "index says (V, C, H, W)"),
])
def test_content_faults_are_named(dataset, fault, change, message):
    root, index, _ = dataset
    rewrite_arrays(root, index, SHARD, change)
    problems = verify(root)
    assert problems and all(p.startswith(f"{SHARD}: ") for p in problems), problems
    assert any(message in p for p in problems), (fault, problems)


def test_object_arrays_are_refused(dataset):
    root, index, samples = dataset
    def pickled(arrays):
        arrays["meta"] = np.array([{"a": 1}] * len(arrays["meta"]), dtype=object)
    rewrite_arrays(root, index, SHARD, pickled)
    problems = verify(root)
    assert any("does not load with np.load(allow_pickle=False)" in p for p in problems), problems
    assert set(pack(list(samples.values())[:1])) == set(np.load(root / "shards/shard-00000.npz").files)


def test_a_sample_pointed_at_another_row_is_reported_and_refused_by_the_readers(dataset):
    """Two samples' rows swapped in index.json, shards and digests untouched: a reader would serve one under the
    other's id (a test sample in the train split)."""
    from meshsar_builder.dataset.readers import MeshSARDataset, MeshSARIterable
    from meshsar_builder.pipeline.errors import InputError

    root, index, _ = dataset
    a, b = index["shards"][0]["sample_ids"][:2]
    index["samples"][a]["row"], index["samples"][b]["row"] = 1, 0
    write_json(root / "index.json", index)
    [problem] = verify(root)
    assert f"'samples' puts {a} at shard 0 row 1, but it is row 0 of shards/shard-00000.npz (shard 0)" in problem
    for reader in (MeshSARDataset, MeshSARIterable):
        with pytest.raises(InputError, match="index.json: malformed: 'samples' puts"):
            reader(root, split=None)


def test_a_shard_replaced_under_its_index_is_refused_by_the_readers(dataset):
    """The index is sound but a shard file holds other samples (copied in from another build): the row's id is
    checked as it is read."""
    from meshsar_builder.dataset.readers import MeshSARDataset, MeshSARIterable
    from meshsar_builder.pipeline.errors import InputError

    root, index, _ = dataset
    first, second = (root / entry["file"] for entry in index["shards"][:2])
    first.write_bytes(second.read_bytes())
    with pytest.raises(InputError, match=r"shard-00000.npz: row 0 holds sample \S+, but index.json puts"):
        MeshSARDataset(root, split=None)[0]
    with pytest.raises(InputError, match=r"shard-00000.npz: row \d holds sample"):
        list(MeshSARIterable(root, split=None, shuffle=False))


@pytest.mark.parametrize("edit, message", [
    (lambda index: index["shards"][0].pop("sha256"), r"shards\[0\] lacks or mistypes \['sha256'\]"),
    (lambda index: index.update(shards=None), r"'shards' must be a list, got NoneType"),
    (lambda index: index.update(counts=None), r"'counts' must be a dict"),
    (lambda index: index.update(channels=None), r"'channels' must be a list"),
    (lambda index: index.update(image_size="64"), r"'image_size' must be \[H, W\] of positive integers, got '64'"),
    (lambda index: next(iter(index["samples"].values())).pop("subject"), r"sample \S+ lacks or mistypes \['subject'\]"),
])
def test_a_malformed_index_is_named_not_a_traceback(dataset, edit, message):
    root, index, _ = dataset
    edit(index)
    write_json(root / "index.json", index)
    [problem] = verify(root)
    assert problem.startswith(f"{root / 'index.json'}: malformed: ") and re.search(message, problem)


def test_an_id_listed_twice_in_one_part_is_reported_and_refused(dataset):
    from meshsar_builder.dataset.readers import MeshSARDataset
    from meshsar_builder.pipeline.errors import InputError

    root, _, _ = dataset
    path = root / "splits" / "seed-0.json"
    split = json.loads(path.read_text())
    split["train"].append(split["train"][0])
    write_json(path, split)
    assert verify(root) == [f"splits/seed-0.json: sample {split['train'][0]} is listed twice in 'train'"]
    with pytest.raises(InputError, match=r"seed-0.json: 1 id\(s\) listed more than once"):
        MeshSARDataset(root, split="train")
