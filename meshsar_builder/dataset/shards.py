"""Shards: samples packed into flat arrays, one `np.savez` file per shard, and the index (DESIGN section 7).

A shard of n samples stores the ragged meshes concatenated, with per-sample
offsets, and the fixed-size arrays stacked:

    sample_id    (n,)             str (fixed-width unicode)
    verts        (ΣV, 3)          float32, mm, heart frame (world minus center_mm)
    vert_offsets (n+1,)           int64: sample i owns verts[vert_offsets[i]:vert_offsets[i+1]]
    faces        (ΣF, 3)          int32, indices into the sample's own vertices
    face_offsets (n+1,)           int64
    vert_labels  (ΣV,)            uint8, structure ids (0 where unlabelled)
    sar          (n, V, C, H, W)  float16
    echo         (n, V, Ex, Ey, Ef) complex64, the recorded echo (noise included) on index echo_grid
    echo_clean   (n, V, Lx, Ly, Lf) complex64, the noise-free echo on index loss_grid (the radar loss's target)
    noise_seed   (n, V)           uint64, each view's noise seed (radar.noise)
    noise_sigma  (n, V)           float64, each view's noise amplitude (echo units; 0: no noise)
    center_mm    (n, 3)           float32, world position of the heart frame's origin
    meta         (n,)             str, one canonical JSON object each

echo_clean with the seeds and sigmas regenerates the recorded echo on the loss grid bit
for bit (recorded_loss_echo). No object arrays: a shard loads with
`np.load(path, allow_pickle=False)`.
Members are stored uncompressed, so `Shard` can memory-map them and read one
sample without loading the rest.
"""

from __future__ import annotations

import json
import mmap
import os
import struct
import zipfile
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from meshsar_builder.pipeline.errors import InputError
from meshsar_builder.pipeline.io import atomic_path, read_json


@dataclass(frozen=True)
class ShardParams:
    shard_size: int = 64

    def __post_init__(self):
        if self.shard_size < 1:
            raise ValueError(f"shard_size: must be >= 1, got {self.shard_size}")

# Format 2 (issue 28): echo_clean, noise_seed and noise_sigma in every shard, loss_grid in the index.
FORMAT_VERSION = 2
# Arrays a format-2 shard has that a format-1 shard lacks: their absence names the old format.
ADDED_IN_FORMAT_2 = ("echo_clean", "noise_seed", "noise_sigma")
INDEX_NAME = "index.json"
SHARD_DIR = "shards"

DTYPES = {
    "sample_id": np.dtype("U"),
    "verts": np.dtype(np.float32),
    "vert_offsets": np.dtype(np.int64),
    "faces": np.dtype(np.int32),
    "face_offsets": np.dtype(np.int64),
    "vert_labels": np.dtype(np.uint8),
    "sar": np.dtype(np.float16),
    "echo": np.dtype(np.complex64),
    "echo_clean": np.dtype(np.complex64),
    "noise_seed": np.dtype(np.uint64),
    "noise_sigma": np.dtype(np.float64),
    "center_mm": np.dtype(np.float32),
    "meta": np.dtype("U"),
}
SHARD_KEYS = tuple(DTYPES)
# Index keys of DESIGN section 7 (more are added: samples, n_samples, shard_size).
INDEX_KEYS = ("format_version", "recipe", "recipe_sha256", "code_version", "views", "fov_mm", "image_size",
              "channels", "radar", "echo_grid", "loss_grid", "shards", "counts")


@dataclass
class Sample:
    """One dataset sample.

    verts (n, 3) float32 mm in the heart frame; faces (m, 3) int indices into verts;
    vert_labels (n,) uint8; sar (V, C, H, W) float16; echo (V, Ex, Ey, Ef) complex64, the
    recorded echo; echo_clean (V, Lx, Ly, Lf) complex64, the noise-free echo on the loss
    grid; noise_seed (V,) uint64 and noise_sigma (V,) float64 (radar.noise); center_mm (3,)
    float32 (world = verts + center_mm); meta: JSON-able dict.
    """

    sample_id: str
    verts: np.ndarray
    faces: np.ndarray
    vert_labels: np.ndarray
    sar: np.ndarray
    echo: np.ndarray
    echo_clean: np.ndarray
    noise_seed: np.ndarray
    noise_sigma: np.ndarray
    center_mm: np.ndarray
    meta: dict


