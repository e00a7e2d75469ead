"""Label-map sources: fixed label tables, NIfTI reading in canonical RAS, and folder indexers.

Every source's labels map into one canonical structure table, so per-vertex
labels mean the same thing whatever dataset a mesh came from. Tables are fixed,
never derived from the sorted values found in a file.
"""

from __future__ import annotations

import gzip
import os
import re
import warnings
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import nibabel as nib
import numpy as np

from meshsar_builder.geometry.meshfile import read_ply
from meshsar_builder.geometry.structures import STRUCTURES
from meshsar_builder.pipeline.errors import InputError, RecipeError
from meshsar_builder.pipeline.recipe import NAME_RE

if TYPE_CHECKING:
    from meshsar_builder.geometry.ssm import ShapeModel

# MM-WHS: 421 occurs in some files for the left atrium.
MMWHS_TABLE: dict[int, str] = {
    205: "myo", 420: "la", 421: "la", 500: "lv", 550: "ra", 600: "rv", 820: "aorta", 850: "pa",
}
ACDC_TABLE: dict[int, str] = {1: "rv", 2: "myo", 3: "lv"}

KINDS = ("phantom", "mmwhs", "acdc", "nifti", "shape_model")
SOURCE_STRUCTURES = {
    "mmwhs": ("lv", "myo", "rv", "la", "ra", "aorta", "pa"),
    "acdc": ("lv", "myo", "rv"),
}

