"""Peak memory of a run, stage by stage.

A stage's marker records the process's peak so far when the stage ends; a run that resumes
stages (or copies them from another run, as the benchmarks' baselines do) still reports the
peak its stages needed, where they ran, not only the peak of the process that finished it.
"""

from __future__ import annotations

import resource

import torch

GPU = "GPU"
RSS = "RSS"


def peak_rss_bytes() -> int:
    """This process's peak resident memory in bytes: Linux's VmHWM, which starts afresh with
    each program (``ru_maxrss`` is kept across exec, so a child started by a larger parent
    would report the parent's peak); ``ru_maxrss`` where /proc is not there."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # KiB on Linux


def memory_kind() -> str:
    """What ``peak_memory_gb`` measures in this process: GPU memory once CUDA was used, else
    the process's resident memory."""
    if torch.cuda.is_available() and torch.cuda.max_memory_allocated() > 0:
        return GPU
    return RSS


def peak_memory_gb(simulator=None) -> float:
    """Peak GPU memory if CUDA was used, else the process's peak resident memory (GiB).

    On CUDA the simulator's own count is included: a backend with its own allocator (Warp's
    pool, Taichi's fields) holds memory that torch's peak does not see."""
    if memory_kind() == GPU:
        backend = simulator.peak_memory_bytes() if simulator is not None else None
        return max(torch.cuda.max_memory_allocated(), backend or 0) / 2**30
    return peak_rss_bytes() / 2**30


def stage_peak(simulator=None) -> dict:
    """What a stage's marker records of memory: the peak so far (GiB) and what it measures."""
    return {"peak_memory_gb": round(peak_memory_gb(simulator), 4), "memory": memory_kind()}


def comparable_peaks(stage_peaks: dict[str, dict | None]) -> dict[str, float | None]:
    """Each stage's recorded peak (GiB) where it measured what this process measures (a stage
    measured as resident memory says nothing of GPU memory, and the reverse); else None."""
    kind = memory_kind()
    return {
        stage: peak.get("peak_memory_gb") if peak and peak.get("memory") == kind else None
        for stage, peak in stage_peaks.items()
    }


def run_peak_gb(own_gb: float, stage_peaks: dict[str, dict | None]) -> float:
    """The run's peak: the finishing process's own and every earlier stage's comparable
    recorded peak."""
    recorded = [gb for gb in comparable_peaks(stage_peaks).values() if gb is not None]
    return max([own_gb, *recorded])
