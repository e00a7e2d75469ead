"""Label-map sources: fixed label tables, NIfTI reading in canonical RAS, and folder indexers.

Every source's labels map into one canonical structure table, so per-vertex
labels mean the same thing whatever dataset a mesh came from. Tables are fixed,
never derived from the sorted values found in a file.
"""

from __future__ import annotations

import csv
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
# ACDC: 4-D label maps predicted for every frame, per patient folder, where present.
ACDC_PREDICTED = "{subject}_4d_pred.nii*"
PHASES = ("ED", "ES")
FRAME_GROUPS = ("subject", "frame", "phase")


def compile_frame_regex(text: str) -> re.Pattern:
    """A `regex` recipe value compiled; ValueError naming the key when it does not compile, lacks
    the `subject` group or names a group other than subject, frame and phase."""
    try:
        rx = re.compile(text)
    except re.error as e:
        raise ValueError(f"regex: not a regular expression ({e}): {text!r}") from None
    if "subject" not in rx.groupindex:
        raise ValueError(f"regex: needs a named group (?P<subject>...), got {text!r}")
    extra = sorted(set(rx.groupindex) - set(FRAME_GROUPS))
    if extra:
        raise ValueError(f"regex: named groups must be among {list(FRAME_GROUPS)}, got {extra}")
    return rx

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
    # Subjects and frames of real cine data (nifti; acdc: predicted; any label-map source: cohort)
    regex: str = ""  # nifti: named groups subject (required), frame, phase, searched in each file's relative path
    frame_table: str = ""  # nifti: CSV (file, subject[, frame, phase, provenance]), relative to `path`
    phases: dict[str, int] = field(default_factory=dict)  # nifti: e.g. { ED = 0, ES = 9 }: frame numbers of ED / ES
    provenance: str = ""  # nifti: annotated (default) | predicted
    predicted: str = ""  # acdc: glob, per patient folder, of predicted label maps; default "{subject}_4d_pred.nii*"
    cohort: str = ""  # label-map sources with the same cohort share subject names (splits group across them)

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
        self._check_frames(set_)
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

    def _check_frames(self, set_) -> None:
        """The subject / frame keys: each only where its kind reads it, and well-formed."""
        only = {"regex": "nifti", "frame_table": "nifti", "phases": "nifti", "provenance": "nifti", "predicted": "acdc"}
        for key, kind in only.items():
            if getattr(self, key) and self.kind != kind:
                raise ValueError(f"{key}: only a{'n' if kind[0] in 'aeiou' else ''} {kind} source takes {key}")
        if self.regex:
            compile_frame_regex(self.regex)
            if self.frame_table:
                raise ValueError("regex: give either regex or frame_table, not both (the table names every file)")
        if self.frame_table:
            if not self.frame_table.endswith(".csv"):
                raise ValueError(f"frame_table: must be a .csv file, got {self.frame_table!r}")
            if self.pattern:
                raise ValueError("pattern: a frame_table names its files; leave pattern out")
        bad = sorted(set(self.phases) - set(PHASES))
        if bad:
            raise ValueError(f"phases: keys must be among {list(PHASES)}, got {bad}")
        if any(v < 0 for v in self.phases.values()):
            raise ValueError(f"phases: frame numbers must be >= 0, got {self.phases}")
        if len(set(self.phases.values())) < len(self.phases):
            raise ValueError(f"phases: ED and ES must be different frames, got {self.phases}")
        if self.provenance and self.provenance not in ("annotated", "predicted"):
            raise ValueError(f"provenance: must be 'annotated' or 'predicted', got {self.provenance!r}")
        if self.kind == "acdc":
            set_("predicted", self.predicted or ACDC_PREDICTED)
            if not re.search(r"\.nii(\.gz)?\*?$", self.predicted):
                raise ValueError(f"predicted: must match NIfTI files (end in .nii, .nii.gz or .nii*), got {self.predicted!r}")
        if self.cohort:
            if self.kind in ("phantom", "shape_model"):
                raise ValueError(f"cohort: only a label-map source (mmwhs, acdc, nifti) has subjects to share, not {self.kind}")
            if not NAME_RE.match(self.cohort):
                raise ValueError(f"cohort: letters, digits, '_' and '-' only, got {self.cohort!r}")

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
    t: int | None = None  # a 4-D label map's T index (0-based) that holds this frame; None: a 3-D map

    def to_json(self) -> dict:
        d = asdict(self)
        d["table"] = {str(k): v for k, v in self.table.items()}
        return d

    @classmethod
    def from_json(cls, d: dict) -> "LabelItem":
        return cls(**{**d, "table": {int(k): v for k, v in d["table"].items()}})


