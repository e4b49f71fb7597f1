"""Preview renderer: files are valid images of the documented size, penetration shows red
exactly when a vertex is inside, the body hides what is behind it, bad inputs raise."""

import importlib.util
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from hairwarp.render import render_animation, render_drape, render_sequence
from hairwarp.render.preview import PANEL_INCHES, _TITLE_INCHES, _cluster_decimate

RADIUS = 0.1  # sphere "head" [m], centred at the origin
# A pixel is "red" when it is close to pure red; no hair, body or text colour comes near it.
_RED_MIN_R, _RED_MAX_GB = 200, 60
# Pixels of a blue strand ("strand" colours: the first palette entry is #1f77b4): blue well
# above red, which the grey-blue body (B - R about 25) and the white background never reach.
_BLUE_MARGIN = 100
# Occlusion: a strand behind the sphere loses the third of its length that the sphere covers,
# one in front loses nothing (anti-aliasing against grey instead of white changes a few pixels).
_HIDDEN_MAX_RATIO, _VISIBLE_MIN_RATIO = 0.8, 0.9
# Coarsening keeps the body's silhouette: decimated meshes cover nearly the same pixels and
# enclose nearly the same volume (cells of a few per cent of the radius).
_COVER_TOL, _VOLUME_TOL = 0.05, 0.15
# A 1024 x 100 drape on a 14k-vertex body renders in about 1 s here (2 shared cores); the bound
# only catches a regression by an order of magnitude.
_FRAME_BUDGET_S = 15.0


def _sphere(subdivisions=2):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=RADIUS)
    return s.vertices.astype(np.float32), np.asarray(s.faces, dtype=np.int64)


def _hanging_hair(rng, m=40, n=16, inside=0):
    """Strands rooted on the upper sphere that follow it 1 cm out down to the equator, then hang
    straight down; the last half of the first `inside` strands moved into the sphere. Returns
    hair (M, N, 3) and the exact signed distance to the sphere (M, N) [m]."""
    theta0 = rng.uniform(0.2, 1.2, m)
    phi = rng.uniform(0, 2 * np.pi, m)
    hair = np.empty((m, n, 3))
    for k in range(m):
        theta = np.linspace(theta0[k], np.pi / 2, 12)
        r = np.full_like(theta, RADIUS + 0.01)
        r[0] = RADIUS + 0.002
        sin, cos = np.sin(theta), np.cos(theta)
        arc = r[:, None] * np.stack([sin * np.cos(phi[k]), cos, sin * np.sin(phi[k])], 1)
        drop = arc[-1] + np.linspace(0, 0.25, 10)[1:, None] * np.array([0.0, -1.0, 0.0])
        line = np.concatenate([arc, drop])
        s = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
        u = np.linspace(0, s[-1], n)
        hair[k] = np.stack([np.interp(u, s, line[:, c]) for c in range(3)], 1)
    if inside:
        h = n - n // 2
        hair[:inside, n // 2:] = np.stack(
            [np.full(h, 0.05) * np.cos(phi[:inside, None]),
             np.broadcast_to(np.linspace(0.05, -0.05, h), (inside, h)),
             np.full(h, 0.05) * np.sin(phi[:inside, None])],
            axis=-1,
        )
    sd = np.linalg.norm(hair, axis=-1) - RADIUS
    return hair.astype(np.float32), sd.astype(np.float32)


def _read(path):
    img = Image.open(path)
    img.load()
    return img


def _red_pixels(img) -> int:
    a = np.asarray(img.convert("RGB")).astype(int)
    return int(((a[..., 0] >= _RED_MIN_R) & (a[..., 1] <= _RED_MAX_GB) & (a[..., 2] <= _RED_MAX_GB)).sum())


def test_render_drape_png_size(tmp_path, rng):
    v, f = _sphere()
    hair, _ = _hanging_hair(rng)
    dpi = 40
    for views, title in [(("front", "side"), None), (("front", "back", "side", "left"), "a title")]:
        path = render_drape(tmp_path / "drape.png", torch.from_numpy(hair), v, f, views=views, title=title,
                            dpi=dpi)
        img = _read(path)
        assert img.format == "PNG"
        height = PANEL_INCHES[1] * dpi + (_TITLE_INCHES * dpi if title else 0)
        assert img.size == (round(len(views) * PANEL_INCHES[0] * dpi), round(height))
        a = np.asarray(img.convert("RGB"))
        assert len(np.unique(a.reshape(-1, 3), axis=0)) > 20  # something was drawn


