"""Groupwise template: the Procrustes mean of the fitted subjects, kept a clean mesh, in a canonical frame.

One subject as the template biases every correspondence towards its shape (DESIGN section 6).
After a first registration to the reference subject, the template is replaced by the
generalised Procrustes mean of the fits (they share its faces, so the mean is a mesh with
the template's connectivity and vertex labels) and everyone is registered again, for up to
`groupwise_rounds` rounds or until the template moves less than `groupwise_converge_mm`.

The mean is put in a canonical frame that no subject's place in the list decides: rotated
to the subjects' population pose (ssm.population_pose: the pose closest to where all of
them lie in the scanner's RAS frame) and centred on its bounding box (the heart frame of
DESIGN section 3). A plain mean of clean meshes can still fold where thin parts (vessels)
disagree between subjects, so it is Taubin-smoothed, a step at a time, until no face
intersects another or turned over against the previous template.

The register stage runs the rounds as passes of parallel items (stages/register.py: a plan
and a per-item call); the files of those rounds are made here (seed_template,
groupwise_template, publish, fit_subject, write_report). register_groupwise here is the same
procedure in one process (bench, tests).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from threadpoolctl import threadpool_limits

from meshsar_builder.geometry.intersections import self_intersecting_faces
from meshsar_builder.geometry.measures import flipped_faces
from meshsar_builder.geometry.meshfile import read_ply, write_ply
from meshsar_builder.geometry.meshing import transfer_labels
from meshsar_builder.geometry.registration import accept, choose_template, register
from meshsar_builder.geometry.registration_params import RegistrationParams
from meshsar_builder.geometry.remesh import simplify
from meshsar_builder.geometry.ssm import procrustes_align, rigid_fit
from meshsar_builder.pipeline.errors import MeshError
from meshsar_builder.pipeline.io import read_json, sha256_file, write_bytes, write_json

# Taubin's lambda|mu pair of the remesh stage: a low-pass filter that barely shrinks.
TAUBIN_LAMBDA, TAUBIN_MU = 0.5, -0.53
# The template is a mean of ~10-100 shapes, not a statistical model: GPA converges in a few
# iterations; this bound only stops a pathological input.
PROCRUSTES_ITERATIONS = 100


def _umbrella(faces: np.ndarray, n: int) -> sp.csr_matrix:
    """(n, n) uniform Laplacian L = D^-1 A - I of the mesh's vertex graph."""
    edges = np.asarray(faces)[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    adjacency = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n)).tocsr()
    adjacency = ((adjacency + adjacency.T) > 0).astype(np.float64)
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    return (sp.diags(1.0 / np.maximum(degree, 1.0)) @ adjacency - sp.identity(n)).tocsr()


def taubin(verts: np.ndarray, faces: np.ndarray, steps: int) -> np.ndarray:
    """verts (n, 3) after `steps` Taubin steps (a lambda then a mu umbrella step each) -> (n, 3)."""
    laplacian = _umbrella(faces, len(verts))
    verts = np.array(verts, dtype=np.float64)
    for _ in range(steps):
        verts = verts + TAUBIN_LAMBDA * (laplacian @ verts)
        verts = verts + TAUBIN_MU * (laplacian @ verts)
    return verts


def bbox_centred(verts: np.ndarray) -> np.ndarray:
    """verts (n, 3) moved so their bounding box is centred on the origin (DESIGN section 3)."""
    return verts - 0.5 * (verts.min(axis=0) + verts.max(axis=0))


def movement(previous: np.ndarray, verts: np.ndarray) -> tuple[float, float]:
    """Mean and largest vertex displacement (mm) from `previous` (n, 3), rigidly fitted first,
    to `verts` (n, 3): how much the template's shape changed, whatever its pose."""
    step = np.linalg.norm(verts - rigid_fit(previous, verts), axis=1)
    return float(step.mean()), float(step.max())


def fit_distances(fits: np.ndarray, verts: np.ndarray) -> np.ndarray:
    """(s,) mean vertex distance (mm) of each fit (s, n, 3), rigidly fitted to `verts` (n, 3), from it."""
    return np.array([np.linalg.norm(rigid_fit(fit, verts) - verts, axis=1).mean() for fit in fits])


