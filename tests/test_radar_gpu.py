"""The radar on a torch device (radar/gpu.py) against the numba echo and numpy imaging, and its plumbing.

CI has no GPU: the torch path runs on device "cpu" there, which checks the same code a
CUDA device runs; the "cuda" cases run where torch sees a GPU and are skipped elsewhere.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import meshsar_builder.radar.echo as RE  # noqa: E402
import meshsar_builder.radar.gpu as RG  # noqa: E402
import meshsar_builder.radar.params as RP  # noqa: E402
import meshsar_builder.radar.render as RR  # noqa: E402
import meshsar_builder.radar.visibility as RV  # noqa: E402
from meshsar_builder.pipeline import recipe as R  # noqa: E402
from meshsar_builder.pipeline.errors import MeshsarError  # noqa: E402
from meshsar_builder.radar.imaging import ImageParams, view_volume, volume_images  # noqa: E402

from .conftest import MANIFESTS  # noqa: E402

NO_CUDA = "no CUDA device: torch.cuda.is_available() is false"
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason=NO_CUDA))]
# A 160 mm aperture like the default's, sampled coarsely (aliased, which both paths share),
# and half the sweep: the demo heart's ~6,000 visible facets still make every sum long.
RADAR = dict(aperture=(10, 10), step_mm=16.0, n_samples=32, echo_decimation=(1, 1, 1))
IMAGES = ImageParams(size=48)
TOLERANCE = 1e-5  # relative L2, torch path against the CPU production path


def relative(got, expected) -> float:
    return float(np.linalg.norm(np.asarray(got) - expected) / np.linalg.norm(expected))


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """One torch thread: on a shared 2-core machine two spinning threads ran the sums ~10x slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def demo():
    from meshsar_builder.bench.suite import demo_mesh

    verts, faces = demo_mesh()
    return verts, faces, RV.embree_intersector(verts, faces)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("facet", ["po", "centroid", "random"])
def test_echo_and_images_match_the_cpu_path_on_the_demo_heart(demo, facet, device):
    verts, faces, intersector = demo
    radar = RP.RadarParams(**RADAR, facet=facet)
    points = RV.scatterer_points(verts, faces, facet, np.random.default_rng(3))
    freqs, (x, y) = RP.frequencies(radar), RP.aperture_axes(radar)
    for view in radar.views:
        vis, _ = RV.visibility(verts, faces, RP.probe_points(radar, view), intersector)
        seen = vis > 0
        args = (verts[faces][seen], vis[seen], RP.aperture_positions(radar, view), freqs, radar)
        cpu = RE.echo(*args, points=points[seen])
        got = RG.echo(*args, points=points[seen], device=device)
        assert got.dtype == np.complex128 and got.shape == cpu.shape
        assert relative(got, cpu) < TOLERANCE, (view, relative(got, cpu))
        cpu_volume = view_volume(cpu.reshape(10, 10, -1), freqs, x, y, radar.z0_mm, IMAGES)
        volume = RG.view_volume(got.reshape(10, 10, -1), freqs, x, y, radar.z0_mm, IMAGES, device=device)
        assert volume.dtype == np.complex64 and volume.shape == cpu_volume.shape
        assert relative(volume, cpu_volume) < TOLERANCE, (view, relative(volume, cpu_volume))
        images = volume_images(volume, freqs, radar.z0_mm, IMAGES)
        cpu_images = volume_images(cpu_volume, freqs, radar.z0_mm, IMAGES)
        for channel in range(len(IMAGES.channels)):
            assert relative(images[channel], cpu_images[channel]) < TOLERANCE, (view, channel)


