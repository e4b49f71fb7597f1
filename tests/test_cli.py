"""The `hairwarp` command line: --help everywhere, drape/simulate/export write what they say,
bad input gives one line naming the argument and a non-zero exit, no traceback.

Sizes are tiny (16-64 strands, 12-30 vertices, 3 frames) so that the file runs in well under
a minute and a half on a 2-core CPU; the commands' own code paths are the same at full size.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from hairwarp.cli import _available_commands, main
from hairwarp.io.export import read_hair_ply, read_obj
from hairwarp.io.hair_data import read_hair_data, write_hair_data
from hairwarp.io.usd import read_usd

# Tiny scenes: every 64th scalp root of the 32 x 32 grid (16 strands), 12 vertices per strand.
TINY = ["--strand-stride", "64", "--num-vertices", "12", "--no-progress", "--grow", "head"]
# float32 text/binary round trips are exact; USD stores float32 too.
_EXACT = 0.0


@pytest.fixture(autouse=True)
def _keep_torch_threads():
    # The commands set torch's thread count (--threads, default 1); give the next tests theirs back.
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def _run(argv, capsys):
    code = main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _subcommands() -> list[list[str]]:
    names = sorted(_available_commands())
    out = [[n] for n in names]
    if "train" in names:
        out.append(["train", "static"])
    if "bench" in names:
        out.append(["bench", "energy"])
    return out


@pytest.mark.parametrize("argv", _subcommands(), ids=lambda a: " ".join(a))
def test_help_exits_zero(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--help"])
    assert exc.value.code == 0
    assert "usage: hairwarp" in capsys.readouterr().out


def test_the_new_commands_are_registered():
    names = _available_commands()
    for name in ("demo", "drape", "simulate", "export"):
        assert name in names


@pytest.mark.slow
def test_drape_rigid_writes_every_output(tmp_path, capsys):
    out = tmp_path / "rigid"
    code, stdout, _ = _run(["drape", *TINY, "--method", "rigid", "--out", str(out)], capsys)
    assert code == 0
    for name in ("drape.usda", "drape.data", "drape.png", "drape_rigid.png", "drape_metrics.json",
                 "drape_metrics.md"):
        assert (out / name).stat().st_size > 0, name
    record = json.loads((out / "drape_metrics.json").read_text())
    assert record["strands"] == 16 and record["vertices"] == 12
    # The rigid method returns the rigid placement: identical metrics.
    assert record["result"]["penetration_percent"] == record["rigid"]["penetration_percent"]
    # What was written is what was draped: .data and USD agree.
    strands = np.stack(read_hair_data(out / "drape.data"))
    usd = read_usd(out / "drape.usda")
    assert strands.shape == (16, 12, 3)
    np.testing.assert_array_equal(usd["hair"][0].numpy(), strands)
    assert usd["body_vertices"] is not None and usd["body_faces"].shape[1] == 3
    assert "| rigid |" in stdout


@pytest.mark.slow
def test_drape_lbfgs_from_a_data_file(tmp_path, capsys):
    # A tiny hairstyle: 24 strands of 20 vertices, written in metres, loaded back by the command.
    from hairwarp.scene.scene import default_scene

    style = default_scene("bob", strand_stride=32, num_vertices=20).hairstyle.strands
    hair_file = tmp_path / "tiny.data"
    write_hair_data(hair_file, style)
    out = tmp_path / "lbfgs"
    code, stdout, _ = _run(["drape", "--hairstyle", str(hair_file), "--num-vertices", "20", "--no-progress",
                            "--method", "lbfgs", "--max-iterations", "3", "--no-hair-hair", "--out", str(out)],
                           capsys)
    assert code == 0
    record = json.loads((out / "drape_metrics.json").read_text())
    assert record["strands"] == style.shape[0] > 0
    assert record["method_info"]["iterations"] <= 3
    # L-BFGS keeps the best iterate: the energy never rises above the rigid placement's.
    assert record["result"]["energy"][0] <= record["rigid"]["energy"][0]
    draped = np.stack(read_hair_data(out / "drape.data"))
    assert draped.shape == (style.shape[0], 20, 3) and np.isfinite(draped).all()
    assert (out / "drape.png").stat().st_size > 0


@pytest.mark.slow
def test_simulate_rigid_three_frames(tmp_path, capsys):
    out = tmp_path / "sim"
    code, _, _ = _run(["simulate", *TINY, "--method", "rigid", "--pose", "nod", "--frames", "3", "--gif-frames", "3",
                       "--out", str(out)], capsys)
    assert code == 0
    for name in ("simulate.usdc", "simulate.data", "simulate.png", "simulate.gif", "simulate_metrics.json",
                 "simulate_metrics.md"):
        assert (out / name).stat().st_size > 0, name
    usd = read_usd(out / "simulate.usdc")
    assert usd["hair"].shape == (3, 16, 12, 3)
    assert usd["body_vertices"].shape[0] == 3
    assert usd["fps"] == 60.0
    record = json.loads((out / "simulate_metrics.json").read_text())
    assert len(record["result"]["penetration_percent"]) == 3
    from PIL import Image

    with Image.open(out / "simulate.gif") as gif:
        assert gif.n_frames == 3


def test_simulate_and_drape_against_the_physics(tmp_path, capsys):
    out = tmp_path / "sim"
    code, stdout, _ = _run(["simulate", *TINY, "--method", "rigid", "--pose", "nod", "--frames", "4", "--gif-frames",
                            "4", "--against", "physics", "--out", str(out)], capsys)
    assert code == 0
    for name in ("simulate_swing.png", "simulate_side_by_side.png", "simulate_side_by_side.gif"):
        assert (out / name).read_bytes()[:3] in (b"\x89PN", b"GIF"), name
    record = json.loads((out / "simulate_metrics.json").read_text())
    assert record["against"] == "physics"
    assert record["fidelity"]["physics"]["mean_distance_mm"] == pytest.approx(0.0, abs=1e-6)
    assert record["fidelity"]["rigid"]["swing_mm"] == pytest.approx(0.0, abs=1e-6)
    assert record["fidelity"]["rigid"]["largest_step_mm"] == pytest.approx(0.0, abs=1e-6)
    assert record["fidelity"]["physics"]["largest_step_mm"] == record["fidelity"]["physics"]["physics_largest_step_mm"]
    assert "swing correlation" in stdout and "largest move a frame [mm]" in stdout
    out = tmp_path / "drape"
    code, stdout, _ = _run(["drape", *TINY, "--method", "rigid", "--against", "physics", "--out", str(out)], capsys)
    assert code == 0 and (out / "drape_side_by_side.png").read_bytes()[:4] == b"\x89PNG"
    record = json.loads((out / "drape_metrics.json").read_text())
    assert record["fidelity"]["physics"]["energy_ratio"] == pytest.approx(1.0)
    assert record["fidelity"]["rigid"]["energy_ratio"] >= 1.0 - 1e-6
    assert "E / E*" in stdout


@pytest.fixture(scope="module")
def small_data(tmp_path_factory):
    """A .data file of 8 strands x 6 vertices in metres (what `hairwarp drape` writes)."""
    rng = np.random.default_rng(0)
    strands = np.cumsum(rng.normal(scale=0.01, size=(8, 6, 3)), axis=1).astype(np.float32)
    strands += np.array([0.0, 1.6, 0.0], dtype=np.float32)
    path = tmp_path_factory.mktemp("data") / "hair.data"
    write_hair_data(path, strands)
    return path, strands


def test_export_data_to_usda_round_trip(small_data, tmp_path, capsys):
    path, strands = small_data
    usda = tmp_path / "hair.usda"
    assert _run(["export", str(path), str(usda)], capsys)[0] == 0
    back = read_usd(usda)["hair"]
    assert back.shape == (1, 8, 6, 3)
    np.testing.assert_array_equal(back[0].numpy(), strands)
    # And back again to .data.
    again = tmp_path / "again.data"
    assert _run(["export", str(usda), str(again)], capsys)[0] == 0
    np.testing.assert_array_equal(np.stack(read_hair_data(again)), strands)


def test_export_obj_ply_and_body(small_data, tmp_path, capsys):
    path, strands = small_data
    obj, ply = tmp_path / "hair.obj", tmp_path / "hair.ply"
    assert _run(["export", str(path), str(obj)], capsys)[0] == 0
    assert _run(["export", str(path), str(ply)], capsys)[0] == 0
    assert obj.stat().st_size > 0
    np.testing.assert_array_equal(read_hair_ply(ply).numpy(), strands)
    # A USD with a body: the body frame goes to .obj, every frame to numbered files.
    usd = tmp_path / "with_body.usda"
    from hairwarp.io.usd import write_usd

    verts = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float32)
    faces = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=torch.int32)
    hair = torch.as_tensor(np.stack([strands, strands + 0.01]))
    write_usd(usd, hair, torch.stack([verts, verts + 0.5]), faces, fps=30)
    body = tmp_path / "body.obj"
    assert _run(["export", str(usd), str(tmp_path / "f1.ply"), "--frame", "1", "--body-out", str(body)], capsys)[0] == 0
    np.testing.assert_allclose(read_obj(body)["vertices"].numpy(), (verts + 0.5).numpy(), atol=_EXACT)
    np.testing.assert_array_equal(read_hair_ply(tmp_path / "f1.ply").numpy(), hair[1].numpy())
    folder = tmp_path / "frames"
    assert _run(["export", str(usd), str(folder), "--all-frames", "--format", "obj"], capsys)[0] == 0
    assert sorted(os.listdir(folder)) == ["body_0000.obj", "body_0001.obj", "hair_0000.obj", "hair_0001.obj"]


def _bad(argv, capsys, *, needle: str, code: int = 1):
    """Runs a failing command; checks the exit code and a one-line message naming `needle`."""
    got, out, err = _run(argv, capsys)
    assert got == code, (got, err)
    lines = [line for line in err.strip().splitlines() if line]
    assert len(lines) == 1, err
    assert needle in lines[0], lines[0]
    assert "Traceback" not in err


def test_bad_inputs_give_one_line(tmp_path, capsys):
    missing = str(tmp_path / "nope.data")
    _bad(["drape", "--hairstyle", missing, "--out", str(tmp_path)], capsys, needle="--hairstyle")
    _bad(["drape", "--hairstyle", "mohawk", "--out", str(tmp_path)], capsys, needle="--hairstyle")
    _bad(["drape", "--body", str(tmp_path / "nobody.npz"), "--out", str(tmp_path)], capsys, needle="--body")
    _bad(["drape", *TINY, "--pose", "moonwalk", "--out", str(tmp_path)], capsys, needle="--pose")
    _bad(["drape", *TINY, "--pose", "nod", "--frame", "100000", "--out", str(tmp_path)], capsys, needle="--frame")
    _bad(["drape", *TINY, "--method", "rigid", "--checkpoint", str(tmp_path / "no.pt"), "--out", str(tmp_path)],
         capsys, needle="--checkpoint")
    _bad(["simulate", *TINY, "--strand-stride", "0", "--out", str(tmp_path)], capsys, needle="--strand-stride")
    _bad(["export", missing, str(tmp_path / "x.usda")], capsys, needle="input")
    _bad(["demo", "--hairstyle", "mohawk", "--out", str(tmp_path)], capsys, needle="--hairstyle")


def test_unknown_method_is_a_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["drape", "--method", "magic", "--out", str(tmp_path)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--method" in err and "Traceback" not in err


def test_malformed_data_file(tmp_path, capsys):
    bad = tmp_path / "bad.data"
    bad.write_bytes(b"\x05\x00\x00\x00\x03\x00")  # 5 strands declared, 2 bytes follow
    _bad(["drape", "--hairstyle", str(bad), "--out", str(tmp_path)], capsys, needle="--hairstyle")
    _bad(["export", str(bad), str(tmp_path / "x.usda")], capsys, needle="input")


@pytest.mark.slow
def test_debug_shows_the_traceback(tmp_path):
    # In a subprocess: --debug re-raises, so the interpreter prints the traceback and exits 1.
    cmd = [sys.executable, "-m", "hairwarp.cli", "--debug", "export", str(tmp_path / "nope.data"),
           str(tmp_path / "x.usda")]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert result.returncode == 1
    assert "Traceback" in result.stderr and "input: no such file" in result.stderr
