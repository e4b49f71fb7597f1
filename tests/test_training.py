"""Training loops (HairFormer Sections 3.3, 3.4.5, 4.1, 4.2): sampler, curriculum, b_p schedule,
static and dynamic steps, stop-gradient inertia, checkpoints and resume, fine-tuning, configs,
the command line, bad input.

Tiny networks on 64 strands x 20 vertices (`DataConfig.tiny()`), the real code path (decoded
latents, posed default body, Eq. 1 placement, Warp energies); the whole file runs in about a
minute on two CPU cores.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os

import numpy as np
import pytest
import torch

from hairwarp import cli
from hairwarp.config import EnergyConfig
from hairwarp.energy import total_energy
from hairwarp.models import DynamicNetwork, StaticNetwork, apply_deformation, length_projection_of, load_checkpoint
from hairwarp.ops import BodyMesh, hair_body_contact_energy, hair_body_signed_distance
from hairwarp.scene.motion import DESCRIPTOR_DIM_NO_BETAS
from hairwarp.scene.skeleton import JOINT
from hairwarp.training import (
    DataConfig,
    DynamicTrainer,
    DynamicTrainingConfig,
    StaticTrainer,
    StaticTrainingConfig,
    TrainingSampler,
    apply_overrides,
    barrier_schedule,
    curriculum_phase,
    dynamic_loss,
    finetune,
    inertia_history,
    load_config,
    to_toml,
)
from hairwarp.training import dynamic as dynamic_module
from references import placement as placement_ref
from references import training as ref

# float64 placement vs the numpy reference of Eq. 1: the same formula, other summation orders.
_F64_TOL = 1e-9
# float64 inertia gradients vs the loop reference: rounding only.
_GRAD_TOL = 1e-10
# b_p from the float formula vs the reference: rounding only.
_BP_TOL = 1e-12
# One Adam step moves every weight by about the learning rate, whatever the gradient's size;
# with the stiff inextensibility of the default energy (k_s = 1e8) the first-order decrease
# wins for steps of 1e-5 (the paper's 1e-4 overshoots on the tiny network's first step).
_STEP_LR = 1e-5
# Cropped vs full body: the same closest points, but the float32 BVHs of the two meshes may
# return a point on a shared edge from either neighbouring triangle (float32 rounding).
_CROP_REL_TOL = 1e-7
# Faces within this distance [m] of the head centre hold every root's closest point.
_REFERENCE_RADIUS = 0.3


@pytest.fixture(scope="module")
def data():
    return DataConfig.tiny()


@pytest.fixture(scope="module")
def sampler(data):
    return TrainingSampler(data, seed=0)


@pytest.fixture(scope="module")
def static_config(data):
    return StaticTrainingConfig.tiny().replace(phase_steps=(1, 1, 1, 1), data=data)


@pytest.fixture(scope="module")
def static_checkpoint(tmp_path_factory, static_config, sampler):
    out = tmp_path_factory.mktemp("static")
    trainer = StaticTrainer(static_config.replace(phase_steps=(1, 1, 0, 0)), out=out, sampler=sampler)
    trainer.train(progress=False)
    trainer.close()
    return os.path.join(out, "checkpoint.pt")


@pytest.fixture(scope="module")
def dynamic_config(data, static_checkpoint):
    return DynamicTrainingConfig.tiny(static_checkpoint).replace(data=data, steps=2)


@pytest.fixture(scope="module")
def dynamic_checkpoint(tmp_path_factory, dynamic_config, sampler):
    out = tmp_path_factory.mktemp("dynamic")
    trainer = DynamicTrainer(dynamic_config, out=out, sampler=sampler)
    trainer.train(progress=False)
    trainer.close()
    return os.path.join(out, "checkpoint.pt")


# ------------------------------------------------------------------------------- schedules
@pytest.mark.parametrize("kind", ["linear", "geometric"])
def test_barrier_schedule_goes_from_0_9_to_0_01(kind):
    total = 50
    values = [barrier_schedule(s, total, kind=kind) for s in range(total)]
    assert values[0] == pytest.approx(0.9, abs=_BP_TOL)
    assert values[-1] == pytest.approx(0.01, abs=_BP_TOL)
    assert all(a > b for a, b in zip(values, values[1:]))  # strictly decreasing
    for s in (0, 7, 25, 49, 80):
        want = ref.barrier_join_fraction(s, total, kind=kind)
        assert barrier_schedule(s, total, kind=kind) == pytest.approx(want, abs=_BP_TOL)
    assert barrier_schedule(0, 1) == pytest.approx(0.01)  # a one-step run ends where it starts


def test_trainer_anneals_bp_over_the_whole_curriculum(static_config, sampler):
    cfg = static_config.replace(phase_steps=(3, 2, 4, 3))
    trainer_schedule = StaticTrainer(cfg, sampler=sampler).schedule
    bps = [trainer_schedule(s)["bp"] for s in range(cfg.total_steps)]
    assert bps[0] == pytest.approx(0.9) and bps[-1] == pytest.approx(0.01)
    assert all(a > b for a, b in zip(bps, bps[1:]))
    clips = [trainer_schedule(s)["clip"] for s in range(cfg.total_steps)]
    assert clips == [0.01] * 3 + [None] * 9  # the clip holds during phase 0 by default


def test_curriculum_phase():
    steps = (2, 0, 3, 1)
    got = [curriculum_phase(s, steps) for s in range(8)]
    assert [p for p, _ in got] == [0, 0, 2, 2, 2, 3, 3, 3]  # phase 1 skipped, past the end stays
    assert [round(f, 6) for _, f in got[:6]] == [0.5, 1.0, round(1 / 3, 6), round(2 / 3, 6), 1.0, 1.0]


def test_schedule_bad_input():
    with pytest.raises(ValueError, match="total_steps"):
        barrier_schedule(0, 0)
    with pytest.raises(ValueError, match="start"):
        barrier_schedule(0, 10, start=1.5)
    with pytest.raises(ValueError, match="kind"):
        barrier_schedule(0, 10, kind="cosine")
    with pytest.raises(ValueError, match="phase_steps"):
        curriculum_phase(0, (0, 0, 0, 0))
    with pytest.raises(ValueError, match="step"):
        curriculum_phase(-1, (1, 1, 1, 1))


# ------------------------------------------------------------------------------- sampler
def _same_batch(a, b):
    pairs = ((a.z, b.z), (a.poses, b.poses), (a.betas, b.betas), (a.rigid, b.rigid))
    return all(torch.equal(x, y) for x, y in pairs)


def test_sampler_is_deterministic_per_seed_and_shards_per_rank(data, sampler):
    again = TrainingSampler(data, seed=0)
    ranks = [TrainingSampler(data, seed=0, rank=r, world_size=2) for r in range(2)]
    other_seed = TrainingSampler(data, seed=1)
    a = sampler.static_batch(5, 3, 0.5, 2, 3)
    assert _same_batch(a, again.static_batch(5, 3, 0.5, 2, 3))  # same seed, step: same batch
    assert not _same_batch(a, other_seed.static_batch(5, 3, 0.5, 2, 3))
    assert not _same_batch(a, sampler.static_batch(6, 3, 0.5, 2, 3))
    # Each rank of 2 builds its own sample of the global batch of 2: different samples, and
    # together the single-process batch (tests/test_distributed.py checks this further).
    shares = [r.static_batch(5, 3, 0.5, 2, 3) for r in ranks]
    assert [s.batch_size for s in shares] == [1, 1] and not torch.equal(shares[0].z, shares[1].z)
    assert torch.equal(torch.cat([s.poses for s in shares]), a.poses)
    assert torch.equal(torch.cat([s.z for s in shares]), a.z)
    kw = dict(num_hairstyles=2, window=3, candidates=16)
    s1 = sampler.sequence_batch(2, 2, 2, 1, **kw)
    s2 = again.sequence_batch(2, 2, 2, 1, **kw)
    s3 = [r.sequence_batch(2, 2, 2, 1, **kw) for r in ranks]
    assert torch.equal(s1.poses, s2.poses) and torch.equal(s1.motion, s2.motion)
    assert torch.equal(s1.rollout.rigid, s2.rollout.rigid)
    assert not torch.equal(s3[0].poses, s3[1].poses)
    assert torch.equal(torch.cat([s.poses for s in s3]), s1.poses)
    # The corpus and the dynamic threshold are shared by every rank.
    assert torch.equal(sampler.latent(1), ranks[1].latent(1))
    assert s1.info["threshold"] == s3[1].info["threshold"]


def test_static_batches_follow_the_curriculum(sampler, data):
    m, n = data.num_strands, data.num_vertices
    b0 = sampler.static_batch(0, 0, 1.0, 4)
    assert b0.batch_size == 1 and b0.hairstyle_ids == [0]
    assert torch.equal(b0.poses[0], sampler.rest_pose)
    assert torch.allclose(b0.betas[0], sampler.mean_betas)

    b1 = sampler.static_batch(1, 1, 0.5, 6)
    assert b1.rigid.shape == (6, m, n, 3) and b1.hairstyle_ids == [0] * 6
    rotated = 0
    for i, r in enumerate(b1.info["head_rotations"]):
        scale = ref.head_rotation_fraction(r, data.head_rotation_radii)
        assert scale == pytest.approx(0.0) or scale == pytest.approx(0.5)
        rotated += scale > 0
        # The neck and head joints share the rotation; nothing else moved.
        neck = b1.poses[i, 3 * JOINT["neck"]:3 * JOINT["neck"] + 3]
        head = b1.poses[i, 3 * JOINT["head"]:3 * JOINT["head"] + 3]
        assert torch.allclose(neck + head, torch.tensor(r, dtype=torch.float32), atol=1e-6)
    assert rotated > 0

    b2 = sampler.static_batch(2, 2, 0.5, 4, num_hairstyles=3)
    subject = sampler.entries[0].subject
    assert all(0 <= i < 3 for i in b2.hairstyle_ids)
    names = {e.name: e.subject for e in sampler.entries}
    assert all(names[name] == subject for name in b2.info["motions"])

    b3 = sampler.static_batch(3, 3, 0.5, 4, num_hairstyles=3)
    # Phase 3 adds shape noise: no sample has a subject's exact shape.
    assert all(not any(torch.equal(beta, s) for s in sampler.subject_betas) for beta in b3.betas)
    # Energy inputs: rest lengths of P_init, roots shared by every hairstyle, one mesh per sample.
    assert b3.inputs.rest_lengths.shape == (4, m, n - 1)
    assert torch.allclose(b3.inputs.rest_lengths, (b3.strands[:, :, 1:] - b3.strands[:, :, :-1]).norm(dim=-1))
    assert torch.equal(b3.strands[:, :, 0], sampler.roots.expand(4, -1, -1))
    assert b3.inputs.body.batch_size == 4 and b3.inputs.scalp_normals.shape == (4, m, 3)


def test_long_hair_fraction_biases_phase_2_3_towards_long_hairstyles(data):
    """long_hair_fraction = 1: every phase-2/3 sample is a long hairstyle of the pool (measured
    on its decoded strands, not only its parameter); the poses drawn stay those of the paper's
    sampler (the swap is drawn last)."""
    long_cfg = dataclasses.replace(data, long_hair_fraction=1.0, long_hair_length=0.3)
    plain, biased = TrainingSampler(data, seed=0), TrainingSampler(long_cfg, seed=0)
    pool = biased.long_hairstyles(40)
    assert pool and len(pool) < 40
    assert pool == [i for i in range(40) if biased.corpus_length(i) >= 0.3]
    for phase in (2, 3):
        a = plain.static_batch(5, phase, 0.5, 6, num_hairstyles=40)
        b = biased.static_batch(5, phase, 0.5, 6, num_hairstyles=40)
        assert all(i in pool for i in b.hairstyle_ids)
        assert torch.equal(a.poses, b.poses)
        # Decoded strand length (arc length) of the long picks vs the pool's short ones.
        arc = (b.strands[:, :, 1:] - b.strands[:, :, :-1]).norm(dim=-1).sum(-1).median(dim=1).values
        short = [i for i in range(40) if i not in pool][:3]
        _, s_strands = biased.hairstyles(short)
        s_arc = (s_strands[:, :, 1:] - s_strands[:, :, :-1]).norm(dim=-1).sum(-1).median(dim=1).values
        assert arc.min() > s_arc.max()
    with pytest.raises(ValueError, match="long_hair_fraction"):
        dataclasses.replace(data, long_hair_fraction=1.5)
    with pytest.raises(ValueError, match="long_hair_fraction"):
        dataclasses.replace(data, long_hair_fraction=0.5, latent_source="sample")


def test_grown_hair_fraction_trains_on_hair_grown_around_the_body(data):
    """grown_hair_fraction: the chosen share of the corpus (per index, the same for every
    sampler) has P_init = its strands grown around the rest body, on the grid roots, with z their
    encoding; a long one rests outside the rest body where its decode(z) cuts into it."""
    grown_cfg = data.replace(grown_hair_fraction=1.0)
    plain, grown = TrainingSampler(data, seed=0), TrainingSampler(grown_cfg, seed=0)
    index = grown.long_hairstyles(40)[0]
    assert grown.is_grown(index) and not plain.is_grown(index)
    z, strands = grown.hairstyle(index)
    z_plain, decoded = plain.hairstyle(index)
    assert strands.shape == decoded.shape == (data.num_strands, data.num_vertices, 3)
    assert torch.equal(strands[:, 0], grown.roots)
    z_grown, full = grown.grown_hairstyle(index)
    assert torch.allclose(z.double(), z_grown, atol=1e-5) and not torch.allclose(z, z_plain, atol=1e-3)
    assert full.shape[1] == grown.basis.num_vertices
    # The decoded hair cuts into the rest body; the grown hair rests (almost) outside it.
    body = BodyMesh(grown.body.rest_vertices, grown.body.faces)
    inside = [float((hair_body_signed_distance(x[None], body)[0, :, 2:] < 0).double().mean())
              for x in (decoded, strands)]
    assert inside[0] > 0.02 and inside[1] < 0.2 * inside[0]
    half = TrainingSampler(data.replace(grown_hair_fraction=0.5), seed=3)
    picks = [half.is_grown(i) for i in range(40)]
    assert 5 < sum(picks) < 35 and picks == [TrainingSampler(data.replace(grown_hair_fraction=0.5)).is_grown(i)
                                            for i in range(40)]
    with pytest.raises(ValueError, match="grown_hair_fraction"):
        data.replace(grown_hair_fraction=1.5)
    with pytest.raises(ValueError, match="grown_hair_fraction"):
        data.replace(grown_hair_fraction=0.5, latent_source="sample")


def test_batched_placement_matches_eq1_reference(data):
    """Different hairstyles and poses in one batch: each sample's P_rigid is Eq. 1's; the
    cropped body gives the uncropped body's contact energy."""
    s64 = TrainingSampler(data.replace(crop_body=True), seed=3, dtype=torch.float64)
    batch = s64.static_batch(0, 3, 1.0, 2, num_hairstyles=3)
    body = s64.body
    posed = body.pose(betas=batch.betas, poses=batch.poses, trans=batch.trans)
    faces = body.faces.long().numpy()
    for b in range(2):
        v = posed.vertices[b].numpy()
        head_centre = v[body.head_vertex_indices.numpy()].mean(0)
        near = np.linalg.norm(v[faces].mean(1) - head_centre, axis=1) < _REFERENCE_RADIUS
        positions, align, _ = placement_ref.rigid_placement(
            batch.strands[b].numpy(), v, posed.head_transform[b].numpy(), body.rest_vertices.double().numpy(),
            body.head_vertex_indices.numpy(), faces[near],
        )
        assert np.abs(align).max() > 1e-3  # the pose and shape moved the head
        assert np.abs(batch.rigid[b].numpy() - positions).max() < _F64_TOL
    cropped = batch.inputs.body
    assert cropped.num_faces < body.num_faces
    # Training bodies keep the uncut surface (new bodies every step: no search for self-intersections).
    full = BodyMesh(posed.vertices, body.faces.to(torch.int32), split_self_intersections=False)
    x = batch.rigid + 0.01 * torch.randn(batch.rigid.shape, generator=torch.Generator().manual_seed(0),
                                         dtype=torch.float64)
    kw = dict(xi=1e-3, dhat=1.5e-3, bp=0.5, weight=1.0)
    e_crop, e_full = hair_body_contact_energy(x, cropped, **kw), hair_body_contact_energy(x, full, **kw)
    assert bool((e_full > 0).all())
    assert torch.allclose(e_crop, e_full, rtol=_CROP_REL_TOL, atol=0)


