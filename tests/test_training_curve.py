"""The learning-curve record of static training (issue 15): its fields, its figure, and resume.

Tiny network on 64 strands x 20 vertices (`DataConfig.tiny()`); held-out scenes table1 and
medium_poses at every 8th scalp root x 20 vertices, reference energy from 3 L-BFGS iterations.
"""

from __future__ import annotations

import json

import pytest
import torch

from hairwarp.evaluation.scenes import comparison_scene
from hairwarp.training import StaticTrainer, StaticTrainingConfig, TrainingSampler
from hairwarp.training.monitor import CURVE_FIGURE, CURVE_NAME

# Two trainings from the same weights and batches on the CPU: the same float32 operations in the
# same order, so resumed weights match to rounding.
_RESUME_TOL = 1e-6


@pytest.fixture(scope="module")
def config():
    return StaticTrainingConfig.tiny().replace(
        phase_steps=(1, 1, 1, 1), curve_every=2, curve_strand_stride=8, curve_reference_iterations=3,
    )


@pytest.fixture(scope="module")
def sampler(config):
    return TrainingSampler(config.data, seed=0)


def _train(config, sampler, out, steps=None, resume=None):
    trainer = StaticTrainer(None if resume else config, out=out, sampler=sampler, resume=resume,
                            scene_factory=comparison_scene)
    trainer.train(steps, progress=False)
    trainer.close()
    return trainer


def test_curve_record_holds_the_named_fields(tmp_path, config, sampler):
    trainer = _train(config, sampler, tmp_path)
    data = json.loads((tmp_path / CURVE_NAME).read_text())
    assert (tmp_path / CURVE_FIGURE).stat().st_size > 0
    assert [e["step"] for e in data["entries"]] == [0, 2, 4]
    n = config.data.num_vertices
    for entry in data["entries"]:
        train = entry["train"]
        assert set(train["gradient"]["norm"]) >= {"stretch", "bending", "smoothness", "auxiliary", "gravity",
                                                  "hair_body_contact", "hair_hair_contact"}
        assert all(v >= 0 for v in train["gradient"]["norm"].values())
        assert len(train["displacement_by_vertex_mm"]) == n
        assert train["displacement_by_vertex_mm"][0] == 0.0  # roots never move
        assert len(train["rigid_penetration_percent"]) == len(train["penetration_percent"])
        for name in ("table1", "medium_poses"):
            scores = entry["held_out"][name]
            for key in ("penetration_percent", "length_change_percent", "energy", "energy_gap", "energy_ratio",
                        "mean_distance_mm", "tip_height_difference_mm"):
                assert torch.isfinite(torch.tensor(scores[key]))
            assert len(scores["displacement_by_vertex_mm"]) == n
    assert data["scenes"]["table1"]["rigid"]["penetration_percent"] > 10.0  # every tip starts inside
    assert trainer.step == 4


def test_curve_off_writes_nothing(tmp_path, config, sampler):
    _train(config.replace(curve_every=0), sampler, tmp_path)
    assert not (tmp_path / CURVE_NAME).exists()


def test_resume_n_plus_n_equals_2n(tmp_path, config, sampler):
    straight = _train(config, sampler, tmp_path / "a")
    _train(config, sampler, tmp_path / "b", steps=2)
    resumed = _train(config, sampler, tmp_path / "b", resume=tmp_path / "b")
    assert resumed.step == straight.step == 4
    a, b = straight.model.state_dict(), resumed.model.state_dict()
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=_RESUME_TOL, atol=_RESUME_TOL)
    curve_a = json.loads((tmp_path / "a" / CURVE_NAME).read_text())["entries"]
    curve_b = json.loads((tmp_path / "b" / CURVE_NAME).read_text())["entries"]
    assert [e["step"] for e in curve_a] == [e["step"] for e in curve_b]
    for ea, eb in zip(curve_a, curve_b):
        assert ea["train"]["loss"] == pytest.approx(eb["train"]["loss"], rel=_RESUME_TOL)
        for name in ea["held_out"]:
            assert ea["held_out"][name]["penetration_percent"] == pytest.approx(
                eb["held_out"][name]["penetration_percent"], abs=1e-6)
            assert ea["held_out"][name]["length_change_percent"] == pytest.approx(
                eb["held_out"][name]["length_change_percent"], rel=1e-5, abs=1e-9)