def item_id(source: str, subject: str, frame: int | None = None, phase: str = "") -> str:
    """A file-name-safe id, unique across a recipe's sources (a frame known only by its phase:
    `<source>-<subject>-ED`)."""
    base = re.sub(r"[^A-Za-z0-9_-]+", "_", f"{source}-{subject}")
    if frame is None:
        return f"{base}-{phase}" if phase else base
    return f"{base}-f{frame:02d}"


# A 4-D label map holds at most this many frames (a cine cycle has a few dozen).
MAX_FRAMES = 10000


def _read_header(path: Path) -> tuple[nib.Nifti1Image, tuple[int, ...]]:
    """The image proxy and its shape, 3-D (X, Y, Z) or 4-D (X, Y, Z, T) with T > 1; InputError
    naming the file when unreadable, of another rank, or oversized (per frame, or T > MAX_FRAMES)."""
    try:
        img = nib.load(str(path))
        shape = tuple(int(s) for s in img.header.get_data_shape())
    except (OSError, EOFError, zlib.error, gzip.BadGzipFile, nib.filebasedimages.ImageFileError, ValueError) as e:
        raise InputError(f"{path}: not a readable NIfTI file ({type(e).__name__}: {e})") from e
    if len(shape) == 4 and shape[3] == 1:
        shape = shape[:3]
    if len(shape) not in (3, 4):
        raise InputError(f"{path}: label map must be 3-D (or 4-D, one frame per T index), got shape {shape}")
    if min(shape) < 1 or int(np.prod(shape[:3], dtype=np.int64)) > MAX_VOXELS or shape[3:4] > (MAX_FRAMES,):
        raise InputError(f"{path}: implausible image size {shape} (limit {MAX_VOXELS} voxels a frame, {MAX_FRAMES} frames)")
    return img, shape


def n_frames(path: str | Path) -> int | None:
    """T of a 4-D label map (X, Y, Z, T), from its header alone; None for a 3-D map. InputError as _read_header."""
    shape = _read_header(Path(path))[1]
    return shape[3] if len(shape) == 4 else None


def _load_header(path: Path, t: int | None = None) -> tuple[nib.Nifti1Image, tuple[int, ...]]:
    """The image proxy and the 3-D shape of the map (of its frame `t`, a T index, when 4-D);
    InputError naming the file when unreadable, oversized, 4-D without `t`, `t` out of range,
    or `t` given for a 3-D map."""
    img, shape = _read_header(path)
    if len(shape) == 4:
        if t is None:
            raise InputError(f"{path}: label map must be 3-D, got shape {shape} (a 4-D map is read one frame "
                             f"per T index: index it through a source)")
        if not 0 <= t < shape[3]:
            raise InputError(f"{path}: frame index t = {t} out of range for a 4-D map of {shape[3]} frames "
                             f"(T indices 0..{shape[3] - 1})")
    elif t is not None and t != 0:
        raise InputError(f"{path}: frame index t = {t} given, but the label map is 3-D, shape {shape}")
    return img, shape[:3]


