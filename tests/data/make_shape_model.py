"""Write a small synthetic PCA shape model in the UK Digital Heart atlas file format, tests/data/shape_model/.

Run from the repository root: python tests/data/make_shape_model.py (the files are committed;
rerunning rewrites the same bytes). The format, as the atlas ships it:
- mean.vtk: legacy ASCII VTK polydata, the mean surface (mm);
- modes.csv.gz: gzipped CSV, 3n rows (x1, y1, z1, x2, ...: xyz interleaved per vertex), one
  column per mode, each column a unit principal direction;
- variances.csv: one variance (mm^2) per mode, descending;
- labels.csv: one label value per vertex (10 on the superior half, 20 on the inferior half).
The mean is an ellipsoid (semi-axes 35, 30, 45 mm); the modes are, orthonormalised in this
order, a uniform scaling, a stretch along z and an x-against-y anisotropy, with standard
deviations of 8 %, 6 % and 4 % of the mean's norm.
"""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import trimesh

FOLDER = Path(__file__).resolve().parent / "shape_model"
SEMI_AXES_MM = (35.0, 30.0, 45.0)
STD_FRACTIONS = (0.08, 0.06, 0.04)


def synthetic_model() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """mean (n, 3), faces (m, 3), components (3n, k) orthonormal columns, variances (k,), labels (n,)."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    mean = np.round(sphere.vertices * SEMI_AXES_MM, 4)
    x, y, z = mean.T
    zero = np.zeros_like(x)
    raw = np.stack([mean.ravel(), np.stack([zero, zero, z], 1).ravel(), np.stack([x, -y, zero], 1).ravel()], axis=1)
    components, _ = np.linalg.qr(raw)
    components *= np.sign(np.diag(components.T @ raw))  # the sign of each input direction kept
    variances = (np.asarray(STD_FRACTIONS) * np.linalg.norm(mean)) ** 2
    labels = np.where(z >= 0, 10, 20)
    return mean, np.asarray(sphere.faces), components, variances, labels


def vtk_text(verts: np.ndarray, faces: np.ndarray) -> str:
    lines = ["# vtk DataFile Version 3.0", "synthetic shape model mean", "ASCII", "DATASET POLYDATA",
             f"POINTS {len(verts)} float", *(f"{a:.4f} {b:.4f} {c:.4f}" for a, b, c in verts),
             f"POLYGONS {len(faces)} {4 * len(faces)}", *(f"3 {a} {b} {c}" for a, b, c in faces)]
    return "\n".join(lines) + "\n"


def main() -> None:
    FOLDER.mkdir(exist_ok=True)
    mean, faces, components, variances, labels = synthetic_model()
    (FOLDER / "mean.vtk").write_text(vtk_text(mean, faces))
    csv = "\n".join(",".join(f"{v:.9f}" for v in row) for row in components) + "\n"
    (FOLDER / "modes.csv.gz").write_bytes(gzip.compress(csv.encode(), mtime=0))
    (FOLDER / "variances.csv").write_text("\n".join(f"{v:.6f}" for v in variances) + "\n")
    (FOLDER / "labels.csv").write_text("\n".join(str(v) for v in labels) + "\n")


if __name__ == "__main__":
    main()