@pytest.mark.parametrize("device", DEVICES)
def test_chunks_over_antennas_and_facets_sum_to_one_pass(monkeypatch, device):
    """A chunk budget far below one antenna's facets splits both axes; the sum is the same to rounding."""
    rng = np.random.default_rng(0)
    tri = rng.normal(size=(50, 3, 3)) * 3 + rng.normal(size=(50, 1, 3)) * 30
    radar = RP.RadarParams(aperture=(4, 3), echo_decimation=(1, 1, 1), n_samples=16)
    args = (tri, rng.random(50), RP.aperture_positions(radar, "left"), RP.frequencies(radar), radar)
    whole = RG.echo(*args, device=device)
    monkeypatch.setattr(RG, "CPU_CHUNK_BYTES", RG.BYTES_PER_TERM * 16 * 7)  # 7 facets of one antenna
    monkeypatch.setattr(RG, "DEVICE_CHUNK_BYTES", RG.BYTES_PER_TERM * 16 * 7)
    assert relative(RG.echo(*args, device=device), whole) < 1e-14
    assert relative(whole, RE.echo(*args, method="direct")) < 1e-12
    assert not RG.echo(tri[:0], np.ones(0), *args[2:], device=device).any()


@pytest.mark.parametrize("device", DEVICES)
def test_the_factorised_echo_on_a_device_follows_the_cpus_to_its_series_not_its_factorisation(monkeypatch, device):
    """The production echo on a device: the CPU's clusters, checks and interpolation on the device's grid sums.

    A bumpy sphere (not the phantom) under a 48 x 48 aperture, whose clusters get coarse
    grids (counted): on the device the grids are summed directly, so its echo follows the
    CPU's to the CPU's per-pair series (facets ~1e-9; the diffuse part's points at their
    series' 1e-5 truncation), far inside the factorisation's own error against the direct
    sum; "direct" on the device is the CPU's direct sum.
    """
    import trimesh

    import meshsar_builder.radar.diffuse as RD
    import meshsar_builder.radar.factorised as RF

    rng = np.random.default_rng(0)
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=35.0)
    verts = mesh.vertices * (1 + 0.08 * rng.standard_normal((len(mesh.vertices), 1)))
    faces = mesh.faces
    radar = RP.RadarParams(aperture=(48, 48), step_mm=3.5, n_samples=16, echo_decimation=(1, 1, 1))
    grids = []
    clusters = RF.factorised_clusters
    monkeypatch.setattr(RF, "factorised_clusters", lambda *a: grids.append(clusters(*a)) or grids[-1])
    freqs = RP.frequencies(radar)
    vis, _ = RV.visibility(verts, faces, RP.probe_points(radar, "anterior"), RV.embree_intersector(verts, faces))
    seen = vis > 0
    args = (verts[faces][seen], vis[seen], RP.aperture(radar, "anterior"), freqs, radar)
    cpu, got = RE.echo(*args), RG.echo(*args, device=device)
    direct = RE.echo(*args, method="direct")
    assert len(grids) == 2 and all(len(found[1]) >= 20 for found in grids)  # both echoes interpolated clusters
    assert relative(got, cpu) < 1e-8 and relative(cpu, direct) > 1e-6, (relative(got, cpu), relative(cpu, direct))
    assert relative(RG.echo(*args, device=device, method="direct"), direct) < 1e-12
    scatterers = RD.draw_scatterers(verts, faces, radar.diffuse_density_per_mm2, np.random.default_rng(1))
    lit = RD.seen_by(*RD.place(verts, faces, scatterers, radar), scatterers.face, vis)
    both = dict(diffuse=(*lit, RD.lambert(radar)), diffuse_on=RP.grid_indices(radar, (2, 2, 2)))
    (cpu, cpu_alone), (got, alone) = RE.echo(*args, **both), RG.echo(*args, **both, device=device)
    assert alone.shape == cpu_alone.shape == (24 * 24, 8)
    assert relative(got, cpu) < 1e-5 and relative(alone, cpu_alone) < 1e-5


# Runs radar/cuda_sum.py's kernel in numba's CUDA simulator: the variable must be set before numba loads.
SIMULATOR = """
import sys
import numpy as np
from meshsar_builder.radar import cuda_sum
from meshsar_builder.radar.params import RadarParams

case = np.load(sys.argv[1])
radar = RadarParams(rvp=bool(case["rvp"]), reflectivity=str(case["reflectivity"]))
edges = case["edges"] if case["edges"].size else None
np.save(sys.argv[2], cuda_sum.direct_sum(case["centres"], case["normals"], case["weights"], edges, case["positions"],
                                         case["freqs"], radar, first=case["first"], last=case["last"]))
"""


