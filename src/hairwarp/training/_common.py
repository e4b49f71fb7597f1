"""What the static and dynamic trainers share: the loop, the log, checkpoints, the progress bar.

A trainer owns a model, its Adam optimizer, a `TrainingSampler` and a step counter (steps
completed). `train_step` draws the batch of the current step (or takes one), evaluates the loss,
steps the optimizer and returns a record {step, loss, terms, ...} that also goes, one JSON
object per line, to `<out>/log.jsonl`. Checkpoints (`<out>/checkpoint.pt`) hold the weights,
the optimizer state, the step and the training config (in `extra`), so a resumed run draws
the same batches (they are keyed by the step) and continues exactly.

Data parallelism (`hairwarp.training.distributed`): with world_size > 1 the trainer wraps its
loss in DistributedDataParallel, each rank builds its share of the global batch, the logged
loss is the global batch mean, and rank 0 alone writes the files (barriers around them).
"""

from __future__ import annotations

import json
import math
import os
import time

import torch

from hairwarp.models import load_checkpoint, save_checkpoint
from hairwarp.training import distributed
from hairwarp.training.config import to_toml

CHECKPOINT_NAME = "checkpoint.pt"
LOG_NAME = "log.jsonl"
CONFIG_NAME = "config.toml"

# Short names of the energy terms on the progress bar.
_SHORT = {
    "stretch": "s", "bending": "b", "auxiliary": "aux", "smoothness": "sm", "gravity": "g",
    "root_alignment": "root", "inertia": "in", "hair_body_contact": "hb", "hair_hair_contact": "hh",
    "func_reg": "fr",
}

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def term_means(terms: dict) -> dict[str, float]:
    """Batch means of an `EnergyResult.terms` dict, as Python floats."""
    return {name: float(value.detach().mean()) for name, value in terms.items()}


class NonFiniteLossError(ValueError):
    """The training loss became NaN or Inf; the weights were left unchanged."""


def check_finite_loss(loss: torch.Tensor, step: int, terms: dict) -> None:
    """Raise instead of stepping the optimizer on a NaN/Inf loss (never a silent NaN)."""
    if not bool(torch.isfinite(loss.detach()).all()):
        bad = sorted(k for k, v in terms.items() if not math.isfinite(v))
        raise NonFiniteLossError(
            f"loss: non-finite ({float(loss)}) at step {step}; non-finite terms: {bad or 'none'}; "
            "lower the learning rate or set grad_clip_norm"
        )


def resolve_checkpoint(path) -> str:
    """A checkpoint file, or the `checkpoint.pt` inside a run folder."""
    path = os.fspath(path)
    if os.path.isdir(path):
        path = os.path.join(path, CHECKPOINT_NAME)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"checkpoint: no such file {path}")
    return path


