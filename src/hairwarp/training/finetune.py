"""Fine-tuning a dynamic network on one hard motion (HairFormer Section 4.4, Fig. 4).

The paper fine-tunes its dynamic network for "a few hundred iterations" on whiplash motions:
a fast head turn that stops abruptly, after which the hair follows through and settles. Here
that is a dynamic-training run (`DynamicTrainer`, the same Eq. 6 loss) started from the
dynamic checkpoint's weights with a fresh optimizer, on sequences of that one motion only:
played as recorded (frame interval k = 1: the motion is already fast), no dynamic-score filter
(every clip of it is the hard case), the mean body shape without noise, and the checkpoint's
hairstyle pool and data sizes.
"""

from __future__ import annotations

import os

import torch

from hairwarp.scene.motion import list_motions
from hairwarp.training import distributed
from hairwarp.training._common import load_training_checkpoint, stored_config
from hairwarp.training.config import DynamicTrainingConfig, apply_overrides
from hairwarp.training.dynamic import DynamicTrainer


def finetune_config(
    base: DynamicTrainingConfig, motion: str = "whiplash", iterations: int = 300
) -> DynamicTrainingConfig:
    """The fine-tuning settings derived from a dynamic run's config.

    Args:
        base: the config the dynamic checkpoint was trained with.
        motion: a procedural motion name (`hairwarp.scene.motion.list_motions()`) or the path
            of an AMASS `.npz` file.
        iterations: optimizer steps (a few hundred in the paper).

    Returns:
        `base` restricted to that motion, k = 1, no filter, no shape noise, `iterations` steps.
    """
    if not isinstance(iterations, int) or isinstance(iterations, bool) or iterations < 1:
        raise ValueError(f"iterations: expected a positive int, got {iterations!r}")
    if not isinstance(motion, (str, os.PathLike)):
        raise ValueError(f"motion: expected a motion name or an AMASS .npz path, got {motion!r}")
    motion = os.fspath(motion)
    if motion in list_motions():
        data = base.data.replace(motions=[motion], amass_paths=[], motion_variants=1, beta_noise_std=0.0)
    elif os.path.isfile(motion):
        data = base.data.replace(motions=[], amass_paths=[motion], motion_variants=1, beta_noise_std=0.0)
    else:
        raise ValueError(
            f"motion: expected one of {list_motions()} or an existing AMASS .npz file, got {motion!r}"
        )
    return base.replace(steps=iterations, subsample_min=1, subsample_max=1, dynamic_filter=False, data=data)


def finetune(
    checkpoint,
    motion: str = "whiplash",
    iterations: int = 300,
    *,
    out=None,
    device: torch.device | str = "cpu",
    seed: int = 0,
    overrides=(),
    progress: bool = True,
) -> DynamicTrainer:
    """Fine-tune a dynamic checkpoint on one motion and write the result.

    Args:
        checkpoint: a dynamic checkpoint written by `hairwarp train dynamic` (file or folder);
            its stored training config supplies the data sizes and the hairstyle pool.
        motion: a procedural motion name or an AMASS `.npz` path ("whiplash": Fig. 4).
        iterations: optimizer steps (300: "a few hundred iterations").
        out: output folder (config.toml, log.jsonl, checkpoint.pt); None writes nothing.
        device: torch device ("cuda" under torchrun: each rank's cuda:LOCAL_RANK).
        seed: sampling seed.
        overrides: "key=value" settings applied last (e.g. "learning_rate=5e-5",
            "rollout_frames=8").
        progress: show the progress bar.

    Returns:
        The trainer: `model` is the fine-tuned network, `history` the per-step records.

    Raises:
        ValueError: on a checkpoint that is not a dynamic one or stores no training config,
            an unknown motion, or a bad override.
    """
    ctx = distributed.init_distributed(device)  # under torchrun: data-parallel, each rank its GPU
    ckpt = load_training_checkpoint(checkpoint, torch.device("cpu"), torch.float32, ("dynamic",))
    base = stored_config(ckpt, DynamicTrainingConfig)
    if base is None:
        raise ValueError("checkpoint: stores no training config (was it written by hairwarp train dynamic?)")
    config = apply_overrides(finetune_config(base, motion, iterations), overrides)
    trainer = DynamicTrainer(config, out=out, device=ctx.device, seed=seed, rank=ctx.rank,
                             world_size=ctx.world_size, init=checkpoint)
    try:
        trainer.train(progress=progress)
    finally:
        trainer.close()
    return trainer


__all__ = ["finetune", "finetune_config"]
