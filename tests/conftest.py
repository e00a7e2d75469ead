"""Shared test helpers: small NIfTI writers and recipe builders."""

from __future__ import annotations

import textwrap
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest

from .data.make_bad import with_sform

ROOT = Path(__file__).resolve().parents[1]
MANIFESTS = ROOT / "manifests"


def pytest_collection_modifyitems(session, config, items):
    """Files with slow tests first: `make test` hands whole files to its processes in this
    order, so the long ones start at once and do not leave one process running alone at the end."""
    slow_files = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.path not in slow_files)  # stable: order within a file kept


def save_nifti(path: Path, data: np.ndarray, affine: np.ndarray | None = None) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    nib.save(nib.Nifti1Image(data, np.eye(4) if affine is None else affine), str(path))
    return path


def save_nifti_with_sform(path: Path, data: np.ndarray, sform: np.ndarray) -> Path:
    """Save with a NaN or singular sform, which nibabel refuses to write (patched into the header)."""
    assert path.suffix == ".nii"
    path.write_bytes(with_sform(nib.Nifti1Image(data, np.eye(4)).to_bytes(), sform))
    return path


def ball_volume(shape, voxel_mm, radius_mm, centre_mm=(0.0, 0.0, 0.0), axes_mm=None):
    """Boolean ellipsoid on a grid whose voxel centres are symmetric about 0, and its affine.

    Returns mask (X, Y, Z) bool and affine (4, 4) (voxel centre i at (i - (n-1)/2)·voxel).
    """
    voxel_mm = np.asarray(voxel_mm, float)
    axes = np.asarray(axes_mm if axes_mm is not None else (radius_mm,) * 3, float)
    coords = [(np.arange(n) - (n - 1) / 2) * v for n, v in zip(shape, voxel_mm)]
    X, Y, Z = np.meshgrid(*coords, indexing="ij")
    c = np.asarray(centre_mm)
    mask = ((X - c[0]) / axes[0]) ** 2 + ((Y - c[1]) / axes[1]) ** 2 + ((Z - c[2]) / axes[2]) ** 2 <= 1
    affine = np.diag([*voxel_mm, 1.0])
    affine[:3, 3] = -(np.asarray(shape) - 1) / 2 * voxel_mm
    return mask, affine


def write_recipe(path: Path, body: str) -> Path:
    path.write_text(textwrap.dedent(body))
    return path


@pytest.fixture
def tmp_recipe(tmp_path):
    def make(body: str, name: str = "recipe.toml") -> Path:
        return write_recipe(tmp_path / name, body)

    return make
