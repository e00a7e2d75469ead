"""Label-map sources: fixed label tables, NIfTI reading in canonical RAS, and folder indexers.

Every source's labels map into one canonical structure table, so per-vertex
labels mean the same thing whatever dataset a mesh came from. Tables are fixed,
never derived from the sorted values found in a file.
"""

from __future__ import annotations

import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

from meshsar_builder.dataset.frames import (
    PHASES,
    Claim,
    check_frames,
    compile_frame_regex,
    expand_claims,
    read_frame_table,
    regex_claims,
)
from meshsar_builder.dataset.label_maps import (
    InputWarning,
    LabelItem,
    failed_item,
    item_id,
    label_map_verdict,
    n_frames,
)
from meshsar_builder.geometry.structures import STRUCTURES
from meshsar_builder.pipeline.errors import InputError, RecipeError
from meshsar_builder.pipeline.recipe import NAME_RE

# MM-WHS: 421 occurs in some files for the left atrium.
MMWHS_TABLE: dict[int, str] = {
    205: "myo", 420: "la", 421: "la", 500: "lv", 550: "ra", 600: "rv", 820: "aorta", 850: "pa",
}
ACDC_TABLE: dict[int, str] = {1: "rv", 2: "myo", 3: "lv"}
# ACDC: 4-D label maps predicted for every frame, per patient folder, where present.
ACDC_PREDICTED = "{subject}_4d_pred.nii*"
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

    What cannot be indexed (a patient's Info.cfg without ED or ES, `_gt` frames in a folder
    without one, an unreadable or inconsistent predicted map) becomes a failed_item, so the
    build names it in failures.json and goes on with the rest. Info.cfg is found in any case.
    """
    root = _require_dir(root)
    infos = [p for p in root.rglob(f"{subject}/*") if p.name.lower() == "info.cfg" and p.is_file()]
    with_info = {p.parent for p in infos}
    orphans: dict[Path, Path] = {}  # a folder of _gt frames without Info.cfg: its first frame
    for frame in sorted(root.rglob(f"{subject}/*_frame[0-9][0-9]_gt.nii*")):
        if frame.parent not in with_info:
            orphans.setdefault(frame.parent, frame)
    info_of = {p.parent: p for p in infos}
    folders = _first_n(list(info_of) + list(orphans), limit)  # `limit` patients, with an Info.cfg or not
    if not folders:
        raise InputError(f"{root}: no ACDC patient folders (patientNNN/Info.cfg) found")
    items = []
    for pdir in folders:
        if pdir not in info_of:
            items.append(failed_item(source, pdir.name, orphans[pdir],
                                     f"{pdir}: _gt frames but no Info.cfg, so ED and ES are unknown"))
            continue
        try:
            items += _acdc_patient(pdir, parse_info_cfg(info_of[pdir]), source, provenance, predicted)
        except InputError as error:
            items.append(failed_item(source, pdir.name, info_of[pdir], error))
    return items


def _acdc_patient(pdir: Path, info: dict[str, str], source: str, provenance: str | None,
                  predicted: str) -> list[LabelItem]:
    """The items of one ACDC patient folder (index_acdc), a failed_item for each predicted map it cannot use."""
    ed, es = int(info["ED"]), int(info["ES"])
    nb = int(info["NbFrame"]) if "NbFrame" in info else None
    extra = {"group": info.get("Group", ""), "n_frames": nb}
    frames = sorted(pdir.glob(f"{pdir.name}_frame[0-9][0-9]_gt.nii*"))
    pred_files = sorted(pdir.glob(predicted.replace("{subject}", pdir.name))) if predicted else []
    if not frames and not pred_files:
        also = f" nor predicted label maps ({predicted.replace('{subject}', pdir.name)})" if predicted else ""
        raise InputError(f"{pdir}: no *_frameYY_gt.nii.gz files{also}")
    found: dict[int, LabelItem] = {}
    failed = []

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
        try:
            pairs = _predicted_frames(f, nb, predicted, pdir.name)
            twice = [frame for frame, _ in pairs if frame in claimed]
            if twice:
                raise InputError(f"{f}: claims {pdir.name} frame {twice[0]}, which {claimed[twice[0]].name} also "
                                 f"claims")
        except InputError as error:
            failed.append(failed_item(source, pdir.name, f, error))
            continue
        for frame, t in pairs:
            claimed[frame] = f
            if frame not in annotated:
                add(frame, f, "predicted", t)
    return [found[k] for k in sorted(found)] + failed


def _predicted_frames(path: Path, nb: int | None, predicted: str, patient: str) -> list[tuple[int, int | None]]:
    """(ACDC frame, T index or None) of each frame a predicted label map holds; InputError when it cannot say."""
    T = n_frames(path)
    if T is None:
        m = re.search(r"frame(\d+)", path.name)
        if not m:
            raise InputError(f"{path}: a 3-D predicted label map (predicted = {predicted!r}) must name its frame "
                             f"(frameYY); a 4-D one holds one frame per T index")
        return [(int(m.group(1)), None)]
    if nb is not None and T != nb:
        raise InputError(f"{path}: {T} frames (T) in a predicted 4-D label map, but {patient}/Info.cfg has "
                         f"NbFrame: {nb}")
    return [(t + 1, t) for t in range(T)]


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
            claims, unmatched = regex_claims(chosen, root, regex)
            skipped.update({p: f"path not matched by regex {regex!r}" for p in unmatched})
            if not claims:
                first = chosen[0].relative_to(root).as_posix() if chosen else "(none)"
                raise InputError(f"regex: {regex!r} matches none of the {len(chosen)} label map(s) under {root} "
                                 f"(searched in each relative path, e.g. {first!r})")
        else:
            claims = [Claim(p, re.sub(r"\.nii(\.gz)?$", "", str(p.relative_to(root))).replace("/", "_"), where=str(p))
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
    items = expand_claims(claims, source, table, phases, provenance or "annotated")
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

