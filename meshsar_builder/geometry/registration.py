"""Template registration: similarity pre-alignment, then non-rigid ICP (Amberg et al. 2007).

Every subject surface is fitted by the template mesh, so all fitted shapes share the
template's vertices and faces (point correspondence for the shape model).

The non-rigid step is the optimal-step NICP of Amberg, Romdhani and Vetter (CVPR 2007),
implemented here: every template vertex v_i carries an affine transform X_i (4 x 3), and
for a decreasing stiffness alpha the cost

    sum_i w_i |[v_i 1] X_i - u_i|^2  +  alpha^2 sum_(i,j) in edges s_ij |G (X_i - X_j)|^2,
    G = diag(1, 1, 1, gamma),

is minimised alternately over the matches u_i (closest surface points, rejected by distance
and normal disagreement) and over X (a sparse symmetric positive definite system, 4n x 4n).
Two additions over the paper, both for thin vessels joined to chambers:
- two-sided matches: each subject vertex also pulls its nearest template vertex, so a template
  vessel shorter than the subject's is drawn to the vessel's end, not only the reverse;
- a fold guard: after each stiffness step, faces that turned over (against the pre-aligned
  template) or intersect another face have the stiffness s_ij of the edges around them
  raised, and the step is repeated; if that does not clear them, the fit stops at the last
  fold-free step.
Speed: the system changes only in its 4 x 4 diagonal data blocks between iterations of one
step, so it is factorised once per step (SuperLU; again after a fold-guard repeat changes
the stiffness) and that factorisation preconditions warm-started conjugate gradients in
every iteration.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import trimesh
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

from meshsar_builder.geometry.meshing import closest_on_triangles, point_to_surface
from meshsar_builder.geometry.remesh import require_valid, self_intersecting_faces
from meshsar_builder.pipeline.errors import MeshError


@dataclass(frozen=True)
class RegistrationParams:
    """The recipe's [registration] section.

    template: "median" (the subject of median volume) or a subject id.
    template_vertices: vertex count the template surface is simplified to.
    max_mean_mm, max_p95_mm: acceptance thresholds of the two-sided surface distance.
    similarity: pre-align with scale (similarity) rather than rigid only.
    icp_points: surface points of the template used by the pre-alignment ICP.
    stiffness: NRICP stiffness per step (Amberg's alpha, with the template scaled to unit
        bounding-box diagonal), decreasing.
    normal_weight: per step, exponent of the normal-agreement weight (cosine of the angle
        between the normals) of each match (0 switches it off); same length as stiffness.
    step_iterations: most iterations per stiffness step (fewer once the fit moves less
        than converge_mm).
    match_distance_mm: matches farther apart than this are ignored by the data term of
        that iteration.
    max_normal_deg: matches whose normals differ by more than this are ignored.
    gamma: weight of the translation part against the linear part in the stiffness term.
    reverse_weight: weight of the subject-to-template matches against the template-to-
        subject ones (0: one-sided, as in the paper).
    converge_mm: a step ends when the vertices moved less than this on average in an iteration.
    fold_retries: how often a stiffness step is repeated with stiffer edges around faces
        that turned over or intersect before the fit stops at the last fold-free step.
    fold_stiffening: factor on the stiffness of those edges per repeat.
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
    max_normal_deg: float = 60.0
    gamma: float = 1.0
    reverse_weight: float = 1.0
    converge_mm: float = 0.02
    fold_retries: int = 4
    fold_stiffening: float = 10.0
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
        if not 0 < self.max_normal_deg <= 180:
            raise ValueError(f"max_normal_deg: must be in (0, 180], got {self.max_normal_deg}")
        if not self.gamma > 0:
            raise ValueError(f"gamma: must be > 0, got {self.gamma}")
        if not self.reverse_weight >= 0:
            raise ValueError(f"reverse_weight: must be >= 0, got {self.reverse_weight}")
        if not self.converge_mm > 0:
            raise ValueError(f"converge_mm: must be > 0, got {self.converge_mm}")
        if self.fold_retries < 0:
            raise ValueError(f"fold_retries: must be >= 0, got {self.fold_retries}")
        if not self.fold_stiffening > 1:
            raise ValueError(f"fold_stiffening: must be > 1, got {self.fold_stiffening}")
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
    # Final refinement against the exact surface (closest points, not samples).
    surface, matrix, last_cost = _Surface(np.asarray(fixed_verts, dtype=np.float64), np.asarray(fixed_faces)), best, np.inf
    for _ in range(20):
        moved = _apply(matrix, points)
        closest, _, _ = surface.closest(moved)
        step, _, cost = trimesh.registration.procrustes(moved, closest, **icp_options)
        matrix = step @ matrix
        if abs(last_cost - cost) < 1e-7:
            break
        last_cost = cost
    return matrix


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def _face_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m, 3) unnormalised face normals (length twice the face area)."""
    corners = verts[faces]
    return np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])


def _vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(n, 3) unit area-weighted vertex normals."""
    normals = np.zeros_like(verts)
    face_normals = _face_normals(verts, faces)
    for corner in range(3):
        np.add.at(normals, faces[:, corner], face_normals)
    return _unit(normals)


