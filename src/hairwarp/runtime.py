"""The ground floor: devices, synchronisation, timing and machine descriptions.

Every layer above (ops, scenes, methods, evaluation, commands, benchmarks) takes its device
and its timings from here, so a figure is always measured the same way: warm-up calls first,
the device synchronised inside the timed region, the median of repeats.
"""

from __future__ import annotations

import math
import os
import platform
import statistics
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

import torch


def resolve_device(name: str | torch.device, *, argument: str = "device") -> torch.device:
    """A torch device that exists on this machine, or a clear error naming `argument`.

    Args:
        name: "cpu", "cuda" or "cuda:N" (or a `torch.device`).
        argument: the name the error message gives (the command line passes "--device").

    Returns:
        torch.device: "cpu" or "cuda:N"/"cuda".

    Raises:
        ValueError: an unknown device type, "cpu:N" (there is one CPU device), no CUDA on
            this machine, or a CUDA index the machine does not have.
    """
    if isinstance(name, torch.device):
        name = str(name)
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError) as exc:
        raise ValueError(f"{argument}: expected cpu or cuda[:N], got {name!r} ({exc})") from None
    if device.type == "cpu":
        if device.index not in (None, 0):  # torch accepts cpu:7 and ignores the index
            raise ValueError(f"{argument}: there is one CPU device ('cpu'), got {name!r}")
        return torch.device("cpu")
    if device.type != "cuda":
        raise ValueError(f"{argument}: expected cpu or cuda[:N], got {name!r}")
    if not torch.cuda.is_available():
        raise ValueError(f"{argument}: {name} was asked for but this machine has no CUDA device")
    count = torch.cuda.device_count()
    if device.index is not None and device.index >= count:
        raise ValueError(f"{argument}: {name} was asked for but this machine has {count} CUDA device(s) "
                         f"(cuda:0..cuda:{count - 1})")
    return device


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work (a no-op on CPU)."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


# The warm-up keys `timed` has run in this process (`timed(warmup_key=...)`).
_WARMED: set = set()


def timed(fn: Callable[[], object], device: torch.device, *, warmup: int = 1,
          warmup_fn: Callable[[], object] | None = None, warmup_key=None) -> tuple[object, float]:
    """(result, seconds) of one call of `fn()` after `warmup` untimed calls, device synchronised.

    For work too long to repeat (a network's drape of a batch, a whole optimization): one
    timed call after the warm-up compiled the kernels and filled the caches.

    Args:
        fn: the work.
        device: where it runs (synchronised around the timed call).
        warmup: untimed calls before it.
        warmup_fn: called for the warm-up instead of `fn`: a smaller piece of the same work (a
            motion's first frames) that compiles the same kernels at a fraction of the cost.
        warmup_key: a hashable naming the work's kind (with its shapes where graphs are
            captured per shape): its warm-up runs once per process, later calls with the key
            are timed cold of nothing (a motion's chunks after the first).
    """
    if warmup_key is None or warmup_key not in _WARMED:
        for _ in range(warmup):
            (fn if warmup_fn is None else warmup_fn)()
        if warmup_key is not None:
            _WARMED.add(warmup_key)
    synchronize(device)
    start = time.perf_counter()
    out = fn()
    synchronize(device)
    return out, time.perf_counter() - start


def _call_ms(fn: Callable[[], object], device: torch.device) -> float:
    """Wall time [ms] of one call of `fn()`, the device synchronised after it."""
    t0 = time.perf_counter()
    fn()
    synchronize(device)
    return (time.perf_counter() - t0) * 1e3


def time_ms(fn: Callable[[], object], device: torch.device, *, warmup: int = 3, repeats: int = 10,
            min_time_s: float = 0.2) -> float:
    """Median wall time of `fn()` in milliseconds, synchronising the device around each call.

    Runs `warmup` untimed calls (kernel compilation, caches), then at least `repeats` timed
    calls and until `min_time_s` has passed (at most 10 x `repeats`).
    """
    for _ in range(warmup):
        fn()
    synchronize(device)
    samples = []
    start_all = time.perf_counter()
    while len(samples) < repeats or (time.perf_counter() - start_all) < min_time_s:
        samples.append(_call_ms(fn, device))
        if len(samples) >= 10 * repeats:
            break
    return statistics.median(samples)


