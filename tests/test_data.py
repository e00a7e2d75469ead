"""PyTorch readers: exact tensors, batching ragged meshes, and every split sample once per epoch over workers and ranks."""

from __future__ import annotations

import pickle
import warnings
from collections import Counter
from unittest import mock

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from meshsar_builder.dataset.readers import MeshSARDataset, MeshSARIterable, collate_meshes
from meshsar_builder.dataset.splits import make_split, read_split, write_split
from meshsar_builder.pipeline.errors import InputError

from meshsar_builder.dataset.shards import recorded_loss_echo

from .test_shards import ECHO, LOSS, C, H, V, W, tiny_dataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    index, samples = tiny_dataset(root, n_ssm=9, direct=(4, 4, 3, 5), shard_size=3)
    return root, index, samples


def test_map_dataset_gives_exact_tensors(dataset):
    root, _, samples = dataset
    ds = MeshSARDataset(root, split="test", seed=0)
    assert ds.ids == read_split(root, 0)["test"] and len(ds) > 0
    for i, sid in enumerate(ds.ids):
        item, want = ds[i], samples[sid]
        assert item["sample_id"] == sid and item["meta"] == want.meta
        assert item["verts"].dtype == torch.float32 and torch.equal(item["verts"], torch.from_numpy(want.verts))
        assert item["faces"].dtype == torch.int64 and item["faces"].tolist() == want.faces.tolist()
        assert item["vert_labels"].dtype == torch.int64 and item["vert_labels"].tolist() == want.vert_labels.tolist()
        assert item["sar"].dtype == torch.float32 and item["sar"].shape == (V, C, H, W)
        assert torch.equal(item["sar"], torch.from_numpy(want.sar.astype(np.float32)))
        assert item["echo"].dtype == torch.complex64 and torch.equal(item["echo"], torch.from_numpy(want.echo))
        assert item["echo_clean"].dtype == torch.complex64 and item["echo_clean"].shape == LOSS
        assert torch.equal(item["echo_clean"], torch.from_numpy(want.echo_clean)) and "echo_noisy" not in item
        assert item["noise_seed"].dtype == np.uint64 and np.array_equal(item["noise_seed"], want.noise_seed)
        assert item["noise_sigma"].dtype == torch.float64 and item["noise_sigma"].tolist() == want.noise_sigma.tolist()
        assert torch.equal(item["center_mm"], torch.from_numpy(want.center_mm))


def test_recorded_echo_on_the_loss_grid(dataset):
    root, index, samples = dataset
    for ds in (MeshSARDataset(root, split=None, noisy_loss_echo=True),
               MeshSARIterable(root, split=None, shuffle=False, noisy_loss_echo=True)):
        items = [ds[i] for i in range(len(ds))] if isinstance(ds, MeshSARDataset) else list(ds)
        assert len(items) == len(samples)
        for item in items:
            want = recorded_loss_echo(samples[item["sample_id"]], index)
            assert item["echo_noisy"].dtype == torch.complex64
            assert torch.equal(item["echo_noisy"], torch.from_numpy(want))
            assert not torch.equal(item["echo_noisy"], item["echo_clean"])  # the tiny dataset's sigmas are > 0


def test_channels_and_whole_dataset(dataset):
    root, index, samples = dataset
    ds = MeshSARDataset(root, split=None, channels=["depth"], cache_shards=1)
    assert ds.ids == [sid for s in index["shards"] for sid in s["sample_ids"]]
    for i in (0, len(ds) - 1, 1):  # revisits an evicted shard
        sid = ds.ids[i]
        assert torch.equal(ds[i]["sar"], torch.from_numpy(samples[sid].sar[:, 1:].astype(np.float32)))
    with pytest.raises(ValueError, match="channels"):
        MeshSARDataset(root, channels=["phase"])
    with pytest.raises(InputError, match="split 'val' not in seed-0.json"):
        MeshSARDataset(root, split="val")
    with pytest.raises(InputError, match="seed-9.json"):
        MeshSARDataset(root, seed=9)


