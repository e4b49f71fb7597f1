"""The registry: every method by name, in one explicit table (no import side effects).

`available()` lists the names; `make(name, options)` builds one. A name ending in "+refine"
("static+refine", "dynamic+refine", ...) composes that method with `options.refine` L-BFGS
iterations, one ending in "+settle" with `options.settle` damped physics steps
(`hairwarp.methods.composed`). Users add their own with `register(name, factory)`,
`factory(options) -> Method`.
"""

from __future__ import annotations

from collections.abc import Callable

from hairwarp.methods.base import Method, MethodOptions
from hairwarp.methods.composed import AutoMethod, RefinedMethod, SettledMethod
from hairwarp.methods.inertial import InertialMethod
from hairwarp.methods.networks import NetworkMethod
from hairwarp.methods.optimizers import OptimizerMethod, PhysicsMethod, ReferenceMethod, RigidMethod

REFINE_SUFFIX = "+refine"
SETTLE_SUFFIX = "+settle"
# The compositions a name may end in, and what each wraps the method in.
_COMPOSITIONS = {REFINE_SUFFIX: RefinedMethod, SETTLE_SUFFIX: SettledMethod}

_BUILT_IN: dict[str, Callable[[MethodOptions], Method]] = {
    "auto": AutoMethod,
    "rigid": RigidMethod,
    "adam": lambda options: OptimizerMethod("adam", options),
    "lbfgs": lambda options: OptimizerMethod("lbfgs", options),
    "physics": PhysicsMethod,
    "reference": ReferenceMethod,
    "static": lambda options: NetworkMethod("static", options),
    "dynamic": lambda options: NetworkMethod("dynamic", options),
    "quaffure": lambda options: NetworkMethod("quaffure", options),
    "inertial": InertialMethod,
}
_REGISTRY: dict[str, Callable[[MethodOptions], Method]] = dict(_BUILT_IN)


def available() -> list[str]:
    """Names of the registered methods (compose any of them with "+refine" or "+settle")."""
    return list(_REGISTRY)


def composed_names() -> list[str]:
    """The registered names and each of them with each composition ("static+refine", "static+settle", ...)."""
    return available() + [name + suffix for suffix in _COMPOSITIONS for name in available()]


def split_composition(name: str) -> tuple[str, str | None]:
    """(the method's name, the composition's suffix or None): "static+settle" -> ("static", "+settle")."""
    for suffix in _COMPOSITIONS:
        if isinstance(name, str) and name.endswith(suffix) and len(name) > len(suffix):
            return name[: -len(suffix)], suffix
    return name, None


def register(name: str, factory: Callable[[MethodOptions], Method], *, overwrite: bool = False) -> None:
    """Make a method available to `make`, the harness and the command line by name.

    Args:
        name: the method's name (letters, digits, "_" and "-").
        factory: `factory(options: MethodOptions) -> Method`.
        overwrite: replace an existing registration instead of raising.
    """
    if not isinstance(name, str) or not name or not all(c.isalnum() or c in "_-" for c in name):
        raise ValueError(f"name: expected a non-empty name of letters, digits, '_' or '-', got {name!r}")
    if not callable(factory):
        raise ValueError(f"factory: expected a callable, got {type(factory).__name__}")
    if name in _REGISTRY and not overwrite:
        raise ValueError(f"name: method {name!r} is already registered (pass overwrite=True to replace it)")
    _REGISTRY[name] = factory


def unregister(name: str) -> None:
    """Remove a user-registered method (the built-in ones stay)."""
    if name in _BUILT_IN:
        raise ValueError(f"name: {name!r} is built in and cannot be removed")
    _REGISTRY.pop(name, None)


def make(name: str, options: MethodOptions | None = None) -> Method:
    """An instance of a registered method, or of "<name>+refine" / "<name>+settle" (compositions
    nest: "static+refine+settle").

    Raises:
        ValueError: an unknown name (naming `method` and listing the registered ones).
    """
    options = options or MethodOptions()
    base, suffix = split_composition(name)
    if suffix is not None and (base in _REGISTRY or split_composition(base)[1] is not None):
        return _COMPOSITIONS[suffix](make(base, options), options)
    if name not in _REGISTRY:
        raise ValueError(f"method: unknown method {name!r}; expected one of {available()} "
                         f"(or any of them followed by {' or '.join(map(repr, _COMPOSITIONS))})")
    method = _REGISTRY[name](options)
    if not isinstance(method, Method):
        raise ValueError(f"method: the factory of {name!r} returned {type(method).__name__}, not a Method")
    return method
