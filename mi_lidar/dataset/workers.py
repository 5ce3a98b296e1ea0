"""The Dask side of a dataset run: each worker process sets itself up once and renders one frame at a time.

Dr.Jit parallelises every kernel over its own thread pool, one per process. A worker process
renders its frames one after the other (:func:`mi_lidar.dataset.run.frame_task` holds a lock, even
when the worker has several Dask threads) on ``cores // (worker processes on its host)`` Dr.Jit
threads: a lone worker keeps every core; two workers on a 2-core machine run one thread each, so
their serial parts (kernel tracing, image encoding, hashing, writing) overlap instead of leaving a
core idle, and no kernel waits for a thread the operating system gave to the other process.
"""

from __future__ import annotations

import os
from collections import Counter
from urllib.parse import urlparse

from distributed.diagnostics.plugin import WorkerPlugin


def host_cores() -> int:
    """CPU cores this process may run on (its affinity mask, else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def host_of(address: str) -> str:
    """Host part of a Dask address (``tcp://10.0.0.5:40123`` -> ``10.0.0.5``)."""
    return urlparse(address).hostname or address


def workers_per_host(addresses) -> dict[str, int]:
    """Number of worker processes per host, from the workers' Dask addresses."""
    return dict(Counter(host_of(a) for a in addresses))


def worker_threads(cores: int, workers_on_host: int) -> int:
    """Dr.Jit threads of one worker process: the host's cores shared evenly, at least one."""
    return max(1, cores // max(1, workers_on_host))


class MitsubaWorker(WorkerPlugin):
    """Imports mi-lidar (LLVM, variant, plugins) and sizes Dr.Jit's thread pool when a worker starts.

    Args:
        per_host: worker processes per host when the run started (:func:`workers_per_host`); a
            worker on a host not listed (it joined later) counts as alone there.
    """

    name = "mi-lidar-dataset"

    def __init__(self, per_host: dict[str, int]):
        self.per_host = dict(per_host)

    def setup(self, worker):
        import drjit as dr

        import mi_lidar  # noqa: F401  (configures LLVM, selects the variant, registers the plugins)

        dr.set_thread_count(worker_threads(host_cores(), self.per_host.get(host_of(worker.address), 1)))


def worker_setup() -> dict:
    """What a worker process runs on (for the run report): Dr.Jit threads, cores, process id."""
    import drjit as dr

    return {"threads": dr.thread_count(), "cores": host_cores(), "pid": os.getpid()}
