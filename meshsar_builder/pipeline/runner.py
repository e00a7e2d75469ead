"""The stage runner: plans items, skips what is up to date, maps the rest over a pool.

A stage (a module in `stages/`, registered under the `meshsar.stages` entry
point group) gives the runner a `Stage`: a plan function listing its items
and a per-item function that writes the item's outputs. The runner owns the
bookkeeping every stage shares:

- a JSON sidecar per item, `<out>/<stage>/<item>.json`, written last and
  atomically, holding the input digests, the parameter hash, the code version,
  output digests and what the item function returned; an item whose sidecar
  matches and whose outputs exist is skipped;
- failures: an exception in an item is recorded (stage, item, type, message)
  and the batch goes on; failures.json and the summary list them at the end;
- temporaries left by a killed run are removed before a stage runs (safe: the build
  holds the folder's lock, lock.py, so no other build has files in flight there);
- passes: a stage whose items feed another round of itself (the register stage's
  groupwise template) is planned and run again while its `again` hook says so; each
  pass is planned after the previous one finished, its items still run side by side
  and are skipped when up to date, and `Results.passes` counts the passes run so far.

The runner never imports a stage; stages import the library.
"""

from __future__ import annotations

import errno
import os
import queue
import sys
import threading
import time
import traceback
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, Callable

from threadpoolctl import threadpool_limits
from tqdm import tqdm

from meshsar_builder import __version__
from meshsar_builder.pipeline.errors import MeshsarError
from meshsar_builder.pipeline.io import (
    read_json,
    remove_stale_temporaries,
    sha256_file,
    sha256_json,
    write_bytes,
    write_json,
)
from meshsar_builder.pipeline.lock import folder_lock
from meshsar_builder.pipeline.pools import make_pool, server_modules, stage_resources, worker_server
from meshsar_builder.pipeline.recipe import Recipe

# A full disk, a read-only or unwritable output folder, an exhausted quota.
UNWRITABLE = {errno.ENOSPC, errno.EROFS, errno.EACCES, errno.EDQUOT}

# How long a stopping build waits for each stage still running in a thread of its own (run_stages) to let go:
# its pool is closed by then, so a stage is at most in its own main-process work (a register template).
STOP_SECONDS = 60.0
STAGE_ORDER = ("sources", "meshes", "remesh", "track", "register", "ssm", "radar", "shards", "card")


@dataclass(frozen=True)
class Item:
    """One unit of work of a stage. `data` travels to the item function; `params` are hashed."""

    id: str
    outputs: tuple[str, ...]  # paths relative to the stage folder
    inputs: tuple[str, ...] = ()  # files whose content the outputs depend on
    params: Any = None  # JSON-able: what, besides inputs, the outputs depend on
    data: Any = None
    # Expected run time relative to the pass's other items (not hashed): a pool starts the costliest first, so a
    # pass does not end on one long item started last while the other workers idle (longest processing time first).
    cost: float = 0.0


@dataclass(frozen=True)
class Context:
    """What an item function may know about the build."""

    out: Path
    recipe: Recipe

    def stage_dir(self, stage: str) -> Path:
        return self.out / stage

    def sidecar(self, stage: str, item_id: str) -> Path:
        return self.out / stage / f"{item_id}.json"


@dataclass(frozen=True)
class Stage:
    name: str
    version: int  # bump when the stage's code changes its outputs
    plan: Callable[[Context, "Results"], list[Item]]
    run: Callable[[Context, Item], dict]
    # Runs in the main process after every item: for outputs that depend on all items
    # (e.g. an index holding each shard's digest), which no single item can write.
    finish: Callable[[Context, "Results"], object] | None = None
    # Dask worker resources each item needs (e.g. {"GPU": 1}), or None: only workers
    # started with those resources take the stage's items. Local pools ignore them.
    resources: Callable[[Context], dict | None] | None = None
    # Raises MeshsarError when the stage cannot run where its items will run (e.g. a
    # GPU asked for and none there). Called once when the build starts, before any stage
    # runs, so a build fails in seconds instead of at the stage or in every item.
    check: Callable[[Context], object] | None = None
    # Runs after each pass (items, then finish): True plans and runs the stage once more.
    # results.of(stage) then holds the last pass's records, results.passes[stage] the count.
    again: Callable[[Context, "Results"], bool] | None = None
    # The stages whose records or files this stage reads; None: every stage before it in STAGE_ORDER.
    # With a pool, a stage starts once these have finished, beside any other stage that may run then.
    after: tuple[str, ...] | None = None
    # Compiles what the stage's items will run (numba's on-disk cache) on a small input, in this process while
    # earlier stages run, when the build has workers (run_stages): each worker then loads the kernels instead of
    # compiling them itself, as every worker of a fresh checkout's first build otherwise does at once.
    warm: Callable[[Context], object] | None = None


