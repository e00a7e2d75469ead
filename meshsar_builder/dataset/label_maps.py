"""Reading label maps: NIfTI files (3-D, or 4-D one frame at a time) in canonical RAS with canonical
structure ids, and the label-map item a stage meshes.
"""

from __future__ import annotations

import gzip
import re
import warnings
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import nibabel as nib
import numpy as np

from meshsar_builder.geometry.structures import STRUCTURES
from meshsar_builder.pipeline.errors import InputError

# Refuse volumes whose header declares more voxels than this before reading any data.
MAX_VOXELS = 1024**3 // 2
# Float label maps (resampled, or written by tools that store floats) are rounded when every
# value is this close to an integer; farther off, it is a probability map or an image.
ROUND_TOLERANCE = 1e-3
# A label map has a few dozen values at most; an intensity image (CT, MR) has thousands.
MAX_LABEL_VALUES = 256
# An 8-bit image has at most 256 values too; its texture tells it apart (image_like): a label map's regions are
# uniform, so along its finest axis few neighbouring voxels differ (0.07-0.13 of the pairs not both background in
# two real CT maps and ACDC-style maps), where an image's noise makes most of them differ.
IMAGE_VALUES = 32
GZIP_CHUNK = 16 << 20  # bytes decompressed at a time to check a .gz file's CRC
IMAGE_TEXTURE = 0.5


class InputWarning(UserWarning):
    """A usable input with something the user should know (unmapped labels, no spatial header)."""


def warning_messages(caught: list[warnings.WarningMessage], category: type[Warning] = InputWarning) -> list[str]:
    """The texts of `category` among recorded warnings, for a stage's sidecar (the user reads them there)."""
    return [str(w.message) for w in caught if issubclass(w.category, category)]


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


def failed_item(source: str, subject: str, path: str | Path, error: Exception | str) -> LabelItem:
    """An item for what a source's index could not use (path and why, in extra["index_error"]): the meshes stage
    raises its error, so failures.json names it while the rest of the source builds."""
    return LabelItem(item_id(source, f"{subject}-{Path(path).name}"), source, str(path), subject, {},
                     extra={"index_error": str(error)})


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


def voxel_affine(path: Path, img: nib.Nifti1Image) -> np.ndarray:
    """The voxel -> world affine (4, 4) of a NIfTI header, its voxel size from pixdim.

    Where the sform/qform's voxel size disagrees with pixdim (by more than 0.1 %), pixdim
    gives the spacing and the affine the orientation and origin, as ITK reads every NIfTI
    file, with a warning naming the file and both sizes. Real ACDC files carry an sform of
    unit voxels (diag(-1, -1, 1)) beside pixdim 1.37 x 1.37 x 10 mm: read by the sform, a
    heart is a 7-16 mm high disc.
    """
    affine = np.asarray(img.affine, dtype=np.float64)
    pixdim = np.asarray(img.header.get_zooms()[:3], dtype=np.float64)
    columns = np.linalg.norm(affine[:3, :3], axis=0)
    if np.all(pixdim > 0) and np.all(np.isfinite(pixdim)) and np.any(np.abs(columns / pixdim - 1) > 1e-3):
        warnings.warn(
            f"{path}: the affine's voxel size {np.round(columns, 4).tolist()} mm disagrees with the header's pixdim "
            f"{np.round(pixdim, 4).tolist()} mm; pixdim gives the spacing, the affine the orientation and origin "
            f"(as ITK reads it)", InputWarning, stacklevel=3)
        affine = affine.copy()
        affine[:3, :3] = affine[:3, :3] / columns * pixdim
    return affine


def _load_data(path: Path, img: nib.Nifti1Image, t: int | None = None) -> tuple[nib.Nifti1Image, np.ndarray]:
    """The image (its frame `t` when 4-D, the affine of voxel_affine) reoriented to closest
    canonical RAS and its voxel data; InputError when corrupt."""
    affine = voxel_affine(path, img)
    try:
        if path.name.endswith(".gz"):
            # Decompress the whole stream: gzip checks its CRC and length, so a truncated file
            # fails here even when the bytes the image needs happen to come before the cut. In
            # chunks: a 4-D CT's frame read whole held the file's every frame (2.0 GB for 8).
            with gzip.open(path) as stream:
                while stream.read(GZIP_CHUNK):
                    pass
        img = type(img)(img.dataobj, affine, img.header)
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
    values, or an image's texture (image_like: an 8-bit image)."""
    path = Path(path)
    try:
        img, _ = _read_header(path)  # refuses oversized headers before any data is read
        data = np.asanyarray(img.dataobj[..., 0] if len(img.shape) == 4 else img.dataobj)  # a 4-D map: its first frame
    except Exception:  # noqa: BLE001 (any unreadable file stays indexed: read_label_map names its problem)
        return ""
    n = len(np.unique(data))
    return f"{n} distinct values, an image rather than a label map" if n > MAX_LABEL_VALUES else image_like(data, n)


def image_like(data: np.ndarray, count: int) -> str:
    """Why a volume (X, Y, Z[, T]) of `count` distinct values is an image, not a label map ('' when it may be one):
    more than IMAGE_VALUES values, and along every axis more than IMAGE_TEXTURE of the neighbouring voxel pairs (not
    both 0) differ."""
    if count <= IMAGE_VALUES:
        return ""
    shares = []
    for axis in range(3):
        a, b = np.moveaxis(data, axis, 0)[:-1], np.moveaxis(data, axis, 0)[1:]
        either = np.count_nonzero((a != 0) | (b != 0))
        shares.append(np.count_nonzero(a != b) / either if either else 0.0)
    if min(shares) <= IMAGE_TEXTURE:
        return ""
    return (f"{count} distinct values that vary from voxel to voxel (along every axis at least "
            f"{min(shares):.0%} of neighbouring voxels differ, where a label map's regions are uniform): an image "
            f"rather than a label map")


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
    # In the file's own type (no int64 copy): a 512 x 512 x 248 CT frame's mapping took 1.7 GB in int64.
    present, counts = np.unique(data, return_counts=True)
    present = present.astype(np.int64)
    why = image_like(data, len(present))
    if why:
        raise InputError(f"{path}: {why}")
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
    labels = np.zeros(data.shape, dtype=np.uint8)
    found = np.isin(lut_keys, present)
    for key, value in zip(lut_keys[found], lut_vals[found]):
        labels[data == key] = value
    return labels, np.asarray(img.affine, dtype=np.float64)

