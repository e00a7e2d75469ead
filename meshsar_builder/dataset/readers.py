"""PyTorch access to a built dataset: a map-style dataset, an iterable one for workers and DDP ranks, a collate.

Samples come as dicts:
    sample_id   str
    verts       (n, 3) float32, mm, heart frame
    faces       (m, 3) int64
    vert_labels (n,) int64, structure ids
    sar         (V, C, H, W) float32 (C = the channels asked for, in that order)
    echo        (V, Ex, Ey, Ef) complex64, the recorded (noisy) echo on index echo_grid
    echo_clean  (V, Lx, Ly, Lf) complex64, the noise-free echo on index loss_grid (the radar loss's target)
    noise_seed  (V,) uint64 numpy array, noise_sigma (V,) float64: what regenerates the recorded noise
    echo_noisy  (V, Lx, Ly, Lf) complex64, the recorded echo on the loss grid (echo_clean plus the
                regenerated noise, bit for bit the build's): only with noisy_loss_echo=True
    center_mm   (3,) float32
    meta        dict
Shards are memory-mapped (`meshsar_builder.shards.Shard`): a sample read touches
only its rows, and memory stays bounded by the few shards kept open.
"""

from __future__ import annotations

import os
import warnings
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset, IterableDataset, get_worker_info

from meshsar_builder.dataset.shards import Sample, Shard, read_index, recorded_loss_echo
from meshsar_builder.dataset.splits import read_split
from meshsar_builder.pipeline.errors import InputError
from meshsar_builder.pipeline.seeding import item_rng


def split_ids(root: str | os.PathLike, index: dict, split: str | None, seed: int) -> list[str]:
    """Sample ids of `split` in OUT/splits/seed-<seed>.json (None: every sample, in dataset order)."""
    if split is None:
        return [sid for shard in index["shards"] for sid in shard["sample_ids"]]
    chosen = read_split(root, seed, index)  # the index read once: it is validated where it is read
    if split not in chosen["ratios"]:
        raise InputError(f"split {split!r} not in seed-{seed}.json; it has {list(chosen['ratios'])}")
    unknown = [s for s in chosen[split] if s not in index["samples"]]
    if unknown:
        raise InputError(f"seed-{seed}.json: split {split!r} names ids not in the index: {unknown[:5]}")
    return list(chosen[split])


def channel_indices(index: dict, channels: list[str] | None) -> list[int] | None:
    """Positions of `channels` on the sar channel axis (None: all, as stored)."""
    if channels is None:
        return None
    unknown = [c for c in channels if c not in index["channels"]]
    if unknown:
        raise InputError(f"channels {unknown} not in the dataset's {index['channels']}")
    return [index["channels"].index(c) for c in channels]


def to_tensors(sample: Sample, channels: list[int] | None = None, index: dict | None = None) -> dict:
    """A `Sample` as the dict of tensors described in the module docstring.

    index: the dataset's index.json, to add `echo_noisy` (the recorded echo on the loss grid);
    None leaves it out (regenerating the noise costs ~60 ms a view at the default radar: it is
    drawn on the full 80 x 80 x 64 grid, then sub-sampled).
    """
    sar = sample.sar if channels is None else sample.sar[:, channels]
    extra = {} if index is None else {"echo_noisy": torch.from_numpy(recorded_loss_echo(sample, index))}
    return {
        "sample_id": sample.sample_id,
        "verts": torch.from_numpy(np.ascontiguousarray(sample.verts, dtype=np.float32)),
        "faces": torch.from_numpy(sample.faces.astype(np.int64)),
        "vert_labels": torch.from_numpy(sample.vert_labels.astype(np.int64)),
        "sar": torch.from_numpy(sar.astype(np.float32)),
        "echo": torch.from_numpy(np.ascontiguousarray(sample.echo, dtype=np.complex64)),
        "echo_clean": torch.from_numpy(np.ascontiguousarray(sample.echo_clean, dtype=np.complex64)),
        "noise_seed": np.array(sample.noise_seed, dtype=np.uint64),  # torch has no full uint64 support
        "noise_sigma": torch.from_numpy(np.array(sample.noise_sigma, dtype=np.float64)),
        "center_mm": torch.from_numpy(np.ascontiguousarray(sample.center_mm, dtype=np.float32)),
        "meta": sample.meta,
        **extra,
    }


class ShardCache:
    """The `capacity` most recently used shards of a build folder, open (memory-mapped).

    Pickles empty, so each DataLoader worker opens its own maps.
    """

    def __init__(self, root: str | os.PathLike, capacity: int = 4):
        self.root, self.capacity = Path(root), max(1, capacity)
        self._open: OrderedDict[str, Shard] = OrderedDict()

    def get(self, file: str) -> Shard:
        shard = self._open.pop(file, None)
        self._open[file] = shard if shard is not None else Shard(self.root / file)
        while len(self._open) > self.capacity:
            self._open.popitem(last=False)  # the map closes when its last array view is gone
        return self._open[file]

    def __getstate__(self) -> dict:
        return {"root": self.root, "capacity": self.capacity}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["root"], state["capacity"])


