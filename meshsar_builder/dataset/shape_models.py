"""External shape models (mean surface, principal components, variances), e.g. the UK Digital Heart atlas."""

from __future__ import annotations

import gzip
import zlib
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from meshsar_builder.geometry.meshfile import read_ply
from meshsar_builder.geometry.structures import STRUCTURES
from meshsar_builder.pipeline.errors import InputError

if TYPE_CHECKING:
    from meshsar_builder.geometry.ssm import ShapeModel


# Principal components must be orthonormal columns to this tolerance (files store ~6 digits).
ORTHONORMAL_TOLERANCE = 1e-3


def read_surface(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A triangle surface from .ply, or .vtk (legacy) / .vtp polydata; polygons are triangulated,
    the point order kept (the model's components index it). Returns verts (n, 3) float64,
    faces (m, 3) int64; InputError naming the file when unreadable or without triangles."""
    path = Path(path)
    if path.suffix.lower() == ".ply":
        verts, faces, _ = read_ply(path)
    elif path.suffix.lower() in (".vtk", ".vtp"):
        import pyvista as pv  # only this reader needs it (slow to import)

        try:
            mesh = pv.read(str(path))
            surface = (mesh if isinstance(mesh, pv.PolyData) else mesh.extract_surface()).triangulate()
        except Exception as e:  # noqa: BLE001 (VTK raises many types; the message names the file)
            raise InputError(f"{path}: not a readable VTK surface ({type(e).__name__}: {e})") from e
        verts = np.asarray(surface.points, np.float64)
        faces = np.asarray(surface.faces, np.int64).reshape(-1, 4)[:, 1:] if surface.n_cells else np.zeros((0, 3), np.int64)
        if not np.all(np.isfinite(verts)):
            raise InputError(f"{path}: mesh has NaN or infinite vertex coordinates")
    else:
        raise InputError(f"{path}: mean surface must be .vtk, .vtp or .ply")
    if not len(faces):
        raise InputError(f"{path}: surface has no polygons")
    return verts, faces


def read_matrix(path: str | Path) -> np.ndarray:
    """A numeric table from .npy, or .csv / .csv.gz (comma or whitespace separated, an optional
    header line). Returns a 2-D float64 array (a single column or row as (n, 1))."""
    path = Path(path)
    try:
        if path.name.endswith(".npy"):
            data = np.load(path, allow_pickle=False)
        elif path.name.endswith((".csv", ".csv.gz", ".txt", ".txt.gz")):
            opener = gzip.open if path.name.endswith(".gz") else open
            with opener(path, "rt") as f:
                lines = [line.replace(",", " ") for line in f if line.strip()]
            try:
                [float(v) for v in lines[0].split()] if lines else None
            except ValueError:
                lines = lines[1:]  # a header line
            data = np.loadtxt(lines, ndmin=2) if lines else np.zeros((0, 0))
        else:
            raise InputError(f"{path}: must be .npy, .csv or .csv.gz")
    except (OSError, EOFError, zlib.error, gzip.BadGzipFile, ValueError) as e:
        raise InputError(f"{path}: not a readable numeric table ({type(e).__name__}: {e})") from e
    data = np.asarray(data, np.float64)
    if data.ndim == 1:
        data = data[:, None]
    if data.ndim != 2 or not data.size:
        raise InputError(f"{path}: expected a non-empty 2-D table, got shape {data.shape}")
    if not np.all(np.isfinite(data)):
        raise InputError(f"{path}: has NaN or infinite values")
    return data


def load_shape_model(
    files: dict[str, Path], n_modes: int = 0, labels: dict[str, int] | None = None, structure: str = ""
) -> ShapeModel:
    """An external PCA shape model: mean surface, components, variances, per-vertex labels.

    files : "mean", "modes", "variances" and optionally "vertex_labels" -> path. The components
        table has 3n rows, x, y, z of vertex 1, then of vertex 2, ... (as the UK Digital Heart
        atlas stores them), one orthonormal column per mode; variances one per mode (mm^2),
        descending. n_modes : leading modes kept (0: all). labels : {structure: value} mapping
        the vertex_labels values; without vertex_labels every vertex is `structure`.
    Returns a ShapeModel: mean (n, 3), modes (k, n, 3), variances (k,), faces (m, 3), labels
    (n,) canonical ids; total_variance sums every variance in the file. InputError names the
    file for each inconsistency.
    """
    # Imported here: recipe parsing imports this module and should not pay for trimesh.
    from meshsar_builder.geometry.ssm import ShapeModel

    verts, faces = read_surface(files["mean"])
    n = len(verts)
    components = read_matrix(files["modes"])
    if components.shape[0] != 3 * n:
        if components.shape[1] == 3 * n:
            hint = " (it has 3n columns: store one mode per column, not per row)"
        else:
            hint = ""
        raise InputError(f"{files['modes']}: {components.shape[0]} rows, expected 3 x {n} vertices of {files['mean'].name}{hint}")
    variances = read_matrix(files["variances"]).ravel()
    if len(variances) != components.shape[1]:
        raise InputError(f"{files['variances']}: {len(variances)} variances for {components.shape[1]} modes in {files['modes'].name}")
    if np.any(variances < 0) or np.any(np.diff(variances) > 1e-9 * variances.max()):
        raise InputError(f"{files['variances']}: variances must be >= 0 and in descending order")
    k = n_modes or len(variances)
    if k > len(variances):
        raise InputError(f"{files['modes']}: n_modes = {n_modes} but the file has {len(variances)} modes")
    gram = components[:, :k].T @ components[:, :k]
    off = float(np.abs(gram - np.eye(k)).max())
    if off > ORTHONORMAL_TOLERANCE:
        raise InputError(f"{files['modes']}: columns are not orthonormal principal directions (|C^T C - I| up to {off:.3g}); "
                         f"if they are scaled by the standard deviations, divide them out")
    if "vertex_labels" in files:
        values = read_matrix(files["vertex_labels"]).ravel()
        if len(values) != n:
            raise InputError(f"{files['vertex_labels']}: {len(values)} labels for {n} vertices of {files['mean'].name}")
        if not np.all(values == np.round(values)):
            raise InputError(f"{files['vertex_labels']}: labels must be integers")
        values = values.astype(np.int64)
        table = {v: STRUCTURES[name] for name, v in (labels or {}).items()}
        unknown = sorted(set(np.unique(values).tolist()) - set(table))
        if unknown:
            raise InputError(f"{files['vertex_labels']}: values {unknown[:10]} not in the label table {labels}")
        vertex_labels = np.array([table[v] for v in values], np.uint8)
    else:
        vertex_labels = np.full(n, STRUCTURES[structure], np.uint8)
    return ShapeModel(
        mean=verts,
        modes=components[:, :k].T.reshape(k, n, 3),
        variances=variances[:k],
        faces=faces,
        total_variance=float(variances.sum()),
        labels=vertex_labels,
    )