class Trainer:
    """Base of `StaticTrainer` and `DynamicTrainer` (not used directly).

    Subclasses set `model`, `optimizer`, `sampler`, `config`, `device` and implement
    `total_steps`, `next_batch(step)` and `compute_loss(batch, step, model=None)` -> (loss
    tensor, terms dict, record extras dict).
    """

    kind = ""

    def _setup_run(self, out, seed: int, rank: int, world_size: int, step: int) -> None:
        self.out = None if out is None else os.fspath(out)
        self.seed, self.rank, self.world_size = seed, rank, world_size
        self.step = step
        self.history: list[dict] = []
        self._log = None
        self._ddp = None
        self.curve = None  # a `hairwarp.training.monitor.LearningCurve` where the trainer keeps one
        if world_size > 1:
            distributed.check_process_group(rank, world_size)
            if self.config.batch_size < world_size:
                raise ValueError(
                    f"batch_size: the global batch of {self.config.batch_size} leaves some of the "
                    f"{world_size} ranks without a sample (batch_size is global: use >= {world_size})"
                )
            self._ddp = distributed.wrap_ddp(self.model, self.compute_loss)
        if self.out is not None and self.is_main:
            os.makedirs(self.out, exist_ok=True)
            with open(os.path.join(self.out, CONFIG_NAME), "w", encoding="utf-8") as f:
                f.write(f"# hairwarp train {self.kind}: seed {seed}, world size {world_size}\n")
                f.write(to_toml(self.config))

    @property
    def is_main(self) -> bool:
        """Rank 0 writes the log and the checkpoints."""
        return self.rank == 0

    @property
    def total_steps(self) -> int:  # pragma: no cover - abstract
        raise NotImplementedError

    def next_batch(self, step: int):  # pragma: no cover - abstract
        raise NotImplementedError

    def compute_loss(self, batch, step: int, model=None):  # pragma: no cover - abstract
        raise NotImplementedError

    def training_batch(self, step: int):
        """The batch `train_step` draws: `next_batch` (a trainer whose captured step needs less
        may draw less).
        """
        return self.next_batch(step)

    def captured_loss(self, batch, step: int):
        """(loss, terms, extras) with the gradients already in `.grad` (a captured step), or None:
        `compute_loss` and a backward instead (the default).
        """
        return None

    def _before_resume(self) -> None:
        """Wait until every rank gets here before a checkpoint is read (rank 0 of this very run
        may have just written it).
        """
        distributed.barrier(self.device)

    # ------------------------------------------------------------------------------ steps
    def train_step(self, batch=None) -> dict:
        """One optimizer step on the current step's batch (or on `batch`).

        Under DDP every rank calls this at every step with its own share of the batch; the
        loss and terms of the record are then the global batch's means.

        Returns:
            The step's record: step (completed steps after it), loss, terms, time_s and
            the trainer's extras (phase, b_p, ...).

        Raises:
            NonFiniteLossError: (a ValueError) if the loss is NaN or Inf; the weights are left
                unchanged. Under DDP every rank raises at the same step.
        """
        start = time.perf_counter()
        step = self.step
        if batch is None:
            batch = self.training_batch(step)
        self.model.train()
        self.optimizer.zero_grad(set_to_none=True)
        captured = self.captured_loss(batch, step) if self._ddp is None else None
        if captured is not None:  # forward and backward replayed from a CUDA graph
            loss, terms, extras = captured
            check_finite_loss(loss, step, terms)
            value = float(loss)
        elif self._ddp is None:
            loss, terms, extras = self.compute_loss(batch, step)
            check_finite_loss(loss, step, terms)
            loss.backward()
            value = float(loss.detach())
        else:
            loss, terms, extras, value = self._distributed_loss(batch, step)
            # DDP averages the ranks' gradients: weighting each rank's batch mean by
            # share * world_size makes that average the gradient of the global batch mean.
            (loss * (batch.share * self.world_size)).backward()
        if self.config.grad_clip_norm > 0:
            torch.nn.utils.clip_grad_norm_(self._parameters(), self.config.grad_clip_norm)
        self.optimizer.step()
        self.step = step + 1
        record = {"step": self.step, "loss": value, "terms": terms, **extras,
                  "time_s": time.perf_counter() - start}
        self.history.append(record)
        self._write_log(record)
        return record

    def _distributed_loss(self, batch, step: int):
        """This rank's loss through DDP, and the global batch's loss and terms."""
        failed = None
        try:
            loss, terms, extras = self._ddp(batch, step)
        except ValueError as exc:  # bad network output, bad batch: stop every rank, not this one
            failed = exc
        if distributed.all_reduce_sum([0.0 if failed is None else 1.0], self.device)[0] > 0:
            if failed is not None:
                raise failed
            raise ValueError(f"loss: another rank failed at step {step} (its error is in its own output)")
        names = sorted(terms)
        share = batch.share
        sums = distributed.all_reduce_sum([float(loss.detach()) * share] + [terms[k] * share for k in names],
                                          self.device)
        value, terms = sums[0], dict(zip(names, sums[1:]))
        check_finite_loss(torch.tensor(value), step, terms)  # the same verdict on every rank
        return loss, terms, extras, value

    def evaluate(self, batch, step: int | None = None) -> tuple[float, dict]:
        """The loss and its terms on `batch` without updating anything (at `step`'s schedule);
        local to this rank (no collective).
        """
        self.model.eval()
        with torch.no_grad():
            loss, terms, _ = self.compute_loss(batch, self.step if step is None else step)
        return float(loss), terms

    def train(self, steps: int | None = None, *, progress: bool = True) -> list[dict]:
        """Run until `total_steps` (or for `steps` more), checkpointing as configured.

        Args:
            steps: steps to run from the current one; None runs to the end of the schedule.
            progress: show a tqdm bar with the loss and the per-term breakdown.

        Returns:
            The records of the steps run.
        """
        end = self.total_steps if steps is None else min(self.total_steps, self.step + int(steps))
        records = []
        bar = None
        if progress and self.is_main:
            from tqdm.auto import tqdm

            bar = tqdm(total=end, initial=self.step, desc=f"train {self.kind}", dynamic_ncols=True)
        try:
            self.record_curve()
            while self.step < end:
                record = self.train_step()
                records.append(record)
                self.record_curve()
                every = self.config.checkpoint_every
                if self.out is not None and every and self.step % every == 0 and self.step < end:
                    self.save()
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix_str(self._postfix(record), refresh=False)
        finally:
            if bar is not None:
                bar.close()
        if self.out is not None:
            self.save()
        return records

    def record_curve(self) -> dict | None:
        """Record the learning curve at the current step when it is due (and write it); None else.

        Every rank evaluates the same record (it is deterministic); rank 0 writes it.
        """
        if self.curve is None or not self.curve.due(self.step):
            return None
        entry = self.curve.record(self.step)
        self.curve.write()
        return entry

    @staticmethod
    def _postfix(record: dict) -> str:
        parts = [f"loss={record['loss']:.4g}"]
        parts += [f"{_SHORT.get(k, k)}={v:.3g}" for k, v in record["terms"].items()]
        if "phase" in record:
            parts.append(f"ph={record['phase']}")
        if "bp" in record:
            parts.append(f"bp={record['bp']:.3g}")
        return " ".join(parts)

    def _parameters(self):
        return [p for group in self.optimizer.param_groups for p in group["params"]]

    # ------------------------------------------------------------------------------ files
    def _write_log(self, record: dict) -> None:
        if self.out is None or not self.is_main:
            return
        if self._log is None:
            self._log = open(os.path.join(self.out, LOG_NAME), "a", encoding="utf-8")
        self._log.write(json.dumps(record) + "\n")
        self._log.flush()

    def checkpoint_extra(self) -> dict:
        """Plain data stored with the weights: what a resume or a fine-tune needs."""
        # world_size is for the record: a resume may use another (the batches are global).
        return {"training": self.kind, "training_config": self.config.to_dict(), "seed": self.seed,
                "world_size": self.world_size}

    def save(self, path=None) -> str | None:
        """Write the model, optimizer state, step and config (rank 0 only).

        Under torchrun every rank calls it (it ends with a barrier, so no rank reads the file
        before it is complete).

        Args:
            path: file to write; None: `<out>/checkpoint.pt`.

        Returns:
            The path written, or None on other ranks.
        """
        if path is None:
            if self.out is None:
                raise ValueError("path: the trainer has no output folder; pass a path")
            path = os.path.join(self.out, CHECKPOINT_NAME)
        written = None
        if self.is_main:
            written = os.fspath(path)
            tmp = written + ".tmp"
            save_checkpoint(tmp, self.model, optimizer=self.optimizer, step=self.step,
                            extra=self.checkpoint_extra())
            os.replace(tmp, written)  # a crash mid-write never leaves a truncated checkpoint
        distributed.barrier(self.device)
        return written

    def close(self) -> None:
        """Close the log file."""
        if self._log is not None:
            self._log.close()
            self._log = None