def canonical_json(obj) -> str:
    """Compact JSON with sorted keys: same object, same string (NaN refused: not JSON)."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)


def pack(samples: list[Sample]) -> dict[str, np.ndarray]:
    """The shard arrays (module docstring) of `samples`, in their order; ValueError naming a bad sample."""
    if not samples:
        raise ValueError("a shard needs at least one sample")
    ids = [s.sample_id for s in samples]
    if len(set(ids)) != len(ids) or not all(isinstance(i, str) and i for i in ids):
        raise ValueError(f"sample ids must be distinct non-empty strings, got {ids}")
    first = samples[0]
    for s in samples:
        n = len(s.verts)
        if np.shape(s.verts) != (n, 3) or np.shape(s.faces)[1:] != (3,) or np.shape(s.vert_labels) != (n,):
            raise ValueError(f"{s.sample_id}: need verts (n, 3), faces (m, 3), vert_labels (n,)")
        if len(s.faces) and (np.min(s.faces) < 0 or np.max(s.faces) >= n):
            raise ValueError(f"{s.sample_id}: face indices out of range [0, {n})")
        if np.shape(s.sar) != np.shape(first.sar) or np.shape(s.echo) != np.shape(first.echo):
            raise ValueError(f"{s.sample_id}: sar {np.shape(s.sar)} / echo {np.shape(s.echo)} differ from "
                             f"{first.sample_id}'s {np.shape(first.sar)} / {np.shape(first.echo)}")
        if np.ndim(s.sar) != 4 or np.ndim(s.echo) != 4 or np.shape(s.center_mm) != (3,):
            raise ValueError(f"{s.sample_id}: need sar (V, C, H, W), echo (V, Ex, Ey, Ef), center_mm (3,)")
        views = np.shape(s.sar)[0]
        if (np.ndim(s.echo_clean) != 4 or np.shape(s.echo_clean)[0] != views or np.shape(s.echo)[0] != views
                or np.shape(s.noise_seed) != (views,) or np.shape(s.noise_sigma) != (views,)):
            raise ValueError(f"{s.sample_id}: need echo (V, Ex, Ey, Ef), echo_clean (V, Lx, Ly, Lf), noise_seed (V,) "
                             f"and noise_sigma (V,) with V = {views} views as in sar")
        if np.shape(s.echo_clean) != np.shape(first.echo_clean):
            raise ValueError(f"{s.sample_id}: echo_clean {np.shape(s.echo_clean)} differs from "
                             f"{first.sample_id}'s {np.shape(first.echo_clean)}")
        if np.asarray(s.noise_seed).dtype != np.uint64:
            raise ValueError(f"{s.sample_id}: noise_seed must be uint64, got {np.asarray(s.noise_seed).dtype}")

    metas = []
    for s in samples:
        try:
            metas.append(canonical_json(s.meta))
        except (TypeError, ValueError) as e:
            raise ValueError(f"{s.sample_id}: meta is not plain JSON ({e})") from e

    def offsets(arrays) -> np.ndarray:
        return np.concatenate([[0], np.cumsum([len(a) for a in arrays])]).astype(np.int64)

    return {
        "sample_id": np.array(ids, dtype=str),
        "verts": np.concatenate([np.asarray(s.verts, np.float32) for s in samples]).reshape(-1, 3),
        "vert_offsets": offsets([s.verts for s in samples]),
        "faces": np.concatenate([np.asarray(s.faces, np.int32) for s in samples]).reshape(-1, 3),
        "face_offsets": offsets([s.faces for s in samples]),
        "vert_labels": np.concatenate([np.asarray(s.vert_labels, np.uint8) for s in samples]),
        "sar": np.stack([np.asarray(s.sar, np.float16) for s in samples]),
        "echo": np.stack([np.asarray(s.echo, np.complex64) for s in samples]),
        "echo_clean": np.stack([np.asarray(s.echo_clean, np.complex64) for s in samples]),
        "noise_seed": np.stack([np.asarray(s.noise_seed, np.uint64) for s in samples]),
        "noise_sigma": np.stack([np.asarray(s.noise_sigma, np.float64) for s in samples]),
        "center_mm": np.stack([np.asarray(s.center_mm, np.float32) for s in samples]),
        "meta": np.array(metas, dtype=str),
    }


def write_shard(path: str | os.PathLike, samples: list[Sample]) -> None:
    """Pack `samples` and write them atomically with np.savez (uncompressed; byte-deterministic)."""
    arrays = pack(samples)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        # A file object, not a name: np.savez would append ".npz" to a name lacking it.
        np.savez(f, **arrays)


def structure_problems(arrays: dict[str, np.ndarray]) -> list[str]:
    """What is wrong with the keys, dtypes, shapes and offsets of shard arrays (cheap: no element scans)."""
    missing = [k for k in SHARD_KEYS if k not in arrays]
    extra = sorted(set(arrays) - set(SHARD_KEYS))
    problems = [f"missing array '{k}'" for k in missing] + [f"unexpected array '{k}'" for k in extra]
    for key, dtype in DTYPES.items():
        if key in arrays and not (arrays[key].dtype == dtype or dtype.kind == "U" == arrays[key].dtype.kind):
            problems.append(f"'{key}' has dtype {arrays[key].dtype}, expected {dtype if dtype.kind != 'U' else 'str'}")
    if problems:
        return problems
    n = len(arrays["sample_id"])
    expected = {
        "sample_id": (n,), "vert_offsets": (n + 1,), "face_offsets": (n + 1,), "center_mm": (n, 3), "meta": (n,),
        "verts": (len(arrays["verts"]), 3), "faces": (len(arrays["faces"]), 3), "vert_labels": (len(arrays["verts"]),),
    }
    for key, shape in expected.items():
        if arrays[key].shape != shape:
            problems.append(f"'{key}' has shape {arrays[key].shape}, expected {shape}")
    for key in ("sar", "echo", "echo_clean"):
        if arrays[key].ndim != 5 or arrays[key].shape[0] != n:
            problems.append(f"'{key}' has shape {arrays[key].shape}, expected ({n}, V, ...) with 5 axes")
    views = arrays["echo_clean"].shape[1] if arrays["echo_clean"].ndim == 5 else None
    for key in ("noise_seed", "noise_sigma"):  # one per view of echo_clean (views against the index: verify)
        if views is not None and arrays[key].shape != (n, views):
            problems.append(f"'{key}' has shape {arrays[key].shape}, expected ({n}, {views}) as echo_clean's views")
    for key, total in (("vert_offsets", "verts"), ("face_offsets", "faces")):
        off = arrays[key]
        if off.shape == (n + 1,) and (off[0] != 0 or off[-1] != len(arrays[total]) or np.any(np.diff(off) < 0)):
            problems.append(f"'{key}' must rise from 0 to len({total}) = {len(arrays[total])}")
    return problems


def _loaded_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every array, read through np.load (the zip CRCs are checked)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as e:
        raise InputError(f"{path}: unreadable shard ({type(e).__name__}: {e})") from e


def _mapped_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every array as a read-only view of one memory map of the file (no CRC check: `verify` hashes files)."""
    try:
        with open(path, "rb") as f:
            infos = zipfile.ZipFile(f).infolist()
            if any(i.compress_type != zipfile.ZIP_STORED for i in infos):
                return _loaded_arrays(path)  # np.savez_compressed shards cannot be mapped
            buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
            arrays = {}
            for info in infos:
                # The local header (30 bytes, then name and extra field) precedes the .npy data.
                name_len, extra_len = struct.unpack("<HH", buf[info.header_offset + 26 : info.header_offset + 30])
                start = info.header_offset + 30 + name_len + extra_len
                f.seek(start)
                version = np.lib.format.read_magic(f)
                if version not in ((1, 0), (2, 0)):
                    raise ValueError(f"{info.filename}: .npy format {version} not supported")
                read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                shape, fortran, dtype = read_header(f)
                if dtype.hasobject:
                    raise ValueError(f"{info.filename}: object array (shards hold no pickles)")
                count = int(np.prod(shape))
                if f.tell() + count * dtype.itemsize > start + info.file_size:
                    raise ValueError(f"{info.filename}: data shorter than its header declares")
                flat = np.frombuffer(buf, dtype=dtype, count=count, offset=f.tell())
                arrays[info.filename.removesuffix(".npy")] = flat.reshape(shape, order="F" if fortran else "C")
            return arrays
    except (OSError, ValueError, EOFError, struct.error, zipfile.BadZipFile) as e:
        raise InputError(f"{path}: unreadable shard ({type(e).__name__}: {e})") from e


