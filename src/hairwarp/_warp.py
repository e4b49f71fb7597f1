"""The one place where torch tensors meet Warp: initialisation, devices, streams, views.

Warp arrays never leave `hairwarp.ops`; public functions take and return torch tensors.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import sys
import tempfile
import threading

import torch
import warp as wp

_initialised = False
# Printed by Warp's native library on every machine without an NVIDIA driver (every CPU-only
# run, CI included): expected there, so not shown; any other line Warp prints still is.
_NO_DRIVER_WARNING = "Could not find or load the NVIDIA CUDA driver"


def init() -> None:
    """Initialise Warp once, quietly (idempotent)."""
    global _initialised
    if not _initialised:
        wp.config.log_level = logging.WARNING
        with _without_no_driver_warning():
            wp.init()
        _initialised = True


@contextlib.contextmanager
def _without_no_driver_warning():
    """Capture what native code writes to stdout/stderr; re-emit all but the no-driver line."""
    try:
        fds = (sys.stdout.fileno(), sys.stderr.fileno())
    except (AttributeError, OSError, ValueError):  # no real file descriptors (some notebooks)
        yield
        return
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(fd) for fd in fds]
    with tempfile.TemporaryFile(mode="w+b") as capture:
        try:
            for fd in fds:
                os.dup2(capture.fileno(), fd)
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            for fd, old in zip(fds, saved):
                os.dup2(old, fd)
                os.close(old)
            capture.seek(0)
            text = capture.read().decode(errors="replace")
            kept = [line for line in text.splitlines(keepends=True) if _NO_DRIVER_WARNING not in line]
            if kept:
                sys.stderr.write("".join(kept))


def warp_device(device: torch.device) -> str:
    """Warp device name for a torch device ("cpu" or "cuda:N")."""
    if device.type == "cuda":
        index = device.index if device.index is not None else torch.cuda.current_device()
        return f"cuda:{index}"
    if device.type == "cpu":
        return "cpu"
    raise ValueError(f"device: expected a cpu or cuda tensor, got device {device}")


def set_default_device(device: torch.device) -> None:
    """Make `device` Warp's default device in this process (one rank of a data-parallel run).

    Every bridge in `hairwarp.ops` names the device of its tensors and runs on torch's current
    stream of that device, so launches never depend on this default; it keeps the Warp work
    that names no device (third-party code, array creation) off cuda:0 on ranks that own
    another GPU, where it would also open a CUDA context.
    """
    init()
    wp.set_device(warp_device(torch.device(device)))


def launch_scope(device: torch.device):
    """Context that makes Warp launches run on torch's current stream for `device`.

    On CPU there is no stream; on CUDA this keeps Warp and torch work ordered without a
    host synchronisation. `device` "cuda" without an index means torch's current device (set
    per rank by `torch.cuda.set_device`); the stream and Warp's device scope both follow it.
    Entering makes the stream wait for Warp's previous one (e.g. a body mesh built there),
    except while torch captures a CUDA graph: a capture may not depend on uncaptured work (the
    graph's inputs were made before the capture began).
    """
    init()
    if device.type == "cuda":
        return wp.ScopedStream(_warp_stream(device), sync_enter=not torch.cuda.is_current_stream_capturing())
    return contextlib.nullcontext()


# Warp's view of each torch stream, by (device index, stream handle): `wp.stream_from_torch`
# registers a new Warp stream on every call (14 us of host time per call on an H100's host,
# docs/contact.md 9). Each keeps its torch stream alive, so a handle is never reused while here.
_streams: dict = {}
_MAX_STREAMS = 64


def _warp_stream(device: torch.device) -> wp.Stream:
    """The Warp stream of torch's current stream on `device`, made once per stream."""
    stream = torch.cuda.current_stream(device)
    key = (stream.device_index, stream.cuda_stream)
    warp_stream = _streams.get(key)
    if warp_stream is None:
        if len(_streams) >= _MAX_STREAMS:
            _streams.clear()
        warp_stream = _streams[key] = wp.stream_from_torch(stream)
    return warp_stream


def torch_stream(device: torch.device) -> wp.Stream | None:
    """The Warp stream of torch's current stream on `device` (None on the CPU), for a launch that
    names its stream instead of entering `launch_scope`: one that reads only torch-made tensors
    needs no wait on Warp's previous stream, and skips the scope's two stream switches.
    """
    return _warp_stream(device) if device.type == "cuda" else None


_VEC3 = {torch.float32: wp.vec3, torch.float64: wp.vec3d}
_MAT33 = {torch.float32: wp.mat33, torch.float64: wp.mat33d}
_SCALAR = {torch.float32: wp.float32, torch.float64: wp.float64}


def scalar_type(dtype: torch.dtype):
    """Warp scalar type for a torch float dtype."""
    return _SCALAR[dtype]


def scalar(value: float, dtype: torch.dtype):
    """A Python float as the Warp scalar that matches `dtype` (generic kernels need it)."""
    return _SCALAR[dtype](value)


# The concrete instance of each generic (`Any`-typed) kernel, by its generic arguments' types;
# and, per generic kernel, which of its arguments are generic (the others cannot choose).
_overloads: dict = {}
_generic_positions: dict = {}


def _argument_key(value):
    if isinstance(value, wp.array):
        return value.dtype, value.ndim
    return type(value)


def _generic_argument_positions(kernel) -> tuple[int, ...]:
    positions = _generic_positions.get(kernel)
    if positions is None:
        from warp._src.types import type_is_generic

        positions = _generic_positions[kernel] = tuple(
            index for index, arg in enumerate(kernel.adj.args) if type_is_generic(arg.type)
        )
    return positions


def _float_key(value: float):
    return value, math.copysign(1.0, value)  # -0.0 == 0.0, yet other bits


def _parameter_key(value):
    """What a launch parameter packs from: an array's address and shape, a scalar's value."""
    keyer = _KEYERS.get(type(value))
    if keyer is not None:
        return keyer(value)
    if isinstance(value, wp.array):
        return value.ptr, value.shape
    scalar = getattr(value, "value", None)  # a Warp scalar
    if scalar is not None:
        return _parameter_key(scalar)
    return tuple(value)  # a Warp vector


# Key makers by exact type (a dict lookup where isinstance chains cost more per argument), Warp's
# scalars included (a strand-term launch passes ten).
_KEYERS = {wp.array: lambda a: (a.ptr, a.shape), int: lambda v: v, float: _float_key, bool: lambda v: v}
_KEYERS.update({t: (lambda v: _float_key(v.value)) for t in (wp.float16, wp.float32, wp.float64)})
_KEYERS.update({t: (lambda v: v.value) for t in (wp.int32, wp.int64, wp.uint32, wp.uint64)})


def _concrete_kernel(kernel, arguments):
    """The instance of a generic kernel for these arguments' types (the kernel itself if not
    generic), made once per type combination.
    """
    if not kernel.is_generic:
        return kernel
    key = (kernel, tuple(_argument_key(arguments[index]) for index in _generic_argument_positions(kernel)))
    concrete = _overloads.get(key)
    if concrete is None:
        concrete = _overloads[key] = kernel.add_overload(kernel.infer_argument_types(arguments))
    return concrete


# The last recorded launch of each kernel per device and thread (a record's parameters are
# rewritten in place: two threads must not share one), with its parameters' keys and its dim.
_launches: dict = {}


def launch(kernel, dim, inputs=(), outputs=(), device=None, stream=None, block_dim: int | None = None,
           threads_per_block: int | None = None) -> None:
    """`wp.launch` with the host work an eager call repeats done once.

    With `block_dim` the kernel is a tile kernel (`wp.launch_tiled`): `dim` blocks of
    `block_dim` threads on CUDA (one thread each on the CPU), `wp.tid()` giving (block, lane).
    With `threads_per_block` a plain kernel's `dim` threads run in CUDA blocks of that size
    (Warp's default 256): a launch of few threads, each long, spreads over more of the GPU's
    multiprocessors in smaller blocks.

    - A generic kernel's instance is looked up per argument types: `wp.launch` infers the types
      and the overload's signature on every call (~70 us per launch on an H100's host).
    - Each kernel's launch is recorded once per device (`wp.launch(record_cmd=True)`) and
      replayed with only the parameters that changed packed again (an array's address and
      shape, a scalar's value): packing every argument cost 25-75 us per launch there, a
      replay 6 us (docs/contact.md 9). The record keeps no argument alive.
    """
    arguments = [*inputs, *outputs]
    kernel = _concrete_kernel(kernel, arguments)
    target = wp.get_device(device) if stream is None else stream.device
    tiled = {}
    if block_dim is not None:
        block_dim = block_dim if target.is_cuda else 1
        tiled = {"block_dim": block_dim}
    elif threads_per_block is not None and target.is_cuda:
        tiled = {"block_dim": int(threads_per_block)}
    if not isinstance(dim, int) or dim <= 0:
        wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=target, stream=stream, **tiled)
        return
    if block_dim is not None:
        dim = (dim, block_dim)
    record_key = (kernel, target.alias, threading.get_ident(), tiled.get("block_dim"))
    record = _launches.get(record_key)
    if record is None:
        command = wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=target, record_cmd=True, **tiled)
        command.fwd_args = None  # retain no argument (they would keep their tensors alive)
        record = _launches[record_key] = [command, [_parameter_key(value) for value in arguments], dim]
    else:
        command, keys, last_dim = record
        if dim != last_dim:
            command.set_dim(dim)
            record[2] = dim
        for index, value in enumerate(arguments):
            value_key = _parameter_key(value)
            if value_key != keys[index]:
                command.set_param_at_index(index, value)
                keys[index] = value_key
    record[0].launch(stream)


