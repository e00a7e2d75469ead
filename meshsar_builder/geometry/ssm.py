"""Statistical shape model: generalised Procrustes alignment, PCA, seeded sampling, quality.

Shapes are template fits that share one set of faces, so vertex i of every shape is the
same anatomical point. Alignment removes rotation and translation only: size is kept,
since it matters clinically.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
import trimesh

from meshsar_builder.geometry.intersections import self_intersecting_faces
from meshsar_builder.pipeline.errors import MeshError
from meshsar_builder.pipeline.io import atomic_path


@dataclass(frozen=True)
class SSMParams:
    """The recipe's [ssm] section.

    samples: shapes drawn from the model for the dataset.
    variance: cumulative fraction of the variance the kept modes explain.
    truncate_sigma: coefficients are drawn from N(0, lambda_i) truncated at +-truncate_sigma.
    max_redraws: redraws allowed per sample whose mesh self-intersects before it fails.
    procrustes_iterations: most generalised Procrustes iterations (stops earlier on convergence).
    specificity_samples: random shapes per number of modes for the specificity measure.
    specificity_items: items those draws are split into (stages/ssm.py), run side by side.
    samples_per_item: the dataset's samples are drawn in items of this many (stages/ssm.py),
        run side by side; each sample has its own seed, so the split changes no sample. Short
        items (125: 1.1-1.3 s each) run last and even out the workers' ends.
    """

    samples: int = 48
    variance: float = 0.98
    truncate_sigma: float = 3.0
    max_redraws: int = 20
    procrustes_iterations: int = 20
    specificity_samples: int = 1000
    specificity_items: int = 4
    samples_per_item: int = 125

    def __post_init__(self) -> None:
        if self.samples < 1:
            raise ValueError(f"samples: must be >= 1 (an SSM source with no samples adds nothing to the dataset), got {self.samples}")
        if not 0 < self.variance <= 1:
            raise ValueError(f"variance: must be in (0, 1], got {self.variance}")
        if not self.truncate_sigma > 0:
            raise ValueError(f"truncate_sigma: must be > 0, got {self.truncate_sigma}")
        if self.max_redraws < 0:
            raise ValueError(f"max_redraws: must be >= 0, got {self.max_redraws}")
        if self.procrustes_iterations < 1:
            raise ValueError(f"procrustes_iterations: must be >= 1, got {self.procrustes_iterations}")
        if self.specificity_samples < 1:
            raise ValueError(f"specificity_samples: must be >= 1, got {self.specificity_samples}")
        if not 1 <= self.specificity_items <= self.specificity_samples:
            raise ValueError(f"specificity_items: must be in [1, specificity_samples], got {self.specificity_items}")
        if self.samples_per_item < 1:
            raise ValueError(f"samples_per_item: must be >= 1, got {self.samples_per_item}")


@dataclass(frozen=True)
class ShapeModel:
    """A PCA shape model in the frame of its Procrustes mean (mm).

    mean : (n, 3) float, modes : (k, n, 3) float (orthonormal as vectors of R^3n),
    variances : (k,) float mm^2 (eigenvalues, descending), faces : (m, 3) int,
    total_variance : float mm^2, the variance of all modes including those dropped,
    labels : (n,) uint8 canonical structure id per vertex (the template's; 0 if unknown).
    """

    mean: np.ndarray
    modes: np.ndarray
    variances: np.ndarray
    faces: np.ndarray
    total_variance: float
    labels: np.ndarray | None = None

    def shape(self, coeffs: np.ndarray) -> np.ndarray:
        """Vertices (n, 3) of the shape mean + sum_i coeffs[i] modes[i], coeffs : (j,) with j <= k."""
        coeffs = np.asarray(coeffs, dtype=np.float64)
        return self.mean + np.tensordot(coeffs, self.modes[: len(coeffs)], axes=1)


def rigid_fit(moving: np.ndarray, fixed: np.ndarray) -> np.ndarray:
    """`moving` (n, 3) rotated and translated to best match `fixed` (n, 3) in least squares (Kabsch, no scale)."""
    _, aligned, _ = trimesh.registration.procrustes(moving, fixed, reflection=False, scale=False)
    return aligned


def population_pose(shapes: np.ndarray) -> np.ndarray:
    """(n, 3) the mean of the shapes (s, n, 3) after centring each on its centroid, without rotating any.

    The reference of the canonical frame when no template is given: a shape rotated onto it
    takes the pose that is closest, summed over every subject, to where the subjects lie in
    their scanner frame (RAS, DESIGN section 3), so the radar views keep their anatomical
    meaning. A sum over subjects, so it does not depend on their order. (With no common
    orientation among the inputs the pose is still order-free but anatomically arbitrary.)
    """
    shapes = np.asarray(shapes, dtype=np.float64)
    return (shapes - shapes.mean(axis=1, keepdims=True)).mean(axis=0)


def procrustes_align(
    shapes: np.ndarray, iterations: int = 20, tol_mm: float = 1e-9, reference: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Generalised Procrustes alignment by rotation and translation (scale kept), in a canonical frame.

    shapes : (s, n, 3) float, reference : (n, 3) float or None  ->  aligned (s, n, 3), mean (n, 3).
    The mean starts as the reference (else the first shape) centred at the origin and is
    updated until it moves less than tol_mm (root-mean-square over vertices) or `iterations`
    is reached. The converged mean is then rigidly fitted to the reference (e.g. the
    template, in its canonical frame), or without one to population_pose(shapes), and the
    shapes are aligned to it: the frame no longer follows whichever subject came first, so
    permuting the subjects leaves the result unchanged up to rounding.
    """
    shapes = np.asarray(shapes, dtype=np.float64)
    start = shapes[0] if reference is None else np.asarray(reference, dtype=np.float64)
    mean = start - start.mean(axis=0)
    for _ in range(iterations):
        aligned = np.stack([rigid_fit(shape, mean) for shape in shapes])
        new_mean = rigid_fit(aligned.mean(axis=0), mean)
        moved = np.sqrt(np.mean(np.sum((new_mean - mean) ** 2, axis=1)))
        mean = new_mean
        if moved < tol_mm:
            break
    mean = rigid_fit(mean, population_pose(shapes) if reference is None else reference)
    return np.stack([rigid_fit(shape, mean) for shape in shapes]), mean


def _pca(aligned: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean (n, 3), modes (r, n, 3) and variances (r,) of aligned shapes (s, n, 3), for the
    r <= s - 1 modes of non-zero variance (the others are arbitrary directions outside the data).

    Each mode's sign is fixed (its entry of largest magnitude is positive): SVD leaves it
    arbitrary, and it would otherwise flip with the order of the shapes.
    """
    count, n_verts, _ = aligned.shape
    mean = aligned.mean(axis=0)
    centred = (aligned - mean).reshape(count, 3 * n_verts)
    _, singular, vt = np.linalg.svd(centred, full_matrices=False)
    variances = singular**2 / max(count - 1, 1)
    rank = int(np.count_nonzero(variances > variances.sum() * 1e-12))
    vt = vt[:rank]
    vt *= np.sign(vt[np.arange(rank), np.abs(vt).argmax(axis=1)])[:, None]
    return mean, vt.reshape(rank, n_verts, 3), variances[:rank]


def build_model(
    shapes: np.ndarray, faces: np.ndarray, variance: float, procrustes_iterations: int = 20,
    labels: np.ndarray | None = None, reference: np.ndarray | None = None,
) -> ShapeModel:
    """Shape model of corresponding shapes : (s, n, 3) float with faces : (m, 3) int, labels : (n,) uint8.

    Keeps the fewest leading modes whose cumulative variance reaches `variance` of the total.
    The model lives in the frame of `reference` : (n, 3) (the template), or without one in
    the subjects' population pose (see procrustes_align); either way the subjects' order
    does not change it.
    """
    shapes = np.asarray(shapes, dtype=np.float64)
    if shapes.ndim != 3 or shapes.shape[2] != 3 or len(shapes) < 2:
        raise ValueError(f"shapes: need (s >= 2, n, 3), got {shapes.shape}")
    aligned, _ = procrustes_align(shapes, procrustes_iterations, reference=reference)
    mean, modes, variances = _pca(aligned)
    total = float(variances.sum())
    if not len(variances):
        raise MeshError(f"shape model: the {len(shapes)} aligned shapes are identical (total variance {total})")
    # The tolerance keeps variance=1.0 from depending on the last bits of a cumulative sum.
    kept = min(int(np.searchsorted(np.cumsum(variances) / total, variance - 1e-12) + 1), len(variances))
    return ShapeModel(
        mean=mean,
        modes=modes[:kept],
        variances=variances[:kept],
        faces=np.asarray(faces, dtype=np.int64),
        total_variance=total,
        labels=np.zeros(shapes.shape[1], np.uint8) if labels is None else np.asarray(labels, np.uint8),
    )


def save_model(path: str | Path, model: ShapeModel) -> None:
    """Write the model as npz (plain arrays, loads with allow_pickle=False) via a temporary name."""
    with atomic_path(path) as tmp:
        np.savez(
            tmp,
            mean=model.mean,
            modes=model.modes,
            variances=model.variances,
            faces=model.faces,
            total_variance=np.float64(model.total_variance),
            labels=model.labels,
        )


def load_model(path: str | Path) -> ShapeModel:
    """The model written by save_model."""
    with np.load(path, allow_pickle=False) as data:
        return ShapeModel(
            mean=data["mean"],
            modes=data["modes"],
            variances=data["variances"],
            faces=data["faces"],
            total_variance=float(data["total_variance"]),
            labels=data["labels"],
        )


def sample(model: ShapeModel, rng: np.random.Generator, truncate_sigma: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """One random shape: coeffs (k,) with b_i ~ N(0, lambda_i) truncated at +-truncate_sigma
    standard deviations (by redrawing the out-of-range entries), and its vertices (n, 3)."""
    standard = rng.standard_normal(len(model.variances))
    outside = np.abs(standard) > truncate_sigma
    while outside.any():
        standard[outside] = rng.standard_normal(int(outside.sum()))
        outside = np.abs(standard) > truncate_sigma
    coeffs = standard * np.sqrt(model.variances)
    return coeffs, model.shape(coeffs)


def sample_valid(
    model: ShapeModel, rng: np.random.Generator, params: SSMParams
) -> tuple[np.ndarray, np.ndarray, int]:
    """A random shape whose mesh does not self-intersect: coeffs (k,), vertices (n, 3), redraws made.

    Raises MeshError when params.max_redraws redraws all self-intersect.
    """
    counts = []
    for redraws in range(params.max_redraws + 1):
        coeffs, verts = sample(model, rng, params.truncate_sigma)
        count = int(self_intersecting_faces(verts, model.faces).sum())
        if count == 0:
            return coeffs, verts, redraws
        counts.append(count)
    raise MeshError(
        f"shape sample: all {params.max_redraws + 1} draws self-intersect "
        f"({min(counts)} to {max(counts)} self-intersecting faces)"
    )


def compactness(model: ShapeModel) -> np.ndarray:
    """(k,) cumulative fraction of the total variance explained by the first 1..k modes."""
    return np.cumsum(model.variances) / model.total_variance


def generalisation(shapes: np.ndarray, max_modes: int, procrustes_iterations: int = 20) -> np.ndarray:
    """(max_modes,) leave-one-out reconstruction error (mm) with 1..max_modes modes.

    For each shape, a model of the other shapes (all their modes) reconstructs it after a
    rigid fit to that model's mean; the error is the mean vertex distance between the
    aligned shape and its projection on the first j modes, averaged over shapes.
    A leave-one-out model has at most s - 2 modes; beyond them the error stays at its last value.
    """
    shapes = np.asarray(shapes, dtype=np.float64)
    errors = np.zeros((len(shapes), max_modes))
    for left_out in range(len(shapes)):
        rest = np.delete(shapes, left_out, axis=0)
        aligned, _ = procrustes_align(rest, procrustes_iterations)
        mean, modes, _ = _pca(aligned)
        target = rigid_fit(shapes[left_out], mean)
        flat_modes = modes.reshape(len(modes), -1)
        coeffs = flat_modes @ (target - mean).ravel()
        for j in range(max_modes):
            used = min(j + 1, len(flat_modes))
            recon = mean + (coeffs[:used] @ flat_modes[:used]).reshape(mean.shape)
            errors[left_out, j] = np.linalg.norm(recon - target, axis=1).mean()
    return errors.mean(axis=0)


def specificity_draws(
    model: ShapeModel, shapes: np.ndarray, rng: np.random.Generator, params: SSMParams, count: int
) -> tuple[np.ndarray, int]:
    """Draws for the specificity (Davies; Styner et al. 2003) as a function of the number of modes.

    For j = 1..k modes, `count` shapes are drawn through the dataset's own sampler
    (sample_valid: truncated coefficients, self-intersecting draws redrawn) from the model cut
    to its first j modes; each scores the mean vertex-to-vertex distance (mm) to the nearest
    training shape (rigidly fitted to the model mean). shapes : (s, n, 3).
    Returns the distances (k, count) and the redraws made.
    """
    # C order whatever rigid_fit returns: the kernel keeps one compiled specialisation (numba cache race: radar/jit.py)
    training = np.ascontiguousarray(np.stack([rigid_fit(shape, model.mean)
                                              for shape in np.asarray(shapes, dtype=np.float64)]))
    k = len(model.variances)
    distances, redraws = np.empty((k, count)), 0
    for j in range(1, k + 1):
        cut = ShapeModel(model.mean, model.modes[:j], model.variances[:j], model.faces, model.total_variance, model.labels)
        for i in range(count):
            _, verts, n = sample_valid(cut, rng, params)
            redraws += n
            distances[j - 1, i] = nearest_mean_distance(training, verts)
    return distances, redraws


@numba.njit(cache=True)
def nearest_mean_distance(shapes: np.ndarray, verts: np.ndarray) -> float:
    """The least over shapes (s, n, 3) of the mean vertex-to-vertex distance to verts (n, 3) (mm).

    One pass, no temporaries: the specificity makes one call per draw, and numpy's norms of
    (s, n, 3) differences took a fifth of a draw's time. A shape's sum stops once it exceeds the
    least so far (its terms are not negative), so the result is the full sum of the nearest shape.
    """
    least = np.inf
    for s in range(shapes.shape[0]):
        total = 0.0
        for v in range(shapes.shape[1]):
            dx, dy, dz = shapes[s, v, 0] - verts[v, 0], shapes[s, v, 1] - verts[v, 1], shapes[s, v, 2] - verts[v, 2]
            total += np.sqrt(dx * dx + dy * dy + dz * dz)
            if total > least:
                break
        least = min(least, total)
    return least / shapes.shape[1]


def model_quality(model: ShapeModel, shapes: np.ndarray, params: SSMParams) -> dict:
    """Compactness and generalisation per number of modes (JSON-ready); shapes : (s, n, 3)."""
    return {
        "modes": int(len(model.variances)),
        "variances_mm2": model.variances.tolist(),
        "compactness": compactness(model).tolist(),
        "generalisation_mm": generalisation(shapes, len(model.variances), params.procrustes_iterations).tolist(),
    }


def specificity_summary(distances: np.ndarray, redraws: int) -> dict:
    """Specificity per number of modes 1..k from its draws' distances (k, N) mm (JSON-ready);
    the scalars are the full model's."""
    mean, std = distances.mean(axis=1), distances.std(axis=1)
    return {
        "specificity_curve_mm": mean.tolist(),
        "specificity_curve_std_mm": std.tolist(),
        "specificity_draws": int(distances.shape[1]),
        "specificity_redraws": int(redraws),
        "specificity_mm": float(mean[-1]),
        "specificity_std_mm": float(std[-1]),
    }


def quality_report(model: ShapeModel, shapes: np.ndarray, rng: np.random.Generator, params: SSMParams) -> dict:
    """The standard SSM quality measures as JSON-ready values (mm, per number of modes), with
    params.specificity_samples specificity draws per number of modes in one run."""
    return model_quality(model, shapes, params) | specificity_summary(
        *specificity_draws(model, shapes, rng, params, params.specificity_samples))
