"""The stage runner end to end: sidecars, skipping, failures, resumption after a kill."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

from meshsar_builder.cli import main
from meshsar_builder.geometry.meshfile import read_ply
from meshsar_builder.pipeline import recipe as R
from meshsar_builder.pipeline.io import TMP_MARK
from meshsar_builder.pipeline.runner import build

from .conftest import MANIFESTS, ball_volume, save_nifti

NIFTI_RECIPE = """\
name = "own"
[[sources]]
kind = "nifti"
path = "{path}"
labels = {{ lv = 1, la = 4 }}
structures = ["lv"]
[meshing]
spacing_mm = {spacing}
"""


def nifti_folder(root: Path, n_good: int = 2) -> Path:
    for i in range(n_good):
        mask, affine = ball_volume((48, 48, 48), (1, 1, 1), 10 + 2 * i)  # inside the box: the border cuts none
        save_nifti(root / f"good{i}.nii.gz", mask.astype(np.int16), affine)
    return root


def outputs_of(out: Path, stage: str) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((out / stage).glob("*")) if p.suffix != ".json"}


def test_failures_are_named_and_the_rest_finishes(tmp_path, tmp_recipe, capsys):
    data = nifti_folder(tmp_path / "data")
    (data / "corrupt.nii.gz").write_bytes((data / "good0.nii.gz").read_bytes()[:200])
    save_nifti(data / "empty.nii.gz", np.zeros((10, 10, 10), np.int16))
    la_only = np.zeros((10, 10, 10), np.int16)
    la_only[3:7, 3:7, 3:7] = 4
    save_nifti(data / "la_only.nii.gz", la_only)
    recipe = tmp_recipe(NIFTI_RECIPE.format(path=data, spacing=1.0))
    out = tmp_path / "out"
    assert main(["build", str(recipe), "--out", str(out)]) == 1
    failures = {f["item"]: f for f in json.loads((out / "failures.json").read_text())}
    assert set(failures) == {"nifti-corrupt", "nifti-empty", "nifti-la_only"}
    assert "corrupt.nii.gz: not a readable NIfTI" in failures["nifti-corrupt"]["message"]
    assert "empty.nii.gz: none of the labels [1, 4] found" in failures["nifti-empty"]["message"]
    assert "la_only.nii.gz: none of the structures ['lv'] present (found: ['la'])" in failures["nifti-la_only"]["message"]
    assert sorted(outputs_of(out, "meshes")) == ["nifti-good0.ply", "nifti-good1.ply"]
    printed = capsys.readouterr().out
    assert "3 item(s) failed" in printed and "meshes/nifti-empty" in printed
    side = json.loads((out / "meshes" / "nifti-good1.json").read_text())
    assert side["euler"] == 2 and side["watertight"] and side["volume_ml"] == pytest.approx(4 / 3 * np.pi * 12**3 / 1000, rel=0.04)  # smoothing shrinks a small ball by ~σ²/R
    assert set(side["inputs"]) == {str(data / "good1.nii.gz")} and side["outputs"]["nifti-good1.ply"]


def test_rerun_skips_and_param_change_reruns(tmp_path, tmp_recipe):
    data = nifti_folder(tmp_path / "data")
    out = tmp_path / "out"
    first = build(R.load(tmp_recipe(NIFTI_RECIPE.format(path=data, spacing=1.0))), out, until="meshes")
    assert [r["ran"] for r in first.summary] == [1, 2]
    again = build(R.load(tmp_recipe(NIFTI_RECIPE.format(path=data, spacing=1.0))), out, until="meshes")
    assert [r["ran"] for r in again.summary] == [0, 0] and [r["skipped"] for r in again.summary] == [1, 2]
    changed = build(R.load(tmp_recipe(NIFTI_RECIPE.format(path=data, spacing=1.5))), out, until="meshes")
    assert [r["ran"] for r in changed.summary] == [0, 2]
    forced = build(R.load(tmp_recipe(NIFTI_RECIPE.format(path=data, spacing=1.5))), out, until="meshes", force=("meshes",))
    assert [r["ran"] for r in forced.summary] == [0, 2]
    # an edited input is remeshed, the other is not
    mask, affine = ball_volume((40, 40, 40), (1, 1, 1), 15)
    save_nifti(data / "good0.nii.gz", mask.astype(np.int16), affine)
    edited = build(R.load(tmp_recipe(NIFTI_RECIPE.format(path=data, spacing=1.5))), out, until="meshes")
    assert [r["ran"] for r in edited.summary] == [1, 1]



def test_a_moved_build_folder_stays_up_to_date(tmp_path, tmp_recipe, monkeypatch):
    """Sidecars name the build's own inputs relative to the folder: moving it, or reaching it by
    another path (relative from another directory, a cluster's mount), reruns nothing."""
    data = nifti_folder(tmp_path / "data")
    recipe = tmp_recipe(NIFTI_RECIPE.format(path=data, spacing=1.0))
    first = build(R.load(recipe), tmp_path / "out", until="remesh")
    assert [r["ran"] for r in first.summary] == [1, 2, 2]
    side = json.loads((tmp_path / "out" / "remesh" / "nifti-good0.json").read_text())
    assert set(side["inputs"]) == {"meshes/nifti-good0.ply"}
    (tmp_path / "out").rename(tmp_path / "moved")
    monkeypatch.chdir(tmp_path)
    again = build(R.load(recipe), Path("moved"), until="remesh")
    assert [r["ran"] for r in again.summary] == [0, 0, 0]
    # a changed input still reruns what reads it, whatever path it is reached by
    mesh = tmp_path / "moved" / "meshes" / "nifti-good0.ply"
    mesh.write_bytes(mesh.read_bytes() + b"\n")
    changed = build(R.load(recipe), tmp_path / "moved", until="remesh")
    assert [r["ran"] for r in changed.summary] == [0, 0, 1]

def test_killed_build_resumes_to_identical_outputs(tmp_path, tmp_recipe):
    data = nifti_folder(tmp_path / "data", n_good=6)
    recipe = tmp_recipe(NIFTI_RECIPE.format(path=data, spacing=0.5))
    clean, killed = tmp_path / "clean", tmp_path / "killed"
    assert build(R.load(recipe), clean, until="meshes").failures == []
    cmd = [sys.executable, "-m", "meshsar_builder.cli", "build", str(recipe), "--out", str(killed), "--until", "meshes"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    def sidecars():  # glob("*.json") also matches a sidecar's temporary, ".<item>.tmp-<pid>.json"
        return [p for p in (killed / "meshes").glob("*.json") if TMP_MARK not in p.name]

    while len(sidecars()) < 2 and time.time() < deadline and proc.poll() is None:
        time.sleep(0.01)
    assert proc.poll() is None, "build finished before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert len(sidecars()) < 6  # killed mid-stage
    resumed = build(R.load(recipe), killed, until="meshes")
    assert resumed.failures == [] and resumed.summary[1]["skipped"] >= 2
    assert outputs_of(killed, "meshes") == outputs_of(clean, "meshes")
    assert not [p for p in killed.rglob("*") if TMP_MARK in p.name]


def test_unknown_stage_is_refused(tmp_path, tmp_recipe, capsys):
    recipe = tmp_recipe(NIFTI_RECIPE.format(path=nifti_folder(tmp_path / "d", 1), spacing=1.0))
    assert main(["build", str(recipe), "--out", str(tmp_path / "o"), "--until", "nonsense"]) == 2
    assert "unknown stage 'nonsense'" in capsys.readouterr().err


@pytest.mark.slow
def test_smoke_recipe_meshes_are_closed_and_same_with_two_workers(tmp_path):
    recipe = R.load(MANIFESTS / "smoke.toml")
    one, two = tmp_path / "w1", tmp_path / "w2"
    r1 = build(recipe, one, until="meshes")
    assert r1.failures == []
    meshes = sorted((one / "meshes").glob("*.ply"))
    assert len(meshes) == 3 + 4  # three whole hearts, one beating subject's four frames
    for p in meshes:
        verts, faces, labels = read_ply(p)
        m = trimesh.Trimesh(verts, faces, process=False)
        assert m.is_watertight and m.euler_number == 2, p.name
        assert labels is not None and labels.min() >= 1
    wh = read_ply(one / "meshes" / "phantom_wh-ct_train_1001.ply")[2]
    # the blood pools are enclosed by myocardium, as in a real heart; the other six reach the surface
    assert set(np.unique(wh)) == set(range(2, 8))
    side = json.loads((one / "meshes" / "phantom_bv-patient001-f01.json").read_text())
    assert (side["phase"], side["provenance"], side["frame"]) == ("ED", "phantom", 1)
    # the beat's base plane descends toward the apex (8 mm slices: the apex is known to a slice)
    frames = [json.loads((one / "meshes" / f"phantom_bv-patient001-f{i:02d}.json").read_text()) for i in range(1, 5)]
    assert 10.0 <= max(f["base_mm"] for f in frames) - side["base_mm"] <= 15.0
    assert max(np.linalg.norm(np.subtract(f["apex_mm"], side["apex_mm"])) for f in frames) <= 8.0
    build(recipe, two, workers=2, until="meshes")
    for stage in ("sources", "meshes"):
        a = {p.relative_to(one / stage): p.read_bytes() for p in (one / stage).rglob("*") if p.is_file() and p.suffix != ".json"}
        b = {p.relative_to(two / stage): p.read_bytes() for p in (two / stage).rglob("*") if p.is_file() and p.suffix != ".json"}
        assert a == b


def test_lost_outputs_are_rebuilt_and_a_removed_source_is_named(tmp_path, tmp_recipe):
    data = nifti_folder(tmp_path / "data", n_good=1)
    recipe = tmp_recipe(NIFTI_RECIPE.format(path=data, spacing=1.0))
    out = tmp_path / "out"
    assert build(R.load(recipe), out, until="remesh").failures == []
    (out / "meshes" / "nifti-good0.ply").unlink()  # an upstream output lost: rebuilt, to the same bytes,
    (out / "meshes" / "nifti-good0.json").unlink()  # so remesh stays up to date
    again = build(R.load(recipe), out, until="remesh")
    assert again.failures == [] and [r["ran"] for r in again.summary] == [0, 1, 0]
    mesh_sidecar = out / "meshes" / "nifti-good0.json"
    mesh_sidecar.unlink()
    (out / "meshes" / "nifti-good0.ply").unlink()
    (data / "good0.nii.gz").unlink()  # now the source itself is gone
    r = build(R.load(recipe), out, until="remesh")
    assert [f["item"] for f in r.failures] == ["nifti"] and "no *.nii or *.nii.gz files" in r.failures[0]["message"]


def test_full_disk_stops_with_a_clear_error_and_keeps_finished_items(tmp_path, tmp_recipe, monkeypatch):
    import errno

    from meshsar_builder.pipeline import io as io_mod
    from meshsar_builder.pipeline.errors import MeshsarError

    data = nifti_folder(tmp_path / "data", n_good=3)
    recipe = R.load(tmp_recipe(NIFTI_RECIPE.format(path=data, spacing=1.0)))
    out = tmp_path / "out"
    build(recipe, out, until="meshes")
    kept = outputs_of(out, "meshes")
    (out / "meshes" / "nifti-good2.json").unlink()  # one item left to do
    (out / "meshes" / "nifti-good2.ply").unlink()
    real_replace = io_mod.os.replace

    def disk_full(suffix):
        def replace(src, dst):
            if not str(dst).endswith(suffix):
                return real_replace(src, dst)
            raise OSError(errno.ENOSPC, "No space left on device", str(dst))
        return replace

    monkeypatch.setattr(io_mod.os, "replace", disk_full(""))
    with pytest.raises(MeshsarError, match=r"out: output folder is not writable \(No space left on device\)"):
        build(recipe, out, until="meshes")
    monkeypatch.setattr(io_mod.os, "replace", disk_full(".ply"))
    with pytest.raises(MeshsarError, match=r"cannot write outputs \(No space left on device, at meshes/nifti-good2\)"):
        build(recipe, out, until="meshes")
    monkeypatch.setattr(io_mod.os, "replace", real_replace)
    assert outputs_of(out, "meshes") == {k: v for k, v in kept.items() if "good2" not in k}
    assert not [p for p in out.rglob("*") if TMP_MARK in p.name]
    assert build(recipe, out, until="meshes").failures == [] and outputs_of(out, "meshes") == kept


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def test_ctrl_c_stops_cleanly_and_the_rerun_resumes(tmp_path, tmp_recipe):
    data = nifti_folder(tmp_path / "data", n_good=6)
    # Copies under other names, meshed at 0.25 mm (~2 s an item): the build is still running when the signal
    # lands, even when a loaded machine lets this test poll only now and then.
    for i in range(6, 12):
        shutil.copy(data / f"good{i % 6}.nii.gz", data / f"good{i}.nii.gz")
    recipe = tmp_recipe(NIFTI_RECIPE.format(path=data, spacing=0.25))
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "meshsar_builder.cli", "build", str(recipe), "--out", str(out), "--until", "meshes",
           "--workers", "2"]
    # Its own session, so the SIGINT reaches the build and its workers as a terminal's Ctrl-C would.
    # Default SIGINT disposition and an empty signal mask, as a shell gives: pytest's own may differ.
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True,
                            preexec_fn=_default_sigint)
    deadline = time.time() + 120
    while not list((out / "meshes").glob("*.json")) and time.time() < deadline and proc.poll() is None:
        time.sleep(0.01)
    assert proc.poll() is None, "build finished before it could be interrupted"
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and b"rerun the same command to resume" in err, (proc.returncode, err.decode()[-3000:])
    assert not [p for p in out.rglob("*") if TMP_MARK in p.name]
    resumed = build(R.load(recipe), out, until="meshes")
    assert resumed.failures == [] and resumed.summary[1]["skipped"] >= 1