def mean_template(
    fits: np.ndarray, faces: np.ndarray, previous: np.ndarray, max_smoothing: int,
    max_distance_mm: float | None = None,
) -> tuple[np.ndarray, dict]:
    """The groupwise template of one round.

    fits : (s >= 2, n, 3) float mm, the previous template fitted to each subject (its faces);
    faces : (m, 3) int; previous : (n, 3) float mm, the template they were fitted to.
    Returns the template vertices (n, 3) in the canonical frame (module docstring) and a
    JSON-ready report: subjects, movement_mm and movement_max_mm (from `previous`, see
    movement), smoothing_steps, and the plain mean's self_intersections and flipped_faces.
    Raises MeshError when max_smoothing Taubin steps leave faces intersecting or flipped.
    With max_distance_mm, the template is checked against the fits it averages before it is
    used: a fit whose mean vertex distance from the mean (rigidly fitted) exceeds it is left
    out and the mean made again without it (report: distance_to_fits_mm, each fit's distance
    from the final template; left_out, the indices left out); fewer than 2 left raises.
    """
    fits = np.asarray(fits, dtype=np.float64)
    if fits.ndim != 3 or len(fits) < 2:
        raise MeshError(f"groupwise template: needs the fits of at least 2 subjects, got {len(fits)}")
    kept = np.arange(len(fits))
    _, mean = procrustes_align(fits, PROCRUSTES_ITERATIONS)
    if max_distance_mm is not None:
        far = fit_distances(fits, mean) > max_distance_mm
        if far.any():
            kept = np.flatnonzero(~far)
            if len(kept) < 2:
                raise MeshError(
                    f"groupwise template: {int(far.sum())} of {len(fits)} fits lie farther than "
                    f"{max_distance_mm} mm (groupwise_max_distance_mm) from their mean: "
                    + ", ".join(f"{d:.1f}" for d in fit_distances(fits, mean)) + " mm")
            _, mean = procrustes_align(fits[kept], PROCRUSTES_ITERATIONS)
    plain = bbox_centred(mean)
    before = rigid_fit(np.asarray(previous, dtype=np.float64), plain)
    verts, report = plain, {"subjects": len(fits)}
    for steps in range(max_smoothing + 1):
        if steps:
            # Smoothing moves the box a little; the frame stays the bounding-box-centred one.
            verts = bbox_centred(taubin(plain, faces, steps))
        crossing = int(self_intersecting_faces(verts, faces).sum())
        flipped = int(flipped_faces(before, verts, faces).sum())
        if steps == 0:
            report |= {"self_intersections": crossing, "flipped_faces": flipped}
        if not crossing and not flipped:
            break
    else:
        raise MeshError(
            f"groupwise template: {crossing} self-intersecting and {flipped} flipped faces remain "
            f"after {max_smoothing} Taubin steps (groupwise_smoothing)"
        )
    moved_mean, moved_max = movement(previous, verts)
    report |= {"smoothing_steps": steps, "movement_mm": moved_mean, "movement_max_mm": moved_max}
    if max_distance_mm is not None:
        report |= {"distance_to_fits_mm": [round(float(d), 4) for d in fit_distances(fits, verts)],
                   "left_out": [int(i) for i in np.setdiff1d(np.arange(len(fits)), kept)]}
    return verts, report


def final_round(round_: int, moved_mm: float | None, params: RegistrationParams) -> bool:
    """Whether the registrations of `round_` (0: to the reference subject) are the last:
    the round limit is reached, or this round's template moved less than the tolerance."""
    if round_ >= params.groupwise_rounds:
        return True
    return round_ >= 1 and moved_mm is not None and moved_mm < params.groupwise_converge_mm


def round_params(params: RegistrationParams, final: bool) -> RegistrationParams:
    """The registration parameters of a round's fits: a round before the last makes only the
    next template, so its fits run round_coarse_steps of the schedule coarse."""
    return params if final else dataclasses.replace(params, coarse_steps=params.round_coarse_steps)


