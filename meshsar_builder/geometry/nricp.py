"""Optimal-step non-rigid ICP (Amberg, Romdhani and Vetter, CVPR 2007) with a second-order
stiffness and label-aware matches.

The non-rigid step is the optimal-step NICP of Amberg, Romdhani and Vetter (CVPR 2007),
implemented here: every template vertex v_i carries an affine transform X_i (4 x 3), and
for a decreasing stiffness alpha the cost

    sum_i w_i |[v_i 1] X_i - u_i|^2  +  alpha^2 sum_i s_i |Q_i [G X_j]_(j in ring i)|^2,
    G = diag(1, 1, 1, gamma),

is minimised alternately over the matches u_i (closest surface points, rejected by distance
and normal disagreement) and over X (a sparse symmetric positive definite system, 4n x 4n).
The stiffness is not the paper's. Amberg's, alpha^2 sum_(i,j) in edges |G (X_i - X_j)|^2,
leaves only one transform for the whole template free: a twist, whose rotation grows along
the axis, costs like any other change, and where the data cannot see a rotation (a heart's
apex is nearly a surface of revolution) the fit keeps the rotation it started with. Here
ring i is v_i and its neighbours, and Q_i projects their stacked transforms onto
what an affine function of position in 3-D cannot fit over that ring (a second difference;
on a curved ring too, since the ring spans the normal). So the stiffness penalises the
second derivatives of X, s_i = 1 / h_i^4 (h_i the mean edge length at v_i) keeps it
independent of the resolution, and every X varying linearly with position is free: a twist,
a bend or a taper is extrapolated into the regions the data leaves ambiguous.
With structure labels on both surfaces (DESIGN section 6), matches pair only points of one
structure, in both directions, and landmarks derived from the labels (structure centroids,
the apex, junction centres: landmarks.py) enter as Amberg's landmark term, whose weight
decays with the stiffness; they also give the pre-alignment and, through a thin-plate
spline, the start of the non-rigid fit, so a shape change is not explained by a rotation or
a slide along the surface (the surface term alone cannot see tangential motion). The
stiffness measures departures from the pre-aligned template, not from that start: the
spline's guesses between the landmarks are not kept for free.
Two further additions over the paper, both for thin vessels joined to chambers:
- two-sided matches: each subject vertex also pulls its nearest template vertex, so a template
  vessel shorter than the subject's is drawn to the vessel's end, not only the reverse;
- a fold guard: after each stiffness step, faces that turned over (against the pre-aligned
  template) or intersect another face have the stiffness s_i of the vertices around them
  raised, and Amberg's first-order term switched on (and raised) on the edges among them,
  and the step is repeated; if that does not clear them, the longest fold-free part of the
  step is kept (half of it, a quarter, ...) and the schedule goes on, still stiffened there;
  a step none of whose parts is fold-free ends the fit at the last fold-free one. The first-order
  term is needed there: the second-order one leaves a linearly varying transform free, and such a
  field can turn faces over.
Speed: the system changes only in its 4 x 4 diagonal data blocks between iterations of one
step, so it is factorised once per step (CHOLMOD, the vertices in minimum degree order; again
after a fold-guard repeat changes the stiffness) and that factorisation preconditions
warm-started conjugate gradients in every iteration (nricp_solve.py); and the stiffest step runs on a coarse
copy of the template (_coarse_start).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from meshsar_builder.geometry.intersections import self_intersecting_faces
from meshsar_builder.geometry.landmarks import face_labels
from meshsar_builder.geometry.measures import edge_lengths, flipped_faces, unique_edges
from meshsar_builder.geometry.closest import closest_among
from meshsar_builder.geometry.meshing import transfer_labels
from meshsar_builder.geometry.nricp_solve import Operator, pcg, preconditioner, unknowns_order
from meshsar_builder.geometry.registration_params import RegistrationParams
from meshsar_builder.geometry.remesh import simplify
from meshsar_builder.geometry.surface_map import interpolation_matrix
from meshsar_builder.pipeline.errors import MeshError


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


class Surface:
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
        best, pick, d2 = closest_among(points, self.verts, self.faces, candidates)
        return best, candidates[np.arange(len(points)), pick], np.sqrt(d2)


class Subject:
    """The subject surface for the matches; with labels, split into one surface per structure.

    Label-aware matching pairs only points of one structure, in both directions: a template
    vertex of structure s is matched to the closest point of the subject faces of s, and a
    subject vertex of s to the nearest template vertex of s. A structure that only one side
    has (or label 0) is matched against the whole other surface.
    """

    def __init__(self, verts: np.ndarray, faces: np.ndarray, labels: np.ndarray | None,
                 template_labels: np.ndarray | None):
        self.surface = Surface(verts, faces, near=1)
        self.verts = verts
        self.parts: dict[int, Surface] = {}
        self.labels, self.template_labels = labels, template_labels
        if labels is None or template_labels is None:
            return
        owner = face_labels(faces, labels)
        for label in np.unique(template_labels):
            chosen = faces[owner == label]
            if label != 0 and len(chosen):
                used, local = np.unique(chosen, return_inverse=True)
                self.parts[int(label)] = Surface(verts[used], local.reshape(-1, 3), near=1)

    def closest(self, fit: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(n, 3) fit vertices -> closest subject points (n, 3), their face normals (n, 3), distances (n,)."""
        points, normals, dist = np.empty_like(fit), np.empty_like(fit), np.empty(len(fit))
        rest = np.ones(len(fit), dtype=bool)
        for label, part in self.parts.items():
            mine = self.template_labels == label
            points[mine], part_face, dist[mine] = part.closest(fit[mine])
            normals[mine] = part.face_normals[part_face]
            rest &= ~mine
        if rest.any():  # a structure only the template has, or label 0: the whole surface
            points[rest], face, dist[rest] = self.surface.closest(fit[rest])
            normals[rest] = self.surface.face_normals[face]
        return points, normals, dist

    def nearest_fit(self, fit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) fit vertices -> per subject vertex the distance (p,) to and index (p,) of its fit match."""
        dist, nearest = np.empty(len(self.verts)), np.empty(len(self.verts), dtype=np.int64)
        rest = np.ones(len(self.verts), dtype=bool)
        for label in self.parts:
            mine = np.flatnonzero(self.template_labels == label)
            theirs = self.labels == label
            dist[theirs], local = cKDTree(fit[mine]).query(self.verts[theirs])
            nearest[theirs] = mine[local]
            rest &= ~theirs
        if rest.any():  # a structure only the subject has, or label 0: the whole fit
            dist[rest], nearest[rest] = cKDTree(fit).query(self.verts[rest])
        return dist, nearest


def _ring_residuals(verts: np.ndarray, edges: np.ndarray, spacing: np.ndarray) -> tuple[np.ndarray, ...]:
    """Each vertex's 1-ring (itself and its r - 1 neighbours) and the projection
    Q = I - A A^+ (r x r) onto what an affine function of position cannot fit there,
    A = [1, (v_j - v_i) / h_i] (h_i = spacing[i], which only keeps A well conditioned).

    Returns the COO entries (rows, cols, values) of sum_i S_i^T Q_i S_i (S_i selects the ring)
    and, per entry, its vertex i (to weigh each ring).
    """
    directed = np.r_[edges, edges[:, ::-1]]
    directed = directed[np.argsort(directed[:, 0], kind="stable")]
    valence = np.bincount(directed[:, 0], minlength=len(verts))
    starts = np.r_[0, np.cumsum(valence)[:-1]]
    parts = []
    for k in np.unique(valence):  # rings of one size at once
        centre = np.flatnonzero(valence == k)
        ring = np.c_[centre, directed[starts[centre][:, None] + np.arange(k), 1]]
        offsets = (verts[ring] - verts[centre][:, None, :]) / spacing[centre][:, None, None]
        basis = np.concatenate([np.ones((len(centre), k + 1, 1)), offsets], axis=2)
        # The ring's curvature spans the normal direction too (so a function linear in 3-D
        # is fitted exactly on a curved ring); only an exactly flat ring drops it.
        residual = np.eye(k + 1) - basis @ np.linalg.pinv(basis, rcond=1e-9)
        parts.append((np.broadcast_to(ring[:, :, None], residual.shape).ravel(),
                      np.broadcast_to(ring[:, None, :], residual.shape).ravel(),
                      residual.ravel(), np.repeat(centre, (k + 1) ** 2)))
    return tuple(np.concatenate(column) for column in zip(*parts))


class _AmbergSystem:
    """Normal equations of the optimal-step NICP for one template (see the module docstring)."""

    def __init__(self, verts: np.ndarray, faces: np.ndarray, gamma: float):
        n = len(verts)
        self.n = n
        self.hom = np.c_[verts, np.ones(n)]  # (n, 4): [v_i 1]
        edges = unique_edges(faces)
        lengths = edge_lengths(verts, edges)
        # (n,) mean length of the edges at each vertex
        self.spacing = np.bincount(edges.ravel(), np.repeat(lengths, 2), minlength=n) / np.bincount(
            edges.ravel(), minlength=n)
        self.rings = _ring_residuals(verts, edges, self.spacing)
        # First differences along edges (Amberg's own term), weighted only where the fold guard
        # stiffens: the second-order term leaves every linearly varying transform free, a folding
        # one too, so holding a folded region needs the transforms there to agree.
        self.edge_base = 1.0 / np.maximum(lengths, 1e-12) ** 2
        count = len(edges)
        self.incidence = sp.csr_matrix(
            (np.r_[np.ones(count), -np.ones(count)], (np.r_[np.arange(count), np.arange(count)], edges.T.ravel())),
            shape=(count, n),
        )
        self.edges = edges
        self.order = unknowns_order(n, np.ascontiguousarray(faces, dtype=np.int64).tobytes())
        self.g2 = sp.diags([1.0, 1.0, 1.0, gamma**2])
        self.block_index = (np.arange(n + 1), np.arange(n))

    def stiffness(self, vertex_weights: np.ndarray, edge_weights: np.ndarray) -> sp.csr_matrix:
        """sum_i s_i |Q_i [G X_j]_(j in ring i)|^2 + sum_(i,j) in edges e_ij |G (X_i - X_j)|^2
        (s_i: vertex_weights, e_ij: edge_weights) -> its matrix (4n, 4n)."""
        rows, cols, values, owner = self.rings
        second = sp.csr_matrix((vertex_weights[owner] * values, (rows, cols)), shape=(self.n, self.n))
        first = self.incidence.T @ sp.diags(edge_weights) @ self.incidence
        return sp.kron(second + first, self.g2, format="csr")

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

    def landmark_rows(self, weights: sp.csr_matrix) -> sp.csr_matrix:
        """(k, n) landmark weights over vertices -> (k, 4n) rows R with R x = the moved landmarks."""
        coo = weights.tocoo()
        cols = (4 * coo.col[:, None] + np.arange(4)).ravel()
        vals = (coo.data[:, None] * self.hom[coo.col]).ravel()
        return sp.csr_matrix((vals, (np.repeat(coo.row, 4), cols)), shape=(weights.shape[0], 4 * self.n))


def _matches(
    fit: np.ndarray,
    faces: np.ndarray,
    subject: Subject,
    template_area: float,
    params: RegistrationParams,
    normal_power: float,
    distance: float,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Data-term weights (n,), targets (n, 3) and the mean distance of every fit vertex to its
    closest subject point (the divergence monitor's measure) of the current fit (normalised units).

    Template-to-subject: each fit vertex to its closest subject surface point. Subject-to-
    template: each subject vertex to its nearest fit vertex, weighted by the subject vertex's
    area over the mean template vertex area (so both sides weigh alike). With labels, both
    directions pair only points of one structure (see Subject). A match is dropped
    when farther than `distance` or when the normals differ by more than max_normal_deg; a
    kept match weighs cos(angle)**normal_power. A vertex's matches combine exactly into one
    weighted mean target.
    """
    cos_limit = np.cos(np.radians(params.max_normal_deg))
    normals = _vertex_normals(fit, faces)
    closest, subject_normals, dist = subject.closest(fit)
    cos = _dot(normals, subject_normals)
    keep = (dist <= distance) & (cos >= cos_limit)
    weights = np.where(keep, np.clip(cos, 0.0, 1.0) ** normal_power, 0.0)
    sums = weights[:, None] * closest
    if params.reverse_weight > 0:
        dist_r, nearest = subject.nearest_fit(fit)
        cos_r = _dot(subject.surface.vertex_normals, normals[nearest])
        keep_r = (dist_r <= distance) & (cos_r >= cos_limit)
        w_r = np.where(keep_r, np.clip(cos_r, 0.0, 1.0) ** normal_power, 0.0)
        w_r *= params.reverse_weight * subject.surface.vertex_areas / template_area
        weights = weights + np.bincount(nearest, w_r, minlength=len(fit))
        for axis in range(3):
            sums[:, axis] += np.bincount(nearest, w_r * subject.verts[:, axis], minlength=len(fit))
    targets = np.where(weights[:, None] > 0, sums / np.maximum(weights, 1e-300)[:, None], fit)
    return weights, targets, float(dist.mean())