@dataclass(frozen=True)
class SourceSpec:
    """One [[sources]] entry. Empty strings / zero mean 'the default for this kind'."""

    kind: str
    name: str = ""  # default: phantom_wh / phantom_bv / mmwhs / acdc / nifti
    anatomy: str = "whole_heart"  # phantom only: whole_heart | biventricular
    subjects: int = 0  # phantom: how many to generate; real data: at most this many (0 = all)
    frames: int = 20  # phantom biventricular: frames per cycle
    voxel_mm: tuple[float, ...] = ()  # phantom: voxel size; default 1 mm (whole heart) or 1.5x1.5x8 (ACDC-like)
    path: str = ""  # real data folder; relative paths are under $MESHSAR_DATA when set
    labels: dict[str, int] = field(default_factory=dict)  # nifti: structure name -> label value
    structures: tuple[str, ...] = ()  # meshed union; default: every structure the source has
    use: str = ""  # ssm | direct; default: ssm for whole-heart sources, direct otherwise
    pattern: str = ""  # nifti: glob of label-map file names (e.g. "*_label.nii.gz"); default: judge by content
    require_affine: bool = False  # real data: a file with neither sform nor qform is an error, not a warning
    # shape_model: files (relative to `path`) of an external PCA model, and what to draw from it
    mean: str = ""  # mean surface, .vtk / .vtp / .ply
    modes: str = ""  # principal components, .csv / .csv.gz / .npy: 3n rows (x1 y1 z1 x2 ...), one column per mode
    variances: str = ""  # one variance (mm^2) per mode, .csv / .csv.gz / .npy
    vertex_labels: str = ""  # optional: one value per vertex, mapped by `labels`; else one structure for all
    samples: int = 0  # shape_model: shapes drawn
    n_modes: int = 0  # shape_model: leading modes used (0 = all in the file)

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"kind: must be one of {KINDS}, got {self.kind!r}")
        if self.anatomy not in ("whole_heart", "biventricular"):
            raise ValueError(f"anatomy: must be whole_heart or biventricular, got {self.anatomy!r}")
        biv = self.kind == "acdc" or (self.kind == "phantom" and self.anatomy == "biventricular")
        whole = self.kind == "mmwhs" or (self.kind == "phantom" and self.anatomy == "whole_heart")
        default_name = {"phantom": "phantom_wh" if whole else "phantom_bv"}.get(self.kind, self.kind)
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen: resolve defaults once)
        set_("name", self.name or default_name)
        if not NAME_RE.match(self.name):
            raise ValueError(f"name: letters, digits, '_' and '-' only, got {self.name!r}")
        if self.kind == "phantom" and self.subjects < 1:
            raise ValueError(f"subjects: a phantom source needs subjects >= 1, got {self.subjects}")
        if self.subjects < 0:
            raise ValueError(f"subjects: must be >= 0, got {self.subjects}")
        if self.frames < 2:
            raise ValueError(f"frames: must be >= 2, got {self.frames}")
        if self.voxel_mm and (len(self.voxel_mm) != 3 or min(self.voxel_mm) <= 0):
            raise ValueError(f"voxel_mm: three positive sizes, got {list(self.voxel_mm)}")
        if self.kind != "phantom":
            if self.voxel_mm:
                raise ValueError("voxel_mm: only a phantom source takes a voxel size")
        else:
            set_("voxel_mm", tuple(self.voxel_mm or ((1.0, 1.0, 1.0) if whole else (1.5, 1.5, 8.0))))
        if self.kind == "nifti" and not self.labels:
            raise ValueError("labels: a nifti source needs a label table, e.g. { lv = 1, myo = 2, rv = 3 }")
        if self.pattern and self.kind != "nifti":
            raise ValueError(f"pattern: only a nifti source takes a file-name pattern ({self.kind} has a fixed layout)")
        if self.pattern and not re.search(r"\.nii(\.gz)?\*?$", self.pattern):
            raise ValueError(f"pattern: must match NIfTI files (end in .nii, .nii.gz or .nii*), got {self.pattern!r}")
        if self.require_affine and self.kind in ("phantom", "shape_model"):
            raise ValueError("require_affine: only a label-map source reads headers that may lack an affine")
        shape_model = self.kind == "shape_model"
        if self.labels and self.kind not in ("nifti", "shape_model"):
            raise ValueError(f"labels: only a nifti or shape_model source takes a label table ({self.kind} has a fixed one)")
        bad = sorted(set(self.labels) - set(STRUCTURES))
        if bad:
            raise ValueError(f"labels: unknown structures {bad}; known: {sorted(STRUCTURES)}")
        model_keys = {"mean": self.mean, "modes": self.modes, "variances": self.variances,
                      "vertex_labels": self.vertex_labels, "samples": self.samples, "n_modes": self.n_modes}
        if not shape_model:
            given = [k for k, v in model_keys.items() if v]
            if given:
                raise ValueError(f"{given[0]}: only a shape_model source takes {given[0]}")
        else:
            missing = [k for k in ("mean", "modes", "variances") if not model_keys[k]]
            if missing:
                raise ValueError(f"{missing[0]}: a shape_model source needs mean, modes and variances files")
            if self.samples < 1:
                raise ValueError(f"samples: a shape_model source needs samples >= 1, got {self.samples}")
            if self.n_modes < 0:
                raise ValueError(f"n_modes: must be >= 0 (0: every mode in the file), got {self.n_modes}")
            if self.vertex_labels and not self.labels:
                raise ValueError("vertex_labels: needs a label table, e.g. labels = { lv = 1, myo = 2, rv = 3 }")
            if self.labels and not self.vertex_labels:
                raise ValueError("labels: a shape_model's label table maps the values of vertex_labels; give that file")
            if not self.vertex_labels and len(self.structures) != 1:
                raise ValueError(f"structures: a shape_model without vertex_labels is one structure, e.g. "
                                 f"structures = [\"lv\"], got {list(self.structures)}")
            if self.use == "direct":
                raise ValueError("use: a shape_model source gives samples (use = \"ssm\"), not meshes to use directly")
            if self.vertex_labels and self.structures and set(self.structures) != set(self.labels):
                raise ValueError("structures: a shape_model's samples are its whole surface, labelled by vertex_labels; "
                                 "leave structures out")
        if self.kind == "nifti" or (shape_model and self.vertex_labels):
            available = tuple(self.labels)
        elif shape_model:
            available = tuple(STRUCTURES)
        else:
            available = SOURCE_STRUCTURES["acdc" if biv else "mmwhs"]
        bad = sorted(set(self.structures) - set(available))
        if bad:
            raise ValueError(f"structures: {bad} not in this source's structures {list(available)}")
        set_("structures", tuple(self.structures or available))
        set_("use", self.use or ("ssm" if whole or shape_model else "direct"))
        if self.use not in ("ssm", "direct"):
            raise ValueError(f"use: must be 'ssm' or 'direct', got {self.use!r}")

    @property
    def subset(self) -> str:
        """The dataset subset a source feeds: SSM-sampled whole heart, or dynamic/direct meshes."""
        return "ssm" if self.use == "ssm" else "direct"

    def data_path(self) -> Path:
        """The real-data folder: `path`, under $MESHSAR_DATA when relative and that is set."""
        root = os.environ.get("MESHSAR_DATA", "")
        if not self.path and not root:
            raise RecipeError(f"[[sources]] {self.name}: path: not given and MESHSAR_DATA is not set")
        p = Path(self.path) if self.path else Path(root)
        return p if p.is_absolute() or not root else Path(root) / p

    def model_files(self) -> dict[str, Path]:
        """shape_model: key -> file (mean, modes, variances and vertex_labels if given), relative
        names under data_path()."""
        names = {k: getattr(self, k) for k in ("mean", "modes", "variances", "vertex_labels") if getattr(self, k)}
        if all(Path(n).is_absolute() for n in names.values()):
            return {k: Path(n) for k, n in names.items()}
        root = self.data_path()
        return {k: Path(n) if Path(n).is_absolute() else root / n for k, n in names.items()}