class LaunchPlan:
    """A launch packed once, for a call site whose calls differ only in a few tensors' addresses.

    `launch` (above) keys and compares every parameter on every call; a call site that knows
    which of its parameters can change between calls with the same key (its own cache key:
    shapes, dtypes, scalars and the addresses of the other arrays) builds a plan once and, per
    call, writes only the data addresses of the `varying` arrays into the packed parameters
    (a field store each). Each tensor passed to `launch` must be contiguous with the dtype and
    the size in bytes of the array it replaces. A plan belongs to one thread (its
    parameters are rewritten in place); it keeps no argument alive.
    """

    def __init__(self, kernel, dim: int, inputs, outputs, device, varying: tuple[int, ...]):
        arguments = [*inputs, *outputs]
        kernel = _concrete_kernel(kernel, arguments)
        self._command = wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device, record_cmd=True)
        self._command.fwd_args = None
        # params[0] is the launch bounds; kernel argument k is params[k + 1].
        self._arrays = [self._command.params[index + 1] for index in varying]
        # Bytes each array spans (not `capacity`: a view's capacity is its whole storage's).
        self._sizes = [arguments[index].size * wp.types.type_size_in_bytes(arguments[index].dtype) for index in varying]

    def launch(self, tensors, stream=None) -> None:
        """Launch with `tensors` (one per varying index, in order) in place of the recorded arrays."""
        for array, size, t in zip(self._arrays, self._sizes, tensors):
            nbytes = t.numel() * t.element_size()
            if nbytes != size:
                raise RuntimeError(f"LaunchPlan: a tensor of {nbytes} bytes for an array of {size} bytes")
            array.data = t.data_ptr()
        self._command.launch(stream)


