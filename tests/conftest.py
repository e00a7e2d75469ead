"""Shared test helpers: small NIfTI writers and recipe builders."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest

from .data.make_bad import with_sform

ROOT = Path(__file__).resolve().parents[1]
MANIFESTS = ROOT / "manifests"


# Measured seconds per test file (`make test PYTEST_ARGS=--store-durations` updates it): the order
# `make test` hands whole files to its processes in.
DURATIONS = Path(__file__).with_name("durations.json")
UNMEASURED_SLOW_S = 60.0  # a file not yet measured that has slow tests: among the long ones
_file_seconds: dict[str, float] = {}  # this run's, for --store-durations


def pytest_addoption(parser):
    parser.addoption("--store-durations", action="store_true",
                     help=f"update {DURATIONS.name} with the seconds each test file of this run took")


def pytest_collection_modifyitems(session, config, items):
    """The longest files first (xdist runs with --no-loadscope-reorder, so this order holds): the
    processes take whole files as they free up, and no long file starts last to run alone."""
    measured = json.loads(DURATIONS.read_text()) if DURATIONS.exists() else {}
    slow_files = {item.path for item in items if item.get_closest_marker("slow")}

    def seconds(item) -> float:
        name = item.path.relative_to(ROOT).as_posix()
        return measured.get(name, UNMEASURED_SLOW_S if item.path in slow_files else 0.0)

    items.sort(key=lambda item: -seconds(item))  # stable: order within a file kept


def pytest_runtest_logreport(report):
    file = report.nodeid.split("::")[0]
    _file_seconds[file] = _file_seconds.get(file, 0.0) + report.duration  # setup, call and teardown


def pytest_sessionfinish(session):
    """With --store-durations, the files this run took updated in DURATIONS (the others kept)."""
    # the controller (or a run without xdist) sees every file's reports; workers see their own
    if session.config.getoption("--store-durations") and not hasattr(session.config, "workerinput"):
        table = {**(json.loads(DURATIONS.read_text()) if DURATIONS.exists() else {}),
                 **{k: round(v, 1) for k, v in _file_seconds.items()}}
        DURATIONS.write_text(json.dumps(dict(sorted(table.items(), key=lambda kv: -kv[1])), indent=1) + "\n")


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