@dataclass
class Results:
    """Per stage, the sidecar records of items that are done (run now or skipped as up to date)."""

    done: dict[str, dict[str, dict]] = field(default_factory=dict)
    failures: list[dict] = field(default_factory=list)
    summary: list[dict] = field(default_factory=list)
    passes: dict[str, int] = field(default_factory=dict)  # per stage, passes completed in this build
    began: float = field(default_factory=time.perf_counter)  # the summary rows' `start` counts from here

    def of(self, stage: str) -> dict[str, dict]:
        return self.done.get(stage, {})


def stage_modules() -> list[str]:
    """The modules of the registered stages, in pipeline order, not imported."""
    found = {ep.name: ep.module for ep in entry_points(group="meshsar.stages")}
    return [found[name] for name in STAGE_ORDER if name in found]


def available_stages() -> dict[str, Stage]:
    """Registered stages in pipeline order (later issues add stages; the pipeline ends where they end)."""
    found = {ep.name: ep for ep in entry_points(group="meshsar.stages")}
    stages = {}
    for name in STAGE_ORDER:
        if name not in found:
            break
        stages[name] = found[name].load()
    return stages


def code_version(stage: Stage) -> str:
    return f"{__version__}+{stage.name}.{stage.version}"


def _input_key(ctx: Context, path: str) -> str:
    """A sidecar's name for an input: the build's own files relative to its output folder, so a
    build that is moved, or reached by another path (a cluster's mount), stays up to date; any
    other file (source data) as given."""
    relative = os.path.relpath(os.path.abspath(path), os.path.abspath(ctx.out))
    return path if relative == ".." or relative.startswith(".." + os.sep) else Path(relative).as_posix()


def _input_digests(ctx: Context, item: Item) -> dict[str, str]:
    return {_input_key(ctx, p): sha256_file(p) for p in item.inputs}


def _up_to_date(ctx: Context, stage: Stage, item: Item) -> dict | None:
    """The item's sidecar record if it matches the item as planned now, else None."""
    path = ctx.sidecar(stage.name, item.id)
    if not path.exists():
        return None
    try:
        rec = read_json(path)
    except (OSError, ValueError):
        return None
    stage_dir = ctx.stage_dir(stage.name)
    if (
        rec.get("code_version") != code_version(stage)
        or rec.get("params_sha256") != sha256_json(item.params)
        or set(rec.get("outputs", {})) != set(item.outputs)
        or any(not (stage_dir / o).exists() for o in item.outputs)
    ):
        return None
    try:  # a record's own keys renamed the same way: those written before relative keys still match
        recorded = {_input_key(ctx, p): digest for p, digest in (rec.get("inputs") or {}).items()}
        same_inputs = recorded == _input_digests(ctx, item)
    except OSError:  # an input went missing: rerun, and let the item fail naming it
        return None
    return rec if same_inputs else None


def run_item(ctx: Context, stage: Stage, item: Item) -> tuple[dict | None, dict | None]:
    """Run one item (in a worker); return (sidecar record, None) or (None, failure record)."""
    t0 = time.perf_counter()
    try:
        inputs = _input_digests(ctx, item)
        # One BLAS/OpenMP thread per item: threaded reductions sum in a different order
        # on another core count, and outputs must not depend on the machine or worker count.
        # Parallelism comes from running items side by side instead.
        with threadpool_limits(limits=1):
            result = stage.run(ctx, item) or {}
        stage_dir = ctx.stage_dir(stage.name)
        missing = [o for o in item.outputs if not (stage_dir / o).exists()]
        if missing:
            raise RuntimeError(f"stage {stage.name} did not write {missing}")
        rec = {
            "stage": stage.name,
            "item": item.id,
            "code_version": code_version(stage),
            "params_sha256": sha256_json(item.params),
            "inputs": inputs,
            "outputs": {o: sha256_file(stage_dir / o) for o in item.outputs},
            "seconds": round(time.perf_counter() - t0, 3),
            **result,
        }
        write_json(ctx.sidecar(stage.name, item.id), rec)
        return rec, None
    except Exception as e:  # a bad item must not stop the batch: record it and go on
        return None, {
            "stage": stage.name,
            "item": item.id,
            "error": type(e).__name__,
            "message": str(e),
            "inputs": list(item.inputs),
            "traceback": traceback.format_exc(limit=6),
            "errno": getattr(e, "errno", None),
        }


def check_stage(ctx: Context, stage: Stage, pool=None) -> None:
    """Stage.check where the stage's items will run: this process, or the pool's workers."""
    if pool is not None:
        pool.check(ctx, stage)
    elif stage.check is not None:
        stage.check(ctx)


