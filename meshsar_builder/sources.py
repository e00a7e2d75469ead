"""Label-map sources: fixed label tables, NIfTI reading in canonical RAS, and folder indexers.

Every source's labels map into one canonical structure table, so per-vertex
labels mean the same thing whatever dataset a mesh came from. Tables are fixed,
never derived from the sorted values found in a file.
"""

from __future__ import annotations

import gzip
import re
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import nibabel as nib
import numpy as np

from .errors import InputError

# Canonical structure ids (the `vert_labels` values of the dataset); 0 = unlabelled.
STRUCTURES: dict[str, int] = {"lv": 1, "myo": 2, "rv": 3, "la": 4, "ra": 5, "aorta": 6, "pa": 7}

# MM-WHS: 421 occurs in some files for the left atrium.
MMWHS_TABLE: dict[int, str] = {
    205: "myo", 420: "la", 421: "la", 500: "lv", 550: "ra", 600: "rv", 820: "aorta", 850: "pa",
}
ACDC_TABLE: dict[int, str] = {1: "rv", 2: "myo", 3: "lv"}

# Refuse volumes whose header declares more voxels than this before reading any data.
MAX_VOXELS = 1024**3 // 2


@dataclass(frozen=True)
class LabelItem:
    """One label map to mesh: a subject, or one frame of a subject."""

    item_id: str
    source: str
    path: str
    subject: str
    table: dict[int, str]
    frame: int | None = None
    phase: str = ""  # "ED", "ES" or "" (other frames)
    cycle_fraction: float | None = None
    provenance: str = "annotated"  # annotated | predicted | phantom
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        d = asdict(self)
        d["table"] = {str(k): v for k, v in self.table.items()}
        return d

    @classmethod
    def from_json(cls, d: dict) -> "LabelItem":
        return cls(**{**d, "table": {int(k): v for k, v in d["table"].items()}})


def item_id(source: str, subject: str, frame: int | None = None) -> str:
    """A file-name-safe id, unique across a recipe's sources."""
    base = re.sub(r"[^A-Za-z0-9_-]+", "_", f"{source}-{subject}")
    return base if frame is None else f"{base}-f{frame:02d}"


def read_label_map(path: str | Path, table: dict[int, str]) -> tuple[np.ndarray, np.ndarray]:
    """Read a NIfTI label map, reorient to the closest canonical RAS, map to canonical ids.

    Returns
    -------
    labels : (X, Y, Z) uint8, canonical structure ids (STRUCTURES), 0 elsewhere
    affine : (4, 4) float64, voxel index -> RAS+ millimetres

    Raises InputError naming the file for unreadable files, non-3-D images,
    non-integer or non-finite labels, bad affines, oversized headers, and maps
    that contain none of the table's labels.
    """
    path = Path(path)
    try:
        img = nib.load(str(path))
        shape = tuple(int(s) for s in img.header.get_data_shape())
    except (OSError, EOFError, zlib.error, gzip.BadGzipFile, nib.filebasedimages.ImageFileError, ValueError) as e:
        raise InputError(f"{path}: not a readable NIfTI file ({type(e).__name__}: {e})") from e
    if len(shape) == 4 and shape[3] == 1:
        shape = shape[:3]
    if len(shape) != 3:
        raise InputError(f"{path}: label map must be 3-D, got shape {shape}")
    if min(shape) < 1 or int(np.prod(shape, dtype=np.int64)) > MAX_VOXELS:
        raise InputError(f"{path}: implausible image size {shape} (limit {MAX_VOXELS} voxels)")
    affine = img.affine
    if affine is None or not np.all(np.isfinite(affine)) or abs(np.linalg.det(affine[:3, :3])) < 1e-9:
        raise InputError(f"{path}: affine is missing, non-finite or singular")
    try:
        if path.name.endswith(".gz"):
            # Decompress the whole stream: gzip checks its CRC and length, so a truncated file
            # fails here even when the bytes the image needs happen to come before the cut.
            img = type(img).from_bytes(gzip.decompress(path.read_bytes()))
        img = nib.as_closest_canonical(img)
        data = np.asanyarray(img.dataobj).reshape(img.shape[:3])
    except (OSError, EOFError, zlib.error, gzip.BadGzipFile, ValueError) as e:
        raise InputError(f"{path}: not a readable NIfTI file, image data truncated or corrupt ({type(e).__name__}: {e})") from e
    if data.dtype.kind == "f":
        if not np.all(np.isfinite(data)):
            raise InputError(f"{path}: label map has NaN or infinite values")
        if not np.all(data == np.round(data)):
            raise InputError(f"{path}: label map has non-integer values (a probability map or an image?)")
    elif data.dtype.kind not in "iub":
        raise InputError(f"{path}: unsupported label data type {data.dtype}")
    data = data.astype(np.int64, copy=False)
    present = np.unique(data)
    lut_keys = np.array(sorted(table), dtype=np.int64)
    lut_vals = np.array([STRUCTURES[table[k]] for k in lut_keys], dtype=np.uint8)
    known = np.isin(present, lut_keys)
    if not known.any():
        raise InputError(
            f"{path}: none of the labels {sorted(table)} found (values present: {present[:20].tolist()})"
        )
    pos = np.searchsorted(lut_keys, data).clip(0, len(lut_keys) - 1)
    labels = np.where(lut_keys[pos] == data, lut_vals[pos], 0).astype(np.uint8)
    return labels, np.asarray(img.affine, dtype=np.float64)


