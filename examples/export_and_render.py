"""Export a small hair motion to USD / OBJ / PLY and draw preview pictures of it.

    python examples/export_and_render.py --out ./hairwarp-out

A synthetic scene stands in for a simulation: a sphere "head" (radius 10 cm) with a few
hundred strands that follow it 1 cm out, then hang; a few strands are deliberately pushed
into the sphere so that the penetration colouring has something to show. The head sways
sideways and the hair follows with a lag that grows along each strand.

Writes into the output folder:
  drape.usda          the whole motion (hair BasisCurves + body Mesh, one sample a frame)
  hair.obj, hair.ply  the first frame's strands as polylines
  body.obj, body.ply  the first frame's body mesh
  drape.png           first frame, front and side, penetrating segments red
  drape_depth.png     first frame, front / side / back, coloured by depth
  sequence.png        a strip of 6 frames
  motion.gif          the motion, animated
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import trimesh

from hairwarp.io.export import write_hair_obj, write_hair_ply, write_mesh_obj, write_mesh_ply
from hairwarp.io.usd import read_usd, write_usd
from hairwarp.render import render_animation, render_drape, render_sequence

RADIUS = 0.1  # head radius [m]
CENTRE = np.array([0.0, 1.6, 0.0])  # head centre [m], y up
HANG = 0.3  # length of the hanging part [m]
OFFSET = 0.01  # the strands follow the head this far out [m]


def build_scene(num_strands: int, num_vertices: int, num_frames: int, seed: int = 0):
    """Hair (T, M, N, 3), body vertices (T, V, 3), faces (F, 3), signed distance (T, M, N)."""
    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS)
    # Roots over the upper cap and the back, none on the face (which looks toward +z).
    theta0 = np.arccos(rng.uniform(np.cos(1.25), 1.0, num_strands))
    phi = rng.uniform(0.0, 2.0 * np.pi, num_strands)
    front = (np.sin(phi) > 0.6) & (theta0 > 0.6)
    phi[front] += np.pi  # move face roots to the back
    rest = np.empty((num_strands, num_vertices, 3))
    for k in range(num_strands):
        theta = np.linspace(theta0[k], np.pi / 2, 24)
        r = np.full_like(theta, RADIUS + OFFSET)
        r[0] = RADIUS + 0.002  # the root sits on the scalp
        arc = r[:, None] * np.stack(
            [np.sin(theta) * np.cos(phi[k]), np.cos(theta), np.sin(theta) * np.sin(phi[k])], axis=1
        )
        drop = arc[-1] + np.linspace(0.0, HANG, 16)[1:, None] * np.array([0.0, -1.0, 0.0])
        line = np.concatenate([arc, drop])
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
        u = np.linspace(0.0, s[-1], num_vertices)
        rest[k] = np.stack([np.interp(u, s, line[:, c]) for c in range(3)], axis=1)
    # Every 30th strand: its middle third pushed 2 cm into the head.
    bad = np.arange(0, num_strands, 30)
    mid = slice(num_vertices // 4, num_vertices // 2)
    rest[bad, mid] *= (RADIUS - 0.02) / np.linalg.norm(rest[bad, mid], axis=-1, keepdims=True)

    t = np.arange(num_frames) / max(num_frames - 1, 1)
    sway = 0.06 * np.sin(2.0 * np.pi * t)  # head x offset [m]
    # Hair lags the head more and more along the strand (a stand-in for dynamics).
    along = np.linspace(0.0, 1.0, num_vertices)
    lag = 0.06 * np.sin(2.0 * np.pi * t[:, None] - 1.2 * along[None, :])  # (T, N)
    follow = sway[:, None] * (1 - along[None, :]) + lag * along[None, :]
    hair = rest[None] + CENTRE
    hair = hair + np.stack([follow, np.zeros_like(follow), np.zeros_like(follow)], axis=-1)[:, None]
    body = sphere.vertices[None] + CENTRE + sway[:, None, None] * np.array([1.0, 0.0, 0.0])
    head = CENTRE + sway[:, None] * np.array([1.0, 0.0, 0.0])  # (T, 3)
    signed_distance = np.linalg.norm(hair - head[:, None, None], axis=-1) - RADIUS
    return (hair.astype(np.float32), body.astype(np.float32), np.asarray(sphere.faces, dtype=np.int32),
            signed_distance.astype(np.float32))


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", default="./hairwarp-out")
    parser.add_argument("--strands", type=int, default=400)
    parser.add_argument("--vertices", type=int, default=40)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--fps", type=float, default=24.0)
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    out = lambda name: os.path.join(args.out, name)  # noqa: E731

    hair, body, faces, sd = build_scene(args.strands, args.vertices, args.frames)
    print(f"scene: {hair.shape[1]} strands x {hair.shape[2]} vertices, {hair.shape[0]} frames, "
          f"body {body.shape[1]} vertices / {len(faces)} triangles, "
          f"{int((sd[0] < 0).sum())} hair vertices inside the head in frame 0")

    start = time.perf_counter()
    write_usd(out("drape.usda"), hair, body, faces, fps=args.fps)
    back = read_usd(out("drape.usda"))
    assert np.array_equal(back["hair"].numpy(), hair)
    write_hair_obj(out("hair.obj"), hair[0])
    write_hair_ply(out("hair.ply"), hair[0])
    write_mesh_obj(out("body.obj"), body[0], faces)
    write_mesh_ply(out("body.ply"), body[0], faces)
    print(f"exported USD / OBJ / PLY in {time.perf_counter() - start:.2f} s")

    start = time.perf_counter()
    render_drape(out("drape.png"), hair[0], body[0], faces, signed_distance=sd[0],
                 title="frame 0: penetrating segments in red")
    print(f"drape.png (2 views): {time.perf_counter() - start:.2f} s")
    start = time.perf_counter()
    render_drape(out("drape_depth.png"), hair[0], body[0], faces, views=("front", "side", "back"),
                 color_by="depth", title="frame 0: coloured by depth (light = near)")
    print(f"drape_depth.png (3 views): {time.perf_counter() - start:.2f} s")
    start = time.perf_counter()
    render_sequence(out("sequence.png"), hair, body, faces, signed_distance=sd, frames=6, fps=args.fps,
                    title="head sway, 6 frames")
    print(f"sequence.png: {time.perf_counter() - start:.2f} s")
    start = time.perf_counter()
    render_animation(out("motion.gif"), hair, body, faces, signed_distance=sd, fps=args.fps)
    elapsed = time.perf_counter() - start
    print(f"motion.gif ({len(hair)} frames, 2 views): {elapsed:.2f} s, {elapsed / len(hair):.2f} s a frame")
    print(f"written to {os.path.abspath(args.out)}")


if __name__ == "__main__":
    main()
