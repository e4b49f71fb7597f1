"""The benchmarks' inputs (`hairwarp.bench.energy.build_energy_inputs`): the mixed-length groom
that docs/contact.md 11 measures."""

import pytest
import torch

from hairwarp.bench.energy import build_energy_inputs, mix_strand_lengths


def test_mixed_lengths_cut_every_other_strand_and_its_inputs():
    """`build_energy_inputs(mixed_lengths=f)`: strands 0, 2, ... cut to f of their length (x,
    rigid, prev, prev2 and the rest lengths alike, roots unchanged), the others as they were;
    a fraction outside (0, 1] is an error naming the argument."""
    x, inputs, _, _ = build_energy_inputs(1, torch.device("cpu"), strand_stride=64, num_vertices=12)
    xm, mixed, _, _ = build_energy_inputs(1, torch.device("cpu"), strand_stride=64, num_vertices=12,
                                          mixed_lengths=0.25)

    def length(h):
        return (h[..., 1:, :] - h[..., :-1, :]).norm(dim=-1).sum(-1)

    rigid_length, mixed_length = length(inputs.rigid), length(mixed.rigid)
    torch.testing.assert_close(mixed_length[:, 1::2], rigid_length[:, 1::2])
    ratio = mixed_length[:, ::2] / rigid_length[:, ::2]
    assert bool(((ratio > 0.2) & (ratio <= 0.2501)).all())  # a chord of a curved quarter: at most 1/4
    torch.testing.assert_close(mixed.rigid[:, :, 0], inputs.rigid[:, :, 0])
    torch.testing.assert_close(mixed.rest_lengths, (mixed.rigid[0, :, 1:] - mixed.rigid[0, :, :-1]).norm(dim=-1))
    torch.testing.assert_close(mixed.prev2, mixed.rigid)
    assert float((xm.detach() - mixed.rigid).abs().max()) < 0.01  # the jitter around the cut hair
    with pytest.raises(ValueError, match="mixed_lengths"):
        mix_strand_lengths(inputs.rigid, 0.0)
