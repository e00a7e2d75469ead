"""Template registration: similarity pre-alignment, then non-rigid ICP (Amberg et al. 2007).

Every subject surface is fitted by the template mesh, so all fitted shapes share the
template's vertices and faces (point correspondence for the shape model). With structure
labels on both surfaces (DESIGN section 6), label landmarks (landmarks.py) give the
pre-alignment and, through a thin-plate spline, the start of the non-rigid fit, whose
matches then pair only points of one structure (nricp.py); a fit is accepted on its surface
distance, its folds and its per-structure label agreement (accept).
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Mapping

import numpy as np
import trimesh

from meshsar_builder.geometry.intersections import self_intersecting_faces
from meshsar_builder.geometry.landmarks import (
    common_landmarks,
    dropped_landmarks,
    face_labels,
    label_agreement,
    label_landmarks,
    landmark_warp,
)
from meshsar_builder.geometry.measures import flipped_faces
from meshsar_builder.geometry.closest import point_to_surface
from meshsar_builder.geometry.nricp import Subject, Surface, nricp
from meshsar_builder.geometry.registration_params import RegistrationParams
from meshsar_builder.geometry.remesh import require_valid
from meshsar_builder.pipeline.errors import MeshError


def choose_template(volumes: Mapping[str, float], template: str = "median") -> str:
    """The template subject: `template` itself if it is a subject id, else the median-volume subject.

    With an even number of subjects the lower of the two middle volumes is taken;
    equal volumes are ordered by subject id, so the choice never depends on input order.
    """
    if not volumes:
        raise ValueError("volumes: no subjects to choose a template from")
    if template != "median":
        if template not in volumes:
            raise ValueError(f"template: subject {template!r} is not among the {len(volumes)} subjects")
        return template
    ordered = sorted(volumes, key=lambda subject: (volumes[subject], subject))
    return ordered[(len(ordered) - 1) // 2]


def _mesh(verts: np.ndarray, faces: np.ndarray) -> trimesh.Trimesh:
    return trimesh.Trimesh(np.asarray(verts, dtype=np.float64), np.asarray(faces), process=False)


def surface_distances(
    verts_a: np.ndarray,
    faces_a: np.ndarray,
    verts_b: np.ndarray,
    faces_b: np.ndarray,
    n_samples: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Point-to-surface distances (mm) from area-weighted samples of each surface to the other.

    verts_* : (n, 3) float, faces_* : (m, 3) int  ->  (n_samples,) a-to-b, (n_samples,) b-to-a.
    """
    points_a, _ = trimesh.sample.sample_surface(_mesh(verts_a, faces_a), n_samples, seed=rng)
    points_b, _ = trimesh.sample.sample_surface(_mesh(verts_b, faces_b), n_samples, seed=rng)
    return point_to_surface(points_a, verts_b, faces_b)[0], point_to_surface(points_b, verts_a, faces_a)[0]


def _apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def _proper_axes(mesh: trimesh.Trimesh) -> np.ndarray:
    """Principal axes of the solid as the columns of a rotation matrix (det +1)."""
    axes = np.array(mesh.principal_inertia_vectors, dtype=np.float64).T
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1
    return axes


