"""What this process has used: CPU seconds and peak resident memory (for run reports and benchmarks)."""

from __future__ import annotations

import resource
from pathlib import Path

STATUS = Path("/proc/self/status")


def cpu_seconds() -> float:
    """User + system CPU seconds of this process so far (all its threads)."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def peak_resident_mib() -> float:
    """Peak resident memory of this process since it started its program, MiB.

    Read from ``VmHWM`` in ``/proc/self/status`` (Linux), the high-water mark of this process's own
    address space. Not ``ru_maxrss``: Linux carries ``ru_maxrss`` across ``exec``, so a process
    started by a large one (a Dask worker spawned by a benchmark holding 2 GB) reports its parent's
    peak, not its own. Where there is no ``/proc`` (macOS), ``ru_maxrss`` it is (bytes there).
    """
    try:
        status = STATUS.read_text()
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    for line in status.splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"{STATUS} has no VmHWM line")
