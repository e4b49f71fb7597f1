"""Frames evaluated a chunk at a time (issue 30, item 5: memory flat in the number of frames).

`SceneFrames.chunks()` hands out at most `FRAME_CHUNK` frames with a body of their own, built at
its first use; the metrics, the static methods' `simulate` and "auto"'s check go through it. A
motion of at most `FRAME_CHUNK` frames is one chunk (the frames themselves); a longer one gives
the same figures as one evaluation of all its frames, up to the rounding of the cut body's
pieces (the pieces of a body that passes through itself are cut for the poses of a batch).
"""

from __future__ import annotations

import gc
import weakref

import pytest
import torch

import hairwarp as hw
from hairwarp.commands.common import describe
from hairwarp.config import EnergyConfig
from hairwarp.energy import total_energy
from hairwarp.methods import MethodOptions, make
from hairwarp.methods.base import MethodResult
from hairwarp.metrics import frame_metrics, frame_metrics_of, penetration_percent
from hairwarp.ops import BodyMesh
from hairwarp.scene import placement
from hairwarp.scene import scene as scene_module

# A signed distance on a body cut for other poses differs by the rounding of its pieces' corners
# (3.7e-9 m seen on the default body's armpits): far below a vertex's float32 spacing of ~1e-7 m.
_CUT_ROUNDING = 1e-6  # m
# Energies of a chunk against the whole batch: the contact terms' float32 sums, same rounding.
_ENERGY_RTOL = 1e-5
CHUNK = 3


@pytest.fixture(scope="module")
def scene():
    # Long hair on the default body: within reach of the armpits, where the body passes through itself.
    return hw.default_scene("long_straight", "head_turn", duration=0.1, strand_stride=64, num_vertices=8)


@pytest.fixture
def small_chunks(monkeypatch):
    monkeypatch.setattr(scene_module, "FRAME_CHUNK", CHUNK)


@pytest.fixture
def bodies_built(monkeypatch):
    """Each body built through the frames, as it is built: (its batch size, how many bodies built
    before it are still alive, a garbage collection done)."""
    built, refs = [], []
    original = scene_module._LazyBody.body

    def body(self):
        fresh = self._body is None and self.recipe is not None
        if fresh:
            gc.collect()
            alive = sum(r() is not None for r in refs)
        out = original(self)
        if fresh:
            built.append((out.batch_size, alive))
            refs.append(weakref.ref(out))
        return out

    monkeypatch.setattr(scene_module._LazyBody, "body", body)
    return built


def test_chunks_hand_out_at_most_k_frames_each_with_its_own_body(scene, bodies_built):
    frames = scene.frames()
    assert frames.num_frames == 7
    chunks = list(frames.chunks(CHUNK))
    assert [c.num_frames for c in chunks] == [3, 3, 1]
    assert torch.equal(torch.cat([c.frame_indices for c in chunks]), frames.frame_indices)
    for c, start in zip(chunks, (0, 3, 6)):
        rows = slice(start, start + c.num_frames)
        assert torch.equal(c.rigid.positions, frames.rigid.positions[rows])
        assert torch.equal(c.posed.vertices, frames.posed.vertices[rows])
        assert torch.equal(c.inputs.rigid, frames.rigid.positions[rows])
        assert c.body_mesh.batch_size == c.num_frames and c.scene is scene
    assert [size for size, _ in bodies_built] == [3, 3, 1]
    assert frames._body._body is None  # the whole batch's body was never built
    # A batch that fits in one chunk is that chunk, and shares its body; so is one whose body is built.
    assert list(frames.chunks(7)) == [frames]
    assert frames.select(slice(None)) is frames
    built = scene.frames([0, 1, 2, 3])
    assert built.body_mesh.batch_size == 4 and list(built.chunks(2)) == [built]
    with pytest.raises(ValueError, match="size"):
        next(frames.chunks(0))
    with pytest.raises(ValueError, match="rows"):
        frames.select([])


def test_the_rigid_placement_is_the_same_placed_a_frame_at_a_time(scene, monkeypatch):
    together = scene.frames(build_body=False).rigid
    monkeypatch.setattr(placement, "_CHUNK", 1)  # one frame per projection chunk
    apart = scene.frames(build_body=False).rigid
    for a, b in zip((together.positions, together.normals, together.root_offsets),
                    (apart.positions, apart.normals, apart.root_offsets)):
        assert torch.equal(a, b)