def test_sequence_batch(sampler, data):
    cfg = dict(num_hairstyles=2, subsample=(2, 3), window=3, candidates=16)
    batch = sampler.sequence_batch(0, 3, 2, 3, **cfg)
    b, t = 3, 5
    assert batch.poses.shape == (b, t, 66)
    assert batch.motion.shape == (b, t, 3, DESCRIPTOR_DIM_NO_BETAS)
    assert batch.warmup.rigid.shape == (b * 2, data.num_strands, data.num_vertices, 3)
    assert batch.rollout.rigid.shape == (b * 3, data.num_strands, data.num_vertices, 3)
    assert batch.warmup.inputs.body is None and batch.rollout.inputs.body.batch_size == b * 3
    assert all(2 <= k <= 3 for k in batch.intervals)
    threshold = batch.info["threshold"]
    assert threshold > 0 and all(s >= threshold for s in batch.info["dynamic_scores"])
    # Every frame of a sequence carries that sequence's hairstyle and shape.
    for i in range(b):
        assert torch.equal(batch.rollout.z[i * 3], batch.z[i])
        assert torch.equal(batch.rollout.betas[i * 3 + 2], batch.betas[i])
        assert torch.equal(batch.rollout.poses[i * 3:(i + 1) * 3], batch.poses[i, 2:])
    unfiltered = sampler.sequence_batch(0, 2, 2, 2, dynamic_filter=False, **cfg)
    assert unfiltered.info["threshold"] is None