# Refuse volumes whose header declares more voxels than this before reading any data.
MAX_VOXELS = 1024**3 // 2
# Float label maps (resampled, or written by tools that store floats) are rounded when every
# value is this close to an integer; farther off, it is a probability map or an image.
ROUND_TOLERANCE = 1e-3
# A label map has a few dozen values at most; an intensity image (CT, MR) has thousands.
MAX_LABEL_VALUES = 256


class InputWarning(UserWarning):
    """A usable input with something the user should know (unmapped labels, no spatial header)."""


def warning_messages(caught: list[warnings.WarningMessage]) -> list[str]:
    """The InputWarning texts among recorded warnings, for a stage's sidecar (the user reads them there)."""
    return [str(w.message) for w in caught if issubclass(w.category, InputWarning)]


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


def _load_header(path: Path) -> tuple[nib.Nifti1Image, tuple[int, ...]]:
    """The image proxy and its 3-D shape; InputError naming the file when unreadable, not 3-D or oversized."""
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
    return img, shape


def _load_data(path: Path, img: nib.Nifti1Image) -> tuple[nib.Nifti1Image, np.ndarray]:
    """The image reoriented to closest canonical RAS and its voxel data; InputError when corrupt."""
    try:
        if path.name.endswith(".gz"):
            # Decompress the whole stream: gzip checks its CRC and length, so a truncated file
            # fails here even when the bytes the image needs happen to come before the cut.
            img = type(img).from_bytes(gzip.decompress(path.read_bytes()))
        img = nib.as_closest_canonical(img)
        return img, np.asanyarray(img.dataobj).reshape(img.shape[:3])
    except (OSError, EOFError, zlib.error, gzip.BadGzipFile, ValueError) as e:
        raise InputError(f"{path}: not a readable NIfTI file, image data truncated or corrupt ({type(e).__name__}: {e})") from e


def label_map_verdict(path: str | Path) -> str:
    """Why a readable NIfTI file is not a label map ('' when it may be one, or cannot be read:
    the loader then names the problem). Judged by content: more than MAX_LABEL_VALUES distinct
    values (an intensity image)."""
    path = Path(path)
    try:
        img, _ = _load_header(path)  # refuses oversized headers before any data is read
        data = np.asanyarray(img.dataobj)
    except Exception:  # noqa: BLE001 (any unreadable file stays indexed: read_label_map names its problem)
        return ""
    n = len(np.unique(data))
    return f"{n} distinct values, an image rather than a label map" if n > MAX_LABEL_VALUES else ""


