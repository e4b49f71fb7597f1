"""Fidelity metrics (static drape vs optimum, motion vs physics) against float64 numpy, and the swing plot."""

import numpy as np
import pytest
import torch

from hairwarp.evaluation.charts import swing_plot
from hairwarp.metrics import largest_step_from_rigid, mean_tip_offset, motion_fidelity, static_fidelity, tip_swing

# float32 inputs, float64 reductions: the differences of ~0.1 m coordinates carry ~1e-8 m of rounding.
_ATOL_MM = 1e-4
_RTOL = 1e-5

T, M, N = 12, 5, 6


def _motion(rng):
    """rigid, physics (rigid + a per-strand swing + a constant sag + noise on the inner vertices), as float64."""
    rigid = rng.normal(scale=0.1, size=(T, M, N, 3))
    rigid[:, :, :, 1] += np.linspace(0, 1, T)[:, None, None] * 0.05  # the head moves
    t = np.arange(T)[:, None, None]
    swing = 0.02 * np.sin(0.7 * t + rng.uniform(0, 6, size=(1, M, 3)))
    sag = np.array([0.0, -0.03, 0.0])
    physics = rigid.copy()
    weight = np.clip(np.arange(N) - 1, 0, None) / (N - 2)  # fixed vertices 0 and 1 stay on the rigid placement
    physics += (swing[:, :, None] + sag) * weight[None, None, :, None]
    return rigid, physics


def _t(a):
    return torch.tensor(a, dtype=torch.float32)


def _swing_np(x, rigid):
    off = x[:, :, -1] - rigid[:, :, -1]
    return off - off.mean(axis=0, keepdims=True)


def test_static_fidelity_matches_numpy(rng):
    opt = rng.normal(scale=0.1, size=(3, M, N, 3))
    x = opt + rng.normal(scale=0.005, size=opt.shape)
    x[:, :, :2] = opt[:, :, :2]
    out = static_fidelity(_t(x), _t(opt), energy=torch.tensor([1.0, 2.0, 3.0]), optimum_energy=4.0)
    xs, os_ = _t(x).double().numpy(), _t(opt).double().numpy()
    d = np.linalg.norm(xs[:, :, 2:] - os_[:, :, 2:], axis=-1)
    assert d.mean() > 1e-3  # not passing on nothing
    assert out["mean_distance_mm"] == pytest.approx(d.mean() * 1e3, rel=_RTOL, abs=_ATOL_MM)
    assert out["p95_distance_mm"] == pytest.approx(np.percentile(d, 95) * 1e3, rel=_RTOL, abs=_ATOL_MM)
    tip = (xs[:, :, -1, 1] - os_[:, :, -1, 1]).mean() * 1e3
    assert out["tip_height_difference_mm"] == pytest.approx(tip, rel=_RTOL, abs=_ATOL_MM)
    assert out["energy_ratio"] == pytest.approx(6.0 / 4.0)


def test_static_fidelity_self_unbatched_and_without_energies(rng):
    opt = _t(rng.normal(size=(M, N, 3)))
    out = static_fidelity(opt, opt)
    assert "energy_ratio" not in out
    assert out["mean_distance_mm"] == out["p95_distance_mm"] == out["tip_height_difference_mm"] == 0.0
    lifted = opt.clone()
    lifted[:, -1, 1] += 0.01
    assert static_fidelity(lifted, opt)["tip_height_difference_mm"] == pytest.approx(10.0, abs=1e-3)


def test_tip_swing_and_mean_tip_offset(rng):
    rigid, physics = _motion(rng)
    s = tip_swing(_t(physics), _t(rigid))
    assert s.shape == (T, M, 3)
    ref = _swing_np(_t(physics).double().numpy(), _t(rigid).double().numpy())
    np.testing.assert_allclose(s.double().numpy(), ref, atol=1e-6)
    off = mean_tip_offset(_t(physics), _t(rigid))
    assert off.shape == (T, 3)
    np.testing.assert_allclose(off.double().numpy(), (physics[:, :, -1] - rigid[:, :, -1]).mean(axis=1), atol=1e-6)
    assert off[:, 1].mean() == pytest.approx(-0.03, abs=0.01)  # the sag is kept, not subtracted


