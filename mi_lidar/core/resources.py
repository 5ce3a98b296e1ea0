"""What this process has used (CPU seconds, peak resident memory) and how it hands freed memory back."""

from __future__ import annotations

import ctypes
import ctypes.util
import resource
from pathlib import Path

STATUS = Path("/proc/self/status")
M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter (malloc.h)
LARGE_BLOCK = 1 << 20  # bytes: blocks from this size up get their own mapping (map_large_blocks)


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


def map_large_blocks(threshold: int = LARGE_BLOCK) -> bool:
    """Give every allocation of ``threshold`` bytes or more its own memory mapping, unmapped when it is freed.

    glibc maps large blocks of their own only above a threshold that rises with every mapped block
    freed, up to 32 MiB; past that, large numpy arrays come from the heaps of the threads that
    allocate them, and what they leave free between live blocks stays with the process. The planar
    benchmark, whose arrays come and go by the hundred megabytes on several threads, then held
    1.84 GB at the end of the Intel log with 0.64 GB of arrays alive (tracemalloc) and 0.23 GB in
    Dr.Jit. A fixed threshold (glibc's ``mallopt(M_MMAP_THRESHOLD)``, which also stops it rising)
    returns such blocks to the system as soon as they are freed. The results do not change.

    Args:
        threshold: bytes, at least 128 KiB (glibc's own starting threshold).

    Returns:
        Whether the threshold was set: False where the C library is not glibc (macOS, musl).
    """
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
        libc.gnu_get_libc_version  # noqa: B018 (glibc only: musl has a mallopt that ignores the threshold)
    except (OSError, AttributeError, TypeError):
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, max(int(threshold), 128 << 10)))
