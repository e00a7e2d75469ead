"""Where a build's items run when not in its own process: local worker processes or a Dask cluster (runner.build).

A pool takes run_item calls (submit), says when some have finished (wait), runs a stage's
check where its items will run (check), and has `slots`, the items a stage keeps in flight.
Its `ctx` and `stage` arguments are runner.Context and runner.Stage (the runner imports this module).
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
import warnings
from contextlib import contextmanager

from meshsar_builder.pipeline.errors import MeshsarError


def stage_resources(ctx, stage) -> dict | None:
    """The Dask resources the stage's items need (Stage.resources), None for none."""
    return (stage.resources(ctx) or None) if stage.resources is not None else None


# Local workers are forked from a server process that has only imported modules (forkserver), never from this
# one, whose Embree, BLAS and torch threads do not survive fork reliably (the server's only threads are OpenBLAS's,
# which it stops and restarts around a fork itself). Where there is no fork (Windows), spawned.
WORKER_START = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"


def server_modules(workers: int, scheduler: str | None, stages: list[str]) -> list[str] | None:
    """What the workers' server preloads for a build's worker processes on this machine (local workers, or a Dask
    LocalCluster's, which also import Dask's worker): `stages`, the stage modules; None where there are none."""
    if scheduler is None:
        return stages if workers > 1 else None
    return ["distributed", *stages] if scheduler.startswith("local:") else None


def start_worker_server(modules: list[str]) -> None:
    """Start the local workers' server, which imports `modules` beside this process's own imports: every worker
    forked from it starts with them (1.2 s of imports a spawned worker paid itself, on its way to its first item).
    It serves every LocalPool of this process; the preload holds only when the server is not yet running."""
    if WORKER_START == "forkserver":
        import multiprocessing.forkserver

        multiprocessing.get_context(WORKER_START).set_forkserver_preload(["meshsar_builder.pipeline.runner", *modules])
        multiprocessing.forkserver.ensure_running()


@contextmanager
def worker_server(modules: list[str] | None):
    """The local workers' server for a build: started with `modules` (start_worker_server), then stopped and waited
    for, so that the workers it reaped count among this process's children (resource.RUSAGE_CHILDREN: the bench's
    peak memory) and the next build's server imports that build's stages. None: no local workers, no server."""
    if modules is None or WORKER_START != "forkserver":
        yield
        return
    import multiprocessing.forkserver

    start_worker_server(modules)
    try:
        yield
    finally:
        # The standard library's own stop (its tests use it); without it the server ends with this process.
        stop = getattr(multiprocessing.forkserver._forkserver, "_stop", None)
        if stop is not None:
            stop()


def _adopt_environment(environ: dict[str, str]) -> None:
    """A worker's environment is its pool's creator's (a forked one would have the server's, from when it started)."""
    os.environ.clear()
    os.environ.update(environ)


class LocalPool:
    """Local worker processes (WORKER_START), each with this process's environment as the pool starts."""

    def __init__(self, workers: int):
        self.executor = cf.ProcessPoolExecutor(max_workers=workers,
                                               mp_context=multiprocessing.get_context(WORKER_START),
                                               initializer=_adopt_environment, initargs=(dict(os.environ),))
        self.slots = 2 * workers

    def submit(self, fn, *args, resources: dict | None = None):
        # One machine: every worker sees what this process sees, so resources mean nothing here.
        return self.executor.submit(fn, *args)

    def check(self, ctx, stage) -> None:
        """Stage.check, here: the workers are this machine's processes."""
        if stage.check is not None:
            stage.check(ctx)

    def wait(self, futures: set) -> tuple[set, set]:
        return cf.wait(futures, return_when=cf.FIRST_COMPLETED)

    def close(self) -> None:  # again after a stop (run_stages): a no-op
        self.executor.shutdown(cancel_futures=True)


# Dask settings for a LocalCluster's scheduler and workers (DaskPool); workers started by hand take them from the
# environment: DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED=False, DASK_DISTRIBUTED__ADMIN__TICK__INTERVAL=1s,
# DASK_DISTRIBUTED__ADMIN__SYSTEM_MONITOR__INTERVAL=5s (docs/data.md).
QUIET_DASK = {"distributed.worker.profile.enabled": False, "distributed.admin.tick.interval": "1s",
              "distributed.admin.system-monitor.interval": "5s"}


# Dask's scheduler sends each worker up to worker-saturation x its threads items (1.1 by default: two for one
# thread), and moves a queued one only by work stealing, which measured up to a second late or not at all: at the
# end of a stage or register round one worker waited behind its second item while the other idled. At 1.0 the
# scheduler keeps the items (once their task group outnumbers the threads twice, as the build's items all share
# run_item's) and sends each worker the next when it finishes. A scheduler started by hand takes it from
# DASK_DISTRIBUTED__SCHEDULER__WORKER_SATURATION=1.0 (docs/data.md).
SCHEDULE_WHEN_FREE = {"distributed.scheduler.worker-saturation": 1.0}