class Shard:
    """Read access to one shard file; `shard[i]` is a `Sample` (copies, safe to keep).

    mmap=True maps the file and reads only the rows asked for; mmap=False loads
    every array through np.load. InputError naming the file for a truncated,
    corrupt or malformed shard.
    """

    def __init__(self, path: str | os.PathLike, mmap: bool = True):
        self.path = Path(path)
        self.arrays = _mapped_arrays(self.path) if mmap else _loaded_arrays(self.path)
        missing = [k for k in SHARD_KEYS if k not in self.arrays]
        if missing and set(missing) <= set(ADDED_IN_FORMAT_2):
            root = self.path.parent.parent if self.path.parent.name == SHARD_DIR else None
            raise InputError(f"{self.path}: a format-1 shard (no {', '.join(missing)}); this code reads format "
                             f"{FORMAT_VERSION} only: {rebuild_advice(root)}")
        problems = structure_problems(self.arrays)
        if problems:
            raise InputError(f"{self.path}: not a valid shard: {'; '.join(problems)}")
        self.sample_ids = [str(s) for s in self.arrays["sample_id"]]

    def __len__(self) -> int:
        return len(self.sample_ids)

    def __getitem__(self, i: int) -> Sample:
        a = self.arrays
        v0, v1 = a["vert_offsets"][i : i + 2]
        f0, f1 = a["face_offsets"][i : i + 2]
        try:
            meta = json.loads(str(a["meta"][i]))
        except ValueError as e:
            raise InputError(f"{self.path}: meta of sample {self.sample_ids[i]} is not JSON ({e})") from e
        return Sample(
            sample_id=self.sample_ids[i],
            verts=np.array(a["verts"][v0:v1]),
            faces=np.array(a["faces"][f0:f1]),
            vert_labels=np.array(a["vert_labels"][v0:v1]),
            sar=np.array(a["sar"][i]),
            echo=np.array(a["echo"][i]),
            echo_clean=np.array(a["echo_clean"][i]),
            noise_seed=np.array(a["noise_seed"][i]),
            noise_sigma=np.array(a["noise_sigma"][i]),
            center_mm=np.array(a["center_mm"][i]),
            meta=meta,
        )