def _bad_faces(aligned: np.ndarray, fit: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m,) faces that turned over against the pre-aligned template or intersect another face."""
    return flipped_faces(aligned, fit, faces) | self_intersecting_faces(fit, faces)


def _fold_free_part(system, reference: np.ndarray, faces: np.ndarray, x: np.ndarray, x_step: np.ndarray,
                    halvings: int = 4) -> tuple[np.ndarray, float]:
    """The longest fold-free part of a step that folded: x + t (x_step - x) for the largest
    t in 1/2, 1/4, ... (halvings of them) that turns over or crosses no face, and t (0 if none).

    x, x_step : (4n, 3) transforms of the last fold-free fit and of the folded step. The fit
    is linear in the transforms, so each blend moves every vertex t of its way along the step.
    """
    for k in range(1, halvings + 1):
        blend = x + 0.5**k * (x_step - x)
        if not _bad_faces(reference, system.apply(blend), faces).any():
            return blend, 0.5**k
    return x, 0.0


def _grow(faces: np.ndarray, vertex_mask: np.ndarray, rings: int) -> np.ndarray:
    """Vertex mask grown by `rings` rings of neighbours."""
    for _ in range(rings):
        vertex_mask = vertex_mask | np.bincount(
            faces.ravel(), np.repeat(vertex_mask[faces].any(axis=1), 3), minlength=len(vertex_mask)
        ).astype(bool)
    return vertex_mask


def nricp(
    aligned: np.ndarray, faces: np.ndarray, subject_verts: np.ndarray, subject_faces: np.ndarray,
    params: RegistrationParams,
    labels: tuple[np.ndarray, np.ndarray] | None = None,
    landmarks: tuple[sp.csr_matrix, np.ndarray] | None = None,
    start: np.ndarray | None = None,
) -> tuple[np.ndarray, dict]:
    """Fold-guarded optimal-step NICP of the pre-aligned template onto the subject.

    aligned : (n, 3) mm, faces : (m, 3), subject_* : the subject surface,
    labels : (template (n,), subject (p,)) structure labels for label-aware matches, or None,
    landmarks : (template landmark weights (k, n), subject landmark points (k, 3) mm) or None,
    start : (n, 3) mm the template warped towards the landmarks (the fit starts there; its
        stiffness still measures departures from `aligned`), or None (start from `aligned`).
    Folds are judged against `aligned`. With params.coarse_steps, the stiffest steps run
    first on the template simplified to params.coarse_vertices (_coarse_start).
    Returns the fitted vertices (n, 3) mm and a summary (JSON-ready): stiffness steps kept,
    fold-guard repeats, vertices stiffened, the fraction kept of each step that still folded
    after its repeats, and the coarse stage's own summary.
    """
    faces = np.asarray(faces, dtype=np.int64)
    frame = (aligned.mean(axis=0), float(np.linalg.norm(np.ptp(aligned, axis=0))))
    transforms, steps, coarse = None, range(len(params.stiffness)), None
    coarse_steps = min(params.coarse_steps, len(params.stiffness) - 1)
    if coarse_steps and len(aligned) >= 2 * params.coarse_vertices:
        transforms, coarse = _coarse_start(aligned, faces, subject_verts, subject_faces, params, labels, landmarks,
                                           start, frame, coarse_steps)
        if transforms is not None:
            start, steps = None, range(coarse_steps, len(params.stiffness))
    fitted, summary, _ = _fit(aligned, faces, subject_verts, subject_faces, params, labels, landmarks, start,
                              steps, frame, transforms)
    if coarse is not None:
        summary["coarse"] = coarse
        if steps.start:
            summary["step_distances_mm"] = coarse["step_distances_mm"] + summary["step_distances_mm"]
    return fitted, summary


def _coarse_start(
    aligned: np.ndarray, faces: np.ndarray, subject_verts: np.ndarray, subject_faces: np.ndarray,
    params: RegistrationParams,
    labels: tuple[np.ndarray, np.ndarray] | None,
    landmarks: tuple[sp.csr_matrix, np.ndarray] | None,
    start: np.ndarray | None,
    frame: tuple[np.ndarray, float],
    coarse_steps: int,
) -> tuple[np.ndarray | None, dict]:
    """The schedule's first coarse_steps (stiffest) steps on the template simplified to
    params.coarse_vertices, as a start for the rest at full resolution.

    A stiff step's transforms vary smoothly over the surface, and a quarter of the vertices
    carry them: the coarse steps cost a fraction of the full ones (their sparse
    factorisations most of all). The transforms, in the full template's normalised frame,
    are interpolated onto its vertices barycentrically, so the full steps' stiffness sees the
    coarse fit as it would see its own (a twist stays a transform varying linearly with
    position, which it leaves free). Labels go to the coarse vertices from the nearest full
    vertex, landmarks and the spline's start through the same interpolation.
    Returns the full template's transforms (n, 4, 3), or None where the simplification fails
    or the coarse fit diverged or was stopped by its fold guard (the whole schedule then runs
    at full resolution), and a summary (JSON-ready).
    """
    try:
        verts, coarse_faces = simplify(aligned, faces, params.coarse_vertices)
    except MeshError as error:
        return None, {"used": False, "reason": str(error)}
    to_full = interpolation_matrix(aligned, verts, coarse_faces)  # (n, n_c)
    _, summary, transforms = _fit(
        verts, coarse_faces, subject_verts, subject_faces, params,
        None if labels is None else (transfer_labels(aligned, labels[0], verts), labels[1]),
        None if landmarks is None else (sp.csr_matrix(landmarks[0] @ to_full), landmarks[1]),
        None if start is None else verts + interpolation_matrix(verts, aligned, faces) @ (start - aligned),
        range(coarse_steps), frame)
    report = {"vertices": len(verts), "steps": coarse_steps, "fold_repeats": summary["fold_repeats"],
              "partial_steps": summary["partial_steps"], "step_distances_mm": summary["step_distances_mm"]}
    if "diverged" in summary or summary["steps_kept"] < coarse_steps:
        reason = "diverged" if "diverged" in summary else "stopped by the fold guard"
        return None, report | {"used": False, "reason": reason}
    return (to_full @ transforms.reshape(len(verts), 12)).reshape(-1, 4, 3), report | {"used": True}


def _fit(
    aligned: np.ndarray, faces: np.ndarray, subject_verts: np.ndarray, subject_faces: np.ndarray,
    params: RegistrationParams,
    labels: tuple[np.ndarray, np.ndarray] | None,
    landmarks: tuple[sp.csr_matrix, np.ndarray] | None,
    start: np.ndarray | None,
    steps: range,
    frame: tuple[np.ndarray, float],
    transforms: np.ndarray | None = None,
) -> tuple[np.ndarray, dict, np.ndarray]:
    """nricp's fit at one resolution: the stiffness steps `steps` of the schedule, those before
    them having brought the template to `transforms` (n, 4, 3) (they count as kept; None: the
    identity), both in the normalised frame `frame` (centre (3,) mm, scale mm).
    Returns the fit (n, 3) mm, the summary and the final transforms (n, 4, 3)."""
    faces = np.asarray(faces, dtype=np.int64)
    centre, scale = frame
    reference = (aligned - centre) / scale
    template_labels, subject_labels = labels if labels is not None else (None, None)
    subject = Subject((np.asarray(subject_verts, dtype=np.float64) - centre) / scale, np.asarray(subject_faces),
                       subject_labels, template_labels)
    system = _AmbergSystem(reference, faces, params.gamma)
    rows, landmark_rhs = None, None
    if landmarks is not None and len(landmarks[1]) and params.landmark_weight > 0:
        rows = system.landmark_rows(landmarks[0])
        landmark_rhs = rows.T @ ((landmarks[1] - centre) / scale)
        # Shared among the landmarks, they weigh landmark_weight times the data term (n vertices).
        beta0 = params.landmark_weight * system.n / len(landmarks[1])
    template_area = float(_vertex_areas(reference, faces).mean())
    distance, converge = params.match_distance_mm / scale, params.converge_mm / scale

    # Rings weigh 1/spacing^4: the residual of an affine fit over a ring is spacing^2 times the
    # second derivatives of the transforms, so the stiffness does not depend on the resolution.
    base_weights = 1.0 / system.spacing**4
    vertex_weights = base_weights.copy()
    edge_weights = np.zeros(len(system.edges))
    x = system.identity() if transforms is None else transforms.reshape(-1, 3).copy()
    if start is not None:
        # Translations that put the fit at the start; the stiffness still measures departures
        # from the pre-aligned template, so the spline's guesses (poor far from the landmarks,
        # as at the apex) are not kept for free.
        x.reshape(system.n, 4, 3)[:, 3] += (start - centre) / scale - reference
    steps_kept, repeats, partials = steps.start, 0, []
    # Divergence monitor: the mean distance of the fit's vertices to their closest subject
    # points (measured anyway by the matches) and its flipped faces, every iteration. A fit
    # whose distance grows past divergence_growth times the least it reached (and by more
    # than max_mean_mm), or whose faces turn over in numbers (divergence_flipped of them),
    # is stopped at once at its last fold-free step; the caller retries or rejects it.
    least, diverged, history = np.inf, None, []
    factorisations = 0
    floor, too_many = params.max_mean_mm / scale, max(1, int(np.ceil(params.divergence_flipped * len(faces))))
    for step in steps:
        alpha, normal_power = params.stiffness[step], params.normal_weight[step]
        # A repeat goes on from the folded fit: flipped faces lose their matches (their normals
        # disagree), so the stiffened region relaxes back while the rest stays fitted.
        x_step, partial = x, 0.0
        beta = beta0 * alpha / params.stiffness[0] if rows is not None else 0.0
        for attempt in range(params.fold_retries + 1):
            stiffness = alpha**2 * system.stiffness(vertex_weights, edge_weights)
            fit = system.apply(x_step)
            precondition = None  # a new stiffness (a fold repeat's too): a new factorisation
            for iteration in range(params.step_iterations):
                weights, targets, mean_distance = _matches(fit, faces, subject, template_area, params, normal_power,
                                                           distance)
                flipped = int(flipped_faces(reference, fit, faces).sum())
                grew = mean_distance > params.divergence_growth * least and mean_distance - least > floor
                if grew or flipped >= too_many:  # least_mm None before a first measure (JSON holds no infinity)
                    diverged = {"reason": "surface distance grew" if grew else "faces flipped in numbers",
                                "step": step, "iteration": iteration, "mean_mm": mean_distance * scale,
                                "least_mm": least * scale if np.isfinite(least) else None, "flipped_faces": flipped}
                    break
                least = min(least, mean_distance)
                data, rhs = system.data(weights, targets)
                matrix = Operator((stiffness + data).tocsr(), rows, beta)
                if rows is not None:
                    rhs = rhs + beta * landmark_rhs
                if precondition is None:
                    precondition, factorisations = preconditioner(matrix.matrix, system.order), factorisations + 1
                # 1e-4: at 3e-4 the fits were 9-12 % faster but moved with the preconditioner's rounding (a smoke
                # subject's least label agreement 0.979 with SuperLU's LU, 0.966 with CHOLMOD's factor).
                x_step = pcg(matrix, rhs, x_step, precondition, rtol=1e-4, max_iterations=50)
                moved = system.apply(x_step)
                change = np.linalg.norm(moved - fit, axis=1).mean()
                fit = moved
                if change < converge:
                    break
            if diverged:
                break
            bad = _bad_faces(reference, fit, faces)
            if not bad.any():
                x, steps_kept = x_step, steps_kept + 1
                break
            if attempt == params.fold_retries:
                x, partial = _fold_free_part(system, reference, faces, x, x_step)
                partials.append(partial)
                break
            repeats += 1
            region = _grow(faces, np.bincount(faces[bad].ravel(), minlength=system.n).astype(bool), 2)
            vertex_weights[region] *= params.fold_stiffening
            inside = region[system.edges].all(axis=1)
            edge_weights[inside] = params.fold_stiffening * np.maximum(edge_weights[inside], system.edge_base[inside])
        history.append(round(least * scale, 4))
        if diverged or (bad.any() and not partial):
            break  # keep the last fold-free step
        if partial:  # the least distance was the folded step's, never kept: the next step measures afresh
            least = np.inf
    if diverged and steps_kept == 0:
        x = system.identity()  # a start that runs away is no fold-free step: back to the pre-aligned template
    summary = {
        "steps_kept": steps_kept,
        "steps": steps.stop,
        "fold_repeats": repeats,
        "factorisations": factorisations,
        "stiffened_vertices": int((vertex_weights > base_weights).sum()),
        # Per step that still folded after its repeats, the fraction of it kept (0: none, the fit ends).
        "partial_steps": partials,
        # Least mean vertex-to-subject distance (mm) reached by the end of each step run.
        "step_distances_mm": history,
    }
    if diverged:
        summary["diverged"] = {k: round(v, 4) if isinstance(v, float) else v for k, v in diverged.items()}
    return system.apply(x) * scale + centre, summary, x.reshape(system.n, 4, 3)
