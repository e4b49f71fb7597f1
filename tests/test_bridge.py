"""The torch-Warp bridge (`hairwarp._warp`): views reused across calls stay correct, generic
kernels resolve once per argument types, and neither trades safety for the host time saved."""

import gc
from typing import Any

import numpy as np
import pytest
import torch
import warp as wp

from hairwarp import _warp

_warp.init()  # quietly, before the kernel below is declared


@wp.kernel
def _scale_kernel(a: wp.array(dtype=Any), s: Any, out: wp.array(dtype=Any)):
    i = wp.tid()
    out[i] = a[i] * s


def test_a_view_keeps_its_tensor_alive_when_the_block_is_handed_out_again():
    """A view of a temporary keeps the temporary's data even after the tensor's last name is
    gone and torch hands the same block to a new tensor (the view must own a reference: a
    cached view that did not would read the new tensor's values)."""
    view = _warp.as_warp(torch.arange(4096, dtype=torch.float32))
    gc.collect()
    others = [torch.full((4096,), 7.0) for _ in range(8)]  # would reuse a freed block
    np.testing.assert_array_equal(view.numpy(), np.arange(4096, dtype=np.float32))
    assert all(float(o[0]) == 7.0 for o in others)


def test_views_of_tensors_at_one_address_follow_each_tensor():
    buffer = torch.zeros(12, dtype=torch.float32)
    first = _warp.as_warp(buffer, vec3=True)
    buffer.copy_(torch.arange(12.0))
    again = _warp.as_warp(buffer, vec3=True)
    assert first is not again and again.dtype == wp.vec3 and again.shape == (4,)
    np.testing.assert_array_equal(again.numpy().reshape(-1), np.arange(12.0))
    # Same address, other dtype or length: another view.
    as_int = _warp.as_warp(buffer.view(torch.int32))
    assert as_int.dtype == wp.int32 and as_int.shape == (12,)
    assert _warp.as_warp(buffer[:6]).shape == (6,)
    # A non-contiguous input is copied (and that copy kept alive by its view).
    strided = torch.arange(24.0, dtype=torch.float64)[::2]
    np.testing.assert_array_equal(_warp.as_warp(strided).numpy(), np.arange(0.0, 24.0, 2.0))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_generic_kernel_resolves_per_argument_types(dtype):
    """One cached instance per argument types: float32 and float64 calls, interleaved, each get
    their own and the right numbers."""
    for kind in (dtype, torch.float64 if dtype == torch.float32 else torch.float32, dtype):
        a = torch.arange(5, dtype=kind)
        out = torch.zeros(5, dtype=kind)
        _warp.launch(_scale_kernel, dim=5, inputs=[_warp.as_warp(a), _warp.scalar(2.5, kind)],
                     outputs=[_warp.as_warp(out)], device="cpu")
        np.testing.assert_allclose(out.numpy(), 2.5 * np.arange(5.0))
    keys = [key for key in _warp._overloads if key[0] is _scale_kernel]
    assert len(keys) == 2
    assert len({id(_warp._overloads[key]) for key in keys}) == 2


def test_a_replayed_launch_follows_every_changed_parameter_and_keeps_nothing_alive():
    """`_warp.launch` replays each kernel's recorded launch, packing again only what changed:
    new arrays (other addresses or lengths), new scalars, a new dim all take effect, and the
    record holds none of the tensors it was given."""
    import weakref

    def scale(a, s, out, dim=None):
        _warp.launch(_scale_kernel, dim=a.numel() if dim is None else dim,
                     inputs=[_warp.as_warp(a), _warp.scalar(s, a.dtype)], outputs=[_warp.as_warp(out)], device="cpu")
        return out

    a = torch.arange(6, dtype=torch.float32)
    np.testing.assert_allclose(scale(a, 2.0, torch.zeros(6)).numpy(), 2.0 * np.arange(6))
    np.testing.assert_allclose(scale(a, 3.0, torch.zeros(6)).numpy(), 3.0 * np.arange(6))  # new scalar
    b = torch.arange(10, 20, dtype=torch.float32)
    np.testing.assert_allclose(scale(b[:4], 3.0, torch.zeros(4)).numpy(), 3.0 * np.arange(10, 14))  # new arrays, dim
    out = torch.full((6,), -1.0)
    np.testing.assert_allclose(scale(a, 3.0, out, dim=2).numpy(), [0.0, 3.0, -1, -1, -1, -1])  # dim only
    a.copy_(torch.arange(6, 12, dtype=torch.float32))  # same addresses, new values: read at launch
    np.testing.assert_allclose(scale(a, 3.0, out).numpy(), 3.0 * np.arange(6, 12))
    np.testing.assert_array_equal(np.signbit(scale(a, 0.0, out).numpy()), False)
    np.testing.assert_array_equal(np.signbit(scale(a, -0.0, out).numpy()), True)  # equal to 0.0, other bits
    ints = torch.arange(4, dtype=torch.int32)
    for factor in (2, 5):  # a Warp int32 scalar, new value
        result_ints = torch.zeros(4, dtype=torch.int32)
        _warp.launch(_scale_kernel, dim=4, inputs=[_warp.as_warp(ints), wp.int32(factor)],
                     outputs=[_warp.as_warp(result_ints)], device="cpu")
        np.testing.assert_array_equal(result_ints.numpy(), factor * np.arange(4))

    temporary = torch.arange(8, dtype=torch.float32)
    result = torch.zeros(8)
    alive = weakref.ref(temporary)
    scale(temporary, 1.0, result)
    del temporary
    gc.collect()
    assert alive() is None
    np.testing.assert_allclose(result.numpy(), np.arange(8))


