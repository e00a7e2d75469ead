"""Template registration: similarity pre-alignment, then non-rigid ICP (Amberg et al. 2007).

Every subject surface is fitted by the template mesh, so all fitted shapes share the
template's vertices and faces (point correspondence for the shape model).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from meshsar_builder.errors import MeshError
from meshsar_builder.remesh import require_valid, self_intersecting_faces


@dataclass(frozen=True)
class RegistrationParams:
    """The recipe's [registration] section.

    template: "median" (the subject of median volume) or a subject id.
    template_vertices: vertex count the template surface is simplified to.
    max_mean_mm, max_p95_mm: acceptance thresholds of the two-sided surface distance.
    similarity: pre-align with scale (similarity) rather than rigid only.
    icp_points: surface points of the template used by the pre-alignment ICP.
    stiffness: NRICP stiffness per step (Amberg's alpha, in trimesh's normalised units:
        the template is scaled to unit bounding-box diagonal), decreasing.
    normal_weight: per step, exponent of the normal-agreement weight of each match
        (0 switches it off); same length as stiffness.
    step_iterations: most iterations per stiffness step.
    match_distance_mm: template vertices farther than this from the subject are ignored
        by the data term of that iteration.
    distance_samples: area-weighted surface samples per side for the fit report.
    """

    template: str = "median"
    template_vertices: int = 6000
    max_mean_mm: float = 0.5
    max_p95_mm: float = 1.5
    similarity: bool = True
    icp_points: int = 3000
    stiffness: tuple[float, ...] = (0.05, 0.02, 0.01, 0.005, 0.002)
    normal_weight: tuple[float, ...] = (0.5, 0.5, 0.5, 0.0, 0.0)
    step_iterations: int = 10
    match_distance_mm: float = 10.0
    distance_samples: int = 20000

    def __post_init__(self) -> None:
        if not self.template:
            raise ValueError(f"template: must be 'median' or a subject id, got {self.template!r}")
        if self.template_vertices < 100:
            raise ValueError(f"template_vertices: must be >= 100, got {self.template_vertices}")
        if not self.max_mean_mm > 0:
            raise ValueError(f"max_mean_mm: must be > 0, got {self.max_mean_mm}")
        if not self.max_p95_mm > 0:
            raise ValueError(f"max_p95_mm: must be > 0, got {self.max_p95_mm}")
        if self.icp_points < 10:
            raise ValueError(f"icp_points: must be >= 10, got {self.icp_points}")
        if not self.stiffness or any(not s > 0 for s in self.stiffness):
            raise ValueError(f"stiffness: must be a non-empty list of values > 0, got {self.stiffness}")
        if len(self.normal_weight) != len(self.stiffness) or any(w < 0 for w in self.normal_weight):
            raise ValueError(
                f"normal_weight: must hold {len(self.stiffness)} values >= 0 (one per stiffness step), "
                f"got {self.normal_weight}"
            )
        if self.step_iterations < 1:
            raise ValueError(f"step_iterations: must be >= 1, got {self.step_iterations}")
        if not self.match_distance_mm > 0:
            raise ValueError(f"match_distance_mm: must be > 0, got {self.match_distance_mm}")
        if self.distance_samples < 100:
            raise ValueError(f"distance_samples: must be >= 100, got {self.distance_samples}")


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
    mesh_a, mesh_b = _mesh(verts_a, faces_a), _mesh(verts_b, faces_b)
    points_a, _ = trimesh.sample.sample_surface(mesh_a, n_samples, seed=rng)
    points_b, _ = trimesh.sample.sample_surface(mesh_b, n_samples, seed=rng)
    a_to_b = trimesh.proximity.closest_point(mesh_b, points_a)[1]
    b_to_a = trimesh.proximity.closest_point(mesh_a, points_b)[1]
    return a_to_b, b_to_a


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
) -> np.ndarray:
    """(4, 4) similarity (or rigid, params.similarity False) transform taking `moving` onto `fixed`.

    Moments give the start: centroids of the solids, scale from the cube root of the
    volume ratio, and rotation either the identity (subjects in one anatomical frame)
    or one of the four proper matchings of the principal axes (sign ambiguity). Each
    start is refined by point-to-point ICP against dense samples of `fixed`; the start
    with the lowest ICP cost wins, and is refined once more against the exact surface.
    """
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
    matrix, _, _ = trimesh.registration.icp(points, fixed, initial=best, max_iterations=20, **icp_options)
    return matrix


def _nricp(
    template: trimesh.Trimesh, subject: trimesh.Trimesh, params: RegistrationParams
) -> np.ndarray:
    steps = [
        [stiffness, 0.0, normal_weight, params.step_iterations]
        for stiffness, normal_weight in zip(params.stiffness, params.normal_weight)
    ]
    return trimesh.registration.nricp_amberg(
        template,
        subject,
        steps=steps,
        # trimesh works on the template scaled to unit bounding-box diagonal.
        distance_threshold=params.match_distance_mm / template.scale,
    )


def flipped_faces(before_verts: np.ndarray, after_verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces whose normal turned by more than 90 degrees between two vertex sets of one mesh.

    before_verts, after_verts : (n, 3) float, faces : (m, 3) int  ->  (m,) bool:
    n_after · n_before < 0 (unnormalised face normals, so degenerate faces count as not flipped).
    """
    def normals(verts: np.ndarray) -> np.ndarray:
        corners = verts[faces]
        return np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])

    return np.einsum("ij,ij->i", normals(before_verts), normals(after_verts)) < 0


def register(
    template_verts: np.ndarray,
    template_faces: np.ndarray,
    subject_verts: np.ndarray,
    subject_faces: np.ndarray,
    params: RegistrationParams,
    rng: np.random.Generator,
    template_labels: np.ndarray | None = None,
    subject_labels: np.ndarray | None = None,
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
      flipped_faces: faces whose normal after the non-rigid fit points against their normal
        in the pre-aligned template (turned by more than 90 degrees; see flipped_faces);
      self_intersections: faces of the fit intersecting a non-adjacent face;
      label_agreement (only when both label arrays are given): fraction of template
        vertices whose label equals the label of the nearest subject vertex after the fit;
      prealign: the (4, 4) pre-alignment as nested lists, prealign_scale: its scale.
    A subject that is not closed genus 0 raises MeshError. Judge the fit with accept().
    """
    require_valid(subject_verts, subject_faces, "registration subject")
    matrix = prealign(template_verts, template_faces, subject_verts, subject_faces, params, rng)
    aligned = _apply(matrix, np.asarray(template_verts, dtype=np.float64))
    subject = _mesh(subject_verts, subject_faces)
    fitted = np.asarray(_nricp(_mesh(aligned, template_faces), subject, params), dtype=np.float64)

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
    }
    if template_labels is not None and subject_labels is not None:
        _, nearest = cKDTree(np.asarray(subject_verts, dtype=np.float64)).query(fitted)
        agree = np.asarray(template_labels) == np.asarray(subject_labels)[nearest]
        report["label_agreement"] = float(agree.mean())
    return fitted, report


def accept(report: dict, params: RegistrationParams) -> None:
    """Raise MeshError naming every threshold a registration report (from register) breaks."""
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
    if reasons:
        raise MeshError("registration rejected: " + "; ".join(reasons))