def test_sequence_batch_long_hair_fraction(sampler, dynamic_config):
    """long_hair_fraction = 1: every sequence's hairstyle is a long one of the pool; the clips,
    intervals and shapes stay those of the uniform draw (the swap is drawn last); the dynamic
    trainer passes its config's fraction through."""
    cfg = dict(num_hairstyles=40, subsample=(2, 3), window=3, candidates=16)
    pool = sampler.long_hairstyles(40)
    assert pool and len(pool) < 40
    plain = sampler.sequence_batch(1, 6, 2, 1, **cfg)
    biased = sampler.sequence_batch(1, 6, 2, 1, long_hair_fraction=1.0, **cfg)
    assert all(i in pool for i in biased.info["hairstyles"])
    assert not all(i in pool for i in plain.info["hairstyles"])
    assert torch.equal(plain.poses, biased.poses) and torch.equal(plain.betas, biased.betas)
    assert plain.intervals == biased.intervals
    trainer = DynamicTrainer(dynamic_config.replace(hairstyles=40, long_hair_fraction=1.0), sampler=sampler)
    assert all(i in pool for i in trainer.next_batch(0).info["hairstyles"])
    with pytest.raises(ValueError, match="long_hair_fraction"):
        sampler.sequence_batch(1, 2, 2, 1, long_hair_fraction=1.5, **cfg)
    with pytest.raises(ValueError, match="long_hair_fraction"):
        dynamic_config.replace(long_hair_fraction=-0.1)
    with pytest.raises(ValueError, match="long_hair_fraction"):
        dynamic_config.replace(long_hair_fraction=0.5, data=dynamic_config.data.replace(latent_source="sample"))


def test_sampler_bad_input(data, sampler):
    with pytest.raises(ValueError, match="rank"):
        TrainingSampler(data, rank=2, world_size=2)
    with pytest.raises(ValueError, match="dtype"):
        TrainingSampler(data, dtype=torch.float16)
    with pytest.raises(ValueError, match="phase"):
        sampler.static_batch(0, 4, 0.0, 2)
    with pytest.raises(ValueError, match="batch_size"):
        sampler.static_batch(0, 1, 0.0, 0)
    with pytest.raises(ValueError, match="warmup_frames"):
        sampler.sequence_batch(0, 2, 1, 2)
    with pytest.raises(ValueError, match="frames"):
        sampler.sequence_batch(0, 1, 2, 500, dynamic_filter=False)  # longer than any motion


# ------------------------------------------------------------------------------- static
@pytest.mark.parametrize("kind,phase", [("static", 0), ("static", 1), ("static", 3), ("quaffure", 2)])
def test_one_static_step_lowers_the_loss(static_config, sampler, kind, phase):
    cfg = static_config.replace(model_kind=kind, learning_rate=_STEP_LR)
    trainer = StaticTrainer(cfg, sampler=sampler)
    trainer.step = phase  # phase_steps (1, 1, 1, 1): step k is phase k
    batch = trainer.next_batch(phase)
    assert batch.info["phase"] == phase
    before, terms = trainer.evaluate(batch)
    assert math.isfinite(before) and terms["stretch"] >= 0 and terms["gravity"] != 0
    record = trainer.train_step(batch)
    assert record["loss"] == pytest.approx(before, rel=1e-5)  # train mode = eval mode (no dropout)
    assert record["phase"] == phase and trainer.step == phase + 1
    after, _ = trainer.evaluate(batch, phase)
    assert after < before


def test_static_training_writes_log_and_checkpoint(tmp_path, static_config, sampler):
    with pytest.raises(ValueError, match="sampler"):
        StaticTrainer(static_config, sampler=sampler, seed=5)  # the sampler draws with seed 0
    trainer = StaticTrainer(static_config, out=tmp_path, sampler=sampler)
    records = trainer.train(progress=False)
    trainer.close()
    assert [r["step"] for r in records] == [1, 2, 3, 4]
    assert [r["phase"] for r in records] == [0, 1, 2, 3]
    lines = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert len(lines) == 4
    assert set(lines[0]["terms"]) >= {"stretch", "bending", "gravity", "hair_body_contact"}
    ckpt = load_checkpoint(tmp_path / "checkpoint.pt")
    assert isinstance(ckpt.model, StaticNetwork) and ckpt.step == 4 and ckpt.optimizer_state is not None
    assert ckpt.extra["training_config"] == static_config.to_dict() and ckpt.extra["seed"] == 0
    assert load_config(tmp_path / "config.toml", "static") == static_config


def test_resume_continues_with_identical_results(tmp_path, static_config, sampler):
    straight = StaticTrainer(static_config, sampler=sampler)
    full = straight.train(progress=False)
    first = StaticTrainer(static_config, out=tmp_path, sampler=sampler)
    first.train(2, progress=False)
    first.close()
    resumed = StaticTrainer(out=tmp_path / "resumed", resume=tmp_path, sampler=sampler)
    assert resumed.step == 2 and resumed.config == static_config
    rest = resumed.train(progress=False)
    resumed.close()
    assert [r["loss"] for r in rest] == [r["loss"] for r in full[2:]]
    state_a, state_b = straight.model.state_dict(), resumed.model.state_dict()
    assert len(state_a) > 10 and all(torch.equal(state_a[k], state_b[k]) for k in state_a)


def test_resume_keeps_the_pool_teachers(tmp_path, static_config, sampler):
    """With `teacher_pool` the teachers solved so far are saved beside the checkpoint: a
    resumed run trains on the same targets as the uninterrupted one (solving them again from
    the trained network would give others)."""
    from hairwarp.training.static import TEACHERS_NAME

    config = static_config.replace(phase_steps=(0, 0, 0, 4), teacher_iterations=20, teacher_pool=2)
    straight = StaticTrainer(config, sampler=sampler)
    full = straight.train(progress=False)
    first = StaticTrainer(config, out=tmp_path, sampler=sampler)
    first.train(2, progress=False)
    first.close()
    assert (tmp_path / TEACHERS_NAME).is_file()
    resumed = StaticTrainer(out=tmp_path / "resumed", resume=tmp_path, sampler=sampler)
    assert sorted(resumed._pool_teachers) == [(3, 0), (3, 1)]
    rest = resumed.train(progress=False)
    resumed.close()
    assert [r["loss"] for r in rest] == [r["loss"] for r in full[2:]]
    (tmp_path / TEACHERS_NAME).unlink()  # without them the targets are solved again, from the trained network
    again = StaticTrainer(out=tmp_path / "again", resume=tmp_path, sampler=sampler)
    assert not again._pool_teachers
    assert [r["loss"] for r in again.train(progress=False)] != [r["loss"] for r in full[2:]]
    again.close()


