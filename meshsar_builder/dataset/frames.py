"""Frames of real cine layouts: which subject, frame and phase each file (or 4-D T index) holds,
from a regular expression over the file's path or a CSV table, with named errors for what cannot be.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass, field
from pathlib import Path


from meshsar_builder.pipeline.errors import InputError

from meshsar_builder.dataset.label_maps import LabelItem, item_id, n_frames


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



@dataclass
class Claim:
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


def read_frame_table(path: Path, root: Path) -> list[Claim]:
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
        claims.append(Claim(
            file, row["subject"], _frame_number(row.get("frame"), where), _phase_name(row.get("phase"), where), prov,
            {h: v for h, v in row.items() if h not in ("file", "subject", "frame", "phase", "provenance")},
            where=where,
        ))
    return claims


def regex_claims(files: list[Path], root: Path, regex: str) -> tuple[list[Claim], list[Path]]:
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
        claims.append(Claim(f, groups["subject"], _frame_number(groups.get("frame"), where),
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


def expand_claims(claims: list[Claim], source: str, table: dict[int, str], phases: dict[str, int],
            provenance: str) -> list[LabelItem]:
    """One item per 3-D file, one per frame (T index) of a 4-D file; InputError for a frame out of range,
    a 4-D file whose name claims a frame or phase, or one file claimed by two subjects."""
    by_file: dict[Path, list[Claim]] = {}
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
        chosen: dict[int, Claim] = {}
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


def source_cohorts(sources) -> dict[str, str]:
    """{source name: cohort} of the recipe's sources that declare one (they share subject names)."""
    return {s.name: s.cohort for s in sources if getattr(s, "cohort", "")}


def direct_meshes(remeshed: dict[str, dict], cohorts: dict[str, str] | None = None) -> dict[str, dict]:
    """The remesh records of sources with `use = "direct"` (every frame goes to the dataset), each frame of a
    cohort's subject once.

    cohorts : {source: cohort} (source_cohorts). Where sources of one cohort give one subject's frame (one
    frame number) twice, the annotated map is kept over a predicted one, and its record names the other
    (`replaces`); two annotated maps of one frame, or one phase (ED, ES) at two frame numbers (the sources
    number frames differently), are an InputError naming both."""
    direct = {mid: rec for mid, rec in remeshed.items() if rec["use"] == "direct"}
    claims: dict[tuple, list[str]] = {}
    for mid in sorted(direct):
        rec = direct[mid]
        cohort = (cohorts or {}).get(rec["source"])
        if cohort and rec["frame"] is not None:
            claims.setdefault((cohort, rec["subject"], "frame", rec["frame"]), []).append(mid)
            if rec["phase"]:
                claims.setdefault((cohort, rec["subject"], "phase", rec["phase"]), []).append(mid)
    for (cohort, subject, kind, value), mids in claims.items():
        if kind == "phase" and len({direct[m]["frame"] for m in mids}) > 1:
            frames = ", ".join(f"{direct[m]['source']} frame {direct[m]['frame']} ({m})" for m in mids)
            raise InputError(f"cohort {cohort!r}: subject {subject!r} has its {value} frame at {frames}: the cohort's "
                             f"sources must number one subject's frames alike (a 4-D map's by T index, from 0)")
    for (cohort, subject, kind, value), mids in claims.items():
        if kind == "frame" and len(mids) > 1:
            annotated = [m for m in mids if direct[m]["provenance"] != "predicted"]
            if len(annotated) > 1:
                raise InputError(f"cohort {cohort!r}: {' and '.join(annotated)} both give subject {subject!r} frame "
                                 f"{value}, neither predicted")
            keep = annotated[0] if annotated else mids[0]
            direct[keep] = {**direct[keep], "replaces": [m for m in mids if m != keep]}
            for m in mids:
                if m != keep:
                    direct.pop(m)
    return direct


def subject_series(records: dict[str, dict], cohorts: dict[str, str] | None = None) -> list[tuple[list[str], str]]:
    """The frames of every subject in cycle order, and its reference frame.

    records : {item id: sidecar with source, subject, frame, phase}; cohorts : {source: cohort}
    for sources that share subject names (annotated and predicted frames of one patient). A
    subject is (cohort or source, subject). Cycle order: by frame number as the source numbers
    frames, frames known by phase only after them (ED before ES). The reference is the ED frame,
    else the first. Returns [(item ids in cycle order, reference id)], subjects in a fixed order.
    """
    subjects: dict[tuple, list[str]] = {}
    for mid, rec in records.items():
        subjects.setdefault(((cohorts or {}).get(rec["source"], rec["source"]), rec["subject"]), []).append(mid)
    out = []
    for key in sorted(subjects):
        mids = sorted(subjects[key], key=lambda mid: _cycle_rank(records[mid], mid))
        reference = min(mids, key=lambda mid: (records[mid]["phase"] != "ED", _cycle_rank(records[mid], mid)))
        out.append((mids, reference))
    return out


def merge_cycles(records) -> list[dict]:
    """The track stage's records (one per chain of a subject, stages/track.py) joined per subject.

    Returns per subject, in reference order, {reference, cycle, frames: {frame: report} in
    cycle order, in_correspondence: frames in cycle order}.
    """
    subjects: dict[str, dict] = {}
    for rec in records:
        merged = subjects.setdefault(rec["reference"], {"reference": rec["reference"], "cycle": rec["cycle"],
                                                        "frames": {}, "in_correspondence": []})
        merged["frames"] |= rec["frames"]
        merged["in_correspondence"] += rec["in_correspondence"]
    for merged in subjects.values():
        rank = {mid: i for i, mid in enumerate(merged["cycle"])}
        merged["frames"] = dict(sorted(merged["frames"].items(), key=lambda kv: rank[kv[0]]))
        merged["in_correspondence"] = sorted(merged["in_correspondence"], key=rank.__getitem__)
    return [subjects[ref] for ref in sorted(subjects)]


def _cycle_rank(rec: dict, mid: str) -> tuple:
    return rec["frame"] is None, rec["frame"] if rec["frame"] is not None else 0, rec["phase"] != "ED", mid