def prealign(
    moving_verts: np.ndarray,
    moving_faces: np.ndarray,
    fixed_verts: np.ndarray,
    fixed_faces: np.ndarray,
    params: RegistrationParams,
    rng: np.random.Generator,
    labels: tuple[np.ndarray, np.ndarray] | None = None,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """(4, 4) similarity (or rigid, params.similarity False) transform taking `moving` onto `fixed`.

    labels : (moving (n,), fixed (p,)) vertex labels or None; landmarks : (moving (k, 3),
    fixed (k, 3)) corresponding landmark points or None.
    With 3 or more landmarks, they give the start (their Procrustes fit), and the
    refinement fits label-aware closest points (each structure to itself) together with
    the landmarks, which weigh landmark_weight times the surface samples: the anatomy pins
    the pose, so a change of shape is not explained away by a rotation. Otherwise
    moments give the start: centroids of the solids, scale from the cube root of the
    volume ratio, and rotation either the identity (subjects in one anatomical frame)
    or one of the four proper matchings of the principal axes (sign ambiguity). Each
    start is refined by point-to-point ICP against dense samples of `fixed`; the start
    with the lowest ICP cost wins, and is refined once more against the exact surface.
    """
    if landmarks is not None and len(landmarks[0]) >= 3 and params.landmark_weight > 0:
        return _prealign_landmarks(moving_verts, moving_faces, fixed_verts, fixed_faces, params, rng, labels, landmarks)
    moving, fixed = _mesh(moving_verts, moving_faces), _mesh(fixed_verts, fixed_faces)
    scale = np.cbrt(fixed.volume / moving.volume) if params.similarity else 1.0
    moving_axes, fixed_axes = _proper_axes(moving), _proper_axes(fixed)
    rotations = [np.eye(3)] + [
        fixed_axes @ np.diag(signs) @ moving_axes.T
        for signs in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1))
    ]
    points, _ = trimesh.sample.sample_surface(moving, params.icp_points, seed=rng)
    targets, _ = trimesh.sample.sample_surface(fixed, 10 * params.icp_points, seed=rng)
    icp_options = {"reflection": False, "scale": params.similarity}
    best_cost, best = np.inf, np.eye(4)
    for rotation in rotations:
        start = np.eye(4)
        start[:3, :3] = scale * rotation
        start[:3, 3] = fixed.center_mass - scale * rotation @ moving.center_mass
        matrix, _, cost = trimesh.registration.icp(
            points, targets, initial=start, max_iterations=50, **icp_options
        )
        if cost < best_cost:
            best_cost, best = cost, matrix
    # Final refinement against the exact surface (closest points, not samples).
    surface, matrix, last_cost = Surface(np.asarray(fixed_verts, dtype=np.float64), np.asarray(fixed_faces)), best, np.inf
    for _ in range(20):
        moved = _apply(matrix, points)
        closest, _, _ = surface.closest(moved)
        step, _, cost = trimesh.registration.procrustes(moved, closest, **icp_options)
        matrix = step @ matrix
        if abs(last_cost - cost) < 1e-7:
            break
        last_cost = cost
    return matrix


def _prealign_landmarks(
    moving_verts: np.ndarray, moving_faces: np.ndarray, fixed_verts: np.ndarray, fixed_faces: np.ndarray,
    params: RegistrationParams, rng: np.random.Generator,
    labels: tuple[np.ndarray, np.ndarray] | None, landmarks: tuple[np.ndarray, np.ndarray],
) -> np.ndarray:
    """prealign() from landmarks: their Procrustes fit, refined with label-aware closest points."""
    options = {"reflection": False, "scale": params.similarity, "return_cost": False}
    moving_marks, fixed_marks = landmarks
    matrix = trimesh.registration.procrustes(moving_marks, fixed_marks, **options)
    points, face = trimesh.sample.sample_surface(_mesh(moving_verts, moving_faces), params.icp_points, seed=rng)
    point_labels = None if labels is None else face_labels(np.asarray(moving_faces), labels[0])[face]
    subject = Subject(np.asarray(fixed_verts, dtype=np.float64), np.asarray(fixed_faces),
                       None if labels is None else np.asarray(labels[1]), point_labels)
    both = np.r_[points, moving_marks]
    weights = np.r_[np.ones(len(points)), np.full(len(moving_marks), params.landmark_weight * len(points) / len(moving_marks))]
    for _ in range(30):
        closest, _, _ = subject.closest(_apply(matrix, points))
        new = trimesh.registration.procrustes(both, np.r_[closest, fixed_marks], weights=weights, **options)
        moved = np.abs(_apply(new, both) - _apply(matrix, both)).max()
        matrix = new
        if moved < 1e-4:
            break
    return matrix


# Least ratio of the smallest to the largest singular value of the centred landmarks that
# steer the spline start: below it they are nearly coplanar and the spline is not used.
SPLINE_MIN_SPREAD = 0.2


def _spread(points: np.ndarray) -> float:
    values = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return float(values[-1] / max(values[0], 1e-12))


def _check_start(
    aligned: np.ndarray, start: np.ndarray, faces: np.ndarray, subject_verts: np.ndarray, subject_faces: np.ndarray,
    params: RegistrationParams,
) -> tuple[np.ndarray | None, dict]:
    """The spline's start of the non-rigid fit, or None (start from the similarity pre-alignment)
    when it is worse than that: it turns faces over in numbers (divergence_flipped) or lies
    farther from the subject (mean vertex distance), by the divergence monitor's rule
    (divergence_growth times, and max_mean_mm more). A spline through a few landmarks
    extrapolates: through 3 centroids and an apex that are nearly coplanar (a biventricular
    heart whose 'apex' is ill-defined), its affine part sent real fits 320 mm away."""
    before = float(point_to_surface(aligned, subject_verts, subject_faces)[0].mean())
    after = float(point_to_surface(start, subject_verts, subject_faces)[0].mean())
    flipped = int(flipped_faces(aligned, start, faces).sum())
    report = {"start": "spline", "start_mean_mm": round(after, 4), "similarity_mean_mm": round(before, 4),
              "start_flipped_faces": flipped}
    if flipped >= max(1, params.divergence_flipped * len(faces)) or after > params.divergence_growth * before + params.max_mean_mm:
        return None, report | {"start": "similarity (spline refused)"}
    return start, report