def _outcomes(ctx: Context, stage: Stage, todo: list[Item], pool):
    """Run items, yielding (record, failure) as they finish; at most pool.slots in flight, costliest first."""
    if pool is None:
        yield from (run_item(ctx, stage, it) for it in todo)
        return
    queue, pending = iter(sorted(todo, key=lambda it: -it.cost)), set()  # stable: equal costs in plan order
    resources = stage_resources(ctx, stage)
    while True:
        for item in queue:
            pending.add(pool.submit(run_item, ctx, stage, item, resources=resources))
            if len(pending) >= pool.slots:
                break
        if not pending:
            return
        done, pending = pool.wait(pending)
        for future in done:
            yield future.result()


def _run_pass(ctx: Context, stage: Stage, results: Results, pool, force: bool) -> tuple[int, int, list[dict]]:
    """Plan and run one pass of a stage; return (items planned, items run, failures)."""
    items = stage.plan(ctx, results)
    ids = [it.id for it in items]
    if len(set(ids)) != len(ids):
        raise RuntimeError(f"stage {stage.name}: duplicate item ids in plan")
    done, todo = {}, []
    for it in items:
        rec = None if force else _up_to_date(ctx, stage, it)
        if rec is None:
            todo.append(it)
        else:
            done[it.id] = rec
    failed = []
    bar = tqdm(total=len(todo), desc=f"{stage.name:>8}", unit="item", disable=not todo, file=sys.stderr)
    for rec, fail in _outcomes(ctx, stage, todo, pool):
        bar.update(1)
        if rec is not None:
            done[rec["item"]] = rec
        elif fail["errno"] in UNWRITABLE:  # every later item would fail the same way: stop now
            bar.close()
            raise MeshsarError(
                f"{ctx.out}: cannot write outputs ({os.strerror(fail['errno'])}, at {stage.name}/{fail['item']}); "
                "finished items are kept: free space or fix permissions, then rerun to resume"
            )
        else:
            failed.append(fail)
            bar.write(f"FAILED {stage.name}/{fail['item']}: {fail['error']}: {fail['message']}")
    bar.close()
    remove_stale_temporaries(ctx.stage_dir(stage.name))  # a worker killed mid-write (its item was rerun) leaves one
    # Keep plan order, so later stages see items in the same order whatever finished first.
    results.done[stage.name] = {i: done[i] for i in ids if i in done}
    results.passes[stage.name] = results.passes.get(stage.name, 0) + 1
    return len(items), len(todo), failed


def _hook(stage: Stage, name: str, ctx: Context, results: Results, failed: list[dict]):
    """Call stage.finish or stage.again; an exception is recorded like an item's (None returned)."""
    try:
        return getattr(stage, name)(ctx, results)
    except Exception as e:  # recorded like an item, so the summary and exit status show it
        failed.append({"stage": stage.name, "item": f"({name})", "error": type(e).__name__,
                       "message": str(e), "inputs": [], "traceback": traceback.format_exc(limit=6)})
        return None


def run_stage(ctx: Context, stage: Stage, results: Results, pool=None, force: bool = False) -> dict:
    """Plan a stage, skip what is up to date, run the rest (pass after pass while stage.again
    says so); return its summary row, counting the items of every pass."""
    t0 = time.perf_counter()
    stage_dir = ctx.stage_dir(stage.name)
    stage_dir.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(stage_dir)
    results.passes.pop(stage.name, None)
    planned = todo = 0
    failed: list[dict] = []
    while True:
        n_items, n_todo, pass_failed = _run_pass(ctx, stage, results, pool, force)
        planned, todo = planned + n_items, todo + n_todo
        failed += pass_failed
        if stage.finish is not None:
            _hook(stage, "finish", ctx, results, failed)
        if stage.again is None or not _hook(stage, "again", ctx, results, failed):
            break
    results.failures.extend(sorted(failed, key=lambda f: f["item"]))
    row = {
        "stage": stage.name,
        "start": round(t0 - results.began, 2),  # seconds into the build: stages side by side overlap (run_stages)
        "items": planned,
        "ran": todo - len(failed),
        "skipped": planned - todo,
        "failed": len(failed),
        "seconds": round(time.perf_counter() - t0, 2),
    }
    results.summary.append(row)
    return row