class MeshSARDataset(Dataset):
    """Map-style dataset of one split (`split=None`: every sample), in dataset order.

    root : build folder with index.json and splits/; seed : which split file;
    channels : sar channel names to keep (default all); cache_shards : shards kept open;
    noisy_loss_echo : also give `echo_noisy`, the recorded echo on the loss grid.
    """

    def __init__(self, root: str | os.PathLike, split: str | None = "train", seed: int = 0,
                 channels: list[str] | None = None, cache_shards: int = 4, noisy_loss_echo: bool = False):
        self.root = Path(root)
        self.index = read_index(self.root)
        self.noisy_loss_echo = noisy_loss_echo
        self.ids = split_ids(self.root, self.index, split, seed)
        self.channels = channel_indices(self.index, channels)
        files = [s["file"] for s in self.index["shards"]]
        self._where = [(files[self.index["samples"][sid]["shard"]], self.index["samples"][sid]["row"]) for sid in self.ids]
        self._cache = ShardCache(self.root, cache_shards)

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, i: int) -> dict:
        file, row = self._where[i]
        sample = self._cache.get(file)[row]
        _check_id(sample, self.ids[i], self.root / file, row)
        return to_tensors(sample, self.channels, self.index if self.noisy_loss_echo else None)


def _check_id(sample, expected: str, path: Path, row: int) -> None:
    """InputError when a shard's row holds another sample than index.json says (a shard replaced after indexing):
    a reader would serve it under the wrong id, and the wrong split."""
    if sample.sample_id != expected:
        raise InputError(f"{path}: row {row} holds sample {sample.sample_id}, but index.json puts {expected} there; "
                         f"`meshsar verify` checks the build")


def collate_meshes(batch: list[dict]) -> dict:
    """Batch samples of different mesh sizes: lists for verts/faces/vert_labels/meta/sample_id,
    stacked tensors for sar (B, V, C, H, W), echo (B, V, Ex, Ey, Ef), echo_clean (and echo_noisy)
    (B, V, Lx, Ly, Lf), noise_sigma (B, V) and center_mm (B, 3); noise_seed (B, V) uint64 numpy."""
    ragged = ("sample_id", "verts", "faces", "vert_labels", "meta")
    stacked = [k for k in ("sar", "echo", "echo_clean", "echo_noisy", "noise_sigma", "center_mm") if k in batch[0]]
    out = {
        **{k: [b[k] for b in batch] for k in ragged},
        **{k: torch.stack([b[k] for b in batch]) for k in stacked},
    }
    if "noise_seed" in batch[0]:
        out["noise_seed"] = np.stack([b["noise_seed"] for b in batch])
    return out


def _distributed() -> tuple[int, int]:
    """(rank, world size) of an initialised torch.distributed group, else (0, 1)."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


class MeshSARIterable(IterableDataset):
    """One split streamed shard by shard, the shards dealt out over DDP ranks and DataLoader workers.

    Consumer c = rank * num_workers + worker_id of C = world_size * num_workers reads
    shards c, c + C, c + 2C, ... of the epoch's shard order, so across all consumers
    every sample of the split comes exactly once per epoch. shuffle=True permutes the
    shards and the samples within each by (seed, epoch) only, so every rank agrees;
    call `set_epoch` between epochs. rank/world_size default to torch.distributed's;
    noisy_loss_echo as for MeshSARDataset.
    Consumers get whole shards: with fewer shards than consumers some get none (a
    warning says so), and ranks may get different sample counts.
    """

    def __init__(self, root: str | os.PathLike, split: str | None = "train", seed: int = 0, shuffle: bool = True,
                 epoch: int = 0, channels: list[str] | None = None, rank: int | None = None,
                 world_size: int | None = None, noisy_loss_echo: bool = False):
        self.root = Path(root)
        index = read_index(self.root)
        self.index = index if noisy_loss_echo else None
        rows: dict[int, list[int]] = {}
        for sid in split_ids(self.root, index, split, seed):
            where = index["samples"][sid]
            rows.setdefault(where["shard"], []).append(where["row"])
        self._ids = {(index["shards"][k]["file"], row): index["shards"][k]["sample_ids"][row]
                     for k, some in rows.items() for row in some}
        # (file, rows of the split in it), in dataset order
        self.shards = [(index["shards"][k]["file"], sorted(rows[k])) for k in sorted(rows)]
        self.seed, self.shuffle, self.epoch = seed, shuffle, epoch
        self.channels = channel_indices(index, channels)
        self.rank, self.world_size = rank, world_size

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def consumer(self) -> tuple[int, int]:
        """(this consumer's number, how many consumers) from the worker info and the rank."""
        info = get_worker_info()
        worker, workers = (info.id, info.num_workers) if info is not None else (0, 1)
        rank, world = _distributed()
        rank = self.rank if self.rank is not None else rank
        world = self.world_size if self.world_size is not None else world
        return rank * workers + worker, world * workers

    def assignment(self, consumer: int, consumers: int) -> list[tuple[str, list[int]]]:
        """The (shard file, rows in reading order) that `consumer` of `consumers` reads this epoch."""
        order = list(self.shards)
        if self.shuffle:
            rng = item_rng(self.seed, "reader", f"epoch-{self.epoch}")
            order = [order[i] for i in rng.permutation(len(order))]
            order = [(file, [rows[i] for i in item_rng(self.seed, "reader", f"epoch-{self.epoch}/{file}").permutation(len(rows))])
                     for file, rows in order]
        return order[consumer::consumers]

    def __iter__(self):
        consumer, consumers = self.consumer()
        if consumer == 0 and len(self.shards) < consumers:
            warnings.warn(f"{len(self.shards)} shard(s) for {consumers} consumers (ranks x workers): "
                          f"{consumers - len(self.shards)} will read nothing; use fewer workers or smaller shards",
                          stacklevel=2)
        for file, rows in self.assignment(consumer, consumers):
            shard = Shard(self.root / file)
            for row in rows:
                sample = shard[row]
                _check_id(sample, self._ids[file, row], self.root / file, row)
                yield to_tensors(sample, self.channels, self.index)