def _assert_trained_alike(expected, got, eager, captured, loss_rel, atol, rtol=1e-3):
    """The captured trainer's records and weights against the eager one's: losses within
    `loss_rel`, weights within `atol` and `rtol`.

    Some weights get a gradient that is zero but for rounding (an attention's key bias, which the
    softmax cannot see; a block whose output starts at zero): Adam divides it by its own size and
    moves the weight by about its step size either way, so the two trainers' summation orders,
    which differ with the number of torch threads, decide the sign. Those weights, whose gradient's
    running RMS is below 1e-6 of the largest, are held only to Adam's step bound; they must stay a
    minority of the weights."""
    for e, g in zip(expected, got):
        assert g["loss"] == pytest.approx(e["loss"], rel=loss_rel)
        assert g["terms"].keys() == e["terms"].keys()
    rms = {name: eager.optimizer.state[p]["exp_avg_sq"].sqrt() for name, p in eager.model.named_parameters()
           if p in eager.optimizer.state}
    largest = max(float(r.max()) for r in rms.values())
    steps_bound = 2.0 * eager.config.learning_rate * len(expected)
    state_a, state_b = eager.model.state_dict(), captured.model.state_dict()
    noise_count = total_count = 0
    for k in state_a:
        if k not in rms:
            torch.testing.assert_close(state_b[k], state_a[k], rtol=rtol, atol=atol)
            continue
        noise = rms[k] < 1e-6 * largest
        noise_count, total_count = noise_count + int(noise.sum()), total_count + noise.numel()
        torch.testing.assert_close(state_b[k][~noise], state_a[k][~noise], rtol=rtol, atol=atol)
        if bool(noise.any()):
            assert float((state_b[k][noise] - state_a[k][noise]).abs().max()) <= steps_bound, k
    assert noise_count < 0.5 * total_count


def test_captured_steps_train_as_the_eager_ones(monkeypatch, static_config, sampler):
    """The captured step's bookkeeping (`_CapturedStaticStep`, run eagerly on the CPU through the
    same buffers): batches copied into fixed tensors, one uncropped body refit to each batch's
    poses, b_p written into a device scalar each step, a new capture where the batch shape (phase
    0's single sample) or the clip changes, a batch that overflows the hair-hair buffer redone
    with a larger one. Four steps give the eager trainer's losses and weights."""
    from hairwarp.training import capture
    from hairwarp.training import static as static_module

    config = static_config.replace(phase_steps=(1, 1, 1, 2), energy={"hair_hair_weight": 1.0})
    eager = StaticTrainer(config.replace(cuda_graph=False), sampler=sampler)
    expected = eager.train(progress=False)
    monkeypatch.setattr(capture, "CAPTURE_ON_CPU", True)
    made = []
    real = static_module._CapturedStaticStep

    class Counted(real):
        def __init__(self, *args, **kwargs):
            if len(made) == 1:  # the second capture's pair buffer too small: redone with a larger one
                kwargs["capacity"] = 1
            made.append(kwargs.get("capacity"))
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(static_module, "_CapturedStaticStep", Counted)
    captured = StaticTrainer(config, sampler=sampler)
    got = [captured.train_step() for _ in range(config.total_steps)]
    # Phase 0 (one sample, clipped), phase 1 (two samples, unclipped: buffer of 1), its redo.
    assert made[:2] == [None, 1] and made[2] > 1 and len(made) == 3
    assert all(g["bp"] == e["bp"] and g["phase"] == e["phase"] for e, g in zip(expected, got))
    _assert_trained_alike(expected, got, eager, captured, 1e-5, 1e-6, rtol=1e-4)


def test_distillation_pulls_the_drape_toward_the_physics_teacher(static_config, sampler):
    """With `teacher_iterations` the batch carries the network's drape refined by the physics'
    static solve (lower energy at the physics' b_p, lengths kept), the log holds the "teacher"
    term, and a step on a teacher-dominated loss moves the drape toward the teacher."""
    from hairwarp.training.config import energy_config
    from hairwarp.training.static import static_loss, teacher_term

    cfg = static_config.replace(teacher_iterations=6, teacher_weight=1e7, learning_rate=_STEP_LR)
    trainer = StaticTrainer(cfg, sampler=sampler)
    trainer.step = 3
    batch = trainer.training_batch(3)
    assert batch.teacher is not None and batch.teacher.shape == batch.rigid.shape
    with torch.no_grad():
        _, _, drape = static_loss(trainer.model, batch, energy_config(cfg.energy, barrier_join_fraction=cfg.bp_end))
        physics = energy_config(cfg.energy, barrier_join_fraction=cfg.bp_end)
        e_drape = total_energy(drape, batch.inputs, physics).total
        e_teacher = total_energy(batch.teacher, batch.inputs, physics).total
    assert bool((e_teacher <= e_drape).all()) and bool((e_teacher < e_drape).any())
    lengths = (batch.teacher[:, :, 1:] - batch.teacher[:, :, :-1]).norm(dim=-1)
    torch.testing.assert_close(lengths, batch.inputs.rest_lengths.to(lengths.dtype), atol=1e-5, rtol=1e-4)
    before = float(teacher_term(drape, batch.teacher, 1.0).mean())
    assert before > 0
    record = trainer.train_step(batch)
    assert record["terms"]["teacher"] == pytest.approx(cfg.teacher_weight * before, rel=1e-4)
    with torch.no_grad():
        _, _, after_drape = static_loss(trainer.model, batch, physics)
    assert float(teacher_term(after_drape, batch.teacher, 1.0).mean()) < before
    with pytest.raises(ValueError, match="teacher_iterations"):
        static_config.replace(teacher_iterations=-1)
    with pytest.raises(ValueError, match="teacher_weight"):
        static_config.replace(teacher_weight=float("nan"))


def test_a_teacher_pool_solves_each_batch_once_to_its_optimum(monkeypatch, static_config, sampler):
    """With `teacher_pool` P the run cycles through P batches; each one's teacher is solved once
    (the static drape with its restarts, not one chunk), then reused: a fresh solve from it
    lowers the energy far less than the K-iteration teacher leaves to gain."""
    from hairwarp.solvers.physics import PhysicsSolver
    from hairwarp.training import static as static_training
    from hairwarp.training.config import energy_config

    cfg = static_config.replace(phase_steps=(0, 0, 0, 6), teacher_iterations=400, teacher_pool=2)
    trainer = StaticTrainer(cfg, sampler=sampler)
    solves = []
    original = static_training._DrapeTeacher.__call__
    monkeypatch.setattr(static_training._DrapeTeacher, "__call__",
                        lambda self, batch, clip: solves.append(1) or original(self, batch, clip))
    batches = [trainer.training_batch(step) for step in range(4)]
    assert len(solves) == 2
    torch.testing.assert_close(batches[2].rigid, batches[0].rigid)
    torch.testing.assert_close(batches[3].rigid, batches[1].rigid)
    assert not torch.equal(batches[0].rigid, batches[1].rigid)
    assert batches[2].teacher is batches[0].teacher
    physics = energy_config(cfg.energy, barrier_join_fraction=cfg.bp_end)

    def energy_after(start, batch, iterations):
        solver = trainer._teacher._make_solver(batch, batch.inputs.body)
        solver.solve(start, iterations)
        with torch.no_grad():
            return float(total_energy(solver.positions(), batch.inputs, physics).total.sum())

    batch = batches[0]
    with torch.no_grad():
        e_teacher = float(total_energy(batch.teacher, batch.inputs, physics).total.sum())
    assert isinstance(trainer._teacher._make_solver(batch, batch.inputs.body), PhysicsSolver)
    # From the rigid placement, 16 iterations (one chunk) leave far more to gain than the pool's teacher.
    short = energy_after(batch.rigid.clone(), batch, 16)
    assert e_teacher < short
    assert e_teacher - energy_after(batch.teacher.clone(), batch, 200) < 0.05 * (short - e_teacher)
    record = trainer.train_step()
    assert "teacher" in record["terms"]
    with pytest.raises(ValueError, match="teacher_pool"):
        static_config.replace(teacher_pool=2)
    with pytest.raises(ValueError, match="teacher_pool"):
        static_config.replace(teacher_iterations=4, teacher_pool=-1)