def run_stages(ctx: Context, stages: dict[str, Stage], results: Results, pool=None,
               force: tuple[str, ...] = ()) -> None:
    """Run `stages` (name -> Stage, in pipeline order), each once the stages it reads (Stage.after) have finished.

    With a pool, stages that do not read each other run side by side: each in a thread of this
    process that plans it and hands its items to the shared pool, so workers do not idle through
    a stage's tail (the track stage's few long chains beside the register stage's rounds). Without
    one, items run in this process, one stage after another. Either way the outputs are the same
    bytes, and the summary and the failures list the stages in pipeline order.
    """
    names = list(stages)
    if pool is None:
        for name in names:
            run_stage(ctx, stages[name], results, None, force=name in force)
        return
    needs = {}
    for i, name in enumerate(names):
        after = stages[name].after
        if set(after or ()) & set(names[i:]):  # it would wait for itself or a stage that waits for it
            raise RuntimeError(f"stage {name}: Stage.after {after} names a stage that does not run before it")
        needs[name] = set(names[:i]) if after is None else set(after) & set(names[:i])
    finished: queue.Queue = queue.Queue()

    def run(name: str) -> None:
        try:
            run_stage(ctx, stages[name], results, pool, force=name in force)
            finished.put((name, None))
        except BaseException as e:  # to the main thread, which stops the build
            finished.put((name, e))

    hooks = [stage.warm for stage in stages.values() if stage.warm is not None]
    if hooks:
        threading.Thread(target=_warm, args=(ctx, hooks), name="warm-kernels", daemon=True).start()
    threads: dict[str, threading.Thread] = {}
    done: set[str] = set()
    try:
        while len(done) < len(names):
            for name in names:
                if name not in threads and needs[name] <= done:
                    threads[name] = threading.Thread(target=run, args=(name,), name=f"stage-{name}", daemon=True)
                    threads[name].start()
            name, error = finished.get()
            if error is not None:
                raise error
            done.add(name)
    except BaseException:
        pool.close()  # pending items are cancelled, so the other stages' threads end at their next wait
        for thread in threads.values():
            thread.join(timeout=STOP_SECONDS)
        raise
    finally:
        order = {name: i for i, name in enumerate(names)}
        results.summary.sort(key=lambda row: order[row["stage"]])
        results.failures.sort(key=lambda f: order.get(f["stage"], len(order)))  # stable: items keep their order


def _warm(ctx: Context, hooks: list) -> None:
    """Stage.warm hooks one after another, on one BLAS thread (the workers hold the cores). A hook's error is
    left to the items: they meet it themselves and record it where the build reports failures."""
    with threadpool_limits(limits=1):
        for hook in hooks:
            try:
                hook(ctx)
            except Exception:  # noqa: BLE001 (the items record it)
                continue


def build(recipe: Recipe, out: Path, workers: int = 1, until: str | None = None, force: tuple[str, ...] = (),
          scheduler: str | None = None, break_lock: bool = False, command: str | None = None) -> Results:
    """Run the registered stages up to `until` (run_stages); write failures.json and the recipe copy.

    Items run in this process (workers=1), on `workers` local processes, or on a
    Dask cluster (`scheduler`), with the same outputs byte for byte.

    The build holds `out`'s lock (lock.py) from before its first write to after its last:
    a second build into the same folder is refused at once (FolderLocked), a lock left by
    a killed build of this host is taken over, and `break_lock` also takes over one held
    from another host. `command` is recorded in the lock (default: this process's command line).
    """
    with worker_server(server_modules(workers, scheduler, stage_modules())):
        return _build(recipe, out, workers, until, force, scheduler, break_lock, command)


def _build(recipe: Recipe, out: Path, workers: int, until: str | None, force: tuple[str, ...], scheduler: str | None,
           break_lock: bool, command: str | None) -> Results:
    stages = available_stages()
    for name in (until, *force):
        if name is not None and name not in stages:
            raise MeshsarError(f"unknown stage {name!r}; available: {', '.join(stages)}")
    if until is not None:
        names = list(stages)
        stages = {name: stages[name] for name in names[: names.index(until) + 1]}
    out = Path(out)
    with folder_lock(out, command, break_lock):
        try:
            write_bytes(out / "recipe.toml", recipe.text.encode("utf-8"))
        except OSError as e:
            raise MeshsarError(f"{out}: output folder is not writable ({e.strerror})") from e
        ctx = Context(out=out, recipe=recipe)
        results = Results()
        pool = make_pool(workers, scheduler)
        try:
            for stage in stages.values():  # every stage that will run, before the first runs
                check_stage(ctx, stage, pool)
            run_stages(ctx, stages, results, pool, force)
        finally:
            if pool is not None:
                pool.close()
        write_json(out / "failures.json", results.failures)
    return results


def format_summary(results: Results) -> str:
    """The end-of-build table, then one line per failure."""
    head = f"{'stage':<10}{'items':>7}{'ran':>7}{'skipped':>9}{'failed':>8}{'seconds':>10}"
    lines = [head, "-" * len(head)]
    for r in results.summary:
        lines.append(f"{r['stage']:<10}{r['items']:>7}{r['ran']:>7}{r['skipped']:>9}{r['failed']:>8}{r['seconds']:>10.1f}")
    if results.failures:
        lines.append(f"\n{len(results.failures)} item(s) failed (see failures.json):")
        lines += [f"  {f['stage']}/{f['item']}: {f['error']}: {f['message']}" for f in results.failures]
    return "\n".join(lines)