class DaskPool:
    """Items as Dask tasks: a scheduler address (tcp://HOST:PORT) or `local:N` for a LocalCluster.

    Workers must import this project (same version) and see the build folder at the
    same path (a shared filesystem). A task whose worker dies is rerun by Dask on
    another worker; writes are atomic, so a rerun leaves no duplicate or partial file.
    """

    def __init__(self, scheduler: str):
        import dask
        from distributed import Client, LocalCluster

        if scheduler.startswith("local:"):
            n = int(scheduler.split(":", 1)[1])
            # Dask's nannies start workers with MALLOC_TRIM_THRESHOLD_=65536: glibc then hands
            # freed memory back at once, and every item's large arrays fault their pages in
            # anew. Measured on the pipeline bench's recipe, 2 workers: the workers' CPU 245 s
            # with it, 213 s without (the local pool's: 202 s), the build 142.6 -> 122.4 s.
            # So the workers get the allocator's own defaults, as the local pool's have (None
            # unsets a variable there). A value already in this process's environment still goes
            # through: Dask's nannies also write their variables into the starting process's.
            # Every worker of a LocalCluster runs on this machine and sees its GPUs, as a local
            # pool's would: each declares one, so items that ask for a GPU (a CUDA radar) run
            # here too, one per worker; Stage.check still tests that CUDA is really there.
            # Dask's own periodic work is kept off the cores that the items use: the workers' statistical
            # profiler (a stack sample of the item's thread every 10 ms, under the GIL), the event loops' 20 ms
            # tick and the 0.5 s system monitor. Measured on the pipeline bench's recipe, 2 workers (two runs
            # each): 86.0-86.9 s with Dask's defaults, 81.7-83.2 s without (a register fit 5.85 -> 5.55 s).
            # Its workers are forked from the build's workers' server too (worker_server), which has imported Dask
            # and the stages: each worker spawned on its own imported both.
            with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
                                  "distributed.worker.multiprocessing-method": WORKER_START,
                                  **QUIET_DASK, **SCHEDULE_WHEN_FREE}):
                self.cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                                            dashboard_address=None, resources={"GPU": 1})
            self.client = Client(self.cluster)
        else:
            self.cluster = None
            self.client = Client(scheduler, timeout="30s")
            # A lambda goes by value: the scheduler need not have this project installed. Schedulers older than
            # the setting (distributed < 2022.11) have no such attribute and are not judged.
            saturation = self.client.run_on_scheduler(
                lambda dask_scheduler: getattr(dask_scheduler, "WORKER_SATURATION", None))
            if saturation not in (None, SCHEDULE_WHEN_FREE["distributed.scheduler.worker-saturation"]):
                warnings.warn(f"Dask scheduler {scheduler}: worker-saturation is {saturation}, so it sends workers "
                              "items ahead and one can wait behind a long item while another worker idles; start "
                              "the scheduler with DASK_DISTRIBUTED__SCHEDULER__WORKER_SATURATION=1.0 (docs/data.md)",
                              stacklevel=2)
        from meshsar_builder.pipeline.dask_worker import MainThreadImports

        self.client.register_plugin(MainThreadImports())
        self.slots = 2 * max(1, sum(self.client.nthreads().values()))

    def submit(self, fn, *args, resources: dict | None = None):
        return self.client.submit(fn, *args, pure=False, resources=resources)

    def worker_resources(self) -> dict[str, dict]:
        """Worker address -> the resources it declared ({} for none), every worker of the cluster."""
        try:
            info = self.client.scheduler_info(n_workers=-1)  # newer distributed lists 5 workers by default
        except TypeError:  # older distributed lists them all and takes no n_workers
            info = self.client.scheduler_info()
        return {addr: dict(w.get("resources") or {}) for addr, w in info["workers"].items()}

    def check(self, ctx, stage) -> None:
        """Stage.check on the workers that will take the stage's items; MeshsarError if none can.

        Dask holds a task that needs resources no worker has until such a worker joins,
        so a build whose GPU workers are missing would wait forever: refuse it here.
        """
        need = stage_resources(ctx, stage)
        workers = self.worker_resources()
        if need:
            workers = {addr: have for addr, have in workers.items()
                       if all(have.get(name, 0) >= amount for name, amount in need.items())}
            if not workers:
                flags = " ".join(f"{name}={amount}" for name, amount in need.items())
                raise MeshsarError(
                    f"stage {stage.name}: its items need Dask worker resources {need}, and no worker of "
                    f"{self.client.scheduler.address} declares them; start such workers first, e.g. "
                    f"dask worker {self.client.scheduler.address} --nthreads 1 --resources \"{flags}\"")
        if stage.check is not None and workers:
            self.client.run(stage.check, ctx, workers=list(workers))

    def wait(self, futures: set) -> tuple[set, set]:
        from distributed import wait

        done, pending = wait(list(futures), return_when="FIRST_COMPLETED")
        return set(done), set(pending)

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def make_pool(workers: int = 1, scheduler: str | None = None) -> LocalPool | DaskPool | None:
    """None (run items in this process), a local process pool, or a Dask client."""
    if scheduler:
        return DaskPool(scheduler)
    return LocalPool(workers) if workers > 1 else None