def test_motion_fidelity_matches_numpy(rng):
    rigid, physics = _motion(rng)
    x = rigid + 0.6 * (physics - rigid) + rng.normal(scale=0.002, size=rigid.shape) * (np.arange(N) >= 2)[:, None]
    out = motion_fidelity(_t(x), _t(physics), _t(rigid))
    xs, ps, rs = (_t(a).double().numpy() for a in (x, physics, rigid))
    per_frame = np.linalg.norm(xs[:, :, 2:] - ps[:, :, 2:], axis=-1).mean(axis=(1, 2)) * 1e3
    np.testing.assert_allclose(out["per_frame_distance_mm"], per_frame, rtol=_RTOL, atol=_ATOL_MM)
    assert out["mean_distance_mm"] == pytest.approx(per_frame.mean(), rel=_RTOL, abs=_ATOL_MM)
    assert out["max_distance_mm"] == pytest.approx(per_frame.max(), rel=_RTOL, abs=_ATOL_MM)
    per_strand = np.linalg.norm(xs[:, :, 2:] - ps[:, :, 2:], axis=-1).mean(axis=2) * 1e3
    assert out["strand_distance_p99_mm"] == pytest.approx(np.percentile(per_strand, 99, axis=1).max(), rel=_RTOL,
                                                          abs=_ATOL_MM)
    sx, sp = _swing_np(xs, rs), _swing_np(ps, rs)
    rms_x = np.sqrt((sx ** 2).sum(-1).mean()) * 1e3
    rms_p = np.sqrt((sp ** 2).sum(-1).mean()) * 1e3
    assert rms_p > 5.0  # the physics swings
    assert out["swing_mm"] == pytest.approx(rms_x, rel=_RTOL)
    assert out["physics_swing_mm"] == pytest.approx(rms_p, rel=_RTOL)
    assert out["swing_amplitude_ratio"] == pytest.approx(rms_x / rms_p, rel=_RTOL)
    assert out["swing_correlation"] == pytest.approx(np.corrcoef(sx.ravel(), sp.ravel())[0, 1], rel=_RTOL)
    for k in range(3):
        assert out["swing_by_axis_mm"][k] == pytest.approx(np.sqrt((sx[..., k] ** 2).mean()) * 1e3, rel=_RTOL)
        assert out["physics_swing_by_axis_mm"][k] == pytest.approx(np.sqrt((sp[..., k] ** 2).mean()) * 1e3, rel=_RTOL)
        assert out["swing_correlation_by_axis"][k] == pytest.approx(
            np.corrcoef(sx[..., k].ravel(), sp[..., k].ravel())[0, 1], rel=_RTOL)
    # the three axes' mean squares add up to the swing's
    assert sum(v ** 2 for v in out["swing_by_axis_mm"]) == pytest.approx(out["swing_mm"] ** 2, rel=1e-9)
    bulk_x, bulk_p = sx.mean(axis=1), sp.mean(axis=1)  # (T, 3): the swing plot's curves less their means
    assert out["bulk_swing_correlation"] == pytest.approx(np.corrcoef(bulk_x.ravel(), bulk_p.ravel())[0, 1],
                                                          rel=_RTOL)


