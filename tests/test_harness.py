"""The speed-versus-accuracy harness, its JSON and markdown, the chart and `hairwarp compare`."""

import json

import pytest
import torch

from hairwarp.config import EnergyConfig
from hairwarp import methods
from hairwarp.evaluation import harness
from hairwarp.evaluation.charts import speed_accuracy_chart
from hairwarp.methods import Method, MethodOptions, MethodResult
from hairwarp.evaluation.scenes import comparison_scene

_SIZE = {"strand_stride": 32, "num_vertices": 10}
# The quartic barrier: on strands of 10 vertices the default quadratic one lets 15 L-BFGS
# iterations end above the rigid penetration (see tests/test_direct.py).
_OPTIONS = dict(max_iterations=15, patience=50, record_every=5, reference_max_iterations=40,
                energy_config=EnergyConfig(barrier_variant="monotone"))


@pytest.fixture(scope="module")
def record():
    return harness.run_comparison("rigid,adam,lbfgs,reference", ["table1"], options=MethodOptions(**_OPTIONS),
                                  command_line="test", **_SIZE)


def test_results_schema(record):
    assert record["schema"] == harness.RESULTS_SCHEMA
    for key in ("machine", "sizes", "scenes_version", "command_line", "options", "created", "seed"):
        assert key in record
    assert record["machine"]["device"] == "cpu" and record["machine"]["device_name"]
    (entry,) = record["scenes"]
    assert entry["name"] == "table1" and entry["size"]["vertices"] == 10
    rows = {r["method"]: r for r in entry["results"]}
    assert list(rows) == ["rigid", "adam", "lbfgs", "reference"]
    assert rows["rigid"]["time_ms"] is None and rows["rigid"]["energy_gap"] == pytest.approx(1.0)
    assert rows["reference"]["energy_gap"] == pytest.approx(0.0, abs=1e-9)
    assert 0.0 < rows["lbfgs"]["energy_gap"] < 1.0
    assert rows["lbfgs"]["penetration_percent"] < rows["rigid"]["penetration_percent"]
    for name in ("adam", "lbfgs"):
        r = rows[name]
        assert r["time_ms"] > 0 and r["finite"]
        assert [h["iteration"] for h in r["history"] if "penetration" in h][:3] == [0, 5, 10]
        assert r["history"][0]["energy_gap"] == pytest.approx(1.0, rel=1e-4)
    assert rows["reference"]["time_ms"] > 0 and rows["reference"]["finite"]
    # Shape against the optimum: the optimum against itself is ratio 1 at distance 0.
    assert rows["reference"]["energy_ratio"] == pytest.approx(1.0)
    assert rows["reference"]["mean_distance_mm"] == pytest.approx(0.0, abs=1e-9)
    assert rows["rigid"]["energy_ratio"] > 1.0 and rows["rigid"]["mean_distance_mm"] > 0.0
    assert rows["lbfgs"]["p95_distance_mm"] >= rows["lbfgs"]["mean_distance_mm"]
    json.dumps(record, allow_nan=False)


def test_json_markdown_and_chart(record, tmp_path):
    path = harness.write_results(record, str(tmp_path / "r.json"))
    assert json.load(open(path))["scenes"][0]["name"] == "table1"
    table = harness.markdown_tables(record)
    assert "| method | ms/drape | penetration % | length change % | E / E* |" in table
    assert all(f"| {m} |" in table for m in ("rigid", "adam", "lbfgs", "reference"))
    png = speed_accuracy_chart(record, str(tmp_path / "chart.png"))
    data = open(png, "rb").read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    with pytest.raises(ValueError, match="path"):
        speed_accuracy_chart(record, str(tmp_path / "chart.jpg"))


def test_unknown_names_are_clear_errors():
    with pytest.raises(ValueError, match="methods: unknown \\['nope'\\]"):
        harness.run_comparison("rigid,nope", "table1", **_SIZE)
    with pytest.raises(ValueError, match="scenes"):
        harness.run_comparison("rigid", "table9", **_SIZE)
    with pytest.raises(ValueError, match="methods"):
        harness.run_comparison("", "table1", **_SIZE)


class _Spy(Method):
    seen = []

    def drape(self, frames, *, metrics=None):
        _Spy.seen.append((self.name, id(frames), frames.rigid.positions.clone()))
        return MethodResult(positions=frames.rigid.positions.clone(), time_ms=1.0)


class _Mutator(Method):
    def drape(self, frames, *, metrics=None):
        frames.rigid.positions.add_(1e-3)
        return MethodResult(positions=frames.rigid.positions.clone(), time_ms=1.0)


@pytest.fixture
def spies():
    def make(name, cls):
        def factory(options):
            m = cls(options)
            m.name = name
            return m
        return factory

    methods.register("spy_a", make("spy_a", _Spy), overwrite=True)
    methods.register("spy_b", make("spy_b", _Spy), overwrite=True)
    methods.register("mutator", make("mutator", _Mutator), overwrite=True)
    _Spy.seen.clear()
    yield
    for name in ("spy_a", "spy_b", "mutator"):
        methods.unregister(name)