def time_ms_interleaved(fns: dict[str, Callable[[], object]], device: torch.device, *, warmup: int = 1,
                        min_rounds: int = 3, max_rounds: int = 50, max_calls: int = 20,
                        min_time_s: float = 0.3) -> dict[str, float]:
    """Median wall time [ms] of each of several functions, timed in alternating rounds.

    Rivals timed one after the other see different machines when the host's speed drifts (on a
    shared GPU host, calls of a few hundred microseconds vary by 2x from one minute to the
    next), so their ratio carries the drift. Here every round times each function in turn (the
    device synchronised around each call, as `time_ms`; the order rotated from round to round),
    a faster one called more times per round (its last warm-up call's time against the slowest
    one's, at most `max_calls`) so each takes about the same share of a round. Rounds go on until
    `min_rounds` are done and `min_time_s` has passed (at most `max_rounds`).

    Returns:
        name -> median of its timed calls [ms].
    """
    if not fns:
        return {}
    names = list(fns)
    first = {}
    for name in names:
        for _ in range(max(1, warmup)):
            first[name] = _call_ms(fns[name], device)
    slowest = max(first.values())
    calls = {name: min(max_calls, max(1, round(slowest / max(t, 1e-9)))) for name, t in first.items()}
    samples = {name: [] for name in names}
    start_all = time.perf_counter()
    rounds = 0
    while rounds < max_rounds and (rounds < min_rounds or time.perf_counter() - start_all < min_time_s):
        shift = rounds % len(names)
        for name in names[shift:] + names[:shift]:
            for _ in range(calls[name]):
                samples[name].append(_call_ms(fns[name], device))
        rounds += 1
    return {name: statistics.median(s) for name, s in samples.items()}


def kernel_device_times(profile, per: float = 1.0, top: int | None = None) -> dict[str, float]:
    """Each device-side row of a finished `torch.profiler.profile` (kernels and copies: rows with
    no CPU time), its total device time [us] divided by `per` (calls, iterations), largest first,
    the `top` largest (None: all); names as the profiler keys them.
    """
    times: dict[str, float] = {}
    for event in profile.key_averages():
        us = getattr(event, "device_time_total", None) or getattr(event, "cuda_time_total", 0.0)
        if us and not event.cpu_time_total:
            times[event.key] = times.get(event.key, 0.0) + us / max(per, 1e-12)
    ranked = sorted(times.items(), key=lambda kv: -kv[1])
    return dict(ranked if top is None else ranked[:top])


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


def machine_name(device: torch.device) -> str:
    """A one-line name of the machine a figure was measured on."""
    device = torch.device(device)
    if device.type == "cuda":
        return f"{torch.cuda.get_device_name(device)} (torch {torch.__version__})"
    cpu = cpu_model_name() or platform.processor() or platform.machine()
    return f"{cpu}, {os.cpu_count()} cores (torch {torch.__version__}, CPU)"


def machine_description(device: torch.device) -> dict:
    """What a set of figures was measured on: device name, CPU, cores, load, library versions."""
    import sys

    import warp as wp

    device = torch.device(device)
    cpu_name = cpu_model_name()
    info = {
        "device": str(device),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "cpu_name": cpu_name,
        "python": sys.version.split()[0],
        "torch": torch.__version__,
        "warp": wp.__version__,
    }
    try:  # other work on the machine slows every timing: say how busy it was
        info["load_average_1min"] = os.getloadavg()[0]
    except OSError:
        info["load_average_1min"] = None
    if device.type == "cuda":
        info["device_name"] = torch.cuda.get_device_name(device)
    else:
        info["device_name"] = f"CPU ({cpu_name or info['processor']}, {os.cpu_count()} cores)"
    return info


