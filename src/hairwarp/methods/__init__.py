"""Every way to drape or simulate hair, behind one interface and one registry.

    import hairwarp as hw
    hw.methods.available()          # ['auto', 'rigid', 'adam', 'lbfgs', 'reference', 'static', ...]
    m = hw.methods.make("static+refine", hw.methods.MethodOptions(refine=20))
    result = m.drape(scene.frames())  # MethodResult: positions (B, M, N, 3), time_ms, history, info

The harness (`hairwarp compare`), the commands (`drape`, `simulate`, `demo`) and the Python API
(`hairwarp.drape`, `hairwarp.simulate`) all build their methods here.
"""

from hairwarp.methods.base import KINDS, REFERENCE_MAX_ITERATIONS, Method, MethodOptions, MethodResult
from hairwarp.methods.composed import AUTO_REFINE, AutoMethod, RefinedMethod
from hairwarp.methods.networks import NETWORK_METHODS, HairFormerSimulator, NetworkMethod, load_simulator
from hairwarp.methods.optimizers import OptimizerMethod, ReferenceMethod, RigidMethod
from hairwarp.methods.registry import REFINE_SUFFIX, available, make, register, unregister

__all__ = [
    "AUTO_REFINE", "KINDS", "NETWORK_METHODS", "REFERENCE_MAX_ITERATIONS", "REFINE_SUFFIX",
    "AutoMethod", "HairFormerSimulator", "Method", "MethodOptions", "MethodResult", "NetworkMethod",
    "OptimizerMethod", "RefinedMethod", "ReferenceMethod", "RigidMethod",
    "available", "load_simulator", "make", "register", "unregister",
]