def _counting_stage(log: list):
    """A toy stage of passes: each pass's items add 1 to the previous pass's value, 3 passes."""
    from meshsar_builder.pipeline.runner import Item, Stage

    def plan(ctx, results):
        round_ = results.passes.get("count", 0)
        start = {i: rec["value"] for i, rec in results.of("count").items()} or {"a": 0, "b": 10}
        log.append(round_)
        return [Item(f"r{round_}-{i[-1]}", (f"r{round_}-{i[-1]}.json",), params={"start": v}) for i, v in start.items()]

    def run(ctx, item):
        (ctx.stage_dir("count") / item.outputs[0]).write_text("x")
        return {"value": item.params["start"] + 1}

    def again(ctx, results):
        return results.passes["count"] < 3

    return Stage(name="count", version=1, plan=plan, run=run, again=again)


def test_a_stage_runs_pass_after_pass_while_again_says_so_and_resumes(tmp_path):
    from meshsar_builder.pipeline.runner import Context, Results, run_stage

    log: list = []
    stage = _counting_stage(log)
    ctx = Context(out=tmp_path, recipe=None)
    results = Results()
    row = run_stage(ctx, stage, results)
    assert log == [0, 1, 2] and results.passes["count"] == 3
    # The last pass's records are the stage's: each value went through all three passes.
    assert {i: rec["value"] for i, rec in results.of("count").items()} == {"r2-a": 3, "r2-b": 13}
    assert (row["items"], row["ran"], row["skipped"], row["failed"]) == (6, 6, 0, 0)
    # A second run plans the same passes and skips every item.
    log.clear()
    row = run_stage(ctx, stage, Results())
    assert log == [0, 1, 2] and (row["ran"], row["skipped"]) == (0, 6)