def test_settled_pool_teachers_rest_no_higher_than_the_static_solve(static_config, sampler):
    """`teacher_settle_time`: each pool teacher is held in its pose and polished
    (`drape_at_rest`); per sample its energy is never above the static solve's teacher, and lower
    in sum where that solve was stopped short (40 iterations)."""
    from hairwarp.training.config import energy_config

    energies = {}
    for settle in (0.0, 0.5):
        cfg = static_config.replace(phase_steps=(0, 0, 0, 2), teacher_iterations=40, teacher_pool=1,
                                    teacher_start="rigid", teacher_settle_time=settle)
        trainer = StaticTrainer(cfg, sampler=sampler)
        batch = trainer.training_batch(0)
        physics = energy_config(cfg.energy, barrier_join_fraction=cfg.bp_end)
        with torch.no_grad():
            energies[settle] = total_energy(batch.teacher, batch.inputs, physics).total.reshape(-1)
    assert bool((energies[0.5] <= energies[0.0] * (1 + 1e-6)).all()), energies
    assert float(energies[0.5].sum()) < float(energies[0.0].sum()) * (1 - 1e-3), energies
    with pytest.raises(ValueError, match="teacher_settle_time"):
        static_config.replace(teacher_settle_time=1.0)  # no pool
    with pytest.raises(ValueError, match="teacher_settle_time"):
        static_config.replace(teacher_iterations=4, teacher_pool=1, teacher_settle_time=-1.0)


def test_a_run_takes_another_runs_pool_teachers_without_solving_them(tmp_path, monkeypatch, static_config, sampler, data):
    """`teachers_from`: a variant of a pool run (another teacher weight) takes the teachers that
    run saved instead of solving them again; a pool batch that is not the one a teacher was
    solved for (another seed), or other teacher settings, is refused by name."""
    from hairwarp.training import static as static_training

    cfg = static_config.replace(phase_steps=(0, 0, 0, 4), teacher_iterations=30, teacher_pool=2)
    first = StaticTrainer(cfg, out=tmp_path / "a", sampler=sampler)
    solved = [first.training_batch(step).teacher for step in range(2)]
    first.save()
    calls = []
    original = static_training._DrapeTeacher.__call__
    monkeypatch.setattr(static_training._DrapeTeacher, "__call__",
                        lambda self, batch, clip: calls.append(1) or original(self, batch, clip))
    variant = StaticTrainer(cfg.replace(teacher_weight=300.0), sampler=sampler, teachers_from=tmp_path / "a")
    for step in range(4):
        torch.testing.assert_close(variant.training_batch(step).teacher, solved[step % 2], rtol=0, atol=0)
    assert calls == []
    other_seed = StaticTrainer(cfg, sampler=TrainingSampler(data, seed=1), seed=1, teachers_from=tmp_path / "a")
    with pytest.raises(ValueError, match="teachers_from: pool batch 0"):
        other_seed.training_batch(0)
    with pytest.raises(ValueError, match="teacher_iterations"):
        StaticTrainer(cfg.replace(teacher_iterations=31), sampler=sampler, teachers_from=tmp_path / "a")
    with pytest.raises(ValueError, match="no teachers.pt"):
        StaticTrainer(cfg, sampler=sampler, teachers_from=tmp_path)
    with pytest.raises(ValueError, match="teacher_pool > 0"):
        StaticTrainer(static_config, sampler=sampler, teachers_from=tmp_path / "a")


def test_the_teacher_of_both_starts_is_per_sample_the_lower_one(static_config, sampler, monkeypatch):
    """teacher_start "lower": the physics teacher solved from the network's drape and from the
    rigid placement, per sample the one of lower energy; "rigid" and "network" are those two;
    "lower_where_clean" takes the rigid start only where the rigid placement has no free vertex
    inside the body, and "rigid_where_clean" there whatever the energies. The untrained test
    network's drape is the rigid placement to a millimetre, so its drape here is the rigid
    placement lifted 3 cm at the tips (a start of its own)."""
    from hairwarp.ops import hair_body_signed_distance
    from hairwarp.training import static as static_training
    from hairwarp.training.config import energy_config

    def lifted(rigid, deformation, root_uv, projection):
        along = torch.linspace(0.0, 1.0, rigid.shape[2], dtype=rigid.dtype)[None, None, :]
        return rigid + torch.stack([torch.zeros_like(along), 0.03 * along, torch.zeros_like(along)], dim=-1)

    monkeypatch.setattr(static_training, "apply_deformation", lifted)
    physics = energy_config(static_config.energy, barrier_join_fraction=static_config.bp_end)
    teachers, energies = {}, {}
    for start in ("network", "rigid", "lower", "lower_where_clean", "rigid_where_clean"):
        cfg = static_config.replace(phase_steps=(0, 0, 0, 4), teacher_iterations=200, teacher_pool=1,
                                    teacher_start=start)
        torch.manual_seed(0)
        trainer = StaticTrainer(cfg, sampler=sampler, seed=0)
        batch = trainer.training_batch(0)
        teachers[start] = batch.teacher
        if start in ("lower", "lower_where_clean", "rigid_where_clean") and trainer._teacher.choices:
            # The record of the choice: one entry per sample, the winner by its own energies.
            record = trainer._teacher.choices[-1]
            n = batch.teacher.shape[0]
            assert all(len(v) == n for v in record.values())
            by_energy = torch.tensor(record["energy_rigid_start"]) < torch.tensor(record["energy_network_start"])
            clean_rigid = torch.tensor(record["rigid_inside_percent"]) == 0
            expected = {"lower": by_energy, "lower_where_clean": by_energy & clean_rigid,
                        "rigid_where_clean": clean_rigid}[start]
            assert record["rigid_chosen"] == expected.tolist()
            assert all(0.0 <= p <= 100.0 for p in record["rigid_inside_percent"])
            assert all(length > 0.0 for length in record["mean_strand_length_m"])
        with torch.no_grad():
            energies[start] = total_energy(batch.teacher, batch.inputs, physics).total
            clean = (hair_body_signed_distance(batch.rigid, trainer._teacher.solver.body)[:, :, 2:] >= 0
                     ).flatten(1).all(dim=1) if trainer._teacher.solver is not None else None
    # The solves of separate runs agree to float32 rounding only (the CPU's two threads sum
    # contact in either order: up to 0.2 mm apart in a full-suite run), so each chosen teacher
    # is matched to the nearer of the two starts' teachers, which lie far apart.
    gap = lambda a, b: (a - b).norm(dim=-1).flatten(1).max(dim=1).values  # noqa: E731
    # Two starts may also rest in one state (the batch drawn depends on the tests run before).
    apart = gap(teachers["network"], teachers["rigid"]) > 2e-3
    assert bool(apart.any())
    lower_is_rigid = energies["rigid"] < energies["network"]
    assert clean is not None
    for start, take_rigid in (("lower", lower_is_rigid), ("lower_where_clean", lower_is_rigid & clean),
                              ("rigid_where_clean", clean)):
        to_rigid, to_network = gap(teachers[start], teachers["rigid"]), gap(teachers[start], teachers["network"])
        nearest = torch.where(take_rigid, to_rigid, to_network)
        assert bool((nearest[apart] < 5e-4).all()), (start, nearest)
        assert bool((torch.minimum(to_rigid, to_network)[~apart] < 2e-3).all()), (start, to_rigid, to_network)
    torch.testing.assert_close(energies["lower"], torch.minimum(energies["rigid"], energies["network"]),
                               atol=1e-4, rtol=1e-3)
    with pytest.raises(ValueError, match="teacher_start"):
        static_config.replace(teacher_start="middle")
    with pytest.raises(ValueError, match="teacher_start"):
        static_config.replace(teacher_iterations=4, teacher_kind="map", teacher_start="rigid")


def test_a_map_teacher_is_a_drape_the_network_can_reach_with_less_energy(static_config, sampler):
    """teacher_kind "map": the teacher is the drape of the best deformation map, from the
    network's: lower energy than the network's drape, the fixed vertices on the rigid placement,
    the rest lengths kept (the network's follow-the-leader projection)."""
    from hairwarp.training.config import energy_config
    from hairwarp.training.static import static_loss

    cfg = static_config.replace(phase_steps=(0, 0, 0, 4), teacher_iterations=30, teacher_pool=1, teacher_kind="map",
                                model={"length_projection": "follow_the_leader"})
    trainer = StaticTrainer(cfg, sampler=sampler)
    batch = trainer.training_batch(0)
    physics = energy_config(cfg.energy, barrier_join_fraction=cfg.bp_end)
    with torch.no_grad():
        _, _, drape = static_loss(trainer.model, batch, physics)
        e_drape = float(total_energy(drape, batch.inputs, physics).total.sum())
        e_teacher = float(total_energy(batch.teacher, batch.inputs, physics).total.sum())
    assert e_teacher < e_drape
    torch.testing.assert_close(batch.teacher[:, :, :2], batch.rigid[:, :, :2])
    lengths = (batch.teacher[:, :, 1:] - batch.teacher[:, :, :-1]).norm(dim=-1)
    torch.testing.assert_close(lengths, batch.inputs.rest_lengths.to(lengths.dtype), atol=1e-5, rtol=1e-4)
    assert trainer.training_batch(1).teacher is batch.teacher  # one pool batch: solved once
    record = trainer.train_step()
    assert record["terms"]["teacher"] > 0
    with pytest.raises(ValueError, match="teacher_kind"):
        static_config.replace(teacher_kind="oracle")