def _vertex_areas(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(n,) a third of the area of the faces around each vertex."""
    areas = np.zeros(len(verts))
    face_areas = 0.5 * np.linalg.norm(_face_normals(verts, faces), axis=1)
    for corner in range(3):
        np.add.at(areas, faces[:, corner], face_areas / 3.0)
    return areas


def _unique_edges(faces: np.ndarray) -> np.ndarray:
    """(e, 2) the undirected edges of a triangle mesh, each once."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(edges, axis=0)


class _Surface:
    """A triangle surface that answers closest-point queries.

    Candidate faces of a query are the faces around its `near` nearest vertices, exact for
    the isotropic meshes used here (the closest face has one of them as a corner).
    """

    def __init__(self, verts: np.ndarray, faces: np.ndarray, near: int = 2):
        self.verts, self.faces, self.near = verts, faces, near
        self.tree = cKDTree(verts)
        self.face_normals = _unit(_face_normals(verts, faces))
        self.vertex_normals = _vertex_normals(verts, faces)
        self.vertex_areas = _vertex_areas(verts, faces)
        order = np.argsort(faces.ravel(), kind="stable")
        owner = order // 3
        counts = np.bincount(faces.ravel(), minlength=len(verts))
        starts = np.r_[0, np.cumsum(counts)[:-1]]
        slot = np.arange(len(order)) - np.repeat(starts, counts)
        # Padded with each vertex's first face (a repeat changes no minimum).
        self.vertex_faces = np.repeat(owner[starts][:, None], counts.max(), axis=1)
        self.vertex_faces[faces.ravel()[order], slot] = owner

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(p, 3) points -> closest surface points (p, 3), their faces (p,), distances (p,)."""
        _, nearest = self.tree.query(points, k=self.near)
        candidates = self.vertex_faces[nearest].reshape(len(points), -1)
        best, d2 = closest_on_triangles(points[:, None, :], self.verts[self.faces[candidates]])
        pick = np.argmin(d2, axis=1)
        rows = np.arange(len(points))
        return best[rows, pick], candidates[rows, pick], np.sqrt(d2[rows, pick])


def _pcg(matrix, rhs: np.ndarray, start: np.ndarray, precondition, rtol: float, max_iterations: int) -> np.ndarray:
    """Preconditioned conjugate gradients for a symmetric positive definite system, columns at once."""
    x = start.copy()
    residual = rhs - matrix @ x
    z = precondition(residual)
    direction = z.copy()
    rz = np.sum(residual * z, axis=0)
    goal = rtol * np.linalg.norm(rhs, axis=0)
    for _ in range(max_iterations):
        if np.all(np.linalg.norm(residual, axis=0) <= goal):
            break
        k_dir = matrix @ direction
        curvature = np.sum(direction * k_dir, axis=0)
        step = np.divide(rz, curvature, out=np.zeros_like(rz), where=curvature > 0)
        x += step * direction
        residual -= step * k_dir
        z = precondition(residual)
        rz_new = np.sum(residual * z, axis=0)
        direction = z + np.divide(rz_new, rz, out=np.zeros_like(rz), where=rz > 0) * direction
        rz = rz_new
    return x


def _preconditioner(matrix: sp.csr_matrix):
    """Sparse LU of a symmetric positive definite matrix, as a function r -> K^-1 r."""
    factor = splu(matrix.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return factor.solve


class _AmbergSystem:
    """Normal equations of the optimal-step NICP for one template (see the module docstring)."""

    def __init__(self, verts: np.ndarray, faces: np.ndarray, gamma: float):
        n = len(verts)
        self.n = n
        self.hom = np.c_[verts, np.ones(n)]  # (n, 4): [v_i 1]
        self.edges = _unique_edges(faces)
        count = len(self.edges)
        self.incidence = sp.csr_matrix(
            (np.r_[np.ones(count), -np.ones(count)], (np.r_[np.arange(count), np.arange(count)], self.edges.T.ravel())),
            shape=(count, n),
        )
        self.g2 = sp.diags([1.0, 1.0, 1.0, gamma**2])
        self.block_index = (np.arange(n + 1), np.arange(n))

    def stiffness(self, edge_weights: np.ndarray) -> sp.csr_matrix:
        laplacian = self.incidence.T @ sp.diags(edge_weights) @ self.incidence
        return sp.kron(laplacian, self.g2, format="csr")

    def data(self, weights: np.ndarray, targets: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
        """sum_i w_i |[v_i 1] X_i - u_i|^2 -> its matrix (4n, 4n) and right-hand side (4n, 3)."""
        blocks = weights[:, None, None] * self.hom[:, :, None] * self.hom[:, None, :]
        indptr, indices = self.block_index
        matrix = sp.bsr_matrix((blocks, indices, indptr), shape=(4 * self.n, 4 * self.n)).tocsr()
        rhs = (weights[:, None, None] * self.hom[:, :, None] * targets[:, None, :]).reshape(4 * self.n, 3)
        return matrix, rhs

    def apply(self, x: np.ndarray) -> np.ndarray:
        """(4n, 3) stacked affine transforms -> (n, 3) moved vertices."""
        return np.einsum("ij,ijk->ik", self.hom, x.reshape(self.n, 4, 3))

    def identity(self) -> np.ndarray:
        return np.tile(np.eye(4, 3), (self.n, 1))


def _matches(
    fit: np.ndarray,
    faces: np.ndarray,
    subject: _Surface,
    template_area: float,
    params: RegistrationParams,
    normal_power: float,
    distance: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Data-term weights (n,) and targets (n, 3) of the current fit (normalised units).

    Template-to-subject: each fit vertex to its closest subject surface point. Subject-to-
    template: each subject vertex to its nearest fit vertex, weighted by the subject vertex's
    area over the mean template vertex area (so both sides weigh alike). A match is dropped
    when farther than `distance` or when the normals differ by more than max_normal_deg; a
    kept match weighs cos(angle)**normal_power. A vertex's matches combine exactly into one
    weighted mean target.
    """
    cos_limit = np.cos(np.radians(params.max_normal_deg))
    normals = _vertex_normals(fit, faces)
    closest, face, dist = subject.closest(fit)
    cos = _dot(normals, subject.face_normals[face])
    keep = (dist <= distance) & (cos >= cos_limit)
    weights = np.where(keep, np.clip(cos, 0.0, 1.0) ** normal_power, 0.0)
    sums = weights[:, None] * closest
    if params.reverse_weight > 0:
        dist_r, nearest = cKDTree(fit).query(subject.verts)
        cos_r = _dot(subject.vertex_normals, normals[nearest])
        keep_r = (dist_r <= distance) & (cos_r >= cos_limit)
        w_r = np.where(keep_r, np.clip(cos_r, 0.0, 1.0) ** normal_power, 0.0)
        w_r *= params.reverse_weight * subject.vertex_areas / template_area
        weights = weights + np.bincount(nearest, w_r, minlength=len(fit))
        for axis in range(3):
            sums[:, axis] += np.bincount(nearest, w_r * subject.verts[:, axis], minlength=len(fit))
    targets = np.where(weights[:, None] > 0, sums / np.maximum(weights, 1e-300)[:, None], fit)
    return weights, targets


def _bad_faces(aligned: np.ndarray, fit: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m,) faces that turned over against the pre-aligned template or intersect another face."""
    return flipped_faces(aligned, fit, faces) | self_intersecting_faces(fit, faces)


def _grow(faces: np.ndarray, vertex_mask: np.ndarray, rings: int) -> np.ndarray:
    """Vertex mask grown by `rings` rings of neighbours."""
    for _ in range(rings):
        vertex_mask = vertex_mask | np.bincount(
            faces.ravel(), np.repeat(vertex_mask[faces].any(axis=1), 3), minlength=len(vertex_mask)
        ).astype(bool)
    return vertex_mask


def _nricp(
    aligned: np.ndarray, faces: np.ndarray, subject_verts: np.ndarray, subject_faces: np.ndarray,
    params: RegistrationParams,
) -> tuple[np.ndarray, dict]:
    """Fold-guarded optimal-step NICP of the pre-aligned template onto the subject.

    aligned : (n, 3) mm, faces : (m, 3), subject_* : the subject surface.
    Returns the fitted vertices (n, 3) mm and a summary (JSON-ready): stiffness steps kept,
    fold-guard repeats, edges stiffened.
    """
    faces = np.asarray(faces, dtype=np.int64)
    centre = aligned.mean(axis=0)
    scale = float(np.linalg.norm(np.ptp(aligned, axis=0)))
    template = (aligned - centre) / scale
    subject = _Surface((np.asarray(subject_verts, dtype=np.float64) - centre) / scale, np.asarray(subject_faces), near=1)
    system = _AmbergSystem(template, faces, params.gamma)
    template_area = float(_vertex_areas(template, faces).mean())
    distance, converge = params.match_distance_mm / scale, params.converge_mm / scale

    # Edges weigh 1/length^2, so the stiffness penalises the gradient of the transforms
    # along the surface and does not depend on the template's resolution.
    lengths = np.linalg.norm(template[system.edges[:, 0]] - template[system.edges[:, 1]], axis=1)
    base_weights = 1.0 / np.maximum(lengths, 1e-12) ** 2
    edge_weights = base_weights.copy()
    x = system.identity()
    steps_kept, repeats = 0, 0
    for alpha, normal_power in zip(params.stiffness, params.normal_weight):
        # A repeat goes on from the folded fit: flipped faces lose their matches (their normals
        # disagree), so the stiffened region relaxes back while the rest stays fitted.
        x_step = x
        for attempt in range(params.fold_retries + 1):
            stiffness = alpha**2 * system.stiffness(edge_weights)
            fit = system.apply(x_step)
            factor = None
            for _ in range(params.step_iterations):
                weights, targets = _matches(fit, faces, subject, template_area, params, normal_power, distance)
                data, rhs = system.data(weights, targets)
                matrix = (stiffness + data).tocsr()
                if factor is None:
                    factor = _preconditioner(matrix)
                x_step = _pcg(matrix, rhs, x_step, factor, rtol=1e-4, max_iterations=50)
                moved = system.apply(x_step)
                change = np.linalg.norm(moved - fit, axis=1).mean()
                fit = moved
                if change < converge:
                    break
            bad = _bad_faces(template, fit, faces)
            if not bad.any():
                x, steps_kept = x_step, steps_kept + 1
                break
            if attempt == params.fold_retries:
                break
            repeats += 1
            region = _grow(faces, np.bincount(faces[bad].ravel(), minlength=len(template)).astype(bool), 2)
            edge_weights[region[system.edges].any(axis=1)] *= params.fold_stiffening
        if bad.any():
            break  # keep the last fold-free step
    summary = {
        "steps_kept": steps_kept,
        "steps": len(params.stiffness),
        "fold_repeats": repeats,
        "stiffened_edges": int((edge_weights > base_weights).sum()),
    }
    return system.apply(x) * scale + centre, summary


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
      prealign: the (4, 4) pre-alignment as nested lists, prealign_scale: its scale;
      nricp: steps_kept (stiffness steps in the fit: fewer than `steps` when the fold guard
        stopped early), steps, fold_repeats, stiffened_edges.
    A subject that is not closed genus 0 raises MeshError. Judge the fit with accept().
    """
    require_valid(subject_verts, subject_faces, "registration subject")
    matrix = prealign(template_verts, template_faces, subject_verts, subject_faces, params, rng)
    aligned = _apply(matrix, np.asarray(template_verts, dtype=np.float64))
    fitted, nricp = _nricp(aligned, template_faces, subject_verts, subject_faces, params)

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
        "nricp": nricp,
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
