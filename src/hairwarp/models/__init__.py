"""hairwarp.models: the HairFormer networks (Sections 3.2-3.3), the Quaffure (adapted) baseline
(Section 4.3.1), deformation application (Eq. 2, Section 4.2.3) and checkpoints.
"""

from hairwarp.models.checkpoint import (
    Checkpoint,
    load_checkpoint,
    parameter_count,
    save_checkpoint,
    storage_bytes,
)
from hairwarp.models.config import (
    FUSION_CROSS_ATTENTION,
    FUSION_LAYERNORM_CONCAT,
    FUSION_LORA,
    FUSIONS,
    DynamicConfig,
    QuaffureConfig,
    StaticConfig,
)
from hairwarp.models.deformation import (
    apply_deformation,
    length_projection_of,
    nearest_cell,
    sample_deformation,
    taper_weights,
)
from hairwarp.models.dynamic import DynamicNetwork, DynamicOutput
from hairwarp.models.inertial import InertialConfig, InertialStep
from hairwarp.models.quaffure import QuaffureNetwork
from hairwarp.models.static import StaticNetwork

__all__ = [
    "Checkpoint",
    "DynamicConfig",
    "DynamicNetwork",
    "DynamicOutput",
    "FUSIONS",
    "InertialConfig",
    "InertialStep",
    "FUSION_CROSS_ATTENTION",
    "FUSION_LAYERNORM_CONCAT",
    "FUSION_LORA",
    "QuaffureConfig",
    "QuaffureNetwork",
    "StaticConfig",
    "StaticNetwork",
    "apply_deformation",
    "length_projection_of",
    "load_checkpoint",
    "nearest_cell",
    "parameter_count",
    "sample_deformation",
    "save_checkpoint",
    "storage_bytes",
    "taper_weights",
]