def _timed_item(ctx, item):
    """A toy item: sleeps item.params["seconds"] (or fails as a full disk), writes its output, returns its times."""
    import errno

    start = time.time()
    if item.params.get("disk_full"):
        raise OSError(errno.ENOSPC, "No space left on device", item.id)
    time.sleep(item.params["seconds"])
    (ctx.stage_dir(item.id.split("-")[0]) / item.outputs[0]).write_text("x")
    return {"start": start, "end": time.time()}


def _toy_plan(name: str, seconds: list[float], disk_full: bool, costs: list[float] | None, ctx, results):
    from meshsar_builder.pipeline.runner import Item

    return [Item(f"{name}-{i}", (f"{name}-{i}.txt",), params={"seconds": s, "disk_full": disk_full},
                 cost=costs[i] if costs else 0.0) for i, s in enumerate(seconds)]


def _toy_stage(name: str, seconds: list[float], after=None, disk_full: bool = False, costs: list[float] | None = None):
    """A stage of items that sleep `seconds` each (workers get the stage pickled: no local functions)."""
    import functools

    from meshsar_builder.pipeline.runner import Stage

    return Stage(name=name, version=1, plan=functools.partial(_toy_plan, name, seconds, disk_full, costs),
                 run=_timed_item, after=after)


def _stage_times(results, name: str) -> tuple[float, float]:
    recs = results.of(name).values()
    return min(r["start"] for r in recs), max(r["end"] for r in recs)