def test_dataset_pickles_without_open_shards(dataset):
    root, _, _ = dataset
    ds = MeshSARDataset(root, split="train")
    first = ds[0]
    copy = pickle.loads(pickle.dumps(ds))  # what a spawned DataLoader worker receives
    assert not copy._cache._open and torch.equal(copy[0]["sar"], first["sar"])


def test_collate_ragged_batch(dataset):
    root, _, _ = dataset
    loader = DataLoader(MeshSARDataset(root, split="train"), batch_size=4, collate_fn=collate_meshes, num_workers=2)
    batch = next(iter(loader))
    assert batch["sar"].shape == (4, V, C, H, W) and batch["echo"].shape == (4, *ECHO)
    assert batch["echo_clean"].shape == (4, *LOSS) and "echo_noisy" not in batch
    assert batch["noise_seed"].shape == (4, V) and batch["noise_seed"].dtype == np.uint64
    assert batch["noise_sigma"].shape == (4, V) and batch["center_mm"].shape == (4, 3)
    noisy = collate_meshes([MeshSARDataset(root, split="train", noisy_loss_echo=True)[i] for i in range(2)])
    assert noisy["echo_noisy"].shape == (2, *LOSS) and noisy["echo_noisy"].dtype == torch.complex64
    assert len(batch["verts"]) == len(batch["faces"]) == len(batch["meta"]) == len(batch["sample_id"]) == 4
    assert len({v.shape[0] for v in batch["verts"]}) > 1  # meshes of different sizes in one batch


def read_all(ds: MeshSARIterable, rank: int, world: int, workers: int) -> list[str]:
    """What one rank reads, each of its DataLoader workers simulated through get_worker_info."""
    got = []
    for worker in range(workers):
        info = mock.Mock(id=worker, num_workers=workers)
        with mock.patch("meshsar_builder.dataset.readers.get_worker_info", return_value=info):
            ds.rank, ds.world_size = rank, world
            got += [item["sample_id"] for item in ds]
    return got


@pytest.mark.parametrize("world, workers", [(1, 1), (1, 3), (2, 2), (3, 1), (2, 3)])
@pytest.mark.parametrize("shuffle", [False, True])
def test_iterable_reads_every_sample_once_per_epoch(dataset, world, workers, shuffle):
    root, _, _ = dataset
    want = read_split(root, 0)["train"]
    ds = MeshSARIterable(root, split="train", seed=0, shuffle=shuffle)
    orders = []
    for epoch in (0, 1):
        ds.set_epoch(epoch)
        got = [sid for rank in range(world) for sid in read_all(ds, rank, world, workers)]
        assert sorted(got) == sorted(want) and len(got) == len(want)
        orders.append(got)
    assert (orders[0] != orders[1]) == shuffle


def test_iterable_uses_torch_distributed_rank(dataset):
    root, index, _ = dataset
    ds = MeshSARIterable(root, split=None, shuffle=False)
    with mock.patch("meshsar_builder.dataset.readers._distributed", return_value=(1, 2)):
        assert ds.consumer() == (1, 2)
        got = [item["sample_id"] for item in ds]
    assert got == [sid for k, s in enumerate(index["shards"]) if k % 2 == 1 for sid in s["sample_ids"]]


def test_iterable_warns_when_consumers_outnumber_shards(dataset):
    root, _, _ = dataset
    ds = MeshSARIterable(root, split="test", rank=0, world_size=len(MeshSARIterable(root, split="test").shards) + 1)
    with pytest.warns(UserWarning, match="will read nothing"):
        list(ds)
    ds.world_size = 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        list(ds)


def test_real_dataloader_workers(dataset):
    root, _, _ = dataset
    ds = MeshSARIterable(root, split="train", seed=0, shuffle=True, epoch=3)
    loader = DataLoader(ds, batch_size=None, num_workers=2)
    got = Counter(item["sample_id"] for item in loader)
    assert got == Counter(read_split(root, 0)["train"])


def test_other_split_seed(dataset):
    root, index, _ = dataset
    write_split(root, make_split(index, 5, {"train": 0.5, "test": 0.5}))
    assert sorted(MeshSARDataset(root, "train", seed=5).ids + MeshSARDataset(root, "test", seed=5).ids) == sorted(index["samples"])
