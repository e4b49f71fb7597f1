"""`hairwarp bench energy`'s sizes follow the device: on the CPU by default a quick run (128
strands x 100 vertices, batch 1 and 4, no torch.compile column; about a minute on a 2-core CPU),
the paper's sizes (1024 x 100, batch 1 and 32, torch.compile on) on CUDA or with --full; each
size flag overrides its field."""

import json

import pytest
import torch

from hairwarp.bench.energy import CPU_SIZES, FULL_SIZES, build_energy_inputs, default_sizes
from hairwarp.cli import build_parser, main
from hairwarp.commands.bench import resolve_sizes

CPU = torch.device("cpu")


def _sizes(*argv, device=CPU):
    return resolve_sizes(build_parser().parse_args(["bench", "energy", *argv]), device)


def test_cpu_defaults_are_the_small_sizes():
    sizes = _sizes("--device", "cpu")
    assert sizes is CPU_SIZES and sizes.name == "cpu"
    assert sizes.batches == (1, 4) and sizes.strand_stride == 8 and sizes.num_vertices == 100
    assert sizes.torch_compile is False and sizes.skip_torch_above_ms == 1_000.0
    assert default_sizes("cpu") is CPU_SIZES
    x, *_ = build_energy_inputs(1, CPU, strand_stride=sizes.strand_stride, num_vertices=sizes.num_vertices)
    assert tuple(x.shape) == (1, 128, 100, 3)  # 1/8 of the paper's 1024 strands


def test_full_and_cuda_are_the_papers_sizes():
    assert FULL_SIZES.batches == (1, 32) and FULL_SIZES.strand_stride == 1 and FULL_SIZES.num_vertices == 100
    assert FULL_SIZES.torch_compile is True
    assert _sizes("--full") is FULL_SIZES
    assert _sizes(device=torch.device("cuda")) is FULL_SIZES  # sized by the device; no GPU needed to resolve
    assert default_sizes(torch.device("cuda:0")) is FULL_SIZES and default_sizes("cpu", full=True) is FULL_SIZES


def test_size_flags_override_the_default():
    sizes = _sizes("--batch", "2", "--torch-compile", "--vertices", "12")
    assert sizes.name == "custom" and sizes.batches == (2,) and sizes.torch_compile and sizes.num_vertices == 12
    assert sizes.strand_stride == CPU_SIZES.strand_stride  # the fields not given stay the device's
    full = _sizes("--full", "--no-torch-compile", "--strand-stride", "2")
    assert full.name == "custom" and not full.torch_compile and full.strand_stride == 2 and full.batches == (1, 32)
    assert _sizes("--batch", "1,4", "--strand-stride", "8") is CPU_SIZES  # the default's own values: still "cpu"
    for argv, flag in ((["--batch", "1,x"], "--batch"), (["--batch", "0"], "--batch"),
                       (["--strand-stride", "0"], "--strand-stride"), (["--vertices", "2"], "--vertices")):
        with pytest.raises(ValueError, match=flag):
            _sizes(*argv)


def test_help_names_the_full_flag_and_its_cpu_time(capsys):
    with pytest.raises(SystemExit):
        main(["bench", "energy", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--full" in text and "2-core CPU" in text and "min" in text


def test_a_cpu_run_prints_a_table_and_writes_its_json(tmp_path, capsys):
    # One cheap term at the CPU's default hair (a few seconds): the command's path end to end.
    path = tmp_path / "b.json"
    assert main(["bench", "energy", "--device", "cpu", "--batch", "1", "--terms", "stretch",
                 "--json", str(path)]) == 0
    out = capsys.readouterr().out
    assert "(custom sizes)" in out and "| stretch | 1 |" in out
    record = json.loads(path.read_text())
    assert record["preset"] == "custom" and record["torch_compile"] is False
    assert record["sizes"]["strands"] == 128 and record["sizes"]["vertices_per_strand"] == 100
    assert [r["name"] for r in record["results"]] == ["stretch"] and "torch_compile_ms" not in record["results"][0]
    assert (tmp_path / "b.md").read_text().startswith("Device:")
