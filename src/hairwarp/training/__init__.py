"""hairwarp.training: the HairFormer training loops (Sections 3.3, 3.4, 4.1, 4.2).

Static curriculum (phases 0-3, b_p annealing, early deformation clip), dynamic training (frozen
static network, subsampled dynamic-score-filtered sequences, GRU state carried over the
frames, Eq. 6 with stop-gradient inertia and functional regularization), fine-tuning on one
motion (Fig. 4), the batch sampler, configs loadable from TOML with `--set` overrides, and
data-parallel training under torchrun (`hairwarp.training.distributed`).
"""

from hairwarp.training.config import (
    DataConfig,
    DynamicTrainingConfig,
    StaticTrainingConfig,
    apply_overrides,
    load_config,
    to_toml,
    write_toml,
)
from hairwarp.training.data import HairBatch, SequenceBatch, TrainingSampler, shard_bounds
from hairwarp.training.distributed import DistributedContext, init_distributed
from hairwarp.training.dynamic import DynamicTrainer, dynamic_loss, inertia_history, train_dynamic
from hairwarp.training.finetune import finetune
from hairwarp.training.static import (
    StaticTrainer,
    barrier_schedule,
    curriculum_phase,
    static_loss,
    train_static,
)

__all__ = [
    "DataConfig",
    "DistributedContext",
    "DynamicTrainer",
    "DynamicTrainingConfig",
    "HairBatch",
    "SequenceBatch",
    "StaticTrainer",
    "StaticTrainingConfig",
    "TrainingSampler",
    "apply_overrides",
    "barrier_schedule",
    "curriculum_phase",
    "dynamic_loss",
    "finetune",
    "inertia_history",
    "init_distributed",
    "load_config",
    "shard_bounds",
    "static_loss",
    "to_toml",
    "train_dynamic",
    "train_static",
    "write_toml",
]
