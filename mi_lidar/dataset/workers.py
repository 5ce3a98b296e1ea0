"""The Dask worker plugin of dataset runs: every worker, including a restarted one, sets itself up once."""

from __future__ import annotations

import os

from distributed.diagnostics.plugin import WorkerPlugin


def worker_threads(workers: int) -> int:
    """Dr.Jit threads per worker process: the cores shared evenly, at least one."""
    return max(1, (os.cpu_count() or 1) // max(1, workers))


class MitsubaWorker(WorkerPlugin):
    """Imports mi-lidar (LLVM, variant, plugins) and sizes Dr.Jit's thread pool when a worker starts.

    Args:
        threads: Dr.Jit threads of this worker (``cores // workers`` keeps workers off each other's cores).
    """

    name = "mi-lidar-dataset"

    def __init__(self, threads: int):
        self.threads = threads

    def setup(self, worker):
        import drjit as dr

        import mi_lidar  # noqa: F401  (configures LLVM, selects the variant, registers the plugins)

        dr.set_thread_count(self.threads)