def test_penetration_is_red_only_when_inside(tmp_path, rng):
    v, f = _sphere()
    hair, sd = _hanging_hair(rng, inside=5)
    assert (sd < 0).sum() >= 5 * 4  # the scene really has vertices inside
    img = _read(render_drape(tmp_path / "in.png", hair, v, f, signed_distance=sd, dpi=50))
    red_inside = _red_pixels(img)
    assert red_inside > 50
    clean, sd_clean = _hanging_hair(np.random.default_rng(7), inside=0)
    assert (sd_clean > 0).all()
    img = _read(render_drape(tmp_path / "out.png", clean, v, f, signed_distance=sd_clean, dpi=50))
    assert _red_pixels(img) == 0
    # The other colour modes never produce red, even with vertices inside.
    for mode in ("depth", "strand"):
        path = render_drape(tmp_path / f"{mode}.png", hair, v, f, signed_distance=sd, color_by=mode, dpi=50)
        img = _read(path)
        assert _red_pixels(img) == 0
    # More vertices inside, more red.
    more, sd_more = _hanging_hair(rng, inside=20)
    img = _read(render_drape(tmp_path / "more.png", more, v, f, signed_distance=sd_more, dpi=50))
    assert _red_pixels(img) > 2 * red_inside


def _blue_pixels(img) -> int:
    a = np.asarray(img.convert("RGB")).astype(int)
    return int((a[..., 2] - a[..., 0] > _BLUE_MARGIN).sum())


def test_body_hides_strands_behind_it(tmp_path):
    v, f = _sphere(subdivisions=3)
    y = np.linspace(0.3, -0.3, 30)
    counts = {}
    for where, z in (("behind", -0.2), ("front", 0.2)):
        strand = np.stack([np.zeros_like(y), y, np.full_like(y, z)], axis=1)[None].astype(np.float32)
        for body in (True, False):
            path = tmp_path / f"{where}{body}.png"
            render_drape(path, strand, v if body else None, f if body else None, views=("front",),
                         color_by="strand", dpi=300)
            counts[where, body] = _blue_pixels(_read(path))
    assert min(counts.values()) > 100
    assert counts["behind", True] < _HIDDEN_MAX_RATIO * counts["behind", False]
    assert counts["front", True] > _VISIBLE_MIN_RATIO * counts["front", False]


def _body_pixels(img) -> int:
    a = np.asarray(img.convert("RGB")).astype(int)
    grey_blue = (np.abs(a[..., 0] - a[..., 1]) < 30) & (a[..., 2] >= a[..., 0]) & (a[..., 0] < 235)
    return int(grey_blue.sum())


def test_many_triangles_are_coarsened_without_holes(tmp_path):
    v, f = _sphere(subdivisions=4)
    coarse_v, coarse_f = _cluster_decimate(v.astype(np.float64), f, 500)
    assert 100 < len(coarse_f) <= 500
    volume = trimesh.Trimesh(coarse_v, coarse_f, process=False).volume
    assert abs(volume / (4 / 3 * np.pi * RADIUS**3) - 1) < _VOLUME_TOL
    # Two strands on either side frame the whole sphere.
    y = np.linspace(-0.15, 0.15, 10)
    hair = np.stack([np.stack([np.full_like(y, sx), y, np.zeros_like(y)], 1) for sx in (-0.15, 0.15)])
    counts = []
    for max_triangles in (20000, 500):
        path = tmp_path / f"cap{max_triangles}.png"
        render_drape(path, hair.astype(np.float32), v, f, views=("front",), max_triangles=max_triangles,
                     dpi=60)
        counts.append(_body_pixels(_read(path)))
    assert counts[0] > 1000
    assert abs(counts[1] / counts[0] - 1) < _COVER_TOL


def test_render_sequence_strip(tmp_path, rng):
    v, f = _sphere(subdivisions=1)
    hair, sd = _hanging_hair(rng, m=10, n=8, inside=2)
    num_frames = 4
    motion = np.stack([hair + np.array([0.01 * t, 0, 0], dtype=np.float32) for t in range(num_frames)])
    body = np.stack([v] * num_frames)
    dpi = 30
    path = render_sequence(tmp_path / "strip.png", motion, body, f,
                           signed_distance=np.stack([sd] * num_frames), frames=6, fps=30, dpi=dpi)
    img = _read(path)
    assert img.format == "PNG"
    # frames=6 > T: every frame once; rows = the 2 default views.
    assert img.size == (round(num_frames * PANEL_INCHES[0] * dpi), round(2 * PANEL_INCHES[1] * dpi))
    assert _red_pixels(img) > 0
    # A still body (V, 3) under moving hair, 2 of 4 frames, one view.
    img = _read(render_sequence(tmp_path / "strip2.png", motion, v, f, views=("side",), frames=2, dpi=dpi))
    assert img.size == (round(2 * PANEL_INCHES[0] * dpi), round(PANEL_INCHES[1] * dpi))