def test_stages_that_do_not_read_each_other_share_the_workers(tmp_path):
    """b and c read only a: c's short items run beside b's long one; d (after all) waits for both;
    the summary keeps pipeline order though c finished first."""
    from meshsar_builder.pipeline.pools import LocalPool
    from meshsar_builder.pipeline.runner import Context, Results, run_stages

    stages = {"a": _toy_stage("a", [0.0]), "b": _toy_stage("b", [4.0], after=("a",)),
              "c": _toy_stage("c", [0.2, 0.2, 0.2], after=("a",)), "d": _toy_stage("d", [0.0])}
    results, pool = Results(), LocalPool(2)
    try:
        run_stages(Context(out=tmp_path, recipe=None), stages, results, pool)
    finally:
        pool.close()
    (a_start, a_end), (b_start, b_end), (c_start, c_end), (d_start, _) = (
        _stage_times(results, name) for name in "abcd")
    assert a_end <= min(b_start, c_start)
    assert c_end < b_end, "c waited for b: the stages ran one after the other"
    assert d_start >= max(b_end, c_end)
    assert [row["stage"] for row in results.summary] == ["a", "b", "c", "d"] and results.failures == []
    # One stage at a time without a pool (items in this process), with the same records.
    serial = Results()
    run_stages(Context(out=tmp_path / "serial", recipe=None), stages, serial)
    assert _stage_times(serial, "c")[0] >= _stage_times(serial, "b")[1]


