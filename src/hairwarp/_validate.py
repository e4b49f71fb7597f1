"""Input checks shared by every public function: one clear ValueError naming the argument."""

from __future__ import annotations

from collections.abc import Sequence

import torch

FLOAT_DTYPES = (torch.float32, torch.float64)

# The NaN/Inf scan reads a reduction back to the host: a synchronisation on CUDA. Hot loops
# that already trust their inputs (training, benchmarks) turn it off with `set_finite_checks`.
_check_finite = True


def finite_checks_enabled() -> bool:
    """Whether public inputs are scanned for NaN/Inf (see `set_finite_checks`)."""
    return _check_finite


def set_finite_checks(enabled: bool) -> bool:
    """Turn the NaN/Inf scan of public inputs on or off; returns the previous setting."""
    global _check_finite
    previous, _check_finite = _check_finite, bool(enabled)
    return previous


def check_tensor(
    name: str,
    t,
    *,
    shape: Sequence[int | None | str] | None = None,
    dtypes: Sequence[torch.dtype] = FLOAT_DTYPES,
    device: torch.device | None = None,
    finite: bool = True,
    allow_empty: bool = True,
) -> torch.Tensor:
    """Validate a tensor argument and return it.

    Args:
        name: argument name used in the error message.
        t: the value to check.
        shape: expected shape; `None` entries accept any size, the string "..." as the
            first entry accepts any number of leading dimensions.
        dtypes: accepted dtypes.
        device: required device (that of the first tensor argument, usually).
        finite: reject NaN and Inf.
        allow_empty: accept tensors with zero elements.

    Raises:
        ValueError: naming `name` and what was expected.
    """
    if not isinstance(t, torch.Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
    if shape is not None:
        dims = list(shape)
        if dims and dims[0] == "...":
            tail = dims[1:]
            ok = t.dim() >= len(tail) and all(
                e is None or e == s for e, s in zip(tail, t.shape[t.dim() - len(tail):])
            )
        else:
            ok = t.dim() == len(dims) and all(e is None or e == s for e, s in zip(dims, t.shape))
        if not ok:  # the message is built only here: a hot caller checks a few tensors per call
            ellipsis = bool(dims) and dims[0] == "..."
            listed = ", ".join("*" if e is None else str(e) for e in (dims[1:] if ellipsis else dims))
            want = f"({'..., ' if ellipsis else ''}{listed})"
            raise ValueError(f"{name}: expected shape {want}, got {tuple(t.shape)}")
    if dtypes is not None and t.dtype not in dtypes:
        names = " or ".join(str(d).replace("torch.", "") for d in dtypes)
        raise ValueError(f"{name}: expected dtype {names}, got {str(t.dtype).replace('torch.', '')}")
    if device is not None and t.device != device:
        raise ValueError(f"{name}: expected a tensor on {device}, got one on {t.device}")
    if not allow_empty and t.numel() == 0:
        raise ValueError(f"{name}: expected a non-empty tensor, got shape {tuple(t.shape)}")
    if finite and _check_finite and t.is_floating_point() and t.numel() > 0 and not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name}: contains NaN or Inf")
    return t


def check_finite(**tensors: torch.Tensor) -> None:
    """No NaN or Inf in any of the named tensors, read back in one synchronisation (a
    `check_tensor(..., finite=True)` per tensor waits for the device once each).

    Raises:
        ValueError: naming the first tensor that holds a NaN or Inf.
    """
    named = [(name, t) for name, t in tensors.items() if t.is_floating_point() and t.numel() > 0]
    if not _check_finite or not named:
        return
    if bool(torch.stack([torch.isfinite(t).all() for _, t in named]).all()):
        return
    for name, t in named:
        if not bool(torch.isfinite(t).all()):
            raise ValueError(f"{name}: contains NaN or Inf")


def check_same_dtype(**tensors: torch.Tensor) -> torch.dtype:
    """All named tensors share one dtype; return it."""
    items = list(tensors.items())
    first_name, first = items[0]
    for name, t in items[1:]:
        if t.dtype != first.dtype:
            raise ValueError(f"{name}: expected dtype {first.dtype} like {first_name}, got {t.dtype}")
    return first.dtype


def check_positive(name: str, value: float, *, allow_zero: bool = False) -> float:
    """A finite positive (or non-negative) number."""
    value = float(value)
    if not (value == value) or value in (float("inf"), float("-inf")):
        raise ValueError(f"{name}: expected a finite number, got {value}")
    if value < 0 or (value == 0 and not allow_zero):
        raise ValueError(f"{name}: expected a {'non-negative' if allow_zero else 'positive'} number, got {value}")
    return value
