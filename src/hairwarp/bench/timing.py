"""Timing helpers shared by every benchmark: warm-up, device synchronisation inside the timed
region, median of repeats."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import torch


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work (a no-op on CPU)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_ms(fn: Callable[[], object], device: torch.device, *, warmup: int = 3, repeats: int = 10,
            min_time_s: float = 0.2) -> float:
    """Median wall time of `fn()` in milliseconds, synchronising the device around each call.

    Runs `warmup` untimed calls (kernel compilation, caches), then at least `repeats` timed
    calls and until `min_time_s` has passed.
    """
    for _ in range(warmup):
        fn()
    synchronize(device)
    samples = []
    start_all = time.perf_counter()
    while len(samples) < repeats or (time.perf_counter() - start_all) < min_time_s:
        t0 = time.perf_counter()
        fn()
        synchronize(device)
        samples.append((time.perf_counter() - t0) * 1e3)
        if len(samples) >= 10 * repeats:
            break
    return statistics.median(samples)


def cpu_model_name() -> str | None:
    """The CPU's model name from /proc/cpuinfo (None where that file is not readable)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


def machine_description(device: torch.device) -> str:
    """A one-line name of the machine a figure was measured on."""
    import os
    import platform

    if device.type == "cuda":
        return f"{torch.cuda.get_device_name(device)} (torch {torch.__version__})"
    cpu = cpu_model_name() or platform.processor() or platform.machine()
    return f"{cpu}, {os.cpu_count()} cores (torch {torch.__version__}, CPU)"