def in_simulator(script: str, *args: str) -> str:
    """Run a Python script in a process where numba's CUDA simulator stands in for a GPU; its stdout."""
    return subprocess.run([sys.executable, "-c", script, *args], env={**os.environ, "NUMBA_ENABLE_CUDASIM": "1"},
                          check=True, capture_output=True, text=True).stdout


@pytest.mark.parametrize("facet, rvp, reflectivity", [("po", True, "lobe"), ("point", False, "po")])
def test_the_cuda_kernel_equals_the_torch_direct_sum_in_numbas_simulator(tmp_path, rvp, reflectivity, facet):
    """The GPU's kernel, run on the CPU by numba's CUDA simulator (CI has no GPU), against echo_chunk's sum.

    Facets of a sphere seen from 3 antennas take the closed form, sub-millimetre ones the
    series (both counted below); 150 facets are several per lane, and 70 frequencies more
    groups than a block has warps, the last one partial; point scatterers carry complex
    weights (the diffuse part). Each antenna sums its own range of the facets, as on the
    factorised echo's grids: the first all, the others ranges that start and end off a
    warp's multiple, and one none.
    """
    import trimesh

    from meshsar_builder.radar.cuda_sum import GROUP, WARP, WARPS
    from meshsar_builder.radar.differentiable import SERIES_GAP

    rng = np.random.default_rng(1)
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=40.0)
    small = rng.normal(size=(30, 1, 3)) * 10 + rng.normal(size=(30, 3, 3)) * 0.3  # sub-millimetre facets
    tri = np.concatenate([sphere.vertices[sphere.faces][:120], small])
    centres, normals, areas = RV.triangle_geometry(tri)
    radar = RP.RadarParams(rvp=rvp, reflectivity=reflectivity, n_samples=70, echo_decimation=(1, 1, 1),
                           loss_decimation=(1, 1, 1))
    freqs = RP.frequencies(radar)
    positions = np.array([[0.0, 0.0, 200.0], [30.0, -20.0, 210.0], [-50.0, 10.0, 190.0], [0.0, 5.0, 200.0]])
    first, last = np.array([0, 37, 0, 60]), np.array([150, 150, 75, 60])
    weights = areas * rng.uniform(0.2, 1.0, len(areas))
    edges = tri - centres[:, None]
    if facet == "po":
        # the corner phases' spread per pair, as the kernel's branch sees it
        toward = positions[:, None] - centres[None]
        beta = -2 * np.einsum("mkc,kic->mki", toward, edges) / np.linalg.norm(toward, axis=-1)[..., None]
        spread = np.ptp(beta, axis=-1) * (2e-3 * np.pi / RP.SPEED_OF_LIGHT_M_PER_S) * freqs.min()
        assert 0 < (spread <= SERIES_GAP).sum() < spread.size  # both branches
    else:
        weights = weights * np.exp(1j * rng.uniform(0.0, 2 * np.pi, len(weights)))
    assert len(freqs) > WARPS * GROUP and len(freqs) % GROUP and len(tri) > 4 * WARP
    np.savez(tmp_path / "case.npz", centres=centres, normals=normals, weights=weights, positions=positions,
             freqs=freqs, edges=edges if facet == "po" else np.zeros(0), rvp=rvp, reflectivity=reflectivity,
             first=first, last=last)
    in_simulator(SIMULATOR, str(tmp_path / "case.npz"), str(tmp_path / "got.npy"))
    got = np.load(tmp_path / "got.npy")
    expected = np.zeros((4, 70), dtype=np.complex128)
    for m, (k0, k1) in enumerate(zip(first, last)):
        expected[m] = RG._torch_sum(centres[k0:k1], normals[k0:k1], weights[k0:k1], edges[k0:k1] if facet == "po"
                                    else None, positions[m:m + 1], freqs, radar, torch.device("cpu"))
    assert got.shape == expected.shape == (4, 70) and not got[3].any()
    # ~700 rad phases carry ~1e-13 rad of rounding, which the two sums round differently (measured 4-8e-14)
    assert relative(got, expected) < 1e-12, relative(got, expected)