def test_the_swing_by_axis_names_the_axis_a_method_misses(rng):
    """A method that swings like the physics sideways and in depth but against it vertically: the
    correlations by axis read +1, -1, +1 where the overall one is in between; a method whose
    strands each swing their own way about a common motion keeps the bulk correlation."""
    rigid, physics = _motion(rng)
    x = physics.copy()
    x[..., 1] = rigid[..., 1] - (physics - rigid)[..., 1]
    out = motion_fidelity(_t(x), _t(physics), _t(rigid))
    assert out["swing_correlation_by_axis"] == pytest.approx([1.0, -1.0, 1.0], abs=1e-6)
    assert -1.0 < out["swing_correlation"] < 1.0
    # A swing along x only: the other axes of the method are still, their correlation undefined.
    still = rigid.copy()
    still[..., 0] = physics[..., 0]
    out = motion_fidelity(_t(still), _t(physics), _t(rigid))
    assert out["swing_correlation_by_axis"][0] == pytest.approx(1.0, abs=1e-6)
    assert out["swing_correlation_by_axis"][1:] == [None, None]
    assert out["swing_by_axis_mm"][1:] == [0.0, 0.0]
    # Every strand swinging with the physics' strand-mean swing plus a private swing of its own
    # that averages out over the strands: the bulk motion matches exactly, each strand only partly.
    t = np.arange(T)[:, None]
    private = 0.02 * np.sin(1.3 * t + np.linspace(0, 2 * np.pi, M, endpoint=False)[None, :])  # (T, M), sums to 0
    weight = np.clip(np.arange(N) - 1, 0, None) / (N - 2)
    mixed = physics + (private[:, :, None, None] * np.array([0.0, 0.0, 1.0])) * weight[None, None, :, None]
    out = motion_fidelity(_t(mixed), _t(physics), _t(rigid))
    assert out["bulk_swing_correlation"] == pytest.approx(1.0, abs=1e-4)
    assert out["swing_correlation"] < 0.99