def test_threads_launching_one_kernel_do_not_share_a_record():
    """Each thread replays its own record (a record's parameters are rewritten in place)."""
    import threading

    errors = []

    def work(offset):
        for k in range(60):
            a = torch.arange(257, dtype=torch.float64) + offset + k
            out = torch.zeros(257, dtype=torch.float64)
            _warp.launch(_scale_kernel, dim=257, inputs=[_warp.as_warp(a), _warp.scalar(-0.5, torch.float64)],
                         outputs=[_warp.as_warp(out)], device="cpu")
            if not torch.equal(out, -0.5 * a):
                errors.append((offset, k))

    threads = [threading.Thread(target=work, args=(1000.0 * t,)) for t in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []


def test_a_scalar_changing_sign_of_zero_is_packed_again():
    a = torch.ones(4, dtype=torch.float64)
    out = torch.zeros(4, dtype=torch.float64)
    for s, negative in ((0.0, False), (-0.0, True), (0.0, False)):
        _warp.launch(_scale_kernel, dim=4, inputs=[_warp.as_warp(a), _warp.scalar(s, torch.float64)],
                     outputs=[_warp.as_warp(out)], device="cpu")
        assert torch.signbit(out).tolist() == [negative] * 4


def test_a_launch_plan_patches_its_varying_arrays_and_checks_their_size():
    """A `LaunchPlan` packs once and, per launch, points its varying arrays at the tensors given
    (new addresses and values take effect); the fixed ones and the scalars stay as recorded, and
    a tensor of another size is refused before anything launches."""
    import weakref

    a = torch.arange(6, dtype=torch.float32)
    out = torch.zeros(6)
    plan = _warp.LaunchPlan(_scale_kernel, 6, [_warp.as_warp(a), _warp.scalar(2.0, torch.float32)],
                            [_warp.as_warp(out)], "cpu", varying=(0, 2))
    plan.launch((a, out))
    np.testing.assert_allclose(out.numpy(), 2.0 * np.arange(6))
    b = torch.arange(10, 16, dtype=torch.float32)
    other = torch.full((6,), -1.0)
    plan.launch((b, other))  # new addresses
    np.testing.assert_allclose(other.numpy(), 2.0 * np.arange(10, 16))
    np.testing.assert_allclose(out.numpy(), 2.0 * np.arange(6))  # the first output untouched
    with pytest.raises(RuntimeError, match="28 bytes for an array of 24 bytes"):
        plan.launch((torch.arange(7, dtype=torch.float32), other))
    temporary = torch.arange(6, dtype=torch.float32)
    alive = weakref.ref(temporary)
    plan.launch((temporary, out))
    del temporary
    gc.collect()
    assert alive() is None
    np.testing.assert_allclose(out.numpy(), 2.0 * np.arange(6))


def test_a_launch_plan_sizes_a_view_by_its_own_elements():
    """A plan built on a view of part of a tensor expects that view's size, not its storage's."""
    storage = torch.arange(12, dtype=torch.float32)
    part = storage[:6]
    out = torch.zeros(6)
    plan = _warp.LaunchPlan(_scale_kernel, 6, [_warp.as_warp(part), _warp.scalar(2.0, torch.float32)],
                            [_warp.as_warp(out)], "cpu", varying=(0, 2))
    plan.launch((torch.arange(6, 12, dtype=torch.float32), out))
    np.testing.assert_allclose(out.numpy(), 2.0 * np.arange(6, 12))
    with pytest.raises(RuntimeError, match="48 bytes for an array of 24 bytes"):
        plan.launch((storage, out))