def test_a_kernel_that_fails_to_compile_is_named_with_the_versions(tmp_path):
    """numba-cuda's compile errors (one release fails under numpy 2.5) come back naming the kernel and the versions."""
    script = """
import numpy as np
from meshsar_builder.pipeline.errors import MeshsarError
from meshsar_builder.radar import cuda_sum
from meshsar_builder.radar.params import RadarParams

class Broken:
    def __getitem__(self, config):
        def launch(*args):
            raise AttributeError("module 'numpy' has no attribute 'row_stack'")
        return launch

cuda_sum._kernel = lambda: Broken()
try:
    cuda_sum.direct_sum(np.zeros((1, 3)), np.array([[0, 0, 1.0]]), np.ones(1), None, np.array([[0, 0, 200.0]]),
                        np.array([7.7e10, 7.8e10]), RadarParams())
except MeshsarError as error:
    print(error)
"""
    out = in_simulator(script)
    assert "CUDA echo kernel failed to compile or run on cuda:0: AttributeError" in out
    assert "row_stack" in out and "numba " in out and "numpy " in out


def test_the_kernel_takes_evenly_spaced_frequencies_only():
    from meshsar_builder.radar.cuda_sum import uniform

    freqs = RP.frequencies(RP.RadarParams())
    assert uniform(freqs) and uniform(freqs[::2]) and uniform(freqs[:1])
    assert not uniform(np.r_[freqs[:5], freqs[6:]]) and not uniform(np.full(3, freqs[0]))


@pytest.mark.parametrize("device", DEVICES)
def test_render_sample_on_the_torch_path_adds_the_same_noise(monkeypatch, device):
    """The whole sample, noise included: it is drawn on the CPU from the same generator, so only rounding differs."""
    import trimesh

    mesh = trimesh.creation.icosphere(3, radius=40.0)
    radar = RP.RadarParams(aperture=(12, 12), step_mm=12.0, n_samples=24, echo_decimation=(2, 2, 2))
    images = ImageParams(size=32)
    cpu = RR.render_sample(mesh.vertices, mesh.faces, radar, images, np.random.default_rng(7))
    if device == "cpu":  # the torch functions, on the CPU: what device = "cuda" runs, elsewhere
        monkeypatch.setattr(RR, "view_functions", lambda device: RG.view_functions("cpu"))
    else:
        radar = dataclasses.replace(radar, device=device)
    got = RR.render_sample(mesh.vertices, mesh.faces, radar, images, np.random.default_rng(7))
    assert relative(got["echo"], cpu["echo"]) < TOLERANCE  # noise included: the same draws
    assert relative(got["sar"].astype(np.float32), cpu["sar"].astype(np.float32)) < 1e-3  # float16 steps
    for mine, theirs in zip(got["views"], cpu["views"]):
        assert mine["visible_facets"] == theirs["visible_facets"]
        assert mine["visible_scatterers"] == theirs["visible_scatterers"] > 0  # the diffuse part, on by default
        np.testing.assert_allclose(mine["diffuse_power"], theirs["diffuse_power"], rtol=1e-6)
        np.testing.assert_allclose(mine["noise_power"], theirs["noise_power"], rtol=1e-5)
        np.testing.assert_allclose(mine["noise_floor_db"], theirs["noise_floor_db"], atol=1e-4)


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA: the error is for machines without")
def test_cuda_without_cuda_fails_before_the_build_starts(tmp_path, capsys):
    from meshsar_builder.cli import main
    from meshsar_builder.pipeline.runner import build

    with pytest.raises(MeshsarError, match=r"\[radar\] device.*--device.*'cuda': CUDA is not available"):
        RG.check_device("cuda")
    recipe = R.override(R.load(MANIFESTS / "smoke.toml"), "radar", "device", "cuda", "--device")
    with pytest.raises(MeshsarError, match="CUDA is not available"):
        build(recipe, tmp_path / "out")
    assert not (tmp_path / "out" / "sources").exists()  # no stage ran
    assert main(["build", str(MANIFESTS / "smoke.toml"), "--out", str(tmp_path / "cli"), "--device", "cuda"]) == 2
    assert "--device" in capsys.readouterr().err
    # a stage that does not run needs no GPU
    assert build(recipe, tmp_path / "sources-only", until="sources").failures == []


