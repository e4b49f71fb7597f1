"""hairwarp: differentiable hair physics in NVIDIA Warp with a PyTorch front end.

    import hairwarp as hw
    scene = hw.default_scene("bob", strand_stride=8)
    r = hw.drape(scene, method="lbfgs", max_iterations=50)
    r.positions, r.metrics["penetration_percent"], r.metrics["length_change_percent"]
    hw.simulate(hw.default_scene("bob", "head_turn"), method="dynamic").positions   # (T, M, N, 3)
    hw.methods.available()
    hw.ops.hair_body_contact_energy(...)   # the kernels, as torch functions

The names below load on first use, so `import hairwarp` (and the command line's --help) stays
quick and Warp is initialised only when a kernel is needed.
"""

from __future__ import annotations

import importlib

from hairwarp._validate import set_finite_checks

__version__ = "0.1.0"

_LAZY = {
    "default_scene": ("hairwarp.scene.scene", "default_scene"),
    "build_scene": ("hairwarp.builder", "build_scene"),
    "drape": ("hairwarp.api", "drape"),
    "simulate": ("hairwarp.api", "simulate"),
    "Result": ("hairwarp.api", "Result"),
    "EnergyConfig": ("hairwarp.config", "EnergyConfig"),
    "methods": ("hairwarp.methods", None),
    "ops": ("hairwarp.ops", None),
    "metrics": ("hairwarp.metrics", None),
}

__all__ = ["set_finite_checks", "__version__", *_LAZY]


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'hairwarp' has no attribute {name!r}")
    module_name, attr = _LAZY[name]
    module = importlib.import_module(module_name)
    value = module if attr is None else getattr(module, attr)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