def jsonable(value):
    """`value` with tensors, tuples and non-finite floats made JSON-safe (NaN/Inf as strings)."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, torch.Tensor):
        return jsonable(value.detach().cpu().tolist()) if value.numel() != 1 else jsonable(value.item())
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    if isinstance(value, (int, str, bool)) or value is None:
        return value
    if hasattr(value, "item"):  # numpy scalars
        return jsonable(value.item())
    return str(value)


class CapturedCall:
    """`fn(*inputs)` captured once in a CUDA graph for fixed shapes, then replayed.

    At batch 1 a network's forward is a few hundred small kernel launches whose host-side cost
    (about 5 us each) is most of its time; a replay launches them all at once. The inputs are
    copied into the graph's own buffers before each replay, and the output is cloned out of
    the graph's buffer (a later replay overwrites it).

    Args:
        fn: a function of CUDA tensors returning a tensor, a tuple of them, or None (a step that
            updates tensors in place); no host synchronisation inside, no data-dependent shapes or
            control flow (the graph records one path).
        *example: tensors with the shapes, dtypes and device of every later call (none for a
            closure over its tensors: it is then replayed on what they hold at capture).
        warmup: eager calls on a side stream before the capture (allocator, cuBLAS handles).
    """

    def __init__(self, fn: Callable[..., torch.Tensor | tuple[torch.Tensor, ...]], *example: torch.Tensor,
                 warmup: int = 3):
        self.inputs = [t.detach().clone() for t in example]
        device = self.inputs[0].device if self.inputs else torch.device("cuda", torch.cuda.current_device())
        stream = torch.cuda.Stream(device=device)
        stream.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(stream):
            for _ in range(warmup):
                fn(*self.inputs)
        torch.cuda.current_stream(device).wait_stream(stream)
        self.graph = torch.cuda.CUDAGraph()
        # Collect garbage first: a Warp array freed by the collector inside the capture (one left
        # by an earlier solver, say) releases its memory there, which invalidates the capture
        # ("operation not permitted when stream is capturing", seen on an H200).
        import gc

        gc.collect()
        # The NaN/Inf scan of inputs reads a value back to the host, which a capture forbids;
        # the inputs were checked by the eager warm-up calls above.
        from hairwarp._validate import set_finite_checks

        previous = set_finite_checks(False)
        try:
            with torch.cuda.graph(self.graph):
                self.output = fn(*self.inputs)
        finally:
            set_finite_checks(previous)

    def matches(self, *args: torch.Tensor) -> bool:
        """Whether `args` have the shapes, dtypes and devices this graph was captured for."""
        return len(args) == len(self.inputs) and all(
            a.shape == b.shape and a.dtype == b.dtype and a.device == b.device for a, b in zip(args, self.inputs))

    def __call__(self, *args: torch.Tensor) -> torch.Tensor | tuple[torch.Tensor, ...] | None:
        for buffer, value in zip(self.inputs, args):
            buffer.copy_(value)
        self.graph.replay()
        if self.output is None:
            return None
        if isinstance(self.output, tuple):
            return tuple(t.clone() for t in self.output)
        return self.output.clone()


# Side streams by (device index, name): created once, reused by every call (and by captures).
_SIDE_STREAMS: dict[tuple[int, str], torch.cuda.Stream] = {}
# Whether `StreamFork` forks at all (set False to run every term on the current stream or thread).
STREAM_FORKS = True
# The CPU's side thread (`StreamFork.call` with cpu_thread): (process id, one-worker executor),
# made again in a forked child (a fork copies no thread).
_cpu_side: tuple[int, ThreadPoolExecutor] | None = None


def cpu_side_executor() -> ThreadPoolExecutor:
    """The CPU's one side thread (made again in a forked child): work submitted to it runs beside
    the caller's thread (Warp's CPU kernels release Python's lock, so the two use two cores).
    """
    global _cpu_side
    if _cpu_side is None or _cpu_side[0] != os.getpid():
        _cpu_side = (os.getpid(), ThreadPoolExecutor(max_workers=1, thread_name_prefix="hairwarp-side"))
    return _cpu_side[1]


class StreamFork:
    """Work that may run beside the current CUDA stream: forked from it, joined back later.

    On one GPU at batch 1 the contact kernels are short and some are latency-bound (a few
    thousand deep hair-body queries), so independent terms overlap instead of queueing. Use as

        fork = StreamFork(device, "hair_body")
        with fork:
            a = f(x)          # on the side stream, after everything queued before the fork
        b = g(x)              # on the current stream, meanwhile
        fork.join(a)          # the current stream waits for the side one; `a` usable there

    Every use of the side stream starts after the current stream's work queued so far, so
    memory freed on the current stream before a fork is never reused under the side stream's
    feet; `join` records its tensors on the current stream. Graph captures follow forks and
    joins (both streams are captured). On the CPU, or with `enabled` False, nothing forks.

    Work given as a function (`call`) may also run beside the caller on the CPU, with
    `cpu_thread`: on one worker thread while the caller goes on (Warp's CPU kernels release
    Python's lock, so the two use two cores), when torch may run independent work side by side
    (`torch.get_num_interop_threads()` > 1, its default on a machine of two cores or more;
    `torch.set_num_interop_threads(1)` keeps every term on the caller's thread). The worker
    takes the caller's grad and inference modes.

        fork = StreamFork(device, "hair_hair", cpu_thread=True)
        pending = fork.call(f, x)   # a side stream on CUDA, the side thread on the CPU
        b = g(x)
        a = pending.result()        # f's value (or its exception), then
        fork.join(a)

    Args:
        device: the tensors' device.
        name: which side stream (one per name and device).
        enabled: fork at all (and `hairwarp.runtime.STREAM_FORKS`, True unless set off).
        high_priority: the side stream's blocks are scheduled before those of streams of
            normal priority (torch's default streams) when both wait for room on the GPU.
        cpu_thread: on the CPU, `call` runs its function on the side thread.
    """

    def __init__(self, device: torch.device, name: str, *, enabled: bool = True, high_priority: bool = False,
                 cpu_thread: bool = False):
        self.active = enabled and STREAM_FORKS and device.type == "cuda"
        self.threaded = (enabled and STREAM_FORKS and cpu_thread and device.type == "cpu"
                         and torch.get_num_interop_threads() > 1)
        self._context = None
        if not self.active:
            return
        index = device.index if device.index is not None else torch.cuda.current_device()
        key = (index, name, high_priority)
        if key not in _SIDE_STREAMS:
            _SIDE_STREAMS[key] = torch.cuda.Stream(device=index, priority=-1 if high_priority else 0)
        self.side = _SIDE_STREAMS[key]
        self.main = torch.cuda.current_stream(index)
        self.side.wait_stream(self.main)

    def __enter__(self):
        if self.active:
            self._context = torch.cuda.stream(self.side)
            self._context.__enter__()
        return self

    def __exit__(self, *exc):
        if self._context is not None:
            self._context.__exit__(*exc)
            self._context = None
        return False

    def call(self, fn: Callable, *args, **kwargs) -> Future:
        """Run fn(*args, **kwargs) beside the caller: on the side stream (CUDA, queued at once),
        or on the side thread (CPU with `cpu_thread`), or here and now; its value (or the
        exception it raised) comes from the returned future's `result()`.
        """
        if self.threaded:
            grad = torch.is_grad_enabled()
            inference = torch.is_inference_mode_enabled()

            def task():
                with torch.inference_mode(inference), torch.set_grad_enabled(grad):
                    return fn(*args, **kwargs)

            return cpu_side_executor().submit(task)
        done: Future = Future()
        with self:
            done.set_result(fn(*args, **kwargs))
        return done

    def join(self, *tensors: torch.Tensor) -> None:
        """Make the current stream wait for the side one; `tensors` (made there) are then safe to use here."""
        if not self.active:
            return
        self.main.wait_stream(self.side)
        for t in tensors:
            if isinstance(t, torch.Tensor) and t.is_cuda:
                t.record_stream(self.main)
