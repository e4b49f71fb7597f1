"""The contact terms side by side on the CPU (`hairwarp.runtime.StreamFork` with `cpu_thread`):
`total_energy` computes hair-hair on a worker thread while hair-body runs on the caller's,
with the same energies and gradients as one thread, the caller's grad mode, its errors."""

import os
import threading

import pytest
import torch

from hairwarp import ops, runtime
from hairwarp.energy import total_energy
from test_captured_energy import _small_inputs


@pytest.fixture
def two_interop_threads(monkeypatch):
    """torch allowing side-by-side work, whatever this machine's core count."""
    monkeypatch.setattr(torch, "get_num_interop_threads", lambda: 2)


def _evaluate(x, inputs, **kw):
    xe = x.detach().clone().requires_grad_(True)
    result = total_energy(xe, inputs, dynamic=True, **kw)
    result.total.sum().backward()
    return result, xe.grad


def _record_threads(monkeypatch):
    """Wrap both contact terms so each call records the thread it ran on."""
    seen = {}
    for name in ("hair_hair_contact_energy", "hair_body_contact_energy"):
        original = getattr(ops, name)

        def wrapped(*args, _original=original, _name=name, **kwargs):
            seen[_name] = threading.get_ident()
            return _original(*args, **kwargs)

        monkeypatch.setattr(ops, name, wrapped)
    return seen


def test_side_thread_equals_one_thread_bit_for_bit(monkeypatch, two_interop_threads):
    x, inputs = _small_inputs("cpu")
    seen = _record_threads(monkeypatch)
    forked, g_forked = _evaluate(x, inputs)
    assert seen["hair_hair_contact_energy"] != threading.get_ident()  # on the side thread
    assert seen["hair_body_contact_energy"] == threading.get_ident()
    monkeypatch.setattr(runtime, "STREAM_FORKS", False)
    seen.clear()
    single, g_single = _evaluate(x, inputs)
    assert seen["hair_hair_contact_energy"] == threading.get_ident()
    assert forked.hair_hair_pairs == single.hair_hair_pairs > 0
    assert torch.equal(forked.total, single.total)
    for name in single.terms:
        assert torch.equal(forked.terms[name], single.terms[name]), name
    # The same gradient up to the order autograd adds the terms' parts (its nodes' numbers are
    # per thread), and the same bits run after run.
    torch.testing.assert_close(g_forked, g_single, rtol=1e-6, atol=1e-6 * float(g_single.abs().max()))
    monkeypatch.setattr(runtime, "STREAM_FORKS", True)
    again, g_again = _evaluate(x, inputs)
    assert torch.equal(again.total, forked.total) and torch.equal(g_again, g_forked)


def test_one_interop_thread_keeps_every_term_on_the_caller(monkeypatch):
    monkeypatch.setattr(torch, "get_num_interop_threads", lambda: 1)
    x, inputs = _small_inputs("cpu", batch=1)
    seen = _record_threads(monkeypatch)
    _evaluate(x, inputs)
    assert set(seen.values()) == {threading.get_ident()}


def test_side_thread_takes_the_callers_grad_mode(two_interop_threads):
    x, inputs = _small_inputs("cpu", batch=1)
    xe = x.detach().clone().requires_grad_(True)
    with torch.no_grad():
        result = total_energy(xe, inputs, dynamic=True)
    assert not result.total.requires_grad and not result.terms["hair_hair_contact"].requires_grad
    with torch.inference_mode():
        result = total_energy(x, inputs, dynamic=True)
    assert result.total.is_inference()
    result = total_energy(xe, inputs, dynamic=True)  # grad enabled again: both terms differentiable
    (grad,) = torch.autograd.grad(result.total.sum(), xe)
    assert bool(torch.isfinite(grad).all()) and float(grad.abs().sum()) > 0


def test_side_threads_error_reaches_the_caller(two_interop_threads):
    x, inputs = _small_inputs("cpu", batch=1)
    with pytest.raises(ValueError, match="capacity"):
        total_energy(x, inputs, hair_hair_capacity=-1)


def test_side_thread_is_made_again_in_a_forked_child(monkeypatch):
    first = runtime.cpu_side_executor()
    assert runtime.cpu_side_executor() is first
    monkeypatch.setattr(os, "getpid", lambda: -1)  # as a child of os.fork sees it: another process
    child = runtime.cpu_side_executor()
    assert child is not first
    assert child.submit(threading.get_ident).result() != threading.get_ident()
