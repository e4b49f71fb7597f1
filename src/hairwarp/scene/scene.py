"""A scene: body + hairstyle + motion, and what each frame hands to the physics.

Data flows one way: scene -> rigid placement (Eq. 1) -> a method proposes hair positions ->
the energy (Eq. 5/6) scores them. `Scene.frames(...)` does the first step for a batch of frames
and returns everything a method or the energy needs, on one device, with the body cropped to
the triangles the hair can reach (`BodyMesh.crop_for_hair`: provably the same contact result).

The posed bodies' `BodyMesh` (cut where the body passes through itself, cropped, its trees) is
what a frame costs in memory: it is built at its first use, and whatever runs over a motion
frame by frame (metrics, the static methods, "auto"'s check) takes `SceneFrames.chunks()`:
at most `FRAME_CHUNK` frames whose body is built for them alone and dropped after them, so
memory stays flat in the motion's length.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace

import torch

from hairwarp.energy import EnergyInputs
from hairwarp.scene.body import Body, PosedBody, default_body
from hairwarp.scene.guides import GuideSet
from hairwarp.scene.hairstyles import Hairstyle, generate_hairstyle
from hairwarp.scene.motion import Motion, procedural_motion
from hairwarp.scene.placement import RigidHair, rigid_placement, root_search
from hairwarp.scene.scalp import Scalp, build_scalp

# Frames per chunk of `SceneFrames.chunks`: the bodies of this many frames are held at once. On
# the body of 49 overlapping primitives (600 strands x 100) a frame's body and L-BFGS
# drape hold about 60 MB while they last (docs/contact.md 18); a motion of at most this many
# frames is one chunk, evaluated exactly as before.
FRAME_CHUNK = 16

# The poses a body moved in place through a motion is split at (`Scene.moving_body`,
# `BodyMesh(split_poses=...)`): every SPLIT_POSE_STRIDE-th frame and the last, at most
# SPLIT_POSES_MAX of them (evenly thinned). Crossings come and go with the limbs' swing over
# tenths of a second; 0 splits at the first frame alone (the body of a walk then missed the arm
# crossing the chest, and the physics flung the hair pinched there at up to 8.8 m/s;
# docs/physics.md, "Twenty-third session"). The search costs ~55 ms a pose on a 2-core CPU.
SPLIT_POSE_STRIDE = 4
SPLIT_POSES_MAX = 64


class _LazyBody:
    """The `BodyMesh` of a batch of frames, built at its first use by `recipe(vertices, roots)`
    (None: frames without a body), and the frames' `EnergyInputs` around it. A `SceneFrames`
    and its copies (`dataclasses.replace`) share one, so the body is built once.
    """

    def __init__(self, recipe: Callable | None, vertices: torch.Tensor, roots: torch.Tensor, inputs: EnergyInputs):
        self.recipe, self.vertices, self.roots, self.bare_inputs = recipe, vertices, roots, inputs
        self._body, self._inputs = None, None

    def body(self):
        if self._body is None and self.recipe is not None:
            self._body = self.recipe(self.vertices, self.roots)
        return self._body

    def inputs(self) -> EnergyInputs:
        if self._inputs is None:
            self._inputs = replace(self.bare_inputs, body=self.body())
        return self._inputs

    @property
    def built(self) -> bool:
        return self._body is not None

    def select(self, rows, inputs: EnergyInputs) -> _LazyBody:
        """The same recipe for the frames `rows` (a slice or indices) alone: their own body, not built yet."""
        return _LazyBody(self.recipe, self.vertices[rows], self.roots[rows], inputs)


@dataclass(eq=False)
class SceneFrames:
    """A batch of B frames of a scene, ready for a method and the energy.

    Attributes:
        frame_indices: (B,) the motion frames.
        posed: the posed bodies (vertices (B, V, 3), M_head (B, 4, 4)).
        rigid: the rigid placement (positions (B, M, N, 3), normals (B, M, 3)).
        betas: (B, 16) body shapes; poses: (B, 66) body poses (the networks' inputs).
        scene: the `Scene` these frames come from (methods read its hairstyle and motion).
        body_mesh: `hairwarp.ops.BodyMesh` of the B posed bodies, cropped to the hair's reach;
            built at the first use (None for frames made with `build_body=False`). For many
            frames, go through `chunks()` instead: it holds a few frames' bodies at a time.
        inputs: the `EnergyInputs` of these frames (no previous states; its body `body_mesh`).
    """

    frame_indices: torch.Tensor
    posed: PosedBody
    rigid: RigidHair
    betas: torch.Tensor
    poses: torch.Tensor
    scene: Scene | None = None
    _body: _LazyBody = field(kw_only=True, repr=False)

    @property
    def body_mesh(self):
        return self._body.body()

    @property
    def inputs(self) -> EnergyInputs:
        return self._body.inputs()

    @property
    def num_frames(self) -> int:
        return int(self.frame_indices.numel())

    def select(self, rows) -> SceneFrames:
        """The frames at positions `rows` of this batch (a slice, or indices in increasing
        order), with a body of their own built at its first use; these frames themselves when
        `rows` takes them all in order.
        """
        if not isinstance(rows, slice):
            rows = torch.as_tensor(rows, dtype=torch.long).reshape(-1).cpu()
        positions = torch.arange(self.num_frames)[rows]
        if positions.numel() == 0:
            raise ValueError("rows: expected at least one frame")
        if torch.equal(positions, torch.arange(self.num_frames)):
            return self
        # A slice takes views; indices go to the tensors' device.
        on = rows if isinstance(rows, slice) else rows.to(self.rigid.positions.device)
        posed = PosedBody(vertices=self.posed.vertices[on],
                          joints=None if self.posed.joints is None else self.posed.joints[on],
                          head_transform=self.posed.head_transform[on])
        rigid = RigidHair(*(t[on] for t in (self.rigid.positions, self.rigid.normals, self.rigid.align,
                                             self.rigid.root_offsets)))
        bare = replace(self._body.bare_inputs, rigid=rigid.positions, scalp_normals=rigid.normals)
        return SceneFrames(self.frame_indices[positions], posed, rigid, self.betas[on], self.poses[on],
                           scene=self.scene, _body=self._body.select(on, bare))

    def triangles_within_reach(self) -> int:
        """How many of the body's triangles the hair can reach in some of these frames: those
        `BodyMesh.crop_for_hair` keeps of the uncut posed bodies (what the commands' scene line
        counts; no self-intersection search and no tree is built for it).
        """
        from hairwarp.ops import BodyMesh

        vertices = self.posed.vertices
        body = BodyMesh(vertices, self.scene.body.faces.to(device=vertices.device, dtype=torch.int32),
                        split_self_intersections=False)
        reach = self.scene.strand_lengths.to(device=vertices.device, dtype=vertices.dtype)
        return body.crop_for_hair(self.rigid.positions[:, :, 0], reach).source_triangle_count

    def chunks(self, size: int | None = None) -> Iterator[SceneFrames]:
        """These frames in consecutive groups of at most `size` (default `FRAME_CHUNK`), each
        with a body of its own built at its first use, to be dropped before the next: what runs
        over many frames one frame at a time holds a few frames' bodies, not all. A batch of at
        most `size` frames, or one whose body is built already (and held anyway), is one group:
        these frames themselves.
        """
        size = FRAME_CHUNK if size is None else int(size)
        if size < 1:
            raise ValueError(f"size: expected a positive number of frames, got {size}")
        if self._body.built:
            yield self
            return
        for start in range(0, self.num_frames, size):
            yield self.select(slice(start, start + size))


@dataclass(eq=False)
class Scene:
    """Body, hairstyle and motion of one scene.

    Attributes:
        body: the body model.
        scalp: the scalp grid the hairstyle grows from.
        hairstyle: rest-pose strands (M, N, 3) [m] with root UVs.
        motion: poses (T, 66), trans (T, 3), betas (16,), fps. A static scene is a motion of
            one frame.
        name: a label.
        guides: for a groom simulated through guide strands, the `GuideSet` (its whole groom
            and how each strand follows the guides); `hairstyle` then holds the guides only,
            what every method runs on. None: the hairstyle is simulated whole.
    """

    body: Body
    scalp: Scalp
    hairstyle: Hairstyle
    motion: Motion
    name: str = ""
    guides: GuideSet | None = None

    def __post_init__(self):
        strands = self.hairstyle.strands
        self._rest_lengths = (strands[:, 1:] - strands[:, :-1]).norm(dim=-1)
        self._strand_lengths = self._rest_lengths.sum(dim=1)
        if self.guides is not None:
            if self.guides.num_guides != self.hairstyle.num_strands:
                raise ValueError(f"guides: {self.guides.num_guides} guides for a hairstyle of "
                                 f"{self.hairstyle.num_strands} strands")
            # The body crop must keep what the followers reach, not only the guides.
            self._strand_lengths = torch.maximum(self._strand_lengths, self.guides.reach_lengths())
        self._search = None
        self._cache = {}

    @property
    def num_frames(self) -> int:
        return self.motion.num_frames

    @property
    def num_strands(self) -> int:
        """Strands of the whole groom (the guides' count when there are no followers)."""
        return self.hairstyle.num_strands if self.guides is None else self.guides.num_strands

    def full_groom(self, positions: torch.Tensor, frames: SceneFrames, *, body_pass: bool = True,
                   guide_signed_distance: torch.Tensor | None = None) -> tuple[torch.Tensor, dict]:
        """Every strand of the groom from the guides' positions on `frames` (`GuideSet.follow`).

        Args:
            positions: (B, K, N, 3) the guides in the B frames of `frames` [m].
            frames: the frames (`Scene.frames`), for the head's rotation and the body.
            body_pass: keep the followers out of the body (False for the rigid placement).
            guide_signed_distance: (B, K, N) the guides' signed distances [m], if known.

        Returns:
            ((B, M, N, 3) [m], the body pass's facts); without guides, `positions` itself.
        """
        if self.guides is None:
            return positions, {}
        body = frames.body_mesh if body_pass else None
        return self.guides.follow(positions, frames.posed.head_transform[:, :3, :3], body,
                                  guide_signed_distance=guide_signed_distance)

    @property
    def rest_lengths(self) -> torch.Tensor:
        """(M, N-1) rest segment lengths of P_init [m] (Eq. 7)."""
        return self._rest_lengths

    @property
    def strand_lengths(self) -> torch.Tensor:
        """(M,) rest arc length of each strand [m]."""
        return self._strand_lengths

    def _on(self, device: torch.device, dtype: torch.dtype):
        key = (str(device), dtype)
        if key not in self._cache:
            strands = self.hairstyle.strands.to(device=device, dtype=dtype)
            self._cache[key] = {
                "strands": strands,
                "root_uv": self.hairstyle.root_uv.to(device),
                "rest_lengths": self._rest_lengths.to(device=device, dtype=dtype),
                "strand_lengths": self._strand_lengths.to(device=device, dtype=dtype),
                "search": None,
            }
        return self._cache[key]

    def _frame_indices(self, indices) -> torch.Tensor:
        if indices is None:
            indices = torch.arange(self.num_frames)
        indices = torch.as_tensor(indices, dtype=torch.long).reshape(-1)
        if indices.numel() == 0:
            raise ValueError("indices: expected at least one frame")
        if int(indices.min()) < 0 or int(indices.max()) >= self.num_frames:
            raise ValueError(f"indices: frames must lie in [0, {self.num_frames}), got {indices.tolist()}")
        return indices

    def posed_body(self, indices=None, *, device="cpu", dtype=torch.float32):
        """The body posed at frames `indices` (default: all): a `PosedBody` with vertices (B, V, 3)
        [m], no hair placed (`frames` places it).

        Raises:
            ValueError: no frame, a frame outside the motion, or a mesh body whose frames are not
                the motion's.
        """
        device = torch.device(device)
        indices = self._frame_indices(indices)
        poses = self.motion.poses[indices].to(device=device, dtype=dtype)
        trans = self.motion.trans[indices].to(device=device, dtype=dtype)
        betas = self.motion.betas.to(device=device, dtype=dtype).expand(len(indices), -1)
        # A model with fewer shape coefficients than the motion carries takes the first ones (as
        # SMPL readers do; `hairwarp.builder` says so once); one with more reads the rest as zero.
        if self.body.has_smpl_pose:
            return self.body.pose(betas=betas[:, : self.body.num_betas], poses=poses, trans=trans)
        # a mesh body plays its own frames (the motion only counts them and gives the rate)
        if self.body.num_frames != self.num_frames:
            raise ValueError(f"body: the mesh has {self.body.num_frames} frames, the motion {self.num_frames}")
        posed = self.body.pose(frames=indices)
        return type(posed)(vertices=posed.vertices.to(device=device, dtype=dtype), joints=None,
                           head_transform=posed.head_transform.to(device=device, dtype=dtype))

    def moving_body(self, indices=None, *, device="cpu", dtype=torch.float32, bvh: str = "sah",
                    split_self_intersections: bool = True):
        """One `BodyMesh` for frames `indices` (default: all), built at the first of them, to be
        moved frame by frame with `BodyMesh.update(posed_body(i).vertices)` (a refit, no
        rebuild): what a method stepping through a motion queries, where a batched body holds
        every frame at once. Not cropped (no crop of one pose is sure to hold the triangles
        another pose brings within reach). Cut where the body passes through itself at the first
        frame or at any of every `SPLIT_POSE_STRIDE`-th frame and the last (`BodyMesh(split_poses=...)`):
        `update` moves the cuts and finds no new crossing.

        Args:
            indices: frame indices the body will move through (int, sequence or tensor).
            device, dtype: of the vertices.
            bvh: "sah" or "lbvh" (`BodyMesh`).
            split_self_intersections: cut the body where it passes through itself (False: the
                uncut surface).

        Returns:
            a `hairwarp.ops.BodyMesh` of batch 1 ((1, V, 3) vertices), posed at the first frame.
        """
        from hairwarp.ops import BodyMesh

        device = torch.device(device)
        indices = self._frame_indices(indices).tolist()
        first = self.posed_body(indices[:1], device=device, dtype=dtype).vertices
        split_poses = None
        if split_self_intersections and len(indices) > 1 and SPLIT_POSE_STRIDE > 0:
            sampled = indices[SPLIT_POSE_STRIDE::SPLIT_POSE_STRIDE]
            if not sampled or sampled[-1] != indices[-1]:
                sampled.append(indices[-1])
            step = max(1, math.ceil(len(sampled) / SPLIT_POSES_MAX))
            split_poses = self.posed_body(sampled[::step], device=device, dtype=dtype).vertices
        faces = self.body.faces.to(device=device, dtype=torch.int32)
        return BodyMesh(first, faces, bvh=bvh, split_self_intersections=split_self_intersections,
                        split_poses=split_poses)

    def frames(self, indices=None, *, device="cpu", dtype=torch.float32, crop: bool = True,
               split_self_intersections: bool = True, build_body: bool = True) -> SceneFrames:
        """Pose the body and place the hair rigidly (Eq. 1) for a batch of frames.

        Args:
            indices: frame indices (int, sequence or tensor); None for all frames.
            device: torch device of every output.
            dtype: float32 (default) or float64.
            crop: crop the body mesh to the triangles the hair can reach (no change to any
                contact result, fewer triangles to query).
            split_self_intersections: query the posed body as the union of its parts where it
                passes through itself (`BodyMesh`; the default body's arms enter its chest at the
                armpits, and the uncut surface calls points up to 9 cm inside the chest outside).
                The search costs ~55 ms per pose on a 2-core CPU (the head turn's 241 frames:
                20-23 s against 6-7 s uncut; docs/contact.md 16); False keeps the uncut surface.
            build_body: give the frames a `BodyMesh` (built at its first use, `SceneFrames`);
                False leaves `body_mesh` and `inputs.body` None (a caller that moves one body
                of its own, as the physics solver does, needs only `posed.vertices`).

        Returns:
            SceneFrames.
        """
        device = torch.device(device)
        indices = self._frame_indices(indices)
        cache = self._on(device, dtype)
        posed = self.posed_body(indices, device=device, dtype=dtype)
        if cache["search"] is None:
            cache["search"] = root_search(self.body, cache["strands"][:, 0])
        rigid = rigid_placement(cache["strands"], posed, self.body, scalp=self.scalp,
                                root_uv=cache["root_uv"], search=cache["search"])
        inputs = EnergyInputs(rest_lengths=cache["rest_lengths"], rigid=rigid.positions,
                              scalp_normals=rigid.normals, body=None)
        recipe = None
        if build_body:
            faces = self.body.faces.to(device=device, dtype=torch.int32)

            def recipe(vertices: torch.Tensor, roots: torch.Tensor):
                from hairwarp.ops import BodyMesh

                # The full body is only cropped (its tree, built at a first query, is never
                # built), the crop is queried (the better tree).
                body = BodyMesh(vertices.to(dtype), faces, bvh="lbvh" if crop else "sah",
                                split_self_intersections=split_self_intersections)
                return body.crop_for_hair(roots, cache["strand_lengths"], bvh="sah") if crop else body

        body = _LazyBody(recipe, posed.vertices, rigid.positions[:, :, 0], inputs)
        poses = self.motion.poses[indices].to(device=device, dtype=dtype)
        betas = self.motion.betas.to(device=device, dtype=dtype).expand(len(indices), -1)
        return SceneFrames(indices, posed, rigid, betas, poses, scene=self, _body=body)


def static_motion(poses: torch.Tensor | None = None, betas: torch.Tensor | None = None, name: str = "rest") -> Motion:
    """A one-frame 'motion' holding a single pose (rest pose by default)."""
    poses = torch.zeros(1, 66) if poses is None else torch.as_tensor(poses, dtype=torch.float32).reshape(1, 66)
    betas = torch.zeros(16) if betas is None else torch.as_tensor(betas, dtype=torch.float32).reshape(16)
    return Motion(poses=poses, trans=torch.zeros(1, 3), betas=betas, fps=60.0, name=name)


def preset_hairstyle(name: str, body: Body, scalp: Scalp, *, seed: int = 0, grow_around_body: bool = False,
                     strand_stride: int = 1, num_vertices: int = 100) -> Hairstyle:
    """A procedural preset grown on a body's scalp (one root in `strand_stride`).

    Args:
        name: a preset name (`hairwarp.scene.hairstyles.list_hairstyle_presets()`).
        body, scalp: the body and its scalp.
        seed: seed of the hairstyle's randomness.
        grow_around_body: grow the strands around the rest body, so long hair falls over the
            shoulders and back instead of through them (about 2-3 s more on the CPU for 1024
            strands); else around the head proxy alone.
        strand_stride: grow on one root in this many only, spread over the whole scalp
            (`Scalp.every`; 1: all 1024; 2: 512; 4: 256; 16: 64). The hairstyle is grown on
            that sparser scalp, so it is close to, not a subset of, the full one.
        num_vertices: vertices per strand N (100 in the paper), >= 3.
    """
    from hairwarp.scene.hairstyles import hairstyle_preset

    if not isinstance(strand_stride, int) or isinstance(strand_stride, bool) or strand_stride < 1:
        raise ValueError(f"strand_stride: expected a positive int, got {strand_stride!r}")
    if not isinstance(num_vertices, int) or isinstance(num_vertices, bool) or num_vertices < 3:
        raise ValueError(f"num_vertices: expected an int >= 3, got {num_vertices!r}")
    surface = (body.rest_vertices, body.faces) if grow_around_body else None
    style = generate_hairstyle(scalp.every(strand_stride), hairstyle_preset(name, seed=seed),
                               num_vertices=num_vertices, body=surface)
    style.name = name
    return style


def default_scene(hairstyle: str = "long_straight", motion: str | None = None, *, seed: int = 0,
                  duration: float | None = None, grow_around_body: bool = False, strand_stride: int = 1,
                  num_vertices: int = 100) -> Scene:
    """The embedded default: default body, a procedural hairstyle, a procedural motion.

    Args:
        hairstyle: a preset name (`hairwarp.scene.hairstyles.list_hairstyle_presets()`).
        motion: a procedural motion name (`hairwarp.scene.motion.list_motions()`), or None for
            the rest pose (one frame).
        seed: seed of the hairstyle's randomness.
        duration: motion length [s] (None: the motion's natural length).
        grow_around_body, strand_stride, num_vertices: see `preset_hairstyle`.

    Returns:
        Scene; nothing is downloaded.
    """
    body = default_body()
    scalp = build_scalp(body)
    style = preset_hairstyle(hairstyle, body, scalp, seed=seed, grow_around_body=grow_around_body,
                             strand_stride=strand_stride, num_vertices=num_vertices)
    mot = static_motion() if motion is None else procedural_motion(motion, duration=duration)
    return Scene(body=body, scalp=scalp.every(strand_stride), hairstyle=style, motion=mot,
                 name=f"{hairstyle}/{motion or 'rest'}")
