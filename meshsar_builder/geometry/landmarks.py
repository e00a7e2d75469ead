"""Structure labels as registration cues: landmarks derived from vertex labels, per-structure agreement.

A landmark is a fixed weighted mean of mesh vertices (a sparse row of weights summing to 1),
so a fitted template moves its landmarks linearly with its vertices, which is what Amberg's
landmark term needs. From the labels alone, every mesh gets:
- `centroid:<s>`: the area-weighted centroid of structure s's surface patch;
- `ring:<a>-<b>`: the centre of the junction between structures a and b (the mean of the
  midpoints of the edges from one to the other), e.g. a valve or a vessel ring;
- `ring:<a>-<b>@<j>` (with `ring_points` K > 0): a mean of those midpoints weighted by a
  smooth window about the angle 2 pi j / K around the ring, in the plane of the midpoints (the
  least principal axis, turned from structure b's centroid toward a's, is its normal): K
  points along the ring, so its motion along the surface (a base descending along the
  ventricular walls) is seen, not only its centre's. Angles are counted in the ring's
  affine-normalised plane (whitened by the second moments of the region the ring encloses),
  so an in-plane affine motion (the shear of a twist, the shortening of a base descent, a
  contraction) moves the points with the tissue up to one turn; the turn's origin is the
  direction toward the centroid of the other structures (of the labelled surface if there
  are none), or, given the ring of a mesh to follow (`like`: a tracked frame's neighbour), the
  turn that best lays this ring's normalised shape onto that one's;
- `apex`: the mean of the ventricular (lv, myo) vertices within `APEX_BAND_MM` of the one
  farthest from the centroid of the other structures (the base of the heart); on a
  biventricular (short-axis) map, whose only other structure is the RV beside the LV, the one
  farthest along the inward normal of the LV's basal disc (the LV's patch on the union
  surface, the cut at the base).
Each landmark carries a confidence (how well the labels define it), and one that is ill
defined is dropped, its reason kept in `Landmarks.dropped` (the fit's report and sidecar):
- the apex only where the ventricle is elongated (the square root of the ratio of its two
  largest principal moments at least `APEX_MIN_ELONGATION`) and the base-to-apex direction
  runs along its long axis (|cos| at least `APEX_MIN_ALIGNMENT`): taken from the RV beside
  the LV, the farthest point is a lateral wall point that moves with every tessellation; its
  confidence is the smaller of the two ratios to their thresholds. On a biventricular map,
  where the disc's normals agree (|sum of area-weighted normals| / area at least
  `APEX_DISC_COHERENCE`) and the ventricle reaches at least `APEX_MIN_ELONGATION` disc radii
  below it; the confidence is again the smaller ratio;
- a junction ring only where the junction is at least `RING_MIN_MM` long (the length of the
  boundary curve through the midpoints of its crossing edges); confidence length / RING_MIN_MM.
Two meshes share the landmarks whose keys both have, so each pair means the same anatomy.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from meshsar_builder.geometry.measures import vertex_areas
from meshsar_builder.geometry.closest import point_to_surface
from meshsar_builder.geometry.structures import STRUCTURES

NAMES = {value: name for name, value in STRUCTURES.items()}
VENTRICLE = (STRUCTURES["lv"], STRUCTURES["myo"])
APEX_BAND_MM = 2.0
APEX_MIN_ELONGATION = 1.2
APEX_MIN_ALIGNMENT = 0.7
APEX_DISC_COHERENCE = 0.5
BIVENTRICULAR = {STRUCTURES["lv"], STRUCTURES["myo"], STRUCTURES["rv"]}
RING_MIN_MM = 20.0
RING_BINS = 360  # of a ring's radius profile, one a degree
RING_PROFILE_SMOOTHING_DEG = 6.0
RING_MAX_TURN_DEG = 30.0  # a ring follows its neighbour's by at most this turn
RING_MIN_CONTRAST = 0.02  # sd over mean of a profile to follow (a circle has none)
# Turned, a profile must match the one it follows to within this fraction of that one's variance.
# Known motion (affine in a junction's plane): <= 0.11 from ED to end-systole; real ED and ES frames
# alone (ACDC; the rings change shape): 0.23-2.1, where a turn lands at random (20-29 deg).
RING_MAX_MISFIT = 0.2


def structure_name(label: int) -> str:
    return NAMES.get(int(label), f"label{int(label)}")


def surface_regions(faces: np.ndarray, labels: np.ndarray, min_vertices: int) -> np.ndarray:
    """Labels (k,) that form a region of the surface: at least `min_vertices` vertices whose faces all carry it.

    faces : (m, 3) int, labels : (n,) int (0 = unlabelled, never a region). A structure that
    shows only as a strip between others has no centre and no patch of its own: on real
    whole-heart CT the LV's blood pool is exposed where a contact between structures was cut,
    13-41 mm^2 (16-33 vertices at 2.5 mm edges, 0-2 of them inside the strip), at a different
    place on every heart, where every anatomical patch has hundreds of inner vertices.
    """
    faces, labels = np.asarray(faces), np.asarray(labels)
    corners = labels[faces]
    on_boundary = np.zeros(len(labels), dtype=bool)
    on_boundary[faces[(corners != corners[:, :1]).any(axis=1)].ravel()] = True
    values, counts = np.unique(labels[~on_boundary], return_counts=True)
    return values[(values != 0) & (counts >= min_vertices)]


@dataclass(frozen=True)
class Landmarks:
    """keys: (k,) names; weights: (k, n) sparse, rows sum to 1 (landmark points = weights @ verts);
    confidence: (k,) >= 1 for a kept landmark (how far past its threshold; module docstring);
    dropped: ill-defined landmarks left out, key -> reason."""

    keys: tuple[str, ...]
    weights: sp.csr_matrix
    confidence: tuple[float, ...] = ()
    dropped: tuple[tuple[str, str], ...] = ()
    ring_shapes: dict[str, np.ndarray] = field(default_factory=dict)  # ring key -> (RING_BINS,) radius profile

    def points(self, verts: np.ndarray) -> np.ndarray:
        """verts (n, 3) -> landmark points (k, 3)."""
        return np.asarray(self.weights @ verts)

    def select(self, keys: list[str]) -> Landmarks:
        rows = [self.keys.index(k) for k in keys]
        confidence = tuple(self.confidence[r] for r in rows) if self.confidence else ()
        return Landmarks(tuple(keys), self.weights[rows], confidence, self.dropped, self.ring_shapes)


def label_landmarks(verts: np.ndarray, faces: np.ndarray, labels: np.ndarray, min_vertices: int = 10,
                    ring_points: int = 0, like: Landmarks | None = None) -> Landmarks:
    """Landmarks of a labelled surface (see the module docstring).

    verts : (n, 3) float mm, faces : (m, 3) int, labels : (n,) int (0 = unlabelled, skipped).
    Structures that form no region (surface_regions: fewer than `min_vertices` inner
    vertices) and junctions with fewer than `min_vertices` crossing edges give no landmark (a
    strip or a few stray vertices have no stable centre). ring_points: sector points per ring
    (0: none); like: landmarks of a mesh whose ring points these should follow (their
    `ring_shapes`; the module docstring).
    """
    verts, faces, labels = np.asarray(verts, dtype=np.float64), np.asarray(faces), np.asarray(labels).astype(np.int64)
    n = len(verts)
    areas = vertex_areas(verts, faces)
    keys, rows, confidence, dropped, shapes = [], [], [], [], {}

    def add(key: str, index: np.ndarray, weight: np.ndarray, sure: float = 1.0) -> None:
        keys.append(key)
        rows.append(sp.csr_matrix((weight / weight.sum(), (np.zeros(len(index), dtype=int), index)), shape=(1, n)))
        confidence.append(round(float(sure), 3))

    present = list(surface_regions(faces, labels, min_vertices))
    for s in present:
        index = np.flatnonzero(labels == s)
        add(f"centroid:{structure_name(s)}", index, areas[index])
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    pairs = labels[edges]
    for i, a in enumerate(present):
        for b in present[i + 1:]:
            crossing = np.unique(edges[((pairs[:, 0] == a) & (pairs[:, 1] == b)) | ((pairs[:, 0] == b) & (pairs[:, 1] == a))], axis=0)
            if len(crossing) >= min_vertices:
                key = f"ring:{structure_name(a)}-{structure_name(b)}"
                length = _junction_length(verts, faces, labels, a, b)
                if length < RING_MIN_MM:
                    dropped.append((key, f"junction {length:.1f} mm long < {RING_MIN_MM} mm"))
                    continue
                # Mean of the crossing edges' midpoints: on the boundary itself, not on one side of it.
                add(key, crossing.ravel(), np.ones(crossing.size), length / RING_MIN_MM)
                sectors = []
                if ring_points:
                    sectors, shapes[key] = _ring_sectors(verts, crossing, labels, a, b, ring_points,
                                                         None if like is None else like.ring_shapes.get(key))
                for j, chosen, weight in sectors:
                    add(f"{key}@{j}", chosen.ravel(), np.repeat(weight, 2), length / RING_MIN_MM)
    ventricle = np.isin(labels, VENTRICLE)
    base = (labels != 0) & ~ventricle
    disc = _basal_disc(verts, faces, labels) if set(present) <= BIVENTRICULAR else None
    if disc is not None and ventricle.sum() >= min_vertices:
        # A short-axis map: the LV shows as its basal cut, whose inward normal is the long axis
        # (within 1-5 deg of the slice normal on 8 real M&Ms maps, where a biventricular
        # union's principal axis runs 46-84 deg off it, toward the RV).
        centre, toward_apex, radius, coherence = disc
        index = np.flatnonzero(ventricle)
        along = (verts[index] - centre) @ toward_apex
        band = index[along >= along.max() - APEX_BAND_MM]
        length = float(along.max()) / radius
        if coherence < APEX_DISC_COHERENCE or length < APEX_MIN_ELONGATION:
            dropped.append(("apex", f"ill-defined: basal LV disc normals agree {coherence:.2f} (least "
                                    f"{APEX_DISC_COHERENCE}), ventricle length over disc radius {length:.2f} "
                                    f"(least {APEX_MIN_ELONGATION})"))
        else:
            add("apex", band, np.ones(len(band)),
                min(coherence / APEX_DISC_COHERENCE, length / APEX_MIN_ELONGATION))
    elif ventricle.sum() >= min_vertices and base.sum() >= min_vertices:
        index = np.flatnonzero(ventricle)
        distance = np.linalg.norm(verts[index] - verts[base].mean(axis=0), axis=1)
        band = index[distance >= distance.max() - APEX_BAND_MM]
        elongation, alignment = _apex_shape(verts[index], areas[index], verts[band].mean(axis=0) - verts[base].mean(axis=0))
        if elongation < APEX_MIN_ELONGATION or alignment < APEX_MIN_ALIGNMENT:
            dropped.append(("apex", f"ill-defined: ventricle elongation {elongation:.2f} (least {APEX_MIN_ELONGATION}), "
                                    f"base-to-apex along its long axis |cos| {alignment:.2f} (least {APEX_MIN_ALIGNMENT})"))
        else:
            add("apex", band, np.ones(len(band)), min(elongation / APEX_MIN_ELONGATION, alignment / APEX_MIN_ALIGNMENT))
    weights = sp.vstack(rows, format="csr") if rows else sp.csr_matrix((0, n))
    return Landmarks(tuple(keys), weights, tuple(confidence), tuple(dropped), shapes)


def _ring_sectors(verts: np.ndarray, crossing: np.ndarray, labels: np.ndarray, a: int, b: int, count: int,
                  like: np.ndarray | None = None) -> tuple[list[tuple[int, np.ndarray, np.ndarray]], np.ndarray | None]:
    """The `count` points along a junction ring (see the module docstring): ([(j, crossing edges
    (e, 2), their weights (e,))], the ring's radius profile (RING_BINS,) from its turn's origin,
    None where it has no origin). Point j weighs each crossing edge's midpoint by a smooth
    window of its normalised angle, exp(kappa (cos(angle - 2 pi j / count) - 1)), half its peak
    at half a sector's width: hard sectors would jump as midpoints cross their borders from one
    mesh to the next. A point whose window holds less than 2 edges' weight (a gap in an open
    junction) is left out. like: the profile of the ring to follow, or None."""
    mid = 0.5 * (verts[crossing[:, 0]] + verts[crossing[:, 1]])
    centre = mid.mean(axis=0)
    axes = np.linalg.eigh(np.cov((mid - centre).T))[1]
    normal = axes[:, 0]
    # Turned from b's side toward a's: a cap (a base's cavity patch) lies nearly in the ring's
    # plane, so its own centroid alone leaves the sign to chance.
    if (verts[labels == a].mean(axis=0) - verts[labels == b].mean(axis=0)) @ normal < 0:
        normal = -normal
    plane = np.stack([axes[:, 2], np.cross(normal, axes[:, 2])], axis=1)  # (3, 2), right-handed about normal
    flat = (mid - centre) @ plane
    region_centre, root = _region_moments(flat)
    whitened = (flat - region_centre) @ root  # (e, 2)
    # Counted from the structures beside the junction: the whole surface's centroid sits near
    # the axis of a ring around the largest structure, where its direction is unstable.
    others = (labels != 0) & (labels != a) & (labels != b)
    toward = ((verts[others if others.any() else labels != 0].mean(axis=0) - centre) @ plane - region_centre) @ root
    if np.linalg.norm(toward) < 1e-6:
        return [], None  # that centroid on the ring's axis: no direction to count from
    angle = np.arctan2(whitened[:, 1], whitened[:, 0]) - np.arctan2(toward[1], toward[0])
    radius = np.linalg.norm(whitened, axis=1)
    profile = _radius_profile(angle, radius)
    if like is not None:
        turn = _best_turn(profile, like)
        angle, profile = angle - turn, _radius_profile(angle - turn, radius)
    kappa = np.log(2.0) / (1.0 - np.cos(np.pi / count))
    out = []
    for j in range(count):
        weight = np.exp(kappa * (np.cos(angle - 2 * np.pi * j / count) - 1.0))
        keep = weight >= 1e-3
        if weight[keep].sum() >= 2.0:
            out.append((j, crossing[keep], weight[keep]))
    return out, profile


def _region_moments(flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The region a ring of points (e, 2) encloses, as the fan of triangles from their mean through
    them in angular order: (its centroid (2,), the inverse square root (2, 2) of its second
    moments, floored at 1e-6 of the larger; points along a line give their own moments). Both
    move with an affine map of the plane (each triangle's area scales alike), where the points'
    own moments follow their spacing along the ring."""
    start = flat.mean(axis=0)
    ring = flat[np.argsort(np.arctan2(*(flat - start).T[::-1]))] - start
    after = np.roll(ring, -1, axis=0)
    area = 0.5 * np.abs(ring[:, 0] * after[:, 1] - ring[:, 1] * after[:, 0])  # (e,)
    total = area.sum()
    if total > 0:
        centroid = (area[:, None] * (ring + after)).sum(axis=0) / (3 * total)
        # a triangle (0, u, v)'s second moment about 0: area (u u' + v v' + (u v' + v u') / 2) / 6
        second = np.einsum("e,ei,ej->ij", area / 6, ring, ring) + np.einsum("e,ei,ej->ij", area / 6, after, after) + (
            np.einsum("e,ei,ej->ij", area / 12, ring, after) + np.einsum("e,ei,ej->ij", area / 12, after, ring))
        covariance = second / total - np.outer(centroid, centroid)
    else:  # points along a line enclose nothing: their own moments
        centroid, covariance = np.zeros(2), ring.T @ ring / len(ring)
    values, vectors = np.linalg.eigh(covariance)
    values = np.maximum(values, 1e-6 * values.max())  # nor across a line
    return start + centroid, vectors @ np.diag(values ** -0.5) @ vectors.T