def register(
    template_verts: np.ndarray,
    template_faces: np.ndarray,
    subject_verts: np.ndarray,
    subject_faces: np.ndarray,
    params: RegistrationParams,
    rng: np.random.Generator,
    template_labels: np.ndarray | None = None,
    subject_labels: np.ndarray | None = None,
    prealigned: bool = False,
) -> tuple[np.ndarray, dict]:
    """Fit the template mesh to a subject surface.

    template_verts : (n, 3) float mm, template_faces : (m, 3) int,
    subject_verts : (p, 3) float mm, subject_faces : (q, 3) int,
    template_labels : (n,) int or None, subject_labels : (p,) int or None.
    Returns the fitted template vertices (n, 3) float in the subject's frame (faces are
    template_faces) and a report (JSON-ready):
      mean_mm, p95_mm, max_mm: two-sided surface distance between fit and subject from
        params.distance_samples area-weighted samples per side; mean_mm is the mean of the
        two directed means, p95_mm and max_mm are over the pooled distances of both sides;
      flipped_faces: faces of the fit turned over against the pre-aligned template's (turned
        by more than 90 degrees against their neighbourhood; see measures.flipped_faces);
      self_intersections: faces of the fit intersecting a non-adjacent face;
      label_agreement, label_agreement_by_structure (only when both label arrays are given):
        fraction of template vertices that land on their own structure after the fit (see
        landmarks.label_agreement), overall and per structure (name -> fraction);
      landmarks (labelled only): the landmark keys both surfaces have (see landmarks.py),
        landmark_error_mm: mean distance between fitted and subject landmarks;
      prealign: the (4, 4) pre-alignment as nested lists, prealign_scale: its scale;
      nricp: steps_kept (stiffness steps kept whole: fewer than `steps` when the fold guard
        stopped the fit early or kept a step only in part), steps, fold_repeats,
        stiffened_vertices, partial_steps (per step that still folded after its repeats, the
        fraction of it kept).
    With labels, matches pair only points of one structure and label landmarks steer the
    pre-alignment and the coarse steps (see prealign and nricp.nricp).
    prealigned: the template already lies on the subject (a frame warm-started from the fit
    of its neighbour in one scanner frame, tracking.py): no similarity pre-alignment, whose
    scale and rotation would take up contraction and twist, which are shape, not pose.
    A subject that is not closed genus 0 raises MeshError. Judge the fit with accept().
    """
    require_valid(subject_verts, subject_faces, "registration subject")
    fitted, report = _register_once(template_verts, template_faces, subject_verts, subject_faces, params, rng,
                                    template_labels, subject_labels, (), prealigned)
    offenders = report.get("landmark_offenders", [])
    if offenders:
        # The fit moved these landmarks away from their subject's by more than the robust start
        # did (landmark_tolerance_mm): again without them, then rejected naming them (accept).
        first = {k: report[k] for k in ("landmark_offenders", "landmark_error_mm", "landmark_start_error_mm")}
        fitted, report = _register_once(template_verts, template_faces, subject_verts, subject_faces, params, rng,
                                        template_labels, subject_labels, tuple(offenders), prealigned)
        report["landmark_retry"] = first
    return fitted, report


