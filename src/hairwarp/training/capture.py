"""Training steps replayed from a CUDA graph (docs/contact.md 16).

A step's forward and backward are captured once per batch shape and replayed with each new
batch copied into the graph's buffers (`FixedHairBatch`: one uncropped body per batch of frames,
refit to each batch's poses, `BodyMesh.update` keeping every array a query reads in place; the
crop changes no contact result). The hair-hair pair buffer is sized from the first batch (twice
its pairs, at least one per segment); the optimizer steps outside the graph, so a batch that
overflows the buffer is redone with a larger one (`CapturedLossStep.overflowed`). On the CPU
(tests) the same buffers are evaluated eagerly.
"""

from __future__ import annotations

import dataclasses

import torch

from hairwarp.training.data import HairBatch

# Run the captured steps' buffers on the CPU too (eagerly, no graph): tests of their bookkeeping.
CAPTURE_ON_CPU = False


def capture_applies(trainer, batch: HairBatch | None = None) -> bool:
    """Whether `trainer`'s step replays from a graph: `cuda_graph` on, CUDA (or `CAPTURE_ON_CPU`),
    one process, and `batch` (when given; None: not drawn yet) carrying its posed bodies.
    """
    on = trainer.device.type == "cuda" or CAPTURE_ON_CPU
    carried = batch is None or batch.body_vertices is not None
    return bool(trainer.config.cuda_graph and on and trainer.world_size == 1 and carried)


def refit_body(batch: HairBatch, faces: torch.Tensor):
    """One uncropped `BodyMesh` of `batch`'s posed bodies (`body_vertices`), which
    `BodyMesh.update` refits to later batches of the same shape (the crop changes no contact
    result).
    """
    from hairwarp.ops import BodyMesh

    return BodyMesh(batch.body_vertices, faces, require_watertight=False, bvh="lbvh")


class FixedHairBatch:
    """The tensors of a `HairBatch` that a loss reads (latents, shapes, poses, rigid placement,
    rest lengths, scalp normals, the teacher's drapes) in fixed buffers, its bodies one uncropped `BodyMesh` refit per
    batch.

    Args:
        batch: a batch with `body_vertices` (the shapes every later batch shares).
        faces: (F, 3) the body model's faces (`TrainingSampler.body_faces`).
        with_body: build the body (False: the batch's inputs keep no body).
    """

    def __init__(self, batch: HairBatch, faces: torch.Tensor, with_body: bool = True):
        self.body = None
        if with_body:
            self.body = refit_body(batch, faces)
        rigid = batch.rigid.clone()
        inputs = dataclasses.replace(batch.inputs, rest_lengths=batch.inputs.rest_lengths.clone(), rigid=rigid,
                                     scalp_normals=batch.inputs.scalp_normals.clone(), body=self.body)
        teacher = None if batch.teacher is None else batch.teacher.clone()
        self.batch = dataclasses.replace(batch, z=batch.z.clone(), betas=batch.betas.clone(),
                                         poses=batch.poses.clone(), rigid=rigid, inputs=inputs, body_vertices=None,
                                         teacher=teacher)

    def copy_from(self, batch: HairBatch) -> None:
        """Write `batch` (same shapes) into the buffers and refit the body to its poses."""
        fixed = self.batch
        for dst, src in ((fixed.z, batch.z), (fixed.betas, batch.betas), (fixed.poses, batch.poses),
                         (fixed.rigid, batch.rigid), (fixed.inputs.rest_lengths, batch.inputs.rest_lengths),
                         (fixed.inputs.scalp_normals, batch.inputs.scalp_normals)):
            dst.copy_(src)
        if (fixed.teacher is None) != (batch.teacher is None):
            raise ValueError("batch: a teacher where the captured step holds none, or none where it holds one")
        if fixed.teacher is not None:
            fixed.teacher.copy_(batch.teacher)
        if self.body is not None:
            self.body.update(batch.body_vertices)


class CapturedLossStep:
    """`evaluate`'s loss and its backward for fixed buffers, captured in a CUDA graph on CUDA.

    Args:
        model: the network whose trainable parameters get the gradients (left in `.grad`).
        evaluate: `evaluate(graph_safe, capacity)` -> (loss () tensor, {name: tensor} terms,
            hair-hair info or None), reading only the fixed buffers (nothing back to the host
            when `graph_safe`).
        segments: hair segments of a batch (the pair buffer holds at least one per segment).
        capacity: the hair-hair pair-buffer capacity; None: twice the pairs of an eager call.
    """

    def __init__(self, model, evaluate, segments: int, capacity: int | None = None):
        from hairwarp.runtime import CapturedCall

        params = [p for p in model.parameters() if p.requires_grad]
        if capacity is None:
            with torch.no_grad():
                _, _, info = evaluate(False, None)
            found = 0 if info is None else int(info.pair_count)
            capacity = max(2 * found, segments, 1)
        self.capacity = capacity

        def step():
            for p in params:  # allocated by the backward (inside a capture: in the graph's pool)
                p.grad = None
            loss, terms, info = evaluate(True, capacity)
            loss.backward()
            self._out = (loss.detach(), {k: v.detach() for k, v in terms.items()}, info)
            return self._out[0]

        self._step, self._params = step, params
        device = params[0].device if params else torch.device("cpu")
        self._graph = CapturedCall(step) if device.type == "cuda" else None
        self._grads = [p.grad for p in params]

    @property
    def captured(self) -> bool:
        """Whether calls replay a CUDA graph."""
        return self._graph is not None

    def run(self):
        """Replay (or evaluate): (loss () tensor, terms {name: tensor}); gradients in `.grad`."""
        if self._graph is None:
            self._step()
            self._grads = [p.grad for p in self._params]
        else:
            self._graph()
            for p, g in zip(self._params, self._grads):  # the graph's gradient buffers
                p.grad = g
        return self._out[0], self._out[1]

    def overflowed(self) -> int:
        """0, or the hair-hair pairs of the last call when they overflowed the buffer (reads the
        device).
        """
        info = self._out[2]
        return int(info.pair_count) if info is not None and info.overflow else 0