def read_label_map(
    path: str | Path, table: dict[int, str], require_affine: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Read a NIfTI label map, reorient to the closest canonical RAS, map to canonical ids.

    Returns
    -------
    labels : (X, Y, Z) uint8, canonical structure ids (STRUCTURES), 0 elsewhere
    affine : (4, 4) float64, voxel index -> RAS+ millimetres

    Raises InputError naming the file for unreadable files, non-3-D images,
    non-finite labels or labels farther than ROUND_TOLERANCE from an integer,
    bad affines, oversized headers, maps that contain none of the table's
    labels, and (with `require_affine`) files with neither sform nor qform.
    Warns (InputWarning, naming the file) for label values outside the table,
    with their voxel counts, and for a header with neither sform nor qform
    (the affine is then pixdim only, and the orientation a guess).
    """
    path = Path(path)
    img, shape = _load_header(path)
    affine = img.affine
    if affine is None or not np.all(np.isfinite(affine)) or abs(np.linalg.det(affine[:3, :3])) < 1e-9:
        raise InputError(f"{path}: affine is missing, non-finite or singular")
    if int(img.header["sform_code"]) == 0 and int(img.header["qform_code"]) == 0:
        what = f"{path}: neither sform nor qform is set; the affine is from pixdim only, so left/right and the origin are guesses"
        if require_affine:
            raise InputError(f"{what} (require_affine = true)")
        warnings.warn(what, InputWarning, stacklevel=2)
    img, data = _load_data(path, img)
    if data.dtype.kind == "f":
        if not np.all(np.isfinite(data)):
            raise InputError(f"{path}: label map has NaN or infinite values")
        rounded = np.round(data)
        off = float(np.max(np.abs(data - rounded))) if data.size else 0.0
        if off > ROUND_TOLERANCE:
            raise InputError(
                f"{path}: label map has non-integer values, up to {off:.3g} from an integer "
                f"(tolerance {ROUND_TOLERANCE}; a probability map or an image?)"
            )
        data = rounded
    elif data.dtype.kind not in "iub":
        raise InputError(f"{path}: unsupported label data type {data.dtype}")
    data = data.astype(np.int64, copy=False)
    present, counts = np.unique(data, return_counts=True)
    lut_keys = np.array(sorted(table), dtype=np.int64)
    lut_vals = np.array([STRUCTURES[table[k]] for k in lut_keys], dtype=np.uint8)
    known = np.isin(present, lut_keys)
    if not known.any():
        raise InputError(
            f"{path}: none of the labels {sorted(table)} found (values present: {present[:20].tolist()})"
        )
    unmapped = ~known & (present != 0)
    if unmapped.any():
        listed = ", ".join(f"{v} ({c} voxels)" for v, c in zip(present[unmapped][:20], counts[unmapped][:20]))
        more = f" and {unmapped.sum() - 20} more" if unmapped.sum() > 20 else ""
        warnings.warn(f"{path}: label values with no mapping, read as background: {listed}{more}", InputWarning, stacklevel=2)
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
            if key == "NbFrame":  # only the cycle fraction needs it
                warnings.warn(f"{path}: no 'NbFrame' in Info.cfg; cycle_fraction left unknown", InputWarning, stacklevel=2)
                continue
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
        ed, es = int(info["ED"]), int(info["ES"])
        nb = int(info["NbFrame"]) if "NbFrame" in info else None
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
                    frame=frame, phase=phase, cycle_fraction=None if nb is None else (frame - 1) / nb, provenance=prov,
                    extra={"group": info.get("Group", ""), "n_frames": nb},
                )
            )
    return items


def index_nifti(
    root: str | Path, source: str, labels: dict[str, int], limit: int | None = None, pattern: str = ""
) -> list[LabelItem]:
    """A folder of `*.nii` / `*.nii.gz` label maps, with a recipe label table {structure: value}.

    Only label maps are indexed: with `pattern`, the files whose name matches that glob;
    without, the files whose content may be a label map (label_map_verdict). An
    InputWarning names the files skipped and why.
    """
    root = _require_dir(root)
    unknown = sorted(set(labels) - set(STRUCTURES))
    if unknown:
        raise InputError(f"labels: unknown structure names {unknown}; known: {sorted(STRUCTURES)}")
    table = {int(v): k for k, v in labels.items()}
    nifti = sorted(p for p in root.rglob("*.nii*") if p.name.endswith((".nii", ".nii.gz")))
    if pattern:
        chosen = [p for p in nifti if p.match(pattern)]
        skipped = {p: f"name does not match {pattern!r}" for p in nifti if p not in chosen}
    else:
        skipped = {p: why for p in nifti if (why := label_map_verdict(p))}
        chosen = [p for p in nifti if p not in skipped]
    if skipped:
        listed = "; ".join(f"{p.relative_to(root)} ({why})" for p, why in skipped.items())
        warnings.warn(f"{root}: skipped {len(skipped)} file(s) that are not label maps: {listed}", InputWarning, stacklevel=2)
    files = _first_n(chosen, limit)
    if not nifti:
        raise InputError(f"{root}: no *.nii or *.nii.gz files found")
    if not files:
        raise InputError(f"{root}: none of the {len(nifti)} *.nii / *.nii.gz files is a label map (see the warning)")
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


# --- external shape models (e.g. the UK Digital Heart atlas) ------------------------------------

# Principal components must be orthonormal columns to this tolerance (files store ~6 digits).
ORTHONORMAL_TOLERANCE = 1e-3


def read_surface(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A triangle surface from .ply, or .vtk (legacy) / .vtp polydata; polygons are triangulated,
    the point order kept (the model's components index it). Returns verts (n, 3) float64,
    faces (m, 3) int64; InputError naming the file when unreadable or without triangles."""
    path = Path(path)
    if path.suffix.lower() == ".ply":
        verts, faces, _ = read_ply(path)
    elif path.suffix.lower() in (".vtk", ".vtp"):
        import pyvista as pv  # only this reader needs it (slow to import)

        try:
            mesh = pv.read(str(path))
            surface = (mesh if isinstance(mesh, pv.PolyData) else mesh.extract_surface()).triangulate()
        except Exception as e:  # noqa: BLE001 (VTK raises many types; the message names the file)
            raise InputError(f"{path}: not a readable VTK surface ({type(e).__name__}: {e})") from e
        verts = np.asarray(surface.points, np.float64)
        faces = np.asarray(surface.faces, np.int64).reshape(-1, 4)[:, 1:] if surface.n_cells else np.zeros((0, 3), np.int64)
        if not np.all(np.isfinite(verts)):
            raise InputError(f"{path}: mesh has NaN or infinite vertex coordinates")
    else:
        raise InputError(f"{path}: mean surface must be .vtk, .vtp or .ply")
    if not len(faces):
        raise InputError(f"{path}: surface has no polygons")
    return verts, faces


def read_matrix(path: str | Path) -> np.ndarray:
    """A numeric table from .npy, or .csv / .csv.gz (comma or whitespace separated, an optional
    header line). Returns a 2-D float64 array (a single column or row as (n, 1))."""
    path = Path(path)
    try:
        if path.name.endswith(".npy"):
            data = np.load(path, allow_pickle=False)
        elif path.name.endswith((".csv", ".csv.gz", ".txt", ".txt.gz")):
            opener = gzip.open if path.name.endswith(".gz") else open
            with opener(path, "rt") as f:
                lines = [line.replace(",", " ") for line in f if line.strip()]
            try:
                [float(v) for v in lines[0].split()] if lines else None
            except ValueError:
                lines = lines[1:]  # a header line
            data = np.loadtxt(lines, ndmin=2) if lines else np.zeros((0, 0))
        else:
            raise InputError(f"{path}: must be .npy, .csv or .csv.gz")
    except (OSError, EOFError, zlib.error, gzip.BadGzipFile, ValueError) as e:
        raise InputError(f"{path}: not a readable numeric table ({type(e).__name__}: {e})") from e
    data = np.asarray(data, np.float64)
    if data.ndim == 1:
        data = data[:, None]
    if data.ndim != 2 or not data.size:
        raise InputError(f"{path}: expected a non-empty 2-D table, got shape {data.shape}")
    if not np.all(np.isfinite(data)):
        raise InputError(f"{path}: has NaN or infinite values")
    return data


def load_shape_model(
    files: dict[str, Path], n_modes: int = 0, labels: dict[str, int] | None = None, structure: str = ""
) -> ShapeModel:
    """An external PCA shape model: mean surface, components, variances, per-vertex labels.

    files : "mean", "modes", "variances" and optionally "vertex_labels" -> path. The components
        table has 3n rows, x, y, z of vertex 1, then of vertex 2, ... (as the UK Digital Heart
        atlas stores them), one orthonormal column per mode; variances one per mode (mm^2),
        descending. n_modes : leading modes kept (0: all). labels : {structure: value} mapping
        the vertex_labels values; without vertex_labels every vertex is `structure`.
    Returns a ShapeModel: mean (n, 3), modes (k, n, 3), variances (k,), faces (m, 3), labels
    (n,) canonical ids; total_variance sums every variance in the file. InputError names the
    file for each inconsistency.
    """
    # Imported here: recipe parsing imports this module and should not pay for trimesh.
    from meshsar_builder.geometry.ssm import ShapeModel

    verts, faces = read_surface(files["mean"])
    n = len(verts)
    components = read_matrix(files["modes"])
    if components.shape[0] != 3 * n:
        if components.shape[1] == 3 * n:
            hint = " (it has 3n columns: store one mode per column, not per row)"
        else:
            hint = ""
        raise InputError(f"{files['modes']}: {components.shape[0]} rows, expected 3 x {n} vertices of {files['mean'].name}{hint}")
    variances = read_matrix(files["variances"]).ravel()
    if len(variances) != components.shape[1]:
        raise InputError(f"{files['variances']}: {len(variances)} variances for {components.shape[1]} modes in {files['modes'].name}")
    if np.any(variances < 0) or np.any(np.diff(variances) > 1e-9 * variances.max()):
        raise InputError(f"{files['variances']}: variances must be >= 0 and in descending order")
    k = n_modes or len(variances)
    if k > len(variances):
        raise InputError(f"{files['modes']}: n_modes = {n_modes} but the file has {len(variances)} modes")
    gram = components[:, :k].T @ components[:, :k]
    off = float(np.abs(gram - np.eye(k)).max())
    if off > ORTHONORMAL_TOLERANCE:
        raise InputError(f"{files['modes']}: columns are not orthonormal principal directions (|C^T C - I| up to {off:.3g}); "
                         f"if they are scaled by the standard deviations, divide them out")
    if "vertex_labels" in files:
        values = read_matrix(files["vertex_labels"]).ravel()
        if len(values) != n:
            raise InputError(f"{files['vertex_labels']}: {len(values)} labels for {n} vertices of {files['mean'].name}")
        if not np.all(values == np.round(values)):
            raise InputError(f"{files['vertex_labels']}: labels must be integers")
        values = values.astype(np.int64)
        table = {v: STRUCTURES[name] for name, v in (labels or {}).items()}
        unknown = sorted(set(np.unique(values).tolist()) - set(table))
        if unknown:
            raise InputError(f"{files['vertex_labels']}: values {unknown[:10]} not in the label table {labels}")
        vertex_labels = np.array([table[v] for v in values], np.uint8)
    else:
        vertex_labels = np.full(n, STRUCTURES[structure], np.uint8)
    return ShapeModel(
        mean=verts,
        modes=components[:, :k].T.reshape(k, n, 3),
        variances=variances[:k],
        faces=faces,
        total_variance=float(variances.sum()),
        labels=vertex_labels,
    )