def loss_grid_indices(index: dict) -> tuple[tuple[int, int, int], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(full grid shape (Nx, Ny, N), indices (x, y, frequency) of the loss grid in it) from index.json's radar."""
    from meshsar_builder.radar.params import decimation_indices

    radar = index["radar"]
    full = (*(int(n) for n in radar["aperture"]), int(radar["n_samples"]))
    return full, tuple(decimation_indices(size, int(f)) for size, f in zip(full, radar["loss_decimation"]))


def recorded_loss_echo(sample: Sample, index: dict) -> np.ndarray:
    """The recorded (noisy) echo of a sample on the loss grid, (V, Lx, Ly, Lf) complex64.

    echo_clean plus each view's noise regenerated from its noise_seed and noise_sigma
    (radar.noise.recorded_echo): bit for bit what the build recorded there, where `echo`
    holds it only on the coarser echo grid. index: the dataset's index.json (read_index).
    """
    from meshsar_builder.radar.noise import recorded_echo

    full, keep = loss_grid_indices(index)
    if sample.echo_clean.shape[1:] != tuple(len(k) for k in keep):
        raise InputError(f"{sample.sample_id}: echo_clean has per-view shape {sample.echo_clean.shape[1:]}, the "
                         f"index's loss grid {tuple(len(k) for k in keep)}")
    return np.stack([recorded_echo(clean, seed, sigma, full, keep)
                     for clean, seed, sigma in zip(sample.echo_clean, sample.noise_seed, sample.noise_sigma)])


def read_shard(path: str | os.PathLike) -> list[Sample]:
    """Every sample of a shard, in stored order, read through np.load (CRC-checked)."""
    shard = Shard(path, mmap=False)
    return [shard[i] for i in range(len(shard))]


def build_index(*, recipe: str, recipe_sha256: str, code_version: str, metadata: dict, shard_size: int,
                shards: list[dict], metas: dict[str, dict]) -> dict:
    """The index.json object (DESIGN section 7).

    metadata : the radar module's index_metadata (views, fov_mm, image_size, channels, radar, echo_grid).
    shards   : [{file (relative to the build root), n, sha256, sample_ids}] in dataset order.
    metas    : sample id -> its meta (source, subject, subset, ...).
    Adds `samples` (id -> shard position, row, source, subject, subset: what splits and
    readers need without opening shards; each view's image noise floor, dB below its
    peak, and its appearance figures where the radar stage made them) and `n_samples`.
    """
    samples = {}
    for k, entry in enumerate(shards):
        for row, sid in enumerate(entry["sample_ids"]):
            m = metas[sid]
            samples[sid] = {"shard": k, "row": row, "source": m["source"], "subject": m["subject"], "subset": m["subset"],
                            "noise_floor_db": m.get("noise_floor_db")}
            if m.get("cohort"):  # a subject namespace shared by sources (splits.group_key)
                samples[sid]["cohort"] = m["cohort"]
            if m.get("appearance"):  # per view: speckle share, glint contrast, depth error (radar.appearance)
                samples[sid]["appearance"] = m["appearance"]
    subjects = {}
    for s in samples.values():
        subjects.setdefault(s["subset"], set()).add((s["source"], s["subject"]))
    counts = {
        "total": len(samples),
        "source": dict(Counter(s["source"] for s in samples.values())),
        "subset": dict(Counter(s["subset"] for s in samples.values())),
        "subjects": {subset: len(keys) for subset, keys in subjects.items()},
    }
    return {
        "format_version": FORMAT_VERSION,
        "recipe": recipe,
        "recipe_sha256": recipe_sha256,
        "code_version": code_version,
        **metadata,
        "shard_size": shard_size,
        "shards": shards,
        "counts": counts,
        "n_samples": len(samples),
        "samples": samples,
    }


def rebuild_advice(root: str | os.PathLike | None) -> str:
    """How to rebuild a dataset made by an older format with this code (the radar stage redoes every sample)."""
    out = str(root) if root is not None else "OUT"
    return (f"rebuild it with this code: meshsar build {out}/recipe.toml --out {out} --force radar (the recipe as "
            f"built is kept in the build folder; the radar and shards stages redo every sample)")


def read_index(out_dir: str | os.PathLike) -> dict:
    """index.json of a build folder; InputError naming the file when missing, unreadable, lacking keys
    or of another format_version (with how to rebuild it)."""
    path = Path(out_dir) / INDEX_NAME
    try:
        index = read_json(path)
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: cannot read the dataset index ({type(e).__name__}: {e})") from e
    version = index.get("format_version") if isinstance(index, dict) else None
    if isinstance(index, dict) and version != FORMAT_VERSION:
        why = (" (its shards lack echo_clean, noise_seed and noise_sigma, and the index loss_grid)"
               if version == 1 else "")
        raise InputError(f"{path}: format_version {version!r}, but this code reads format {FORMAT_VERSION} only"
                         f"{why}; {rebuild_advice(Path(out_dir))}")
    missing = [k for k in (*INDEX_KEYS, "samples") if not isinstance(index, dict) or k not in index]
    if missing:
        raise InputError(f"{path}: missing keys {missing}")
    problems = index_problems(index)
    if problems:
        more = f" (and {len(problems) - 5} more)" if len(problems) > 5 else ""
        raise InputError(f"{path}: malformed: {'; '.join(problems[:5])}{more}")
    return index


def index_problems(index: dict) -> list[str]:
    """What in an index.json object (its keys present) the readers and splits cannot trust: entries of the wrong
    type, and a sample whose (shard, row) is not where its shard entry lists it (a reader would serve another
    sample under its id)."""
    problems = []
    for key, kind in (("shards", list), ("samples", dict), ("counts", dict), ("views", list), ("channels", list)):
        if not isinstance(index[key], kind):
            problems.append(f"'{key}' must be a {kind.__name__}, got {type(index[key]).__name__}")
    size = index["image_size"]
    if not (isinstance(size, list) and len(size) == 2 and all(isinstance(n, int) and n > 0 for n in size)):
        problems.append(f"'image_size' must be [H, W] of positive integers, got {size!r}")
    if problems:
        return problems
    fields = {"file": str, "n": int, "sha256": str, "sample_ids": list}
    for k, entry in enumerate(index["shards"]):
        bad = [f for f, kind in fields.items() if not isinstance(entry, dict) or not isinstance(entry.get(f), kind)]
        if bad:
            problems.append(f"shards[{k}] lacks or mistypes {bad}")
            continue
        for row, sid in enumerate(entry["sample_ids"]):
            where = index["samples"].get(sid)
            if not isinstance(where, dict):
                problems.append(f"sample {sid!r} of {entry['file']} has no entry in 'samples'")
            elif (where.get("shard"), where.get("row")) != (k, row):
                problems.append(f"'samples' puts {sid} at shard {where.get('shard')} row {where.get('row')}, but it "
                                f"is row {row} of {entry['file']} (shard {k})")
    for sid, where in index["samples"].items():
        bad = [f for f in ("source", "subject", "subset")
               if not isinstance(where, dict) or not isinstance(where.get(f), str)]
        if bad:
            problems.append(f"sample {sid} lacks or mistypes {bad}")
    return problems
