"""Every way to drape or simulate hair, behind one interface and one registry.

    import hairwarp as hw
    hw.methods.available()          # ['auto', 'rigid', 'adam', 'lbfgs', 'reference', 'static', ...]
    m = hw.methods.make("static+refine", hw.methods.MethodOptions(refine=20))
    m = hw.methods.make("static+settle")  # the network's drape brought to rest by 20 physics steps
    result = m.drape(scene.frames())  # MethodResult: positions (B, M, N, 3), time_ms, history, info

The harness (`hairwarp compare`), the commands (`drape`, `simulate`, `demo`) and the Python API
(`hairwarp.drape`, `hairwarp.simulate`) all build their methods here.
"""

from hairwarp.methods.base import KINDS, REFERENCE_MAX_ITERATIONS, Method, MethodOptions, MethodResult
from hairwarp.methods.composed import AUTO_REFINE, SETTLE_STEPS, AutoMethod, RefinedMethod, SettledMethod
from hairwarp.methods.networks import NETWORK_METHODS, HairFormerSimulator, NetworkMethod, load_simulator
from hairwarp.methods.optimizers import OptimizerMethod, ReferenceMethod, RigidMethod
from hairwarp.methods.registry import (REFINE_SUFFIX, SETTLE_SUFFIX, available, composed_names, make, register,
                                      split_composition, unregister)

__all__ = [
    "AUTO_REFINE", "KINDS", "NETWORK_METHODS", "REFERENCE_MAX_ITERATIONS", "REFINE_SUFFIX", "SETTLE_STEPS",
    "SETTLE_SUFFIX", "AutoMethod", "HairFormerSimulator", "Method", "MethodOptions", "MethodResult", "NetworkMethod",
    "OptimizerMethod", "RefinedMethod", "ReferenceMethod", "RigidMethod", "SettledMethod",
    "available", "composed_names", "load_simulator", "make", "register", "split_composition", "unregister",
]