def register_groupwise(
    template: tuple[np.ndarray, np.ndarray, np.ndarray],
    subjects: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
    params: RegistrationParams,
    rng: Callable[[int, int], np.random.Generator],
) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """The register stage's rounds in one process, for benches and tests.

    template : (verts (n, 3), faces (m, 3), labels (n,)) the reference subject's template;
    subjects : (verts (p, 3), faces (q, 3), labels (p,)) per subject; rng(round, subject index).
    Returns the final fits (s, n, 3), the templates of every round (rounds, n, 3; the last
    is the one the final fits were fitted to) and one record per round: round, its
    template's movement (None for round 0), seconds per subject, the fits' reports, and
    next_template (mean_template's report) unless it is the last. A rejected fit raises
    (registration.accept; label agreement is judged in the last round, as in the stage).
    """
    t_verts, t_faces, t_labels = template
    rounds, templates, moved, round_ = [], [t_verts], None, 0
    while True:
        record, fits, reports = {"round": round_, "movement_mm": moved}, [], []
        t0 = time.perf_counter()
        final = final_round(round_, moved, params)
        fit_params = round_params(params, final)
        for index, (verts, faces, labels) in enumerate(subjects):
            fitted, report = register(t_verts, t_faces, verts, faces, fit_params, rng(round_, index), t_labels, labels)
            try:
                accept(report, params, correspondence=final)
            except MeshError as error:
                raise MeshError(f"subject {index}, round {round_}: {error}") from error
            fits.append(fitted)
            reports.append(report)
        record |= {"seconds_per_subject": (time.perf_counter() - t0) / len(subjects), "fits": reports}
        rounds.append(record)
        if final:
            return np.stack(fits), np.stack(templates), rounds
        t_verts, summary = mean_template(np.stack(fits), t_faces, t_verts, params.groupwise_smoothing,
                                         params.groupwise_max_distance_mm)
        templates.append(t_verts)
        moved, round_ = summary["movement_mm"], round_ + 1
        rounds[-1]["next_template"] = summary


def resolve_template(name: str, subjects: dict[str, dict]) -> str:
    """`median`, an item id, or a subject name (as in the source) -> item id."""
    if name == "median" or name in subjects:
        return name
    matches = [i for i, rec in subjects.items() if rec["subject"] == name]
    if len(matches) != 1:
        raise MeshError(f"registration.template: {name!r} names {len(matches)} of the registered subjects")
    return matches[0]


def _current(meta, want: dict) -> bool:
    return meta.exists() and {k: read_json(meta).get(k) for k in want} == want


def seed_template(folder: Path, remeshed: Path, subjects: Mapping[str, dict], params: RegistrationParams) -> str:
    """Write <folder>/template-0.ply (the reference subject, from the remeshed surfaces in
    `remeshed`; subjects: remesh records by item id) unless it is up to date; return its path."""
    volumes = {i: rec["volume_ml"] for i, rec in subjects.items()}
    chosen = choose_template(volumes, resolve_template(params.template, subjects))
    source = remeshed / f"{chosen}.ply"
    want = {"round": 0, "subject": chosen, "source_sha256": sha256_file(source),
            "template_vertices": params.template_vertices}
    path, meta = folder / "template-0.ply", folder / "template-0.json"
    if path.exists() and _current(meta, want):
        return str(path)
    verts, faces, labels = read_ply(source)
    t_verts, t_faces = simplify(verts, faces, params.template_vertices)
    write_ply(path, t_verts, t_faces, transfer_labels(verts, labels, t_verts))
    write_json(meta, {**want, "n_vertices": len(t_verts), "n_faces": len(t_faces), "volumes_ml": volumes})
    return str(path)


def groupwise_template(folder: Path, round_: int, fits: Mapping[str, dict], params: RegistrationParams) -> tuple[str, float]:
    """Write <folder>/template-<round_>.ply, the mean of the previous round's fits (records by
    item id), unless it is up to date; return its path and its movement from the previous one (mm).
    The mean is checked against the fits it averages (mean_template's max_distance_mm)."""
    previous = folder / f"template-{round_ - 1}.ply"
    want = {"round": round_, "previous_sha256": sha256_file(previous),
            "fits": {i: rec["outputs"][f"{i}.ply"] for i, rec in fits.items()},
            "smoothing": params.groupwise_smoothing, "max_distance_mm": params.groupwise_max_distance_mm}
    path, meta = folder / f"template-{round_}.ply", folder / f"template-{round_}.json"
    if path.exists() and _current(meta, want):
        return str(path), read_json(meta)["movement_mm"]
    t_verts, t_faces, t_labels = read_ply(previous)
    shapes = np.stack([read_ply(folder / f"{i}.ply")[0] for i in fits])
    verts, report = mean_template(shapes, t_faces, t_verts, params.groupwise_smoothing, params.groupwise_max_distance_mm)
    ids = list(fits)
    report["left_out"] = [ids[k] for k in report["left_out"]]
    report["distance_to_fits_mm"] = dict(zip(ids, report["distance_to_fits_mm"]))
    write_ply(path, verts, t_faces, t_labels)
    write_json(meta, {**want, **report})
    return str(path), report["movement_mm"]


