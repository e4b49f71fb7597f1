"""`hairwarp bench energy`'s torch.compile column, on the CPU at a tiny size: the compiled
plain-torch peer gives the eager peer's energy, is timed, and lands in the table; a peer that
cannot be compiled is recorded as such instead of failing the benchmark."""

import pytest
import torch

from hairwarp.bench import energy as bench


@pytest.mark.slow
def test_compile_column_matches_eager_and_is_timed():
    record = bench.run_energy_benchmark(torch.device("cpu"), batches=(1,), names={"stretch"}, progress=False,
                                        strand_stride=8, num_vertices=12)
    (row,) = record["results"]
    assert record["sizes"]["strands"] == 1024 // 8 and record["sizes"]["vertices_per_strand"] == 12
    assert row["name"] == "stretch" and row["torch_compile_ms"] > 0
    assert row["torch_compile_first_ms"] > row["torch_compile_ms"]  # the first call compiled
    assert row["compile_rel_diff"] < 1e-5
    assert row["speedup_vs_compile"] == pytest.approx(row["torch_compile_ms"] / row["warp_ms"])
    table = bench.markdown_table(record)
    assert "torch.compile fwd+bwd (ms)" in table and f"{row['torch_compile_ms']:.3f}" in table


def test_a_peer_that_does_not_compile_is_recorded_not_raised(monkeypatch):
    def broken(fn, **kw):
        raise RuntimeError("no C++ compiler\nsecond line")

    monkeypatch.setattr(torch, "compile", broken)
    record = bench.run_energy_benchmark(torch.device("cpu"), batches=(1,), names={"gravity"}, progress=False,
                                        strand_stride=16, num_vertices=8)
    (row,) = record["results"]
    assert row["torch_compile_ms"] is None and row["compile_note"] == "RuntimeError: no C++ compiler"
    assert "| n/a | n/a |" in bench.markdown_table(record)