def test_a_cuda_index_beyond_the_devices_is_named():
    if not torch.cuda.is_available():
        pytest.skip(NO_CUDA)
    with pytest.raises(MeshsarError, match="cuda:99.*sees"):
        RG.check_device("cuda:99")


def test_the_radar_stage_keeps_cpu_hashes_and_tags_gpu_items():
    from stages import radar as stage

    from meshsar_builder.pipeline.runner import Context

    recipe = R.load(MANIFESTS / "smoke.toml")
    ctx = Context(out=MANIFESTS, recipe=recipe)
    params = stage.item_params(ctx)
    assert "device" not in params and "device" not in params["radar"]  # the hash a CPU build had before
    assert stage.resources(ctx) is None
    for device in ("cuda", "cuda:1"):
        gpu = Context(out=MANIFESTS, recipe=R.override(recipe, "radar", "device", device, "--device"))
        assert stage.item_params(gpu) == {**params, "device": "cuda", "device_version": stage.GPU_VERSION}
        assert stage.resources(gpu) == {"GPU": 1}


# ------------------------------------------------------------------ Dask: GPU items go to GPU workers


def _where(ctx, item):
    from distributed import get_worker

    return {"worker": get_worker().name}


def _refuse(ctx, dask_worker=None):  # Client.run hands the worker to a `dask_worker` parameter
    raise MeshsarError(f"checked on {dask_worker.name}")


def test_dask_sends_resource_tagged_items_only_to_workers_with_the_resource(tmp_path):
    """A cluster of a CPU worker and a GPU=1 worker: tagged items all run on the latter; checks run there."""
    import dask
    from distributed import Scheduler, SpecCluster, Worker

    from meshsar_builder.pipeline.pools import SCHEDULE_WHEN_FREE, DaskPool
    from meshsar_builder.pipeline.runner import Context, Item, Results, Stage, check_stage, run_stage

    workers = {"cpu": {"cls": Worker, "options": {"nthreads": 1}},
               "gpu": {"cls": Worker, "options": {"nthreads": 1, "resources": {"GPU": 1}}}}
    scheduler = {"cls": Scheduler, "options": {"dashboard_address": ":0", "host": "127.0.0.1"}}
    ctx = Context(out=tmp_path, recipe=R.load(MANIFESTS / "smoke.toml"))
    items = lambda ctx, results: [Item(f"i{n}", ()) for n in range(8)]  # noqa: E731
    tagged = Stage(name="tagged", version=1, plan=items, run=_where, resources=lambda ctx: {"GPU": 1}, check=_refuse)
    needs_tpu = Stage(name="tpu", version=1, plan=items, run=_where, resources=lambda ctx: {"TPU": 1})
    with dask.config.set(SCHEDULE_WHEN_FREE), SpecCluster(workers=workers, scheduler=scheduler) as cluster:
        pool = DaskPool(cluster.scheduler_address)
        try:
            results = Results()
            run_stage(ctx, tagged, results, pool)
            assert {rec["worker"] for rec in results.of("tagged").values()} == {"gpu"}
            with pytest.raises(MeshsarError, match="checked on gpu"):  # the check ran where the items go
                check_stage(ctx, tagged, pool)
            with pytest.raises(MeshsarError, match=r"resources \{'TPU': 1\}.*--resources \"TPU=1\""):
                check_stage(ctx, needs_tpu, pool)
        finally:
            pool.close()


