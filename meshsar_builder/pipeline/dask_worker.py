"""What every Dask worker of a build loads on its own main thread before any task (pools.DaskPool registers it)."""

from __future__ import annotations

from distributed import WorkerPlugin


class MainThreadImports(WorkerPlugin):
    """Imports pymeshlab on the worker's main thread when the worker joins the cluster (a plugin's setup runs
    there, on the worker's event loop; workers that join later get it too).

    Dask runs tasks on a thread pool. pymeshlab loaded first on such a thread, after scipy.sparse, leaves glibc's
    heap corrupt once a MeshSet is made: the process aborts at exit ("malloc_consolidate(): unaligned fastbin
    chunk detected"). Loaded on the main thread first, it does not, wherever it is used after.
    """

    name = "meshsar-main-thread-imports"

    def setup(self, worker) -> None:
        import pymeshlab  # noqa: F401