def load_training_checkpoint(path, device, dtype, expected_kinds):
    """Load a checkpoint written by a trainer; check its model kind."""
    ckpt = load_checkpoint(resolve_checkpoint(path), device, dtype=dtype)
    kind = type(ckpt.model).kind
    if kind not in expected_kinds:
        raise ValueError(f"checkpoint: holds a {kind} network, expected {' or '.join(expected_kinds)}")
    return ckpt


def stored_config(ckpt, cls):
    """The training config stored in a checkpoint's extra data, or None."""
    extra = ckpt.extra if isinstance(ckpt.extra, dict) else {}
    data = extra.get("training_config")
    if data is None:
        return None
    return cls.from_dict(data)


def stored_seed(ckpt, default: int) -> int:
    """The seed a checkpoint's run used (so a resume draws the same batches), else `default`."""
    extra = ckpt.extra if isinstance(ckpt.extra, dict) else {}
    seed = extra.get("seed", default)
    return int(seed) if isinstance(seed, int) else default


def checkpoint_config(path, kind: str):
    """The training config stored in a checkpoint written by `hairwarp train <kind>`.

    Raises:
        ValueError: if the checkpoint holds another kind of network or stores no config.
    """
    from hairwarp.training.config import CONFIG_CLASSES

    if kind not in CONFIG_CLASSES:
        raise ValueError(f"kind: expected one of {list(CONFIG_CLASSES)}, got {kind!r}")
    ckpt = load_training_checkpoint(path, "cpu", torch.float32, (kind,))
    config = stored_config(ckpt, CONFIG_CLASSES[kind])
    if config is None:
        raise ValueError(f"checkpoint: {os.fspath(path)} stores no training config")
    return config
