"""Data-parallel training under torchrun (issue 7): two gloo ranks on the CPU against one process.

The test launches `python -m torch.distributed.run --nproc_per_node 2` on this file (its
`__main__` part is the rank's program): the ranks train a tiny static network for 3 steps
(phase 0, replicated; phases 1 and 3, a global batch of 3 split 1 + 2) and a tiny dynamic
network for 2 steps (3 sequences, split 1 + 2) through the public `train_static` /
`train_dynamic`, which join the run from torchrun's environment. Then, in this process (no
torchrun environment: the single-process path): the same runs with the same global batch,
a resume of the 2-rank checkpoint, the sampler's sharding, the environment parsing.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys

import pytest
import torch

from hairwarp import _warp
from hairwarp.models import load_checkpoint
from hairwarp.training import (
    DataConfig,
    DynamicTrainingConfig,
    StaticTrainer,
    StaticTrainingConfig,
    TrainingSampler,
    shard_bounds,
    train_dynamic,
    train_static,
)
from hairwarp.training.distributed import check_process_group, plan_from_env

SEED = 3
STATIC_STEPS = 3  # of the 4 in the config: the 4th is run by the single-process resume
WORLD = 2
# The runs compared are float64. DDP sums the ranks' gradient shares where the single process
# sums the whole batch: the same numbers added in another order. Adam moves the weights whose
# exact gradient is zero (attention key biases: softmax ignores them) by lr * noise / eps per
# step. In float32 the noise (1e-7 relative) beats eps = 1e-8 and those steps are +-lr = 1e-3,
# sign by chance; in float64 (noise about 1e-15) they are about 4e-10 (1.3e-9 seen over 3 steps).
_PARAM_ATOL = 1e-8
_PARAM_RTOL = 1e-7
# Checkpoints store float32 weights: a float64 run resumed from one continues from weights
# rounded to float32 (6e-8 relative), which one more step carries along.
_RESUME_RTOL = 1e-6
_RESUME_ATOL = 1e-8
# The logged global loss: an all-reduce of the ranks' weighted batch means (float64).
_LOSS_RTOL = 1e-10
# A sample placed in a batch of 1 or of 2: the same float32 posing and Eq. 1, other matrix
# blocking (one float32 ulp at 0.5 m is 6e-8 m).
_PLACEMENT_ATOL = 1e-6
# The torchrun job: start-up of two Python processes, two samplers each, 5 steps.
_JOB_TIMEOUT_S = 240


def _static_config() -> StaticTrainingConfig:
    # Phase 0 (one replicated sample), phase 1 (head rotations) and phase 3 (noisy shapes) with
    # a global batch of 3: uneven shares (1 + 2) test the loss weighting.
    return StaticTrainingConfig.tiny().replace(phase_steps=(1, 1, 0, 2), batch_size=3, dtype="float64",
                                               data=DataConfig.tiny())


def _dynamic_config(static_checkpoint: str) -> DynamicTrainingConfig:
    return DynamicTrainingConfig.tiny(static_checkpoint).replace(steps=2, batch_size=3, dtype="float64")


def _rank_main(out: str) -> None:
    """One rank of the torchrun job (the test reads what it writes)."""
    torch.set_num_threads(1)
    static = train_static(_static_config(), os.path.join(out, "static"), seed=SEED, steps=STATIC_STEPS,
                          progress=False)
    rank = static.rank
    torch.save(static.model.state_dict(), os.path.join(out, f"static_rank{rank}.pt"))
    dynamic = train_dynamic(_dynamic_config(os.path.join(out, "static", "checkpoint.pt")),
                            os.path.join(out, "dynamic"), seed=SEED, progress=False)
    torch.save(dynamic.model.state_dict(), os.path.join(out, f"dynamic_rank{rank}.pt"))
    shard = static.sampler.static_batch(5, 3, 1.0, 3, 3).info["shard"]
    with open(os.path.join(out, f"rank{rank}.json"), "w", encoding="utf-8") as f:
        json.dump({"rank": rank, "world_size": static.world_size, "device": str(static.device),
                   "static_losses": [r["loss"] for r in static.history],
                   "dynamic_losses": [r["loss"] for r in dynamic.history], "shard": shard}, f)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    """Run the 2-rank torchrun job once; its output folder."""
    out = tmp_path_factory.mktemp("ddp")
    env = {k: v for k, v in os.environ.items() if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK")}
    env.update(OMP_NUM_THREADS="1", MASTER_ADDR="127.0.0.1", PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", str(WORLD), "--nnodes", "1",
           "--master_addr", "127.0.0.1", "--master_port", str(_free_port()), os.path.abspath(__file__),
           "--out", str(out)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=_JOB_TIMEOUT_S)
    assert proc.returncode == 0, f"torchrun failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-6000:]}"
    return out


@pytest.fixture(scope="module")
def single(job):
    """The single-process runs with the same global batches (this process has no torchrun env)."""
    assert "WORLD_SIZE" not in os.environ
    trainer = StaticTrainer(_static_config(), seed=SEED)
    trainer.train(STATIC_STEPS, progress=False)
    after3 = {k: v.clone() for k, v in trainer.model.state_dict().items()}
    trainer.train(progress=False)  # the 4th step, for the resume test
    dynamic = train_dynamic(_dynamic_config(str(job / "static" / "checkpoint.pt")), None, seed=SEED,
                            progress=False)
    return {"static3": after3, "static4": trainer.model.state_dict(), "static_history": trainer.history,
            "dynamic": dynamic.model.state_dict(), "dynamic_history": dynamic.history}


def _ranks(job):
    return [json.loads((job / f"rank{r}.json").read_text()) for r in range(WORLD)]


def _assert_close(state, reference, what, rtol=_PARAM_RTOL, atol=_PARAM_ATOL):
    assert len(state) > 10 and set(state) == set(reference)
    for k, v in state.items():
        assert torch.allclose(v, reference[k], rtol=rtol, atol=atol), (
            f"{what}: {k} differs by {float((v - reference[k]).abs().max()):.3g}")


def _moved(state, before) -> bool:
    return any(not torch.equal(v, before[k]) for k, v in state.items())


@pytest.mark.slow
def test_ranks_end_with_identical_parameters(job):
    ranks = _ranks(job)
    assert [r["rank"] for r in ranks] == [0, 1] and all(r["world_size"] == WORLD for r in ranks)
    assert [r["shard"] for r in ranks] == [[0, 1], [1, 3]]  # each rank built its own share
    for kind in ("static", "dynamic"):
        a, b = (torch.load(job / f"{kind}_rank{r}.pt") for r in range(WORLD))
        assert len(a) > 10 and all(torch.equal(a[k], b[k]) for k in a), kind
    # The logged loss is the global batch's: the same number on both ranks.
    assert ranks[0]["static_losses"] == ranks[1]["static_losses"]
    assert ranks[0]["dynamic_losses"] == ranks[1]["dynamic_losses"]


@pytest.mark.slow
def test_two_ranks_match_one_process_with_the_same_global_batch(job, single):
    initial = StaticTrainer(_static_config(), seed=SEED).model.state_dict()
    static = torch.load(job / "static_rank0.pt")
    assert _moved(static, initial)  # 3 steps of training changed the weights
    _assert_close(static, single["static3"], "static")
    losses = _ranks(job)[0]["static_losses"]
    assert losses == pytest.approx([r["loss"] for r in single["static_history"][:STATIC_STEPS]], rel=_LOSS_RTOL)
    dynamic = torch.load(job / "dynamic_rank0.pt")
    start = load_checkpoint(job / "static" / "checkpoint.pt").model.state_dict()
    assert _moved({k[len("static."):]: v for k, v in dynamic.items() if k.startswith("static.")}, start) is False
    _assert_close(dynamic, single["dynamic"], "dynamic")
    assert _ranks(job)[0]["dynamic_losses"] == pytest.approx(
        [r["loss"] for r in single["dynamic_history"]], rel=_LOSS_RTOL)


def test_rank0_writes_the_files_once(job):
    for kind, steps in (("static", STATIC_STEPS), ("dynamic", 2)):
        folder = job / kind
        assert sorted(os.listdir(folder)) == ["checkpoint.pt", "config.toml", "log.jsonl"]
        records = [json.loads(line) for line in (folder / "log.jsonl").read_text().splitlines()]
        assert [r["step"] for r in records] == list(range(1, steps + 1))  # one writer: no line twice
        assert all(r["batch_size"] == 3 for r in records[1:])  # the global batch is logged
        ckpt = load_checkpoint(folder / "checkpoint.pt")
        assert ckpt.step == steps and ckpt.extra["world_size"] == WORLD and ckpt.extra["seed"] == SEED
        state = torch.load(job / f"{kind}_rank0.pt")  # float64; the checkpoint stores float32
        assert all(torch.equal(v, state[k].to(v.dtype)) for k, v in ckpt.model.state_dict().items())


def test_resume_of_a_two_rank_checkpoint_in_one_process(job, single, tmp_path):
    """World size 2 -> 1: the resumed run draws the same global batch and continues the run."""
    resumed = StaticTrainer(out=tmp_path, resume=job / "static")
    assert resumed.step == STATIC_STEPS and resumed.world_size == 1 and resumed.config == _static_config()
    record = resumed.train_step()
    resumed.save()
    resumed.close()
    assert record["step"] == STATIC_STEPS + 1 and record["batch_size"] == 3
    assert record["loss"] == pytest.approx(single["static_history"][-1]["loss"], rel=_RESUME_RTOL)
    _assert_close(resumed.model.state_dict(), single["static4"], "resumed", _RESUME_RTOL, _RESUME_ATOL)
    assert load_checkpoint(tmp_path / "checkpoint.pt").extra["world_size"] == 1


# ------------------------------------------------------------------------------- in process
def test_shards_partition_the_global_batch():
    assert [shard_bounds(5, r, 2) for r in range(2)] == [(0, 2), (2, 5)]
    assert [shard_bounds(8, r, 4) for r in range(4)] == [(0, 2), (2, 4), (4, 6), (6, 8)]
    assert shard_bounds(3, 0, 1) == (0, 3)
    with pytest.raises(ValueError, match="batch_size"):
        shard_bounds(1, 0, 2)
    with pytest.raises(ValueError, match="rank"):
        shard_bounds(4, 2, 2)


def test_ranks_build_disjoint_shares_of_the_single_process_batch():
    data = DataConfig.tiny()
    whole = TrainingSampler(data, seed=SEED)
    parts = [TrainingSampler(data, seed=SEED, rank=r, world_size=WORLD) for r in range(WORLD)]
    for phase in (1, 3):
        full = whole.static_batch(4, phase, 0.5, 3, 3)
        shares = [p.static_batch(4, phase, 0.5, 3, 3) for p in parts]
        assert [s.batch_size for s in shares] == [1, 2] and sum(s.share for s in shares) == pytest.approx(1.0)
        for name in ("z", "poses", "betas", "strands"):
            joined = torch.cat([getattr(s, name) for s in shares])
            assert torch.equal(joined, getattr(full, name)), (phase, name)
        rigid = torch.cat([s.rigid for s in shares])
        assert torch.allclose(rigid, full.rigid, rtol=0, atol=_PLACEMENT_ATOL)
        assert sum((s.hairstyle_ids for s in shares), []) == full.hairstyle_ids
        assert shares[0].info["hairstyles"] == full.info["hairstyles"]  # the info is the global batch's
    zero = [p.static_batch(0, 0, 1.0, 3) for p in parts]  # phase 0: one sample, on every rank
    assert all(b.batch_size == 1 and b.share == pytest.approx(1 / WORLD) for b in zero)
    kw = dict(num_hairstyles=2, window=3, candidates=16)
    full = whole.sequence_batch(2, 3, 2, 1, **kw)
    shares = [p.sequence_batch(2, 3, 2, 1, **kw) for p in parts]
    assert torch.equal(torch.cat([s.poses for s in shares]), full.poses)
    assert torch.equal(torch.cat([s.motion for s in shares]), full.motion)
    assert torch.allclose(torch.cat([s.rollout.rigid for s in shares]), full.rollout.rigid, rtol=0,
                          atol=_PLACEMENT_ATOL)
    assert sum((s.intervals for s in shares), []) == full.intervals


def test_plan_from_env():
    assert plan_from_env("cpu", env={}).world_size == 1  # no torchrun: the single-process path
    one = plan_from_env("cuda:1", env={"RANK": "0", "WORLD_SIZE": "1", "LOCAL_RANK": "0"}, cuda_device_count=2)
    assert one.backend is None and one.device == torch.device("cuda:1")  # world 1: as given
    env = {"RANK": "3", "WORLD_SIZE": "4", "LOCAL_RANK": "1"}
    gpu = plan_from_env("cuda", env=env, cuda_device_count=2)
    assert (gpu.rank, gpu.world_size, gpu.local_rank, gpu.backend) == (3, 4, 1, "nccl")
    assert gpu.device == torch.device("cuda", 1) and not gpu.is_main
    cpu = plan_from_env("cpu", env=env)
    assert cpu.backend == "gloo" and cpu.device == torch.device("cpu")
    assert _warp.warp_device(gpu.device) == "cuda:1"  # the Warp launches follow the rank's GPU


@pytest.mark.parametrize("env,device,match", [
    ({"RANK": "0", "WORLD_SIZE": "two", "LOCAL_RANK": "0"}, "cpu", "WORLD_SIZE"),
    ({"RANK": "2", "WORLD_SIZE": "2", "LOCAL_RANK": "0"}, "cpu", "RANK"),
    ({"WORLD_SIZE": "2", "LOCAL_RANK": "0"}, "cpu", "RANK"),
    ({"RANK": "1", "WORLD_SIZE": "2", "LOCAL_RANK": "-1"}, "cpu", "LOCAL_RANK"),
    ({"RANK": "1", "WORLD_SIZE": "2", "LOCAL_RANK": "2"}, "cuda", "LOCAL_RANK"),
    ({"RANK": "1", "WORLD_SIZE": "2", "LOCAL_RANK": "1"}, "cuda:0", "device"),
    ({}, "mps", "device"),
])
def test_plan_from_env_bad_input(env, device, match):
    with pytest.raises(ValueError, match=match):
        plan_from_env(device, env=env, cuda_device_count=2)


def test_trainer_needs_the_process_group_for_several_ranks():
    with pytest.raises(ValueError, match="world_size"):
        StaticTrainer(_static_config(), rank=0, world_size=2)
    with pytest.raises(ValueError, match="rank"):
        check_process_group(2, 2)
    check_process_group(0, 1)  # one rank: nothing to check


if __name__ == "__main__":  # one rank of the torchrun job started by the `job` fixture
    import argparse

    parser = argparse.ArgumentParser()
    parser.add_argument("--out", required=True)
    _rank_main(parser.parse_args().out)
