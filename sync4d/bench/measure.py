"""Measuring one call's time and memory, and describing the machine: what the rasterizer
benchmarks (`sync4d.bench.raster`'s grid of random scenes and `sync4d.bench.raster_run`'s
trained run) share. Both import it; it imports neither.

Memory: peak resident set size per measurement (see `sync4d.bench.raster`'s notes), either in
process (:data:`METHOD_CLEAR_REFS`: reset the kernel's high-water mark through
``/proc/self/clear_refs``, read ``VmHWM``) or in a dedicated child process
(:data:`METHOD_SUBPROCESS`: the child's ``ru_maxrss``). Contention: :class:`OtherLoad` counts
the CPU cores other processes kept busy over an interval.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import importlib.metadata
import os
import platform
import resource
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

import sync4d

__all__ = [
    "MEMORY_METHODS",
    "METHOD_CLEAR_REFS",
    "METHOD_SUBPROCESS",
    "OtherLoad",
    "Timing",
    "clear_refs_available",
    "machine_info",
    "measure",
    "mem_available_gb",
    "proc_status_kb",
]

METHOD_CLEAR_REFS = "clear_refs"
METHOD_SUBPROCESS = "subprocess"
MEMORY_METHODS = {
    METHOD_CLEAR_REFS: (
        "in process: gc.collect() + malloc_trim(0), baseline = VmRSS, reset the high-water mark "
        "with '5' > /proc/self/clear_refs, run the warm-up and timed calls of one mode, "
        "peak = VmHWM from /proc/self/status"
    ),
    METHOD_SUBPROCESS: (
        "one child process per measurement (scene built in the child), baseline = VmRSS before "
        "the warm-up, peak = the child's resource.getrusage(RUSAGE_SELF).ru_maxrss"
    ),
}


# --------------------------------------------------------------------------------------------
# Memory probes
# --------------------------------------------------------------------------------------------


def proc_status_kb(pid: int | str = "self") -> dict[str, int]:
    """``Vm*`` / ``Rss*`` fields of ``/proc/<pid>/status`` in kB (empty if unreadable)."""
    out: dict[str, int] = {}
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                key, _, rest = line.partition(":")
                if key.startswith(("Vm", "Rss")):
                    fields = rest.split()
                    if fields and fields[0].isdigit():
                        out[key] = int(fields[0])
    except OSError:
        pass
    return out


def rss_mb() -> float | None:
    kb = proc_status_kb().get("VmRSS")
    return None if kb is None else kb / 1024.0


def reset_hwm() -> None:
    """Reset this process's peak-RSS high-water mark (VmHWM) to its current RSS."""
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")


def clear_refs_available() -> bool:
    """Whether the high-water mark can be reset here (writable ``/proc/self/clear_refs``)."""
    if "VmHWM" not in proc_status_kb():
        return False
    try:
        reset_hwm()
    except OSError:
        return False
    return True


_LIBC: Any = None


def malloc_trim() -> bool:
    """Return freed glibc heap memory to the kernel (``malloc_trim(0)``); False if no glibc."""
    global _LIBC
    if _LIBC is None:
        try:
            _LIBC = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            _LIBC.malloc_trim.argtypes = [ctypes.c_size_t]
        except (OSError, AttributeError):
            _LIBC = False
    if not _LIBC:
        return False
    _LIBC.malloc_trim(0)
    return True


def mem_available_gb() -> float | None:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) / (1024.0 * 1024.0)
    except (OSError, ValueError, IndexError):
        pass
    return None


def system_busy_s() -> float | None:
    """CPU seconds all processes have been busy (user + nice + system + irq + steal)."""
    try:
        with open("/proc/stat") as fh:
            fields = [int(v) for v in fh.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
    guest = sum(fields[8:10])  # already counted in user / nice
    return (sum(fields) - idle - guest) / os.sysconf("SC_CLK_TCK")


def own_cpu_s() -> float:
    """CPU seconds used by this process and its waited-for children."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


class OtherLoad:
    """CPU cores used by *other* processes over an interval (a contention check)."""

    def __init__(self) -> None:
        self.busy0 = system_busy_s()
        self.own0 = own_cpu_s()
        self.t0 = time.monotonic()

    def cores(self) -> float | None:
        busy = system_busy_s()
        wall = time.monotonic() - self.t0
        if busy is None or self.busy0 is None or wall <= 0:
            return None
        other = (busy - self.busy0) - (own_cpu_s() - self.own0)
        return round(max(other, 0.0) / wall, 3)


# --------------------------------------------------------------------------------------------
# Measurements
# --------------------------------------------------------------------------------------------


@dataclass
class Timing:
    """One measured mode of one renderer: wall times in ms, memory in MB (MiB)."""

    warmup: int
    repeats: int
    times_ms: list[float]
    median_ms: float
    rss_baseline_mb: float | None
    rss_peak_mb: float | None
    rss_delta_mb: float | None
    memory_method: str


def measure(fn: Callable[[], None], warmup: int, repeats: int, memory_method: str) -> Timing:
    """Run ``fn`` ``warmup`` times untimed, then ``repeats`` timed; peak RSS over all of it."""
    gc.collect()
    malloc_trim()
    baseline = rss_mb()
    if memory_method == METHOD_CLEAR_REFS:
        reset_hwm()
    for _ in range(warmup):
        fn()
    times: list[float] = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    if memory_method == METHOD_CLEAR_REFS:
        hwm = proc_status_kb().get("VmHWM")
        peak = None if hwm is None else hwm / 1024.0
    else:  # a dedicated child process: its lifetime peak is this measurement's peak
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    delta = None if peak is None or baseline is None else peak - baseline
    return Timing(
        warmup=warmup,
        repeats=repeats,
        times_ms=[round(t, 4) for t in times],
        median_ms=round(statistics.median(times), 4),
        rss_baseline_mb=None if baseline is None else round(baseline, 2),
        rss_peak_mb=None if peak is None else round(peak, 2),
        rss_delta_mb=None if delta is None else round(delta, 2),
        memory_method=memory_method,
    )


# --------------------------------------------------------------------------------------------
# Machine description
# --------------------------------------------------------------------------------------------


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def dist_version(dist: str) -> str | None:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def machine_info() -> dict[str, Any]:
    """CPU, core counts, memory, OS, Python and library versions."""
    try:
        affinity = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        affinity = None
    mem_total = None
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemTotal:"):
                    mem_total = round(int(line.split()[1]) / (1024.0 * 1024.0), 2)
    except OSError:
        pass
    return {
        "cpu_model": cpu_model(),
        "nproc": affinity if affinity is not None else os.cpu_count(),
        "cpu_count": os.cpu_count(),
        "mem_total_gb": mem_total,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch_version": torch.__version__,
        "torch_parallel_info": torch.__config__.parallel_info().strip().splitlines(),
        "sync4d_version": sync4d.__version__,
        "gsplat_version": dist_version("gsplat"),
        "numpy_version": dist_version("numpy"),
    }
