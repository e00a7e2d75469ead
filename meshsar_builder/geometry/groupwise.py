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

The register stage runs the rounds as passes of parallel items (stages/register.py);
register_groupwise here is the same procedure in one process (bench, tests).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np
import scipy.sparse as sp

from meshsar_builder.geometry.nricp import flipped_faces
from meshsar_builder.geometry.registration import accept, register
from meshsar_builder.geometry.registration_params import RegistrationParams
from meshsar_builder.geometry.remesh import self_intersecting_faces
from meshsar_builder.geometry.ssm import procrustes_align, rigid_fit
from meshsar_builder.pipeline.errors import MeshError

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
        for index, (verts, faces, labels) in enumerate(subjects):
            fitted, report = register(t_verts, t_faces, verts, faces, params, rng(round_, index), t_labels, labels)
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