def _first_n(paths: list[Path], limit: int | None) -> list[Path]:
    paths = sorted(paths)
    return paths if limit is None else paths[:limit]


def index_mmwhs(
    root: str | Path, source: str, limit: int | None = None, provenance: str = "annotated", subject: str = "*"
) -> list[LabelItem]:
    """MM-WHS layout: `<root>/**/<subject>_label.nii.gz`, one item per subject (glob `subject` to pick)."""
    root = _require_dir(root)
    files = _first_n(list(root.rglob(f"{subject}_label.nii.gz")) + list(root.rglob(f"{subject}_label.nii")), limit)
    if not files:
        raise InputError(f"{root}: no MM-WHS label maps (*_label.nii.gz) found")
    items = []
    for f in files:
        name = re.sub(r"_label\.nii(\.gz)?$", "", f.name)
        items.append(LabelItem(item_id(source, name), source, str(f), name, MMWHS_TABLE, provenance=provenance))
    return items


def parse_info_cfg(path: Path) -> dict[str, str]:
    """ACDC Info.cfg: lines 'Key: value'."""
    info = {}
    for line in path.read_text().splitlines():
        if ":" in line:
            k, v = line.split(":", 1)
            info[k.strip()] = v.strip()
    for key in ("ED", "ES", "NbFrame"):
        if key not in info:
            raise InputError(f"{path}: missing '{key}' in Info.cfg")
        if not info[key].isdigit():
            raise InputError(f"{path}: '{key}' must be an integer, got {info[key]!r}")
    return info


def index_acdc(
    root: str | Path, source: str, limit: int | None = None, provenance: str | None = None, subject: str = "*"
) -> list[LabelItem]:
    """ACDC layout: `<root>/**/patientNNN/Info.cfg` and `patientNNN_frameYY_gt.nii.gz`.

    Every `_gt` frame present becomes an item. Real ACDC annotates ED and ES
    only, so other frames are recorded as predicted unless `provenance` says
    otherwise (the phantom passes "phantom").
    """
    root = _require_dir(root)
    patients = _first_n([p.parent for p in root.rglob(f"{subject}/Info.cfg")], limit)
    if not patients:
        raise InputError(f"{root}: no ACDC patient folders (patientNNN/Info.cfg) found")
    items = []
    for pdir in patients:
        info = parse_info_cfg(pdir / "Info.cfg")
        ed, es, nb = int(info["ED"]), int(info["ES"]), int(info["NbFrame"])
        frames = sorted(pdir.glob(f"{pdir.name}_frame[0-9][0-9]_gt.nii*"))
        if not frames:
            raise InputError(f"{pdir}: no *_frameYY_gt.nii.gz files")
        for f in frames:
            frame = int(re.search(r"_frame(\d\d)_gt", f.name).group(1))
            phase = "ED" if frame == ed else "ES" if frame == es else ""
            prov = provenance or ("annotated" if phase else "predicted")
            items.append(
                LabelItem(
                    item_id(source, pdir.name, frame), source, str(f), pdir.name, ACDC_TABLE,
                    frame=frame, phase=phase, cycle_fraction=(frame - 1) / nb, provenance=prov,
                    extra={"group": info.get("Group", ""), "n_frames": nb},
                )
            )
    return items


def index_nifti(root: str | Path, source: str, labels: dict[str, int], limit: int | None = None) -> list[LabelItem]:
    """Any folder of `*.nii` / `*.nii.gz` label maps, with a recipe label table {structure: value}."""
    root = _require_dir(root)
    unknown = sorted(set(labels) - set(STRUCTURES))
    if unknown:
        raise InputError(f"labels: unknown structure names {unknown}; known: {sorted(STRUCTURES)}")
    table = {int(v): k for k, v in labels.items()}
    files = _first_n([p for p in root.rglob("*.nii*") if p.name.endswith((".nii", ".nii.gz"))], limit)
    if not files:
        raise InputError(f"{root}: no *.nii or *.nii.gz files found")
    items = []
    for f in files:
        subject = re.sub(r"\.nii(\.gz)?$", "", str(f.relative_to(root))).replace("/", "_")
        items.append(LabelItem(item_id(source, subject), source, str(f), subject, table))
    return items


def _require_dir(root: str | Path) -> Path:
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: data folder does not exist")
    return root