def _load_data(path: Path, img: nib.Nifti1Image, t: int | None = None) -> tuple[nib.Nifti1Image, np.ndarray]:
    """The image (its frame `t` when 4-D, same affine) reoriented to closest canonical RAS and
    its voxel data; InputError when corrupt."""
    try:
        if path.name.endswith(".gz"):
            # Decompress the whole stream: gzip checks its CRC and length, so a truncated file
            # fails here even when the bytes the image needs happen to come before the cut.
            img = type(img).from_bytes(gzip.decompress(path.read_bytes()))
        if len(img.shape) == 4:
            # One T index: slicing the last axis keeps the affine (and reads only that frame).
            img = img.slicer[:, :, :, t if t is not None else 0]
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
        img, _ = _read_header(path)  # refuses oversized headers before any data is read
        data = np.asanyarray(img.dataobj)
    except Exception:  # noqa: BLE001 (any unreadable file stays indexed: read_label_map names its problem)
        return ""
    n = len(np.unique(data))
    return f"{n} distinct values, an image rather than a label map" if n > MAX_LABEL_VALUES else ""


def read_label_map(
    path: str | Path, table: dict[int, str], require_affine: bool = False, t: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Read a NIfTI label map, reorient to the closest canonical RAS, map to canonical ids.

    A 4-D map (X, Y, Z, T) is read one frame at a time: `t` is the T index (0-based) to read,
    with the file's one affine; a 3-D map takes t None (or 0).

    Returns
    -------
    labels : (X, Y, Z) uint8, canonical structure ids (STRUCTURES), 0 elsewhere
    affine : (4, 4) float64, voxel index -> RAS+ millimetres

    Raises InputError naming the file for unreadable files, non-3-D images (a 4-D one
    without `t`, or `t` out of range),
    non-finite labels or labels farther than ROUND_TOLERANCE from an integer,
    bad affines, oversized headers, maps that contain none of the table's
    labels, and (with `require_affine`) files with neither sform nor qform.
    Warns (InputWarning, naming the file) for label values outside the table,
    with their voxel counts, and for a header with neither sform nor qform
    (the affine is then pixdim only, and the orientation a guess).
    """
    path = Path(path)
    img, shape = _load_header(path, t)
    affine = img.affine
    if affine is None or not np.all(np.isfinite(affine)) or abs(np.linalg.det(affine[:3, :3])) < 1e-9:
        raise InputError(f"{path}: affine is missing, non-finite or singular")
    if int(img.header["sform_code"]) == 0 and int(img.header["qform_code"]) == 0:
        what = f"{path}: neither sform nor qform is set; the affine is from pixdim only, so left/right and the origin are guesses"
        if require_affine:
            raise InputError(f"{what} (require_affine = true)")
        warnings.warn(what, InputWarning, stacklevel=2)
    img, data = _load_data(path, img, t)
    path = f"{path} [t={t}]" if t is not None else path  # the messages below name the frame
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
    root: str | Path, source: str, limit: int | None = None, provenance: str | None = None, subject: str = "*",
    predicted: str = ACDC_PREDICTED,
) -> list[LabelItem]:
    """ACDC layout: `<root>/**/patientNNN/Info.cfg` and `patientNNN_frameYY_gt.nii.gz`.

    Every `_gt` frame present becomes an item. Real ACDC annotates ED and ES
    only, so other frames are recorded as predicted unless `provenance` says
    otherwise (the phantom passes "phantom"). Frames are numbered as ACDC numbers
    them, from 1 (frameYY; Info.cfg's ED and ES).

    `predicted` (a glob in each patient folder, `{subject}` standing for the folder's
    name; "" for none) finds label maps predicted for every frame, where present: a 4-D
    map's T index t is ACDC frame t + 1 (its T must equal NbFrame); a 3-D one names its
    frame as `frameYY`. Their frames are recorded as provenance "predicted", each read
    from its T index; a frame that has a `_gt` map keeps that one (annotated wins).
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
        extra = {"group": info.get("Group", ""), "n_frames": nb}
        frames = sorted(pdir.glob(f"{pdir.name}_frame[0-9][0-9]_gt.nii*"))
        pred_files = sorted(pdir.glob(predicted.replace("{subject}", pdir.name))) if predicted else []
        if not frames and not pred_files:
            also = f" nor predicted label maps ({predicted.replace('{subject}', pdir.name)})" if predicted else ""
            raise InputError(f"{pdir}: no *_frameYY_gt.nii.gz files{also}")
        found: dict[int, LabelItem] = {}

        def add(frame: int, path: Path, prov: str, t: int | None = None) -> None:
            phase = "ED" if frame == ed else "ES" if frame == es else ""
            found[frame] = LabelItem(
                item_id(source, pdir.name, frame), source, str(path), pdir.name, ACDC_TABLE,
                frame=frame, phase=phase, cycle_fraction=None if nb is None else (frame - 1) / nb, provenance=prov,
                extra=dict(extra), t=t,
            )

        for f in frames:
            frame = int(re.search(r"_frame(\d\d)_gt", f.name).group(1))
            add(frame, f, provenance or ("annotated" if frame in (ed, es) else "predicted"))
        annotated = set(found)
        claimed: dict[int, Path] = {}
        for f in pred_files:
            if f in frames:
                continue
            T = n_frames(f)
            if T is None:
                m = re.search(r"frame(\d+)", f.name)
                if not m:
                    raise InputError(f"{f}: a 3-D predicted label map (predicted = {predicted!r}) must name its frame "
                                     f"(frameYY); a 4-D one holds one frame per T index")
                pairs = [(int(m.group(1)), None)]
            else:
                if nb is not None and T != nb:
                    raise InputError(f"{f}: {T} frames (T) in a predicted 4-D label map, but {pdir.name}/Info.cfg "
                                     f"has NbFrame: {nb}")
                pairs = [(t + 1, t) for t in range(T)]
            for frame, t in pairs:
                if frame in claimed:
                    raise InputError(f"{f}: claims {pdir.name} frame {frame}, which {claimed[frame].name} also claims")
                claimed[frame] = f
                if frame not in annotated:
                    add(frame, f, "predicted", t)
        items += [found[k] for k in sorted(found)]
    return items


@dataclass
class _Claim:
    """What a file (or a table row) says of itself: its subject, and frame / phase where known."""

    path: Path
    subject: str
    frame: int | None = None  # 3-D: the frame number; 4-D: one T index (None: every T index)
    phase: str = ""
    provenance: str = ""
    extra: dict = field(default_factory=dict)
    where: str = ""  # the file and how it was claimed, for messages
    from_name: bool = False  # frame / phase read from the file name (regex), not a table


def _phase_name(value: str | None, where: str) -> str:
    """'ED' / 'ES' / '' from a file name's or table's phase text (any case); InputError otherwise."""
    value = (value or "").strip()
    if value.upper() in PHASES or not value:
        return value.upper()
    raise InputError(f"{where}: phase must be one of {list(PHASES)} (any case) or empty, got {value!r}")


def _frame_number(value: str | None, where: str) -> int | None:
    value = (value or "").strip()
    if not value:
        return None
    if not value.isdigit():
        raise InputError(f"{where}: frame must be a non-negative integer, got {value!r}")
    return int(value)


def read_frame_table(path: Path, root: Path) -> list[_Claim]:
    """A frame_table CSV: a header with `file` and `subject` (required), `frame`, `phase`,
    `provenance` (optional); other columns are kept in each item's `extra`. `file` is relative
    to `root` (or absolute). InputError naming the table and row for each fault."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot read the frame_table ({type(e).__name__}: {e})") from e
    rows = [(n, r) for n, r in enumerate(rows, start=1) if any(c.strip() for c in r)]
    if not rows:
        raise InputError(f"{path}: frame_table is empty (needs a header line: file,subject,frame,phase)")
    (_, header), body = rows[0], rows[1:]
    header = [h.strip().lower() for h in header]
    missing = [c for c in ("file", "subject") if c not in header]
    if missing:
        raise InputError(f"{path}: frame_table header needs columns file and subject (optional frame, phase, "
                         f"provenance), got {header}")
    if len(set(header)) < len(header):
        raise InputError(f"{path}: frame_table header names a column twice: {header}")
    if not body:
        raise InputError(f"{path}: frame_table has a header and no rows")
    claims = []
    for n, r in body:
        where = f"{path}: row {n}"
        if len(r) != len(header):
            raise InputError(f"{where}: {len(r)} fields, the header has {len(header)}")
        row = {h: v.strip() for h, v in zip(header, r)}
        if not row["file"] or not row["subject"]:
            raise InputError(f"{where}: file and subject must not be empty")
        file = Path(row["file"]) if Path(row["file"]).is_absolute() else root / row["file"]
        if not file.is_file():
            raise InputError(f"{where}: file {row['file']!r} not found under {root}")
        prov = row.get("provenance", "")
        if prov not in ("", "annotated", "predicted"):
            raise InputError(f"{where}: provenance must be annotated or predicted (or empty), got {prov!r}")
        claims.append(_Claim(
            file, row["subject"], _frame_number(row.get("frame"), where), _phase_name(row.get("phase"), where), prov,
            {h: v for h, v in row.items() if h not in ("file", "subject", "frame", "phase", "provenance")},
            where=where,
        ))
    return claims


def _regex_claims(files: list[Path], root: Path, regex: str) -> tuple[list[_Claim], list[Path]]:
    """Claims of the files whose relative path (with '/') the regex finds (re.search), and the files it does not."""
    rx = compile_frame_regex(regex)
    claims, unmatched = [], []
    for f in files:
        rel = f.relative_to(root).as_posix()
        m = rx.search(rel)
        if m is None:
            unmatched.append(f)
            continue
        where = f"{f}: regex {regex!r}"
        groups = m.groupdict()
        if not groups.get("subject"):
            raise InputError(f"{where} matched with an empty subject group")
        claims.append(_Claim(f, groups["subject"], _frame_number(groups.get("frame"), where),
                             _phase_name(groups.get("phase"), where), where=where, from_name=True))
    return claims, unmatched


def _phase_of(frame: int | None, phase: str, phases: dict[str, int], where: str) -> tuple[int | None, str]:
    """(frame, phase) with the recipe's `phases` applied: a frame it names gets that phase; a frame
    known only by its phase gets the frame the recipe gives that phase. InputError when the two disagree."""
    by_frame = {v: k for k, v in phases.items()}
    if frame is None:
        return (phases.get(phase), phase) if phase else (None, "")
    named = by_frame.get(frame, "")
    if phase and phase in phases and phases[phase] != frame:
        raise InputError(f"{where}: frame {frame} is {phase}, but the recipe's phases puts {phase} at frame {phases[phase]}")
    if phase and named and named != phase:
        raise InputError(f"{where}: frame {frame} is {phase}, but the recipe's phases makes it {named}")
    return frame, phase or named


def _expand(claims: list[_Claim], source: str, table: dict[int, str], phases: dict[str, int],
            provenance: str) -> list[LabelItem]:
    """One item per 3-D file, one per frame (T index) of a 4-D file; InputError for a frame out of range,
    a 4-D file whose name claims a frame or phase, or one file claimed by two subjects."""
    by_file: dict[Path, list[_Claim]] = {}
    for c in claims:
        by_file.setdefault(c.path, []).append(c)
    items = []
    for path, cs in by_file.items():
        subjects = sorted({c.subject for c in cs})
        if len(subjects) > 1:
            raise InputError(f"{cs[1].where}: {path.name} is claimed by subjects {subjects}; a file holds one subject")
        try:
            T = n_frames(path)
        except InputError:  # unreadable here: one item, whose meshing names the problem (as for any bad file)
            T = None
        prov = lambda c: c.provenance or provenance  # noqa: E731
        if T is None:
            if len(cs) > 1:
                raise InputError(f"{cs[1].where}: {path.name} is named twice, and it is a 3-D label map (one frame)")
            c = cs[0]
            frame, phase = _phase_of(c.frame, c.phase, phases, c.where or str(path))
            items.append(LabelItem(item_id(source, c.subject, frame, phase), source, str(path), c.subject, table,
                                   frame=frame, phase=phase, provenance=prov(c), extra=dict(c.extra)))
            continue
        bad = {k: v for k, v in phases.items() if v >= T}
        if bad:
            k, v = next(iter(bad.items()))
            raise InputError(f"{path}: the recipe's phases puts {k} at frame {v}, out of range for this 4-D label map "
                             f"of {T} frames (T indices 0..{T - 1})")
        chosen: dict[int, _Claim] = {}
        every = None
        for c in cs:
            if c.from_name and (c.frame is not None or c.phase):
                raise InputError(f"{c.where}: a 4-D label map ({T} frames) numbers its frames by T index; its name "
                                 f"cannot give a frame or phase (give ED / ES by the recipe's phases or a frame_table)")
            if c.frame is None:
                if c.phase:
                    raise InputError(f"{c.where}: a phase for a 4-D label map needs its frame (the T index)")
                every = c
            elif not 0 <= c.frame < T:
                raise InputError(f"{c.where}: frame {c.frame} out of range for {path.name}, a 4-D label map of "
                                 f"{T} frames (T indices 0..{T - 1})")
            elif c.frame in chosen:
                raise InputError(f"{c.where}: {path.name} frame {c.frame} is named twice")
            else:
                chosen[c.frame] = c
        for t in range(T) if every is not None else sorted(chosen):
            c = chosen.get(t, every)
            frame, phase = _phase_of(t, c.phase if t in chosen else "", phases, c.where or str(path))
            items.append(LabelItem(
                item_id(source, c.subject, frame), source, str(path), c.subject, table, frame=frame, phase=phase,
                cycle_fraction=t / T, provenance=prov(c), extra={**c.extra, "n_frames": T}, t=t,
            ))
    return items


def check_frames(items: list[LabelItem], where: str) -> None:
    """InputError naming both files when two items claim one subject and frame (or, frames known
    by phase only, one subject and phase), one subject has two ED or two ES frames, or two items'
    ids collide after making them file-name safe."""
    seen: dict[tuple, LabelItem] = {}
    for li in items:
        frame = f"frame {li.frame}" if li.frame is not None else f"phase {li.phase}" if li.phase else "(no frame)"
        for key in ((li.subject, frame), (li.subject, "phase", li.phase) if li.phase else None):
            if key is None:
                continue
            other = seen.get(key)
            if other is not None:
                what = frame if len(key) == 2 else f"phase {li.phase} (frames {other.frame} and {li.frame})"
                here = lambda x: x.path + ("" if x.t is None else f" [t={x.t}]")  # noqa: E731
                raise InputError(f"{where}: {here(other)} and {here(li)} both claim subject {li.subject!r} {what}")
            seen[key] = li
    ids: dict[str, LabelItem] = {}
    for li in items:
        if li.item_id in ids:
            raise InputError(f"{where}: subjects {ids[li.item_id].subject!r} and {li.subject!r} give the same item id "
                             f"{li.item_id!r} (names are made file-name safe); rename one")
        ids[li.item_id] = li


def index_nifti(
    root: str | Path, source: str, labels: dict[str, int], limit: int | None = None, pattern: str = "",
    regex: str = "", frame_table: str = "", phases: dict[str, int] | None = None, provenance: str = "annotated",
) -> list[LabelItem]:
    """A folder of `*.nii` / `*.nii.gz` label maps, with a recipe label table {structure: value}.

    Which files: with `frame_table`, the files its rows name; else with `pattern`, the files
    whose name matches that glob; with `regex`, those whose relative path it finds; with
    neither, the files whose content may be a label map (label_map_verdict). An InputWarning
    names the files skipped and why.

    Subjects and frames: from `regex` (named groups subject, frame, phase, re.search over the
    path relative to `root` with '/'), or the table's columns; else each file is its own
    subject (its relative path). A 4-D map (X, Y, Z, T) gives one frame per T index, its frame
    number being the T index (0-based), and its cycle fraction t / T; a 3-D map one item, its
    frame numbered as the file name or table numbers it. `phases` ({ED: n, ES: m}) names the
    frames of ED and ES where the name or table does not (a frame known only by its phase
    takes the recipe's frame for it). `limit`: the first subjects, by name.

    InputError naming the file, the table row or the recipe key: a regex that matches no
    file, a frame index out of range, a row whose file is missing, two files claiming one
    subject and frame.
    """
    root = _require_dir(root)
    unknown = sorted(set(labels) - set(STRUCTURES))
    if unknown:
        raise InputError(f"labels: unknown structure names {unknown}; known: {sorted(STRUCTURES)}")
    table = {int(v): k for k, v in labels.items()}
    phases = dict(phases or {})
    if frame_table:
        table_path = Path(frame_table) if Path(frame_table).is_absolute() else root / frame_table
        if not table_path.is_file():
            raise InputError(f"frame_table: {table_path} not found")
        claims = read_frame_table(table_path, root)
    else:
        nifti = sorted(p for p in root.rglob("*.nii*") if p.name.endswith((".nii", ".nii.gz")))
        if not nifti:
            raise InputError(f"{root}: no *.nii or *.nii.gz files found")
        if pattern:
            chosen = [p for p in nifti if p.match(pattern)]
            skipped = {p: f"name does not match {pattern!r}" for p in nifti if p not in chosen}
        elif regex:
            chosen, skipped = nifti, {}
        else:
            skipped = {p: why for p in nifti if (why := label_map_verdict(p))}
            chosen = [p for p in nifti if p not in skipped]
        if regex:
            claims, unmatched = _regex_claims(chosen, root, regex)
            skipped.update({p: f"path not matched by regex {regex!r}" for p in unmatched})
            if not claims:
                first = chosen[0].relative_to(root).as_posix() if chosen else "(none)"
                raise InputError(f"regex: {regex!r} matches none of the {len(chosen)} label map(s) under {root} "
                                 f"(searched in each relative path, e.g. {first!r})")
        else:
            claims = [_Claim(p, re.sub(r"\.nii(\.gz)?$", "", str(p.relative_to(root))).replace("/", "_"), where=str(p))
                      for p in chosen]
        if skipped:
            listed = "; ".join(f"{p.relative_to(root)} ({why})" for p, why in skipped.items())
            warnings.warn(f"{root}: skipped {len(skipped)} file(s) that are not label maps: {listed}", InputWarning, stacklevel=2)
        if not claims:
            raise InputError(f"{root}: none of the {len(nifti)} *.nii / *.nii.gz files is a label map (see the warning)")
    subjects = sorted({c.subject for c in claims})
    if limit is not None:
        keep = set(subjects[:limit])
        claims = [c for c in claims if c.subject in keep]
    items = _expand(claims, source, table, phases, provenance or "annotated")
    # Subjects in the order their first file comes (path order for a folder), frames in order within each.
    first = {}
    for li in items:
        first.setdefault(li.subject, len(first))
    order = {"ED": 0, "ES": 1, "": 2}
    items.sort(key=lambda li: (first[li.subject], li.frame is None, li.frame or 0, order[li.phase], li.path))
    check_frames(items, f"[[sources]] {source}" + (f" (frame_table {frame_table})" if frame_table else
                                                    f" (regex {regex!r})" if regex else ""))
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