def publish(folder: Path, template: str, round_: int) -> None:
    """<folder>/template.ply: the last round's template (only rewritten when it changed)."""
    data = Path(template).read_bytes()
    path = folder / "template.ply"
    if not path.exists() or path.read_bytes() != data:
        write_bytes(path, data)
    write_json(folder / "template.json", {**read_json(f"{template[:-4]}.json"), "round": round_,
                                          "template": f"template-{round_}.ply"})


def fit_subject(subject_path: str, template_path: str, out_path: Path, params: RegistrationParams,
                rng: np.random.Generator, final: bool) -> dict:
    """One item of a round: register the template at template_path to the subject surface at
    subject_path, judge it (accept; label agreement only when `final`), write the fit (the
    template's faces and labels on the fitted vertices) to out_path; return the fit's report."""
    s_verts, s_faces, s_labels = read_ply(subject_path)
    t_verts, t_faces, t_labels = read_ply(template_path)
    fitted, report = register(t_verts, t_faces, s_verts, s_faces, round_params(params, final), rng, t_labels, s_labels)
    accept(report, params, correspondence=final)
    write_ply(out_path, fitted, t_faces, t_labels)
    return report


def _round_summary(records: list[dict], planned: int) -> dict:
    fits = [rec["fit"] for rec in records]
    structures = sorted({s for f in fits for s in f.get("label_agreement_by_structure", {})})
    by_structure = {s: [f["label_agreement_by_structure"][s] for f in fits if s in f.get("label_agreement_by_structure", {})]
                    for s in structures}
    return {
        "registered": len(records),
        "failed": planned - len(records),
        "fit_mean_mm": float(np.mean([f["mean_mm"] for f in fits])) if fits else None,
        "fit_p95_mm": float(np.mean([f["p95_mm"] for f in fits])) if fits else None,
        # Mean over subjects, and the worst subject, per structure.
        "label_agreement_by_structure": {s: float(np.mean(v)) for s, v in by_structure.items()},
        "least_label_agreement_by_structure": {s: float(np.min(v)) for s, v in by_structure.items()},
        "seconds_per_subject": float(np.mean([rec["seconds"] for rec in records])) if records else None,
    }


def write_report(folder: Path, records: Mapping[str, dict], planned: int, params: RegistrationParams) -> None:
    """After the last round: <folder>/groupwise.json, one entry per round (template movement,
    smoothing, fits accepted, their distances, label agreement and time), from the last round's
    item records (by item id) and the sidecars of earlier rounds; `planned`: subjects registered.

    Also how far the last round's own mean lies from the template it was fitted to (the
    movement the next round would have had), so convergence can be judged.
    """
    last = next(iter(records.values()))["round"]
    rounds = []
    for r in range(last + 1):
        meta = read_json(folder / f"template-{r}.json")
        if r < last:  # the fits the next template was made of: this round's accepted ones
            done = [read_json(folder / f"{i}.json") for i in read_json(folder / f"template-{r + 1}.json")["fits"]]
        else:
            done = list(records.values())
        entry = {"round": r, "template": f"template-{r}.ply", "template_sha256": sha256_file(folder / f"template-{r}.ply")}
        if r:
            entry |= {k: meta[k] for k in ("movement_mm", "movement_max_mm", "smoothing_steps",
                                           "self_intersections", "flipped_faces")}
        rounds.append(entry | _round_summary(done, planned))
    residual = None
    if len(records) >= 2:
        t_verts, t_faces, _ = read_ply(folder / f"template-{last}.ply")
        try:
            with threadpool_limits(limits=1):
                _, report = mean_template(np.stack([read_ply(folder / f"{i}.ply")[0] for i in records]), t_faces,
                                          t_verts, params.groupwise_smoothing)
            residual = {k: report[k] for k in ("movement_mm", "movement_max_mm")}
        except MeshError as e:  # a report only: the fits stand
            residual = {"error": str(e)}
    write_json(folder / "groupwise.json", {"rounds": rounds, "last_round": last, "next_round_movement": residual,
                                           "converge_mm": params.groupwise_converge_mm,
                                           "max_rounds": params.groupwise_rounds})
