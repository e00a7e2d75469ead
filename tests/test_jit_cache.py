"""numba's on-disk cache stays sound: each cached kernel compiles one specialisation (radar/jit.py says why)."""

from __future__ import annotations

import sys

import numpy as np
import trimesh
from numba.core import types
from numba.core.caching import NullCache
from numba.core.registry import CPUDispatcher

import meshsar_builder.radar.factorised as RF
import meshsar_builder.radar.params as RP
from meshsar_builder.geometry.intersections import self_intersecting_faces
from meshsar_builder.geometry.ssm import SSMParams, build_model, specificity_draws


def cached_kernels() -> dict[str, CPUDispatcher]:
    """Every numba kernel of the loaded meshsar_builder modules that caches on disk."""
    return {f"{name}.{attr}": value for name, module in list(sys.modules.items())
            if name.startswith("meshsar_builder") for attr, value in vars(module).items()
            if isinstance(value, CPUDispatcher) and not isinstance(value._cache, NullCache)}


def test_kernels_fed_other_memory_layouts_keep_one_specialisation_each():
    """The calls that used to compile a second layout: the factorised echo onto a strided sub-grid beside the
    whole grid, the specificity's distances to Fortran-ordered training shapes, and the self-intersection check of
    read-only arrays (the ssm stage's shared model). Two specialisations of one kernel compiled by two processes
    at once can swap their machine code in the cache; literal constants (digital_topology's fixed arguments,
    compiled in one order inside their caller) do not count."""
    rng = np.random.default_rng(0)
    radar = RP.RadarParams(aperture=(24, 24), step_mm=6.0, echo_decimation=(1, 1, 1), loss_decimation=(1, 1, 1))
    normals = rng.normal(size=(400, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[:, 2] = np.abs(normals[:, 2])  # facing the anterior aperture
    points = 50.0 * normals
    weights = rng.normal(size=400) + 1j * rng.normal(size=400)
    grid, freqs = RP.aperture(radar, "anterior"), RP.frequencies(radar)
    parts = [(points, normals, weights, None, radar)]
    assert RF.factorised_clusters(points, points[:, None], grid, 2.0)[1], "no cluster: nothing is interpolated"
    whole = RF.echo_factorised(parts, grid, freqs)
    _, alone = RF.echo_factorised(parts, grid, freqs, last_on=(np.arange(1, 24, 3), np.arange(24), np.arange(0, 64, 2)))
    assert np.isfinite(whole).all() and np.isfinite(alone).all()

    shapes = rng.normal(size=(6, 50, 3)) * [30.0, 20.0, 10.0]
    model = build_model(shapes, np.zeros((0, 3), dtype=np.int64), variance=0.9)
    specificity_draws(model, np.asfortranarray(shapes), rng, SSMParams(specificity_samples=4), 2)

    sphere = trimesh.creation.icosphere(subdivisions=1)
    verts, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces, dtype=np.int64)
    self_intersecting_faces(verts, faces)
    verts.flags.writeable = faces.flags.writeable = False  # as the ssm stage's shared model
    self_intersecting_faces(verts, faces)

    kernels = cached_kernels()
    for name in ("meshsar_builder.radar.factorised._spread_cluster",
                 "meshsar_builder.geometry.ssm.nearest_mean_distance"):
        assert {t.layout for signature in kernels[name].signatures for t in signature
                if isinstance(t, types.Array)} == {"C"}, (name, kernels[name].signatures)
    specialised = {name: {tuple(types.unliteral(t) for t in signature) for signature in kernel.signatures}
                   for name, kernel in kernels.items()}
    assert all(len(found) <= 1 for found in specialised.values()), \
        {name: found for name, found in specialised.items() if len(found) > 1}