def test_a_pool_starts_the_costliest_items_first_and_equal_ones_in_plan_order(tmp_path):
    """Item.cost is a hint: with workers, items start from the costliest (ties in plan order), so a long item
    planned last does not leave the other workers idle at the pass's end; in this process, plan order. The
    records keep plan order either way."""
    from meshsar_builder.pipeline.pools import LocalPool
    from meshsar_builder.pipeline.runner import Context, Results, run_stage

    costs = [1.0, 0.0, 5.0, 1.0, 3.0]
    stage = _toy_stage("a", [0.0] * len(costs), costs=costs)
    pool = LocalPool(1)  # one worker: items start in the order they were handed over
    try:
        for out, used in ((tmp_path / "pool", pool), (tmp_path / "here", None)):
            results = Results()
            run_stage(Context(out=out, recipe=None), stage, results, used)
            records = results.of("a")
            assert list(records) == [f"a-{i}" for i in range(len(costs))]
            started = sorted(records, key=lambda i: records[i]["start"])
            assert started == (["a-2", "a-4", "a-0", "a-3", "a-1"] if used else list(records)), started
    finally:
        pool.close()


def test_local_workers_start_with_the_stages_imported_and_their_pools_environment(monkeypatch):
    """The workers of a local pool and of a Dask LocalCluster are forked from a server that imported the
    stages beside the build's own imports (pools.start_worker_server), so a worker's first item does not wait
    for them; and a local worker has the environment of its pool's creator, not the server's from when the
    server started."""
    from meshsar_builder.pipeline.pools import WORKER_START, LocalPool, start_worker_server

    if WORKER_START != "forkserver":
        pytest.skip(f"no fork server on this platform: workers are {WORKER_START}ed")
    # In a fresh process: a server already running in this one keeps the preload it started with.
    loaded = "sorted(m for m in __import__('sys').modules if m.startswith('stages.'))"
    code = ("from meshsar_builder.pipeline.pools import DaskPool, LocalPool, server_modules, start_worker_server\n"
            "from meshsar_builder.pipeline.runner import stage_modules\n"
            "if __name__ == '__main__':\n"
            "    start_worker_server(server_modules(1, 'local:1', stage_modules()))\n"
            "    pool = LocalPool(1)\n"
            f"    print(pool.executor.submit(eval, {loaded!r}).result())\n"
            "    pool.close()\n"
            "    pool = DaskPool('local:1')\n"
            f"    print(pool.submit(eval, {loaded!r}).result())\n"
            "    pool.close()\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    from meshsar_builder.pipeline.runner import stage_modules

    assert run.stdout.split("\n")[:2] == [str(sorted(stage_modules()))] * 2, run.stdout + run.stderr
    start_worker_server([])  # running before the variable is set, as after a first build in this process
    monkeypatch.setenv("MESHSAR_TEST_VARIABLE", "set after the server started")
    pool = LocalPool(1)
    try:
        seen = pool.executor.submit(eval, "__import__('os').environ.get('MESHSAR_TEST_VARIABLE')").result()
    finally:
        pool.close()
    assert seen == "set after the server started"


def test_a_stage_that_stops_the_build_stops_the_stages_beside_it(tmp_path):
    """b finds the disk full while c has many items to go: the build raises b's error, c's pending
    items are cancelled, and no stage's thread is left running."""
    import threading

    from meshsar_builder.pipeline.errors import MeshsarError
    from meshsar_builder.pipeline.pools import LocalPool
    from meshsar_builder.pipeline.runner import Context, Results, run_stages

    stages = {"b": _toy_stage("b", [1.0], disk_full=True, after=()), "c": _toy_stage("c", [0.5] * 20, after=())}
    pool = LocalPool(2)
    try:
        with pytest.raises(MeshsarError, match=r"cannot write outputs \(No space left on device, at b/b-0\)"):
            run_stages(Context(out=tmp_path, recipe=None), stages, Results(), pool)
    finally:
        pool.close()
    assert not [t for t in threading.enumerate() if t.name.startswith("stage-")]
    assert len(list((tmp_path / "c").glob("c-*.json"))) < 20
    with pytest.raises(RuntimeError, match="names a stage that does not run before it"):
        run_stages(Context(out=tmp_path, recipe=None), {"b": _toy_stage("b", [0.0], after=("b",))}, Results(), pool)


def test_a_local_dask_cluster_keeps_its_periodic_work_off_the_items():
    """The LocalCluster's workers run without Dask's statistical profiler, 20 ms tick and 0.5 s system monitor
    (pools.QUIET_DASK): they sample and wake under the GIL of the item's thread."""
    import dask

    from meshsar_builder.pipeline.pools import QUIET_DASK, DaskPool

    def settings():
        return {key: dask.config.get(key) for key in QUIET_DASK}

    pool = DaskPool("local:1")
    try:
        assert list(pool.client.run(settings).values()) == [QUIET_DASK]
    finally:
        pool.close()


def _sleep_and_time(seconds: float, origin: float) -> tuple[str, float, float]:
    from distributed import get_worker

    start = time.time()
    time.sleep(seconds)
    return get_worker().address, start - origin, time.time() - origin


def test_a_local_dask_cluster_gives_a_worker_its_next_item_when_it_is_free():
    """A long item and three short ones on 2 workers: the shorts run one after the other on the worker that the
    long one leaves free. With Dask's default worker-saturation (1.1) the scheduler sent each worker two of them,
    and a short one queued behind the long item waited until work stealing moved it, measured 0.95 s late, or
    until the long one ended (pools.SCHEDULE_WHEN_FREE)."""
    from meshsar_builder.pipeline.pools import DaskPool

    pool = DaskPool("local:2")
    try:
        # The scheduler holds back a task group's tasks once it outnumbers the threads twice, as a build's items do
        # after its first few: so a few first.
        origin = time.time()
        for future in [pool.submit(_sleep_and_time, 0.01, origin) for _ in range(8)]:
            future.result()
        origin = time.time()
        futures = [pool.submit(_sleep_and_time, seconds, origin) for seconds in (2.0, 0.3, 0.3, 0.3)]
        (long_worker, _, long_end), *shorts = [future.result() for future in futures]
        assert long_worker not in {worker for worker, _, _ in shorts}, (long_worker, shorts)
        shorts.sort(key=lambda row: row[1])
        assert all(nxt[1] - prev[2] < 0.5 for prev, nxt in zip(shorts, shorts[1:])), shorts
        assert shorts[-1][2] < long_end, (shorts, long_end)
    finally:
        pool.close()


def test_a_dask_scheduler_that_sends_items_ahead_is_named_when_the_build_connects():
    """A scheduler started by hand keeps Dask's worker-saturation (1.1) unless told: the build warns with the
    setting to use, and says nothing to one started with it."""
    import warnings

    import dask
    from distributed import LocalCluster

    from meshsar_builder.pipeline.pools import SCHEDULE_WHEN_FREE, DaskPool

    for settings, warned in (({}, True), (SCHEDULE_WHEN_FREE, False)):  # a scheduler alone: no worker in this process
        with dask.config.set(settings), LocalCluster(n_workers=0, processes=False, dashboard_address=None) as cluster:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                pool = DaskPool(cluster.scheduler_address)
                pool.close()
        named = [w for w in caught if "DASK_DISTRIBUTED__SCHEDULER__WORKER_SATURATION=1.0" in str(w.message)]
        assert bool(named) == warned, [str(w.message) for w in caught]


def _record_warm(path, ctx):
    import os
    import threading

    with open(path, "a") as out:
        out.write(f"{os.getpid()} {threading.current_thread().name}\n")


def _failing_warm(ctx):
    raise RuntimeError("no compiler here")


def test_warm_hooks_run_once_in_the_builds_process_when_it_has_workers(tmp_path):
    """Stage.warm: once per stage, in a thread of the build's own process, with workers only; a hook that
    fails leaves the build to its items."""
    import dataclasses
    import functools
    import os
    import time

    from meshsar_builder.pipeline.pools import LocalPool
    from meshsar_builder.pipeline.runner import Context, Results, run_stages

    record = tmp_path / "warm.txt"
    stages = {"a": dataclasses.replace(_toy_stage("a", [0.0]), warm=_failing_warm),
              "b": dataclasses.replace(_toy_stage("b", [0.5]), warm=functools.partial(_record_warm, str(record)))}
    pool = LocalPool(2)
    try:
        results = Results()
        run_stages(Context(out=tmp_path / "pool", recipe=None), stages, results, pool)
    finally:
        pool.close()
    assert results.failures == [] and len(results.of("b")) == 1
    for _ in range(100):  # the hook's thread is a daemon: give it its moment
        if record.exists():
            break
        time.sleep(0.05)
    assert record.read_text() == f"{os.getpid()} warm-kernels\n"
    run_stages(Context(out=tmp_path / "serial", recipe=None), stages, Results())  # items in this process: no hooks
    assert record.read_text().count("\n") == 1


def test_dask_workers_load_pymeshlab_on_their_main_thread_and_exit_cleanly(capfd):
    """Dask runs tasks on a thread pool; pymeshlab loaded first there (after scipy.sparse) left glibc's heap
    corrupt and the worker aborted at exit. DaskPool has every worker load it on its main thread first."""
    from meshsar_builder.pipeline.pools import DaskPool

    # exec of source: unpickling the task imports nothing on the worker's main thread (a function of this file would
    # import its module there first); scipy.sparse before pymeshlab, as the register stage's modules load them.
    task = "import scipy.sparse, pymeshlab\npymeshlab.MeshSet()"
    pool = DaskPool("local:1")
    try:
        assert pool.client.submit(exec, task, {}, pure=False).result() is None
    finally:
        pool.close()
    assert "malloc" not in capfd.readouterr().err