def test_a_run_starts_from_the_weights_of_another_checkpoint(static_config, sampler, static_checkpoint,
                                                              dynamic_checkpoint):
    """`init` takes a static checkpoint's network, or a dynamic checkpoint's frozen static one,
    with a fresh optimizer at step 0; a network of other sizes is refused by name."""
    from hairwarp.models.checkpoint import load_checkpoint

    for source in (static_checkpoint, dynamic_checkpoint):
        model = load_checkpoint(source).model
        model = getattr(model, "static", model)
        trainer = StaticTrainer(static_config, sampler=sampler, init=source)
        assert trainer.step == 0 and not trainer.optimizer.state
        for a, b in zip(trainer.model.state_dict().values(), model.state_dict().values()):
            torch.testing.assert_close(a, b)
        trainer.train_step()  # every weight trains, a dynamic checkpoint's frozen ones too
        assert all(p.grad is not None for p in trainer.model.parameters())
    other = static_config.replace(model={"num_encoder_layers": 3})
    with pytest.raises(ValueError, match="init"):
        StaticTrainer(other, sampler=sampler, init=static_checkpoint)
    with pytest.raises(ValueError, match="init"):
        StaticTrainer(static_config, sampler=sampler, init=static_checkpoint, resume=static_checkpoint)


def test_captured_distillation_steps_train_as_the_eager_ones(monkeypatch, static_config, sampler):
    """The teacher's drapes go into the captured step's fixed buffers: the captured trainer
    (its bookkeeping run eagerly on the CPU) gives the eager trainer's losses and weights."""
    from hairwarp.training import capture

    config = static_config.replace(phase_steps=(0, 1, 1, 1), teacher_iterations=4)
    eager = StaticTrainer(config.replace(cuda_graph=False), sampler=sampler)
    expected = eager.train(progress=False)
    assert all("teacher" in e["terms"] for e in expected)
    monkeypatch.setattr(capture, "CAPTURE_ON_CPU", True)
    captured = StaticTrainer(config, sampler=sampler)
    got = [captured.train_step() for _ in range(config.total_steps)]
    assert captured._teacher.solver is not None  # one solver for the batches that carry their bodies
    # Weights to 1e-4: each trainer's teacher solves on its own body (float32 sums in another
    # order), and line-search decisions amplify that; the losses agree to 1e-4 relative.
    _assert_trained_alike(expected, got, eager, captured, 1e-4, 1e-4, rtol=1e-3)


@pytest.mark.parametrize("kind", ["physics", "map"])
def test_captured_steps_on_a_teacher_pool_train_as_the_eager_ones(monkeypatch, static_config, sampler, kind):
    """The pool's teachers (solved on the captured step's refit body) go into its fixed buffers:
    the captured trainer (its bookkeeping run eagerly on the CPU) gives the eager trainer's
    losses and weights, batch after batch of the cycle."""
    from hairwarp.training import capture

    config = static_config.replace(phase_steps=(0, 0, 0, 4), teacher_iterations=12, teacher_pool=2,
                                   teacher_kind=kind)
    eager = StaticTrainer(config.replace(cuda_graph=False), sampler=sampler)
    expected = eager.train(progress=False)
    monkeypatch.setattr(capture, "CAPTURE_ON_CPU", True)
    captured = StaticTrainer(config, sampler=sampler)
    got = [captured.train_step() for _ in range(config.total_steps)]
    assert sorted(captured._pool_teachers) == [(3, 0), (3, 1)]
    _assert_trained_alike(expected, got, eager, captured, 1e-4, 1e-4, rtol=1e-3)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device; this machine has none")
def test_cuda_graph_training_steps_equal_eager(data):
    """On CUDA the default trainer replays each step from a CUDA graph: the same losses and
    weights as the eager trainer, to float-atomics noise."""
    cuda_sampler = TrainingSampler(data, seed=0, device="cuda")
    config = StaticTrainingConfig.tiny().replace(phase_steps=(1, 1, 1, 2), data=data,
                                                 energy={"hair_hair_weight": 1.0})
    eager = StaticTrainer(config.replace(cuda_graph=False), device="cuda", sampler=cuda_sampler)
    expected = eager.train(progress=False)
    captured = StaticTrainer(config, device="cuda", sampler=cuda_sampler)
    got = captured.train(progress=False)
    assert captured._captured is not None and captured._captured.step.captured
    _assert_trained_alike(expected, got, eager, captured, 1e-4, 1e-5)


def test_non_finite_loss_raises_and_keeps_weights(static_config, sampler):
    trainer = StaticTrainer(static_config, sampler=sampler)
    with torch.no_grad():
        next(trainer.model.head.parameters()).fill_(float("nan"))
    poisoned = {k: torch.nan_to_num(v.clone()) for k, v in trainer.model.state_dict().items()}
    with pytest.raises(ValueError, match="deformation_map"):
        trainer.train_step()  # a NaN network output is refused, never turned into a silent NaN loss
    assert trainer.step == 0 and not trainer.history
    assert all(torch.equal(torch.nan_to_num(v), poisoned[k]) for k, v in trainer.model.state_dict().items())


# ------------------------------------------------------------------------------- dynamic
def test_inertia_history_stops_the_gradient(rng):
    """Eq. 16 over a rollout with the previous states from `inertia_history`: each frame gets
    its own term's gradient only (a torch Eq. 16, which would back-propagate into the history
    if it were not detached)."""
    m, n, r = 3, 5, 4
    cfg = EnergyConfig()
    warm = torch.tensor(rng.normal(size=(1, 2, m, n, 3)), requires_grad=True)
    x = torch.tensor(rng.normal(size=(1, r, m, n, 3)), requires_grad=True)
    prev, prev2 = inertia_history(warm, x)
    assert not prev.requires_grad and not prev2.requires_grad
    assert torch.equal(prev[0, 1:], x[0, :-1].detach()) and torch.equal(prev2[0, 2:], x[0, :-2].detach())
    assert torch.equal(prev[0, 0], warm[0, 1].detach()) and torch.equal(prev2[0, :2], warm[0].detach())
    proj = 2.0 * prev - prev2
    energy = (cfg.inertia_weight / (m * (n - 2)) * cfg.vertex_mass / (2 * cfg.time_step**2)
              * ((x - proj)[..., 2:, :] ** 2).sum())
    energy.backward()
    want = ref.rollout_inertia_gradient(warm[0].detach().numpy(), x[0].detach().numpy(), cfg.vertex_mass,
                                        cfg.time_step, cfg.inertia_weight)
    assert np.abs(want).max() > 0 and warm.grad is None
    assert np.abs(x.grad[0].numpy() - want).max() < _GRAD_TOL * max(1.0, np.abs(want).max())
    e = ref.inertia_energy(x[0].detach().numpy(), prev[0].numpy(), prev2[0].numpy(), cfg.vertex_mass,
                           cfg.time_step, cfg.inertia_weight)
    assert float(energy.detach()) == pytest.approx(e.sum(), rel=1e-12)


def test_dynamic_loss_feeds_detached_previous_states(monkeypatch, dynamic_config, sampler):
    trainer = DynamicTrainer(dynamic_config, sampler=sampler)
    batch = trainer.next_batch(0)
    seen = {}
    real = dynamic_module.total_energy

    def spy(x, inputs, config, **kw):
        seen.update(x=x, inputs=inputs, kw=kw)
        return real(x, inputs, config, **kw)

    monkeypatch.setattr(dynamic_module, "total_energy", spy)
    energy = EnergyConfig(barrier_join_fraction=0.01)
    loss, terms, positions = dynamic_loss(trainer.model, batch, energy)
    b, r = batch.batch_size, batch.rollout_frames
    assert seen["kw"]["dynamic"] is True and seen["x"].requires_grad
    prev = seen["inputs"].prev.reshape(positions.shape)
    prev2 = seen["inputs"].prev2.reshape(positions.shape)
    assert not prev.requires_grad and not prev2.requires_grad
    assert torch.equal(prev[:, 1:], positions[:, :-1].detach())
    assert terms["inertia"] > 0 and terms["func_reg"] == 0.0  # the dynamic head starts as the static head
    assert positions.shape == (b, r, 64, 20, 3)