# A Warp view made by `wp.from_torch` for each (address, length, dtype, vec3, device): an eager
# call wraps ~20 tensors, whose blocks torch's caching allocator hands out again call after
# call, and `wp.from_torch` costs 10-17 us per tensor on an H100's host (docs/contact.md 9).
# `as_warp` returns a shallow copy of it (under 1 us) that keeps its own tensor alive, as
# `wp.from_torch`'s views do; the kept templates hold no tensor.
_views: dict = {}
_MAX_VIEWS = 1024


def as_warp(t: torch.Tensor, vec3: bool = False, quat: bool = False, mat33: bool = False) -> wp.array:
    """Zero-copy Warp view of a tensor, flat; `vec3=True` views (..., 3) as vec3, `quat=True` a
    float32 (..., 4) as quaternions (x, y, z, w), `mat33=True` (..., 3, 3) as row-major 3x3
    blocks. A non-contiguous tensor is copied first (pass
    only inputs so). The view keeps the tensor alive.
    """
    init()
    t = t.detach()
    if not t.is_contiguous():
        t = t.contiguous()
    key = (t.data_ptr(), t.numel(), t.dtype, vec3, quat, mat33, t.device)
    template = _views.get(key)
    if template is None:
        if len(_views) >= _MAX_VIEWS:
            _views.clear()
        if quat:
            flat, dtype = t.reshape(-1, 4), wp.quat
        elif mat33:
            flat, dtype = t.reshape(-1, 3, 3), _MAT33[t.dtype]
        else:
            flat = t.reshape(-1, 3) if vec3 else t.reshape(-1)
            dtype = _VEC3[t.dtype] if vec3 else _SCALAR.get(t.dtype)
        template = wp.from_torch(flat, dtype=dtype, requires_grad=False)
        template._tensor = None
        _views[key] = template
    view = object.__new__(type(template))
    view.__dict__.update(template.__dict__)
    view._tensor = t
    return view
