"""The build's warm-up (the registered stages' Stage.warm hooks) compiles what the items run: after it, a
heart-sized surface's radar and surface checks compile nothing more in a process of their own (numba's on-disk
cache, in an empty folder here)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

WARM = """
import sys
from pathlib import Path
from meshsar_builder.pipeline.recipe import load
from meshsar_builder.pipeline.runner import Context, _warm, available_stages
recipe = load(sys.argv[1])
_warm(Context(Path("."), recipe), [stage.warm for stage in available_stages().values() if stage.warm is not None])
"""

ITEMS = """
import sys
import numpy as np
import trimesh
from meshsar_builder.geometry.intersections import self_intersecting_faces
from meshsar_builder.geometry.remesh import mesh_checks
from meshsar_builder.pipeline.recipe import load
from meshsar_builder.radar.render import render_sample
recipe = load(sys.argv[1])
sphere = trimesh.creation.icosphere(subdivisions=5)
rng = np.random.default_rng(1)
verts = sphere.vertices * [55.0, 45.0, 70.0] * (1 + 0.05 * np.sin(3 * sphere.vertices @ rng.normal(size=3)))[:, None]
faces = np.asarray(sphere.faces)
mesh_checks(verts, faces)
self_intersecting_faces(verts.astype(np.float32), faces.astype(np.int32))
render_sample(verts, faces, recipe.radar, recipe.images, np.random.default_rng(0))
"""


DEMO = str(Path(__file__).resolve().parents[1] / "manifests" / "demo.toml")


def _cache(folder):
    """The cache files of the radar's and the self-intersection test's kernels: name -> (size, mtime)."""
    return {p.relative_to(folder): (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*")
            if p.is_file() and (p.relative_to(folder).parts[0].startswith("radar") or "intersections." in p.name)}


def test_the_warm_up_leaves_a_surfaces_radar_and_checks_nothing_to_compile(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "OMP_NUM_THREADS": "1"}
    subprocess.run([sys.executable, "-c", WARM, DEMO], check=True, env=env, capture_output=True)
    warmed = _cache(tmp_path)
    assert any(name.parts[0].startswith("radar") for name in warmed)
    assert any("_self_intersections" in name.name for name in warmed)
    subprocess.run([sys.executable, "-c", ITEMS, DEMO], check=True, env=env, capture_output=True)
    assert _cache(tmp_path) == warmed