def _procrustes_many(moving: np.ndarray, fixed: np.ndarray, similarity: bool) -> np.ndarray:
    """Procrustes fits of many small point sets at once, by trimesh.registration.procrustes's
    formula (no reflection; scale with `similarity`), one batched SVD instead of a call each.

    moving, fixed : (t, p, 3) mm  ->  (t, 4, 4) matrices sending moving[i] onto fixed[i]; NaN
    where a scale is fitted to a set with no spread (its points coincide): no fit exists.
    """
    weight = np.full((moving.shape[1], 1), 1.0 / moving.shape[1])
    centres = [(points * weight).sum(axis=1) for points in (moving, fixed)]  # (t, 3) each
    centred = [points - centre[:, None, :] for points, centre in zip((moving, fixed), centres)]
    if similarity:
        scales = [np.sqrt((c**2 * weight).reshape(len(c), -1).sum(axis=1)) for c in centred]  # (t,) each
    else:
        scales = [np.ones(len(moving))] * 2
    good = (scales[0] > 0) & (scales[1] > 0)
    safe = [np.where(good, s, 1.0)[:, None, None] for s in scales]
    target = np.where(good[:, None, None],
                      np.swapaxes(centred[1] / safe[1], 1, 2) @ (centred[0] / safe[0]), np.eye(3))  # (t, 3, 3)
    u, _, vh = np.linalg.svd(target)
    flip = np.ones((len(target), 3))
    flip[:, 2] = np.linalg.det(u @ vh)
    rotation = (u * flip[:, None, :]) @ vh  # (t, 3, 3)
    linear = (safe[1] / safe[0]) * rotation
    matrices = np.zeros((len(target), 4, 4))
    matrices[:, :3, :3] = linear
    matrices[:, :3, 3] = centres[1] - np.einsum("tij,tj->ti", linear, centres[0])
    matrices[:, 3, 3] = 1.0
    matrices[~good] = np.nan
    return matrices