def test_render_animation_gif(tmp_path, rng):
    v, f = _sphere(subdivisions=1)
    hair, _ = _hanging_hair(rng, m=10, n=8)
    num_frames = 5
    motion = np.stack([hair + np.array([0, 0.01 * t, 0], dtype=np.float32) for t in range(num_frames)])
    dpi = 25
    path = render_animation(tmp_path / "motion.gif", torch.from_numpy(motion), torch.from_numpy(v)[None], f,
                            views=("front",), fps=25, stride=2, dpi=dpi)
    img = _read(path)
    assert img.format == "GIF" and img.is_animated
    assert img.n_frames == 3  # frames 0, 2, 4
    assert img.size == (round(PANEL_INCHES[0] * dpi), round(PANEL_INCHES[1] * dpi))
    assert img.info["duration"] == 80  # 2 frames at 25 fps
    first = np.asarray(img.convert("RGB")).copy()
    img.seek(2)
    assert (np.asarray(img.convert("RGB")) != first).any()  # the frames differ: the hair moved


def test_render_speed_full_size(tmp_path, rng):
    # The size the paper uses (1024 strands x 100 vertices) on a ~14k-vertex body.
    sphere = trimesh.creation.uv_sphere(radius=0.1, count=[84, 84])
    v, f = sphere.vertices.astype(np.float32), np.asarray(sphere.faces)
    assert 13000 <= len(v) <= 15000
    hair, _ = _hanging_hair(rng, m=1024, n=100)
    start = time.perf_counter()
    render_drape(tmp_path / "full.png", hair, v, f, dpi=100)
    elapsed = time.perf_counter() - start
    assert elapsed < _FRAME_BUDGET_S, f"one frame took {elapsed:.1f} s"


def test_bad_inputs_name_the_argument(tmp_path, rng):
    v, f = _sphere(subdivisions=1)
    hair, sd = _hanging_hair(rng, m=6, n=5)
    bad_hair = hair.copy()
    bad_hair[1, 2, 0] = np.nan
    png = tmp_path / "x.png"
    cases = [
        ("hair", dict(hair=hair[None])),
        ("hair", dict(hair=hair[..., :2])),
        ("hair", dict(hair=bad_hair)),
        ("hair", dict(hair=hair[:0])),
        ("body_vertices", dict(body_vertices=v[None], body_faces=f)),
        ("body_vertices", dict(body_faces=f, body_vertices=None)),
        ("body_faces", dict(body_vertices=v, body_faces=None)),
        ("body_faces", dict(body_vertices=v, body_faces=f + 1000)),
        ("signed_distance", dict(signed_distance=sd[:, :3])),
        ("signed_distance", dict(signed_distance=np.full_like(sd, np.inf))),
        ("signed_distance", dict(color_by="penetration")),
        ("views", dict(views=())),
        ("views", dict(views=("top",))),
        ("color_by", dict(color_by="rainbow")),
        ("dpi", dict(dpi=0)),
        ("max_triangles", dict(max_triangles=0)),
        ("path", dict(path=tmp_path / "x.jpg")),
    ]
    for name, override in cases:
        args = dict(path=png, hair=hair)
        args.update(override)
        with pytest.raises(ValueError, match=f"^{name}:"):
            render_drape(**args)
    motion = np.stack([hair, hair])
    seq_cases = [
        ("hair", lambda: render_sequence(png, hair)),  # needs (T, M, N, 3)
        ("frames", lambda: render_sequence(png, motion, frames=0)),
        ("fps", lambda: render_sequence(png, motion, fps=-1)),
        ("body_vertices", lambda: render_sequence(png, motion, np.stack([v] * 3), f)),
        ("path", lambda: render_animation(tmp_path / "x.png", motion)),
        ("stride", lambda: render_animation(tmp_path / "x.gif", motion, stride=0)),
    ]
    for name, call in seq_cases:
        with pytest.raises(ValueError, match=f"^{name}:"):
            call()
    assert not any(tmp_path.iterdir())  # nothing written on failure


@pytest.mark.slow
def test_example_export_and_render_runs(tmp_path, capsys):
    path = Path(__file__).resolve().parents[1] / "examples" / "export_and_render.py"
    spec = importlib.util.spec_from_file_location("export_and_render_example", path)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    example.main(["--out", str(tmp_path), "--strands", "60", "--vertices", "12", "--frames", "3"])
    names = ["drape.usda", "hair.obj", "hair.ply", "body.obj", "body.ply", "drape.png", "drape_depth.png",
             "sequence.png", "motion.gif"]
    for name in names:
        assert (tmp_path / name).stat().st_size > 0, name
    assert _red_pixels(_read(tmp_path / "drape.png")) > 0  # the scene pushes strands inside
    assert _red_pixels(_read(tmp_path / "drape_depth.png")) == 0
    assert "written to" in capsys.readouterr().out
