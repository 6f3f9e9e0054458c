"""This process's own figures for ``summary.json`` (``processes``): peak RSS, CPU seconds,
USS and its threads, read from ``/proc`` where Linux has it."""

from __future__ import annotations

import math
import resource

import numpy as np

from transport.zenoh_session import thread_counts

__all__ = ["maxrss_mb", "cpu_s", "uss_mb", "process_figures", "unrecorded"]


def maxrss_mb() -> float:
    """Peak resident set size of this process (MB): ``VmHWM`` of ``/proc/self/status``
    (``ru_maxrss`` is inherited across ``exec`` on Linux, so a spawned child would
    report its launcher's peak), else psutil's current RSS."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    try:
        import psutil

        return psutil.Process().memory_info().rss / 2**20
    except Exception:  # pragma: no cover
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def cpu_s() -> float:
    """CPU seconds (user + system) of every thread of this process so far."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return round(usage.ru_utime + usage.ru_stime, 3)


def uss_mb() -> float:
    """Unique set size of this process now (MB): its private pages (``Private_Clean`` +
    ``Private_Dirty`` of ``/proc/self/smaps_rollup``), what it costs beyond the shared
    libraries; NaN where that file does not exist."""
    try:
        total = 0
        with open("/proc/self/smaps_rollup") as f:
            for line in f:
                if line.startswith(("Private_Clean:", "Private_Dirty:")):
                    total += int(line.split()[1])
        return total / 1024.0
    except (OSError, ValueError):
        return float("nan")


def process_figures() -> dict[str, float]:
    """This process's figures for ``summary.json`` (``processes``): peak RSS, CPU seconds, its
    threads (:func:`transport.zenoh_session.thread_counts`) and USS where the system gives it
    (the codec carries finite numbers only)."""
    figs: dict[str, float] = {"maxrss_mb": maxrss_mb(), "cpu_s": cpu_s(), **thread_counts()}
    uss = uss_mb()
    if math.isfinite(uss):
        figs["uss_mb"] = uss
    return figs


def unrecorded(truth_norm: np.ndarray) -> list[list[int]]:
    """``[first, last]`` of every run of rounds with no record (no monitor ran then)."""
    miss = np.isnan(truth_norm)
    out: list[list[int]] = []
    for k in np.flatnonzero(miss):
        if out and out[-1][1] == k - 1:
            out[-1][1] = int(k)
        else:
            out.append([int(k), int(k)])
    return out