def test_methods_see_identical_inputs(spies):
    harness.run_comparison("spy_a,spy_b", "medium_poses", **_SIZE)
    (a, id_a, xa), (b, id_b, xb) = _Spy.seen
    assert (a, b) == ("spy_a", "spy_b") and id_a == id_b and torch.equal(xa, xb)
    assert xa.shape[0] == 3  # medium_poses: three drapes in one batch


def test_a_method_changing_the_inputs_is_caught(spies):
    with pytest.raises(RuntimeError, match="mutator"):
        harness.run_comparison("spy_a,mutator", "table1", **_SIZE)


class _Offset(Method):
    """A 'simulation' that is the rigid placement shifted by 1 mm along x."""

    def __init__(self, options=None, offset=0.0):
        super().__init__(options)
        self.offset = offset

    def simulate(self, frames):
        x = frames.rigid.positions.clone()
        x[..., 0] += self.offset
        return MethodResult(positions=x, time_ms=2.0)


def test_motion_metrics_against_the_reference():
    scene = comparison_scene("whiplash", **_SIZE)
    frames = scene.frames([0, 1, 2, 3])
    rows, plot = harness._run_motion(scene, frames, {"reference": _Offset(), "shifted": _Offset(offset=1e-3)},
                                     lambda *_: None)
    ref, shifted = rows
    assert plot is None  # no plots_dir
    # Against the physics: 1 mm everywhere, and a constant offset is no swing.
    assert ref["physics"] == "reference" and ref["mean_distance_mm"] == pytest.approx(0.0, abs=1e-9)
    assert shifted["mean_distance_mm"] == pytest.approx(1.0, rel=1e-3)
    assert shifted["max_distance_mm"] == pytest.approx(1.0, rel=1e-3)
    assert shifted["swing_mm"] == pytest.approx(0.0, abs=1e-3) and shifted["swing_correlation"] is None
    assert ref["distance_mean_m"] == pytest.approx(0.0) and ref["jitter_m"] == pytest.approx(0.0, abs=1e-9)
    assert shifted["distance_mean_m"] == pytest.approx(1e-3, rel=1e-4)
    assert shifted["distance_max_m"] == pytest.approx(1e-3, rel=1e-4)
    assert len(shifted["distance_mean_per_frame_m"]) == 4
    assert shifted["jitter_m"] == pytest.approx(0.0, abs=1e-7)  # a constant offset does not jitter
    assert shifted["time_ms"] == 2.0 and shifted["penetration_percent"] is not None


def test_compare_command(tmp_path, capsys):
    from hairwarp.cli import main

    out = tmp_path / "cmp"
    code = main(["compare", "--methods", "rigid,lbfgs,reference", "--scenes", "table1", "--strand-stride", "32",
                 "--num-vertices", "8", "--max-iterations", "5", "--reference-max-iterations", "10",
                 "--reference-starts", "2", "--record-every", "2", "--out", str(out), "--quiet"])
    assert code == 0
    record = json.load(open(out / "compare.json"))
    assert record["options"]["reference_starts"] == 2
    assert len(record["scenes"][0]["results"][2]["info"]["start_energies"]) == 2
    assert [r["method"] for r in record["scenes"][0]["results"]] == ["rigid", "lbfgs", "reference"]
    assert record["command_line"].startswith("hairwarp")
    assert (out / "compare.md").read_text().count("| lbfgs |") == 1
    assert (out / "speed_accuracy.png").read_bytes()[:4] == b"\x89PNG"
    assert main(["compare", "--methods", "rigid,nope", "--out", str(out), "--quiet"]) == 1
    assert "--methods: unknown" in capsys.readouterr().err
    assert main(["compare", "--strand-stride", "0", "--out", str(out), "--quiet"]) == 1
    assert "--strand-stride" in capsys.readouterr().err
    assert main(["compare", "--reference-starts", "0", "--out", str(out), "--quiet"]) == 1
    assert "--reference-starts" in capsys.readouterr().err


def test_motion_rows_against_the_physics_and_the_swing_plot(tmp_path):
    from hairwarp.methods import MethodOptions
    from hairwarp.methods.optimizers import PhysicsMethod, RigidMethod
    from hairwarp.solvers.physics import PhysicsConfig

    scene = comparison_scene("whiplash", **_SIZE)
    frames = scene.frames(list(range(12, 20)))
    methods = {"rigid": RigidMethod(), "physics": PhysicsMethod(MethodOptions(), PhysicsConfig(max_iterations=12))}
    rows, plot = harness._run_motion(scene, frames, methods, lambda *_: None, str(tmp_path))
    rigid, physics = rows
    assert physics["physics"] == "physics" and physics["mean_distance_mm"] == pytest.approx(0.0, abs=1e-9)
    assert physics["swing_correlation"] == pytest.approx(1.0) and physics["swing_amplitude_ratio"] == pytest.approx(1.0)
    assert physics["physics_swing_mm"] > 0.0  # the head whips: the hair swings beyond it
    assert rigid["swing_mm"] == pytest.approx(0.0, abs=1e-6) and rigid["swing_correlation"] is None
    assert rigid["mean_distance_mm"] > 0.0
    assert open(plot, "rb").read()[:4] == b"\x89PNG" and plot.endswith("swing_whiplash.png")