def robust_landmarks(moving: np.ndarray, fixed: np.ndarray, similarity: bool, floor_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Least-median-of-squares similarity (or rigid) fit between corresponding landmarks.

    moving, fixed : (k, 3) mm. Every triple of landmarks (at most 560, chosen evenly) proposes a
    Procrustes fit; the one with the least median squared residual over all landmarks wins
    (Rousseeuw's LMedS: half the landmarks may disagree; the first such triple on a tie). A
    landmark is an inlier when its residual is within 2.5 robust standard deviations
    (1.4826 (1 + 5 / (k - 3)) sqrt(median)) or floor_mm, whichever is larger; the fit is then
    redone on the inliers.
    Returns the inlier mask (k,) and every landmark's residual (k,) mm under that final fit.
    With fewer than 4 landmarks nothing can be outvoted: all are inliers.
    """
    k = len(moving)
    options = {"reflection": False, "scale": similarity, "return_cost": False}
    if k < 4:
        matrix = trimesh.registration.procrustes(moving, fixed, **options) if k >= 3 else np.eye(4)
        return np.ones(k, bool), np.linalg.norm(_apply(matrix, moving) - fixed, axis=1)
    triples = np.array(list(itertools.combinations(range(k), 3)))
    triples = triples[np.linspace(0, len(triples) - 1, min(len(triples), 560)).astype(int)]
    # All triples' fits at once: one at a time they took 0.09 s of a 2 s frame fit.
    matrices = _procrustes_many(moving[triples], fixed[triples], similarity)  # (t, 4, 4)
    moved = np.einsum("tij,kj->tki", matrices[:, :3, :3], moving) + matrices[:, None, :3, 3]  # (t, k, 3)
    medians = np.median(np.sum((moved - fixed) ** 2, axis=2), axis=1)  # (t,)
    medians[~np.isfinite(medians)] = np.inf
    if not np.isfinite(medians).any():
        return np.ones(k, bool), np.zeros(k)
    best_median = medians.min()
    best = matrices[int(np.argmin(medians))]
    sigma = 1.4826 * (1 + 5 / (k - 3)) * np.sqrt(best_median)
    inliers = np.linalg.norm(_apply(best, moving) - fixed, axis=1) <= max(2.5 * sigma, floor_mm)
    if inliers.sum() >= 3:
        best = trimesh.registration.procrustes(moving[inliers], fixed[inliers], **options)
    return inliers, np.linalg.norm(_apply(best, moving) - fixed, axis=1)


def _register_once(
    template_verts, template_faces, subject_verts, subject_faces, params: RegistrationParams, rng,
    template_labels, subject_labels, exclude: tuple[str, ...], prealigned: bool,
) -> tuple[np.ndarray, dict]:
    """register() without the landmark retry; `exclude`: landmark keys left out."""
    template_verts = np.asarray(template_verts, dtype=np.float64)
    subject_verts = np.asarray(subject_verts, dtype=np.float64)
    labels = marks = None
    dropped: dict[str, str] = {}
    if template_labels is not None and subject_labels is not None:
        labels = (np.asarray(template_labels), np.asarray(subject_labels))
        template_marks = label_landmarks(template_verts, template_faces, labels[0], ring_points=params.ring_points)
        # The subject's ring points follow the template's: a tracked frame's neighbour.
        both = (template_marks, label_landmarks(subject_verts, subject_faces, labels[1], ring_points=params.ring_points,
                                                like=template_marks))
        dropped = dropped_landmarks(*both)
        marks = common_landmarks(*both)
        dropped |= {key: "moved away by an earlier fit (landmark_tolerance_mm)" for key in exclude if key in marks[0].keys}
        keep = [key for key in marks[0].keys if key not in exclude]
        inliers, residual = robust_landmarks(marks[0].select(keep).points(template_verts),
                                             marks[1].select(keep).points(subject_verts), params.similarity,
                                             params.landmark_outlier_mm)
        dropped |= {key: f"disagrees with the robust similarity fit of the others by {r:.1f} mm"
                    for key, ok, r in zip(keep, inliers, residual) if not ok}
        keep = [key for key, ok in zip(keep, inliers) if ok]
        marks = (marks[0].select(keep), marks[1].select(keep))
    points = None if marks is None else (marks[0].points(template_verts), marks[1].points(subject_verts))
    matrix = np.eye(4) if prealigned else prealign(template_verts, template_faces, subject_verts, subject_faces,
                                                   params, rng, labels, points)
    aligned = _apply(matrix, template_verts)
    start = None
    # The spline follows the centroids and the apex only: junction centres move with where
    # each mesh's label boundary runs out (1-2 mm between tessellations of one surface).
    # Points along a ring (ring_points) steer it too: a frame's base descends along the walls.
    steer = [i for i, key in enumerate(marks[0].keys) if not key.startswith("ring:") or "@" in key] if marks is not None else []
    start_report = {"start": "similarity"}
    spread = _spread(points[0][steer]) if len(steer) >= 4 else 0.0
    if len(steer) >= 4 and params.landmark_weight > 0 and spread < SPLINE_MIN_SPREAD:
        # A spline's affine part through nearly coplanar landmarks (centroids of structures
        # side by side) is unbounded across their plane.
        start_report = {"start": f"similarity (landmarks nearly coplanar: spread {spread:.2f})"}
    elif len(steer) >= 4 and params.landmark_weight > 0:
        start = landmark_warp(aligned, _apply(matrix, points[0][steer]), points[1][steer], params.landmark_smoothing)
        start, start_report = _check_start(aligned, start, template_faces, subject_verts, subject_faces, params)
    fitted, summary = nricp(aligned, template_faces, subject_verts, subject_faces, params, labels,
                           None if marks is None else (marks[0].weights, points[1]), start)
    if "diverged" in summary or summary["steps_kept"] < summary["steps"]:
        # Stopped as it ran away, or held back by the fold guard (a step kept only in part, or
        # the schedule ended early; of 20 real ACDC ventricles, one fit with a step kept in part
        # stayed at 1.51 mm p95 unless retried): again from the similarity start alone (no
        # spline, no landmark term: a landmark that disagrees is the likeliest cause), every
        # stiffness step retry_stiffening times stiffer, then the
        # schedule's softest step once more to close in. The stiff steps settle a thin vessel's
        # correspondence before the soft one (real CT whole heart: the first attempt stopped at
        # step 1 after 7 fold repeats, 1.44 / 7.4 mm, aorta agreement 0.77; the retry kept all 6
        # steps, 0.24 / 1.07 mm, every structure >= 0.997). The retry is kept unless it fared
        # worse than a first attempt that did not diverge: it diverged, or the fold guard stopped
        # it too and it lies no closer to the subject (mean vertex distance; a real ACDC
        # ventricle's first attempt stopped at 0.74 mm, its retry one step short at 0.25 mm).
        # The other is recorded as retry_attempt or first_attempt. Two divergences are rejected
        # with both attempts' figures (accept).
        stiffer = dataclasses.replace(
            params, stiffness=tuple(a * params.retry_stiffening for a in params.stiffness) + params.stiffness[-1:],
            normal_weight=params.normal_weight + params.normal_weight[-1:])
        first, first_fit = summary, fitted
        fitted, summary = nricp(aligned, template_faces, subject_verts, subject_faces, stiffer, labels)
        worse = "diverged" in summary or (
            summary["steps_kept"] < summary["steps"]
            and point_to_surface(fitted, subject_verts, subject_faces)[0].mean()
            >= point_to_surface(first_fit, subject_verts, subject_faces)[0].mean())
        if "diverged" not in first and worse:
            fitted, summary = first_fit, {**first, "retry_attempt": summary}
        else:
            summary["first_attempt"] = first
        summary["retry_stiffness"] = list(stiffer.stiffness)

    to_subject, to_fit = surface_distances(
        fitted, template_faces, subject_verts, subject_faces, params.distance_samples, rng
    )
    pooled = np.concatenate([to_subject, to_fit])
    report = {
        "mean_mm": float(0.5 * (to_subject.mean() + to_fit.mean())),
        "p95_mm": float(np.percentile(pooled, 95)),
        "max_mm": float(pooled.max()),
        "flipped_faces": int(flipped_faces(aligned, fitted, template_faces).sum()),
        "self_intersections": int(self_intersecting_faces(fitted, template_faces).sum()),
        "prealign": matrix.tolist(),
        "prealign_scale": float(np.cbrt(np.linalg.det(matrix[:3, :3]))),
        "nricp": summary,
        **start_report,
    }
    if labels is not None:
        overall, per_structure = label_agreement(fitted, template_faces, labels[0], subject_verts, subject_faces,
                                                      labels[1])
        report["label_agreement"] = overall
        report["label_agreement_by_structure"] = per_structure
        report["landmarks"] = list(marks[0].keys)
        report["landmark_confidence"] = dict(zip(marks[0].keys, marks[0].confidence))
        report["landmarks_dropped"] = dropped
        if marks[0].keys:
            after = np.linalg.norm(marks[0].points(fitted) - points[1], axis=1)
            before = np.linalg.norm(marks[0].points(aligned) - points[1], axis=1)
            report["landmark_error_mm"] = float(after.mean())
            report["landmark_start_error_mm"] = float(before.mean())
            report["landmark_errors_mm"] = {k: round(float(e), 3) for k, e in zip(marks[0].keys, after)}
            if after.mean() > before.mean() + params.landmark_tolerance_mm:
                report["landmark_offenders"] = [k for k, a, b in zip(marks[0].keys, after, before)
                                                if a > b + params.landmark_tolerance_mm]
    return fitted, report


def _diverged_text(d: dict) -> str:
    least = "none yet" if d["least_mm"] is None else f"{d['least_mm']:.2f} mm"
    return (f"{d['reason']} at stiffness step {d['step'] + 1}, iteration {d['iteration'] + 1} "
            f"(mean distance {d['mean_mm']:.2f} mm, least {least}, {d['flipped_faces']} faces flipped)")


def accept(report: dict, params: RegistrationParams, correspondence: bool = True) -> None:
    """Raise MeshError naming every threshold a registration report (from register) breaks.

    correspondence=False leaves out the label agreement: a fit to an intermediate template
    (a groupwise round before the last) only feeds the next mean, and its correspondence
    to a single reference subject is the bias those rounds remove.
    """
    reasons = []
    if report["mean_mm"] > params.max_mean_mm:
        reasons.append(
            f"two-sided mean surface distance {report['mean_mm']:.3f} mm > {params.max_mean_mm} mm"
        )
    if report["p95_mm"] > params.max_p95_mm:
        reasons.append(f"95th-percentile surface distance {report['p95_mm']:.3f} mm > {params.max_p95_mm} mm")
    if report["flipped_faces"]:
        reasons.append(f"{report['flipped_faces']} flipped faces")
    if report["self_intersections"]:
        reasons.append(f"{report['self_intersections']} self-intersecting faces")
    if "diverged" in report.get("nricp", {}):
        reasons.append("diverged twice: " + "; then ".join(
            _diverged_text(d) for d in (report["nricp"].get("first_attempt", {}).get("diverged"), report["nricp"]["diverged"]) if d))
    agreement = report.get("label_agreement_by_structure", {}) if correspondence else {}
    low = {s: a for s, a in agreement.items() if a < params.min_label_agreement}
    if low:
        listed = ", ".join(f"{s} {a:.3f}" for s, a in sorted(low.items(), key=lambda item: item[1]))
        reasons.append(f"label agreement < {params.min_label_agreement} for {listed}")
    if report.get("landmark_offenders"):
        reasons.append(
            f"landmark error {report['landmark_error_mm']:.2f} mm > the robust start's "
            f"{report['landmark_start_error_mm']:.2f} mm + {params.landmark_tolerance_mm} mm (landmark_tolerance_mm), "
            f"after a retry without {', '.join(report.get('landmark_retry', {}).get('landmark_offenders', [])) or 'none'}; "
            f"moved away: {', '.join(report['landmark_offenders'])}")
    if reasons:
        raise MeshError("registration rejected: " + "; ".join(reasons))