def test_captured_dynamic_steps_train_as_the_eager_ones(monkeypatch, dynamic_config, sampler):
    """The dynamic trainer's captured step (warm-up and rollout frames in fixed buffers, their
    bodies refit per batch, the intervals a tensor; run eagerly on the CPU through the same
    buffers), its first pair buffer too small and the batch redone: three steps give the eager
    trainer's losses and weights."""
    from hairwarp.training import capture
    from hairwarp.training import dynamic as dynamic_module

    config = dynamic_config.replace(steps=3, energy={"hair_hair_weight": 1.0})
    eager = DynamicTrainer(config.replace(cuda_graph=False), sampler=sampler)
    expected = eager.train(progress=False)
    monkeypatch.setattr(capture, "CAPTURE_ON_CPU", True)
    made = []
    real = dynamic_module._CapturedDynamicStep

    class Counted(real):
        def __init__(self, *args, **kwargs):
            if not made:
                kwargs["capacity"] = 1
            made.append(kwargs.get("capacity"))
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(dynamic_module, "_CapturedDynamicStep", Counted)
    captured = DynamicTrainer(config, sampler=sampler)
    got = captured.train(progress=False)
    assert made[0] == 1 and len(made) == 2 and made[1] > 1
    assert all(g["intervals"] == e["intervals"] for e, g in zip(expected, got))
    # Within a tenth of one Adam step (lr 1e-3): Adam normalises each gradient element, so an
    # element whose gradient is float noise (1e-8 of the largest, the pair buffer's other sum
    # order) moves by a fraction of a step either way.
    _assert_trained_alike(expected, got, eager, captured, 1e-5, 1e-4)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device; this machine has none")
def test_cuda_graph_dynamic_training_steps_equal_eager(data, dynamic_config):
    """On CUDA the dynamic trainer replays each step from a CUDA graph: the eager trainer's
    losses and weights, to float-atomics noise."""
    cuda_sampler = TrainingSampler(data, seed=0, device="cuda")
    config = dynamic_config.replace(steps=3, energy={"hair_hair_weight": 1.0})
    eager = DynamicTrainer(config.replace(cuda_graph=False), device="cuda", sampler=cuda_sampler)
    expected = eager.train(progress=False)
    captured = DynamicTrainer(config, device="cuda", sampler=cuda_sampler)
    got = captured.train(progress=False)
    assert captured._captured is not None and captured._captured.step.captured
    _assert_trained_alike(expected, got, eager, captured, 1e-4, 1e-4)


def test_one_dynamic_step_lowers_the_loss_and_keeps_the_static_network(dynamic_config, sampler):
    trainer = DynamicTrainer(dynamic_config.replace(learning_rate=_STEP_LR), sampler=sampler)
    model = trainer.model
    assert isinstance(model, DynamicNetwork)
    static_before = {k: v.clone() for k, v in model.static.state_dict().items()}
    trained = {id(p) for p in trainer._parameters()}
    assert trained and not any(id(p) in trained for p in model.static.parameters())
    batch = trainer.next_batch(0)
    before, _ = trainer.evaluate(batch)
    trainer.train_step(batch)
    after, terms = trainer.evaluate(batch)
    assert after < before
    assert terms["func_reg"] > 0  # the dynamic head moved away from the static one
    assert all(torch.equal(v, static_before[k]) for k, v in model.static.state_dict().items())


def test_dynamic_checkpoint_and_finetune(tmp_path, dynamic_checkpoint):
    ckpt = load_checkpoint(dynamic_checkpoint)
    assert isinstance(ckpt.model, DynamicNetwork) and ckpt.step == 2
    trainer = finetune(dynamic_checkpoint, "whiplash", iterations=1, out=tmp_path,
                       overrides=["rollout_frames=1"], progress=False)
    assert trainer.step == 1 and trainer.config.data.motions == ["whiplash"]
    assert trainer.history[0]["intervals"] == [1] * trainer.config.batch_size
    tuned = load_checkpoint(tmp_path / "checkpoint.pt")
    before = ckpt.model.state_dict()
    changed = [k for k, v in tuned.model.state_dict().items() if not torch.equal(v, before[k])]
    assert changed and not any(k.startswith("static.") for k in changed)


def test_dynamic_resume_continues_with_identical_results(tmp_path, dynamic_config, dynamic_checkpoint, sampler):
    first = DynamicTrainer(dynamic_config, out=tmp_path, sampler=sampler)
    first.train(1, progress=False)
    first.close()
    resumed = DynamicTrainer(resume=tmp_path, sampler=sampler)
    assert resumed.step == 1 and resumed.config == dynamic_config
    resumed.train(progress=False)
    straight = load_checkpoint(dynamic_checkpoint).model.state_dict()  # the same run, uninterrupted
    state = resumed.model.state_dict()
    assert len(state) > 10 and all(torch.equal(state[k], straight[k]) for k in straight)


def test_dynamic_bad_input(dynamic_config, static_checkpoint, sampler):
    with pytest.raises(ValueError, match="static_checkpoint"):
        DynamicTrainer(dynamic_config.replace(static_checkpoint=""), sampler=sampler)
    with pytest.raises(ValueError, match="checkpoint"):
        finetune(static_checkpoint, "whiplash", iterations=1, progress=False)
    with pytest.raises(ValueError, match="data"):
        DynamicTrainer(dynamic_config.replace(data=dynamic_config.data.replace(num_vertices=12)))
    with pytest.raises(ValueError, match="warmup_positions, positions"):
        inertia_history(torch.zeros(1, 1, 2, 3, 3), torch.zeros(1, 2, 2, 3, 3))


# ------------------------------------------------------------------------------- configs, CLI
def test_toml_config_and_set_overrides(tmp_path):
    path = tmp_path / "cfg.toml"
    path.write_text(
        'model_preset = "tiny"\nphase_steps = [1, 2, 3, 4]\nbatch_size = 8\n'
        "[data]\nstrand_stride = 4\nnum_vertices = 20\nmotions = [\"nod\"]\n"
        "[energy]\nhair_hair_weight = 5\n"
    )
    cfg = load_config(path, "quaffure", ["batch_size=4", "data.num_vertices=16", "clip_steps=none",
                                         "energy.bending_weight=2e-6", "model.channels=[16, 8, 8, 4]",
                                         "learning_rate=3e-4", "bp_schedule=linear"])
    assert cfg.model_kind == "quaffure" and cfg.phase_steps == (1, 2, 3, 4) and cfg.batch_size == 4
    assert cfg.data.num_vertices == 16 and cfg.data.strand_stride == 4 and cfg.data.motions == ["nod"]
    assert cfg.energy == {"hair_hair_weight": 5, "bending_weight": 2e-6} and cfg.clip_steps is None
    assert cfg.learning_rate == 3e-4 and cfg.bp_schedule == "linear"
    assert cfg.model == {"channels": [16, 8, 8, 4]}
    again = tmp_path / "again.toml"
    again.write_text(to_toml(cfg))
    assert load_config(again, "quaffure") == cfg
    dyn = load_config(None, "dynamic", ["static_checkpoint=/x/y.pt", "rollout_frames=6", "model.fusion=lora"])
    assert dyn.static_checkpoint == "/x/y.pt" and dyn.rollout_frames == 6 and dyn.model == {"fusion": "lora"}
    assert isinstance(apply_overrides(dyn, ["data.beta_noise_std=0"]).data.beta_noise_std, float)


@pytest.mark.parametrize("override,match", [
    ("nonsense", "key=value"),
    ("foo=1", "foo"),
    ("data.bar=1", "data.bar"),
    ("batch_size=0", "batch_size"),
    ("phase_steps=[1, 2]", "phase_steps"),
    ("energy.nope=1", "nope"),
    ("energy.hair_body_xi=-1", "hair_body_xi"),
    ("data.motions=['dance']", "motions"),
    ("bp_end=1.5", "bp_end"),
    ("model.num_layers=3", "num_layers"),
])
def test_bad_overrides_name_the_setting(override, match):
    with pytest.raises(ValueError, match=match):
        load_config(None, "static", [override])