def _radius_profile(angle: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """(RING_BINS,) radius of a normalised ring at each degree, a Gaussian-weighted mean of its
    points' radii (e,) over their angles (e,) (rad)."""
    grid = np.linspace(-np.pi, np.pi, RING_BINS, endpoint=False)
    apart = np.angle(np.exp(1j * (grid[:, None] - angle[None, :])))  # (RING_BINS, e)
    weight = np.exp(-0.5 * (apart / np.radians(RING_PROFILE_SMOOTHING_DEG)) ** 2)
    return (weight @ radius) / np.maximum(weight.sum(axis=1), 1e-300)


def _best_turn(profile: np.ndarray, like: np.ndarray) -> float:
    """The turn (rad, within RING_MAX_TURN_DEG) of a ring's origin that lays its radius profile
    (RING_BINS,) best onto `like` (least squares, refined between degrees by a parabola); 0
    where `like` is too round to show one (RING_MIN_CONTRAST), the best lies at the limit, or
    the turned profile still misses `like` (RING_MAX_MISFIT): the ring changed its shape, not
    only its turn."""
    if np.std(like) < RING_MIN_CONTRAST * np.mean(like):
        return 0.0
    limit = int(RING_MAX_TURN_DEG * RING_BINS / 360)
    shifts = np.arange(-limit, limit + 1)
    cost = np.array([np.mean((np.roll(profile, -k) - like) ** 2) for k in shifts])
    best = int(np.argmin(cost))
    if best in (0, len(shifts) - 1) or cost[best] > RING_MAX_MISFIT * np.var(like):
        return 0.0
    left, mid, right = cost[best - 1:best + 2]
    step = 0.5 * (left - right) / max(left - 2 * mid + right, 1e-300)
    return float(np.radians((shifts[best] + step) * 360 / RING_BINS))


def _basal_disc(verts: np.ndarray, faces: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float] | None:
    """The LV's patch on a biventricular union surface, its basal cut: (area-weighted centre (3,),
    unit inward normal (3,) (toward the apex), radius of a disc of its area (mm), coherence
    |sum of area-weighted normals| / area (1 for a flat disc)), or None without LV faces."""
    patch = faces[(labels[faces] == STRUCTURES["lv"]).all(axis=1)]
    if not len(patch):
        return None
    corners = verts[patch]
    normals = 0.5 * np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # area-weighted
    areas = np.linalg.norm(normals, axis=1)
    area, total = float(areas.sum()), normals.sum(axis=0)
    if not np.linalg.norm(total) > 0:
        return None
    centre = (corners.mean(axis=1) * areas[:, None]).sum(axis=0) / area
    return centre, -total / np.linalg.norm(total), float(np.sqrt(area / np.pi)), float(np.linalg.norm(total) / area)


def _apex_shape(points: np.ndarray, weights: np.ndarray, direction: np.ndarray) -> tuple[float, float]:
    """Elongation (sqrt of the largest over the second principal moment) of weighted points (p, 3)
    and |cos| between `direction` (3,) and their long axis."""
    centred = points - np.average(points, axis=0, weights=weights)
    values, vectors = np.linalg.eigh((centred * weights[:, None]).T @ centred / weights.sum())
    elongation = float(np.sqrt(values[2] / max(values[1], 1e-12)))
    alignment = float(abs(vectors[:, 2] @ direction) / max(np.linalg.norm(direction), 1e-12))
    return elongation, alignment


def _junction_length(verts: np.ndarray, faces: np.ndarray, labels: np.ndarray, a: int, b: int) -> float:
    """Length (mm) of the boundary between structures a and b: in every face with corners of both
    (and no third label), the segment between the midpoints of its two edges that cross it."""
    corner = labels[faces]
    total = 0.0
    for odd in range(3):  # the corner whose label the other two do not share
        others = [(odd + 1) % 3, (odd + 2) % 3]
        mine = (corner[:, others[0]] == corner[:, others[1]]) & (corner[:, odd] != corner[:, others[0]]) & (
            np.isin(corner[:, odd], (a, b)) & np.isin(corner[:, others[0]], (a, b)))
        f = faces[mine]
        first = 0.5 * (verts[f[:, odd]] + verts[f[:, others[0]]])
        second = 0.5 * (verts[f[:, odd]] + verts[f[:, others[1]]])
        total += float(np.linalg.norm(first - second, axis=1).sum())
    return total


def common_landmarks(a: Landmarks, b: Landmarks) -> tuple[Landmarks, Landmarks]:
    """The landmarks both sets have, in one order."""
    keys = [k for k in a.keys if k in b.keys]
    return a.select(keys), b.select(keys)


def dropped_landmarks(a: Landmarks, b: Landmarks) -> dict[str, str]:
    """Landmarks either side dropped as ill-defined, key -> reason (template's first)."""
    out = {key: f"subject: {why}" for key, why in b.dropped}
    out |= {key: f"template: {why}" for key, why in a.dropped}
    return out


def face_labels(faces: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(m,) label of each face: the label most of its corners carry (the first corner's on a three-way tie)."""
    corners = np.asarray(labels)[np.asarray(faces)]
    second_third = corners[:, 1] == corners[:, 2]
    return np.where(second_third, corners[:, 1], corners[:, 0])


def label_agreement(
    fitted: np.ndarray, template_faces: np.ndarray, template_labels: np.ndarray, subject_verts: np.ndarray,
    subject_faces: np.ndarray, subject_labels: np.ndarray, min_vertices: int = 10,
) -> tuple[float, dict[str, float]]:
    """Overall and per-structure fraction of template vertices that land on their own structure.

    fitted : (n, 3), template_faces : (m, 3), template_labels : (n,), subject_verts : (p, 3),
    subject_faces : (q, 3), subject_labels : (p,). A vertex lands on structure s when the subject face holding its
    closest surface point has a corner labelled s. Vertex labels place a boundary between two
    structures only to within the strip of faces whose corners carry both, so a point in that
    strip is on either; splitting the strip by nearest vertex instead scores an exact
    correspondence 0.96-0.99 (two tessellations draw the split up to half an edge apart).
    Structures that form no region on the template (surface_regions with `min_vertices`) are
    left out of the per-structure figures: a strip is all boundary, and a few stray vertices
    give no meaningful fraction (the whole-heart LV strips scored 0.48-0.86 on fits whose
    every other structure agreed >= 0.978 at 0.13-0.26 mm).
    """
    subject_faces = np.asarray(subject_faces)
    _, face = point_to_surface(fitted, subject_verts, subject_faces)
    template_labels = np.asarray(template_labels)
    agree = (np.asarray(subject_labels)[subject_faces[face]] == template_labels[:, None]).any(axis=1)
    per = {structure_name(s): float(agree[template_labels == s].mean())
           for s in surface_regions(template_faces, template_labels, min_vertices)}
    return float(agree.mean()), per


def landmark_warp(points: np.ndarray, source: np.ndarray, target: np.ndarray, smoothing: float) -> np.ndarray:
    """Move points by the thin-plate spline (with an affine part) that takes landmarks `source` to `target`.

    points : (n, 3), source, target : (k, 3) mm, k >= 4 -> (n, 3). `smoothing` (mm^2 scale of
    the spline's regulariser) lets the spline miss landmarks that disagree a little (their
    positions depend on each mesh's label boundaries) rather than bend to them.
    """
    from scipy.interpolate import RBFInterpolator

    spline = RBFInterpolator(source, target - source, kernel="thin_plate_spline", smoothing=smoothing, degree=1)
    return points + spline(points)