def test_metrics_in_chunks_equal_all_at_once_with_one_body_at_a_time(scene, small_chunks, bodies_built):
    whole = scene.frames()
    x = whole.rigid.positions + 0.01 * torch.randn(whole.rigid.positions.shape, generator=torch.Generator().manual_seed(0))
    config = EnergyConfig()
    with pytest.MonkeyPatch.context() as one_chunk:
        one_chunk.setattr(scene_module, "FRAME_CHUNK", 100)
        expected, expected_sd = frame_metrics(x, whole, config)
    assert bodies_built == [(7, 0)]
    assert max(expected["penetration_percent"]) > 0  # some vertices inside: the sign is tested
    del whole  # and its body
    bodies_built.clear()
    frames = scene.frames()
    scored = frame_metrics_of({"x": x, "rigid": frames.rigid.positions}, frames, config)
    found, sd = scored["x"]
    # One pass: one body per chunk for both labels, each built after the last one was dropped.
    assert bodies_built == [(3, 0), (3, 0), (1, 0)]
    assert frames._body._body is None
    assert found["penetration_percent"] == expected["penetration_percent"]
    assert found["length_change_percent"] == expected["length_change_percent"]
    torch.testing.assert_close(sd, expected_sd, rtol=0, atol=_CUT_ROUNDING)
    torch.testing.assert_close(torch.tensor(found["energy"]), torch.tensor(expected["energy"]), rtol=_ENERGY_RTOL,
                               atol=0)
    rigid_sd = scored["rigid"][1]
    assert rigid_sd.shape == sd.shape and not torch.equal(rigid_sd, sd)


def test_static_methods_simulate_a_chunk_at_a_time(scene, small_chunks, bodies_built):
    frames = scene.frames()
    rigid = make("rigid").simulate(frames)
    assert torch.equal(rigid.positions, frames.rigid.positions) and rigid.time_ms is None
    lbfgs = make("lbfgs", MethodOptions(max_iterations=2)).simulate(frames)
    assert lbfgs.positions.shape == frames.rigid.positions.shape
    assert [c["frames"] for c in lbfgs.info["chunks"]] == [[0, 2], [3, 5], [6, 6]]
    assert all(c["iterations"] == 2 for c in lbfgs.info["chunks"]) and lbfgs.time_ms > 0
    assert {h["chunk"] for h in lbfgs.history} == {0, 1, 2}
    assert max(size for size, _ in bodies_built) <= CHUNK and max(alive for _, alive in bodies_built) == 0
    # Each chunk is the drape of its frames alone.
    first = make("lbfgs", MethodOptions(max_iterations=2)).drape(frames.select(slice(0, 3)))
    assert torch.equal(lbfgs.positions[:3], first.positions)


def test_auto_redoes_the_frames_worse_than_rigid_chunk_by_chunk(scene, small_chunks):
    frames = scene.frames()
    rigid = frames.rigid.positions
    worse = [1, 4, 5]  # across two chunks
    positions = rigid.clone()
    # Crumpled: every moving vertex 2 cm off its strand, alternating sides (stretch, bending and
    # smoothness far above the rigid placement's, whatever contact the shift relieves)
    sides = torch.tensor([(-1.0) ** v for v in range(rigid.shape[2] - 2)])
    positions[worse, :, 2:, 0] += 0.02 * sides
    auto = make("auto", MethodOptions(max_iterations=5))
    result = auto._never_worse_than_rigid(MethodResult(positions=positions, time_ms=1.0), frames, 5, "test")
    assert result.info["fallback_frames"] == worse and result.info["chosen"] == "test"
    kept = [i for i in range(frames.num_frames) if i not in worse]
    assert torch.equal(result.positions[kept], rigid[kept])
    assert result.time_ms > 1.0
    with torch.no_grad():
        energy = total_energy(result.positions, frames.inputs, EnergyConfig()).total
        energy_rigid = total_energy(rigid, frames.inputs, EnergyConfig()).total
    pen, pen_rigid = (penetration_percent(x, frames.body_mesh) for x in (result.positions, rigid))
    bound = energy_rigid + _ENERGY_RTOL * energy_rigid.abs()  # the check's bodies are the chunks'
    assert bool((energy[worse] <= bound[worse]).all()) and bool((pen <= pen_rigid).all())


def test_the_scene_line_counts_the_bodys_own_triangles_within_reach(scene):
    frames = scene.frames()
    count = frames.triangles_within_reach()
    faces = scene.body.faces.to(torch.int32)
    uncut = BodyMesh(frames.posed.vertices, faces, split_self_intersections=False)
    kept = uncut.crop_for_hair(frames.rigid.positions[:, :, 0], scene.strand_lengths).face_indices
    assert count == kept.numel() == int(torch.unique(kept).numel())
    assert 0 < count < scene.body.num_faces
    assert frames.body_mesh.self_intersections["pieces"] > 0  # the cut body's pieces are not what is counted
    assert f"({count} of {scene.body.num_faces} triangles within the hair's reach)" in describe(scene, frames)