def test_bad_config_files(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("batch_size = \n")
    with pytest.raises(ValueError, match="TOML"):
        load_config(bad, "static")
    bad.write_text('model_kind = "quaffure"\n')
    with pytest.raises(ValueError, match="model_kind"):
        load_config(bad, "static")
    with pytest.raises(FileNotFoundError):
        load_config(tmp_path / "missing.toml", "static")
    with pytest.raises(ValueError, match="kind"):
        load_config(None, "transformer")


def test_cli_train_static_two_steps(tmp_path, capsys):
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(to_toml(StaticTrainingConfig.tiny()))
    out = tmp_path / "run"
    rc = cli.main(["train", "static", "--config", str(cfg), "--set", "phase_steps=[1, 1, 0, 0]",
                   "--set", "data.motions=['nod']", "--out", str(out), "--seed", "1", "--no-progress"])
    assert rc == 0
    assert "2/2 steps" in capsys.readouterr().out
    ckpt = load_checkpoint(out / "checkpoint.pt")
    assert isinstance(ckpt.model, StaticNetwork) and ckpt.step == 2 and ckpt.extra["seed"] == 1
    assert len((out / "log.jsonl").read_text().splitlines()) == 2
    assert load_config(out / "config.toml", "static").phase_steps == (1, 1, 0, 0)
    # Resuming a finished run runs nothing more and keeps the step.
    assert cli.main(["train", "static", "--resume", str(out), "--out", str(out), "--no-progress"]) == 0
    assert load_checkpoint(out / "checkpoint.pt").step == 2
    # Errors: one line naming the bad argument, exit status 1.
    capsys.readouterr()
    assert cli.main(["train", "static", "--set", "batch_size=-3", "--out", str(tmp_path / "x")]) == 1
    assert "batch_size" in capsys.readouterr().err
    assert cli.main(["train", "quaffure", "--resume", str(out), "--out", str(tmp_path / "y")]) == 1
    assert "static" in capsys.readouterr().err


def test_cli_finetune(tmp_path, dynamic_checkpoint, capsys):
    out = tmp_path / "ft"
    rc = cli.main(["finetune", "--checkpoint", dynamic_checkpoint, "--motion", "whiplash",
                   "--iterations", "1", "--set", "rollout_frames=1", "--set", "batch_size=1",
                   "--out", str(out), "--no-progress"])
    assert rc == 0 and "whiplash: 1 steps" in capsys.readouterr().out
    assert load_checkpoint(out / "checkpoint.pt").step == 1
    argv = ["finetune", "--checkpoint", dynamic_checkpoint, "--motion", "moonwalk", "--out", str(out)]
    assert cli.main(argv) == 1
    assert "motion" in capsys.readouterr().err


def test_dataclass_configs_validate():
    with pytest.raises(ValueError, match="strand_stride"):
        DataConfig(strand_stride=5)
    with pytest.raises(ValueError, match="warmup_frames"):
        DynamicTrainingConfig(warmup_frames=1)
    with pytest.raises(ValueError, match="model.window"):
        DynamicTrainingConfig(model={"window": 3})
    with pytest.raises(ValueError, match="fusoin"):
        DynamicTrainingConfig(model={"fusoin": "lora"})
    with pytest.raises(ValueError, match="subsample_max"):
        DynamicTrainingConfig(subsample_min=4, subsample_max=2)
    cfg = StaticTrainingConfig()
    paper = (cfg.learning_rate, cfg.batch_size, cfg.bp_start, cfg.bp_end, cfg.deformation_clip)
    assert paper == (1e-4, 32, 0.9, 0.01, 0.01)
    dyn = DynamicTrainingConfig()
    paper = (dyn.window, dyn.subsample_min, dyn.subsample_max, dyn.dynamic_candidates, dyn.dynamic_quantile)
    assert paper == (10, 2, 5, 500, 0.5)
    assert dataclasses.asdict(cfg)["data"]["num_vertices"] == 100 and cfg.data.num_strands == 1024


def test_networks_beyond_the_paper_train_static_then_dynamic(tmp_path, static_config, sampler):
    """Contact features, the length projection and the inverse-energy weighting through both
    trainings: the static loss falls, the dynamic network reads every frame's contact features
    (warm-up frames' bodies built), and its drapes keep the rest lengths."""
    cfg = static_config.replace(phase_steps=(2, 2, 0, 0), learning_rate=_STEP_LR, loss_normalization="inverse",
                                model={"contact_samples": 3, "length_projection": "follow_the_leader"})
    static = StaticTrainer(cfg, out=tmp_path / "static", sampler=sampler)
    assert static.model.contact_encoder is not None
    batch = static.next_batch(0)
    before, _ = static.evaluate(batch, 0)
    static.train_step(batch)
    after, _ = static.evaluate(batch, 0)
    assert after < before
    static.train(progress=False)
    static.close()
    dyn_cfg = DynamicTrainingConfig.tiny(str(tmp_path / "static" / "checkpoint.pt")).replace(
        data=static_config.data, steps=1)
    dynamic = DynamicTrainer(dyn_cfg, sampler=sampler)
    seq = dynamic.next_batch(0)
    assert seq.warmup.inputs.body is not None  # the contact features of the warm-up frames need it
    loss, terms, positions = dynamic_loss(dynamic.model, seq, EnergyConfig(barrier_join_fraction=0.01))
    assert torch.isfinite(loss) and positions.requires_grad
    rigid = seq.rollout.rigid.reshape(positions.shape)
    seg = (positions[..., 1:, :] - positions[..., :-1, :]).norm(dim=-1)
    rest = (rigid[..., 1:, :] - rigid[..., :-1, :]).norm(dim=-1)
    assert float((seg - rest).abs().max().detach()) < 1e-5
    dynamic.train_step(seq)
    with pytest.raises(ValueError, match="contact: this network reads contact features"):
        dynamic.model.simulate(seq.z, seq.betas, seq.poses, seq.motion)


def test_inertia_time_step_follows_the_sampling_interval(dynamic_config, sampler):
    """Eq. 16 ~ 1 / h^2: with "interval" a sequence sampled every k frames has its inertia term
    divided by k^2 against "frame" (h = 1 / fps for every k); the other terms are the same."""
    trainer = DynamicTrainer(dynamic_config, sampler=sampler)
    batch = trainer.next_batch(0)
    energy = EnergyConfig(barrier_join_fraction=0.01)
    torch.manual_seed(0)
    _, frame_terms, x_frame = dynamic_loss(trainer.model, batch, energy, inertia_time_step="frame")
    _, interval_terms, x_interval = dynamic_loss(trainer.model, batch, energy, inertia_time_step="interval")
    assert torch.equal(x_frame, x_interval)
    k = torch.tensor(batch.intervals, dtype=torch.float64)
    assert len(set(batch.intervals)) >= 1 and min(batch.intervals) >= 2
    # Per-sequence inertia at h = 1/fps, then weighted by 1/k^2 and averaged over the frames.
    per_item = total_energy(x_frame.reshape(-1, *x_frame.shape[2:]).detach(), dataclasses.replace(
        batch.rollout.inputs, **_history(trainer, batch, x_frame)), energy, dynamic=True, terms=("inertia",)).total
    per_seq = per_item.double().reshape(batch.batch_size, -1).mean(1)
    assert interval_terms["inertia"] == pytest.approx(float((per_seq / k**2).mean()), rel=1e-5)
    assert frame_terms["inertia"] == pytest.approx(float(per_seq.mean()), rel=1e-5)
    for name in ("gravity", "hair_body_contact", "auxiliary"):
        assert interval_terms[name] == pytest.approx(frame_terms[name], rel=1e-6)
    with pytest.raises(ValueError, match="inertia_time_step"):
        DynamicTrainingConfig.tiny("x.pt").replace(inertia_time_step="never")


def _history(trainer, batch, positions):
    """prev / prev2 of the rollout frames as `dynamic_loss` builds them."""
    b, w = batch.batch_size, batch.warmup_frames
    m, n = positions.shape[2], positions.shape[3]
    model = trainer.model
    root_uv = batch.rollout.root_uv
    with torch.no_grad():
        warm = model.simulate(batch.z, batch.betas, batch.poses[:, :w], batch.motion[:, :w], None, None)
        maps = warm.deformation_map.reshape(b * w, *warm.deformation_map.shape[2:])
        warm_x = apply_deformation(batch.warmup.rigid, maps, root_uv, length_projection_of(model)).reshape(b, w, m, n, 3)
    prev, prev2 = inertia_history(warm_x, positions.detach())
    return {"prev": prev.reshape(-1, m, n, 3), "prev2": prev2.reshape(-1, m, n, 3)}