def test_bench_gpu_row_is_skipped_with_a_reason_or_filled(monkeypatch):
    """`meshsar bench radar --device cuda`'s row: a reason without CUDA; its numbers (here with "cuda" routed to
    the CPU), the diffuse part in the view's seconds, and the device's direct sum (the speed target's) against the
    CPU's."""
    import trimesh

    import meshsar_builder.radar.diffuse as RD
    from meshsar_builder.bench import radar as BR
    from meshsar_builder.bench import radar_gpu as BG

    mesh = trimesh.creation.icosphere(2, radius=40.0)
    verts, faces = mesh.vertices, mesh.faces
    radar, images = RP.RadarParams(aperture=(6, 6), step_mm=20.0, n_samples=16, echo_decimation=(1, 1, 1),
                                   views=("anterior", "left")), ImageParams(size=16)
    intersector = RV.embree_intersector(verts, faces)
    scatterers = RD.draw_scatterers(verts, faces, radar.diffuse_density_per_mm2, np.random.default_rng(0))
    cpu_views = [BR.view_seconds(verts, faces, intersector, radar, images, view, scatterers) for view in radar.views]
    if not torch.cuda.is_available():
        assert BG.gpu_row(verts, faces, radar, images, cpu_views, scatterers) == {"skipped": NO_CUDA}
        monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
        monkeypatch.setattr(RG, "check_device", lambda device: torch.device("cpu"))
        for name, value in (("get_device_name", "cpu"), ("reset_peak_memory_stats", None),
                            ("max_memory_allocated", 0)):
            monkeypatch.setattr(torch.cuda, name, lambda *args, value=value: value)
    cpu_views[0].update(BR.direct_check(verts, faces, radar, radar.views[0], cpu_views[0]))
    cpu_views[0]["seconds_echo_direct_scaled"] = 100.0
    row = BG.gpu_row(verts, faces, radar, images, cpu_views, scatterers)
    assert [v["view"] for v in row["views"]] == list(radar.views)
    for view in row["views"]:
        assert view["echo_relative_error"] < TOLERANCE and view["volume_relative_error"] < TOLERANCE
        assert view["seconds_view"] > view["seconds_echo"] + view["seconds_diffuse"] and view["seconds_diffuse"] > 0
        assert view["speedup_view"] > 0
        assert 0 <= view["intensity_max_difference"] < 1e-3 and 0.9 <= view["depth_within_one_slice"] <= 1
    first, second = row["views"]
    assert first["speedup_echo_direct"] == pytest.approx(100.0 / first["seconds_echo_direct"])
    assert all(0 <= view["echo_factorised_relative_error"] < 1e-4 for view in row["views"])
    assert first["echo_direct_relative_error"] < 1e-12  # the same model, summed directly on both
    assert "speedup_echo_direct" not in second and "echo_direct_relative_error" not in second
    targets = row["targets"]
    assert targets["speedup_echo_direct"]["measured_min"] == first["speedup_echo_direct"]
    worst = max(first["intensity_max_difference"], second["intensity_max_difference"])
    assert targets["intensity_max_difference"] == {"target": 1e-5, "measured_max": worst, "met": worst <= 1e-5}
    assert targets["depth_within_one_slice"]["met"] == (
        min(first["depth_within_one_slice"], second["depth_within_one_slice"]) >= 0.99)


@pytest.mark.slow  # starts a process cluster: ~10-20 s on 2 cores
def test_a_local_dask_cluster_can_take_gpu_items_and_keeps_the_allocators_defaults(monkeypatch):
    """`--scheduler local:N` workers share this machine's GPUs, so each declares one (a CUDA build can
    use them); and they run without Dask's MALLOC_TRIM_THRESHOLD_ (it cost their items ~15 % more CPU),
    with its one-thread settings kept."""

    from meshsar_builder.pipeline.pools import DaskPool

    import multiprocessing.forkserver

    # As in a `meshsar build` process: a Dask cluster started earlier in this test process has
    # written its nanny's variables into os.environ, and spawned workers inherit them.
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    # The workers fork from the workers' server, which has the environment it started with: one that an earlier test
    # started while a default Dask cluster's variable was in os.environ would hand it on. A build stops its server at
    # its end (pools.worker_server); here the pool starts its own.
    stop = getattr(multiprocessing.forkserver._forkserver, "_stop", None)
    if stop is not None:
        stop()
    pool = DaskPool("local:1")
    try:
        assert [have.get("GPU") for have in pool.worker_resources().values()] == [1]
        environ = pool.client.run(lambda: {k: os.environ.get(k) for k in ("MALLOC_TRIM_THRESHOLD_", "OMP_NUM_THREADS")})
        assert list(environ.values()) == [{"MALLOC_TRIM_THRESHOLD_": None, "OMP_NUM_THREADS": "1"}]
    finally:
        pool.close()