def test_motion_fidelity_sees_the_few_strands_that_fly_out(rng):
    """One strand 0.2 m off in one frame: the mean distance is 200 mm over the strands and the
    frames, the worst strands' distance (p99 over the strands, worst frame) shows nearly all of it."""
    rigid, physics = _motion(rng)
    x = physics.copy()
    x[T // 2, 0, 2:] += np.array([0.2, 0.0, 0.0])
    out = motion_fidelity(_t(x), _t(physics), _t(rigid))
    assert out["mean_distance_mm"] == pytest.approx(200.0 / M / T, rel=1e-4)
    assert out["strand_distance_p99_mm"] > 150.0
    assert motion_fidelity(_t(physics), _t(physics), _t(rigid))["strand_distance_p99_mm"] == 0.0


def test_the_largest_step_from_the_rigid_placement_sees_a_strand_flung_in_one_frame(rng):
    """numpy float64: max over frames, strands and moving vertices of the change of the offset
    from the rigid placement; 0 for the rigid placement, and one strand thrown 0.2 m for a frame
    shows as ~200 mm where the swing's steps are a few millimetres."""
    rigid, physics = _motion(rng)
    offset = (physics - rigid)[:, :, 2:]
    expected = np.linalg.norm(offset[1:] - offset[:-1], axis=-1).max() * 1e3
    out = motion_fidelity(_t(physics), _t(physics), _t(rigid))
    assert out["largest_step_mm"] == out["physics_largest_step_mm"]
    assert out["largest_step_mm"] == pytest.approx(expected, rel=_RTOL, abs=_ATOL_MM)
    assert expected < 30.0
    flung = physics.copy()
    flung[T // 2, 0, 2:] += np.array([0.2, 0.0, 0.0])
    assert motion_fidelity(_t(flung), _t(physics), _t(rigid))["largest_step_mm"] > 180.0
    assert largest_step_from_rigid(_t(rigid), _t(rigid)) == 0.0
    assert largest_step_from_rigid(_t(physics[:1]), _t(rigid[:1])) == 0.0
    with pytest.raises(ValueError, match="^rigid:"):
        largest_step_from_rigid(_t(physics), _t(rigid[:, :, :3]))
    with pytest.raises(ValueError, match="^x:"):
        largest_step_from_rigid(_t(physics[:, :, :2]), _t(rigid[:, :, :2]))


def test_motion_fidelity_physics_against_itself(rng):
    rigid, physics = _motion(rng)
    out = motion_fidelity(_t(physics), _t(physics), _t(rigid))
    assert out["mean_distance_mm"] == out["max_distance_mm"] == 0.0
    assert out["per_frame_distance_mm"] == [0.0] * T
    assert out["swing_correlation"] == pytest.approx(1.0, abs=1e-9)
    assert out["swing_amplitude_ratio"] == pytest.approx(1.0, abs=1e-12)


def test_motion_fidelity_rigid_placement(rng):
    rigid, physics = _motion(rng)
    out = motion_fidelity(_t(rigid), _t(physics), _t(rigid))
    assert out["mean_distance_mm"] > 1.0
    assert out["swing_mm"] == 0.0
    assert out["swing_amplitude_ratio"] == 0.0
    assert out["swing_correlation"] is None
    # A rigid "physics" has no swing to compare with.
    still = motion_fidelity(_t(physics), _t(rigid), _t(rigid))
    assert still["physics_swing_mm"] == 0.0
    assert still["swing_amplitude_ratio"] is None and still["swing_correlation"] is None


@pytest.mark.parametrize("scale, corr", [(0.5, 1.0), (-1.0, -1.0)])
def test_motion_fidelity_scaled_swing(rng, scale, corr):
    rigid, physics = _motion(rng)
    x = rigid + scale * (physics - rigid)  # the offset scaled: its mean (sag) and swing alike
    out = motion_fidelity(_t(x), _t(physics), _t(rigid))
    assert out["swing_amplitude_ratio"] == pytest.approx(abs(scale), rel=1e-5)
    assert out["swing_correlation"] == pytest.approx(corr, abs=1e-6)


@pytest.mark.parametrize("fn, bad", [
    (lambda a, b: static_fidelity(a, b), "optimum"),
    (lambda a, b: tip_swing(a, b), "rigid"),
    (lambda a, b: mean_tip_offset(a, b), "rigid"),
    (lambda a, b: motion_fidelity(a, b, a), "physics"),
    (lambda a, b: motion_fidelity(a, a, b), "rigid"),
])
def test_shape_mismatch_names_the_argument(fn, bad):
    a, b = torch.zeros(T, M, N, 3), torch.zeros(T, M, N - 1, 3)
    with pytest.raises(ValueError, match=f"^{bad}:"):
        fn(a, b)


def test_too_few_vertices_and_bad_x():
    with pytest.raises(ValueError, match="^x:"):
        static_fidelity(torch.zeros(M, 2, 3), torch.zeros(M, 2, 3))
    with pytest.raises(ValueError, match="^x:"):
        tip_swing(torch.zeros(T, M, N, 2), torch.zeros(T, M, N, 2))


def test_swing_plot_writes_a_png(rng, tmp_path):
    rigid, physics = _motion(rng)
    curves = {"physics": mean_tip_offset(_t(physics), _t(rigid)),
              "rigid": np.zeros((T, 3)),
              "static": mean_tip_offset(_t(0.5 * (physics + rigid)), _t(rigid))}
    path = str(tmp_path / "sub" / "swing.png")
    assert swing_plot(curves, path, fps=30.0, title="test") == path
    with open(path, "rb") as f:
        data = f.read()
    assert len(data) > 1000 and data[:8] == b"\x89PNG\r\n\x1a\n"


def test_swing_plot_rejects_bad_input(tmp_path):
    path = str(tmp_path / "swing.png")
    with pytest.raises(ValueError, match="^curves:"):
        swing_plot({}, path, fps=30.0)
    with pytest.raises(ValueError, match=r"^curves\['b'\]:"):
        swing_plot({"a": np.zeros((5, 3)), "b": np.zeros((4, 3))}, path, fps=30.0)
    with pytest.raises(ValueError, match=r"^curves\['a'\]:"):
        swing_plot({"a": np.zeros((5, 2))}, path, fps=30.0)
    with pytest.raises(ValueError, match="^fps:"):
        swing_plot({"a": np.zeros((5, 3))}, path, fps=0.0)
    with pytest.raises(ValueError, match="^path:"):
        swing_plot({"a": np.zeros((5, 3))}, str(tmp_path / "swing.pdf"), fps=30.0)
