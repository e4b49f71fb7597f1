"""Preview pictures of draped hair: orthographic views, a frame strip, an animated GIF.

Pictures to judge a drape by eye, not production renders. Everything is drawn with
matplotlib's Agg canvas (no screen, no pyplot state, the caller's backend untouched):

- The body: its triangles projected orthographically, back faces culled (body normals point
  outward, DESIGN.md), flat Lambert shading from a light fixed to the camera, drawn far to near
  (painter's algorithm).
- The hair: every segment of every strand, sorted into the same far-to-near order as the
  triangles, so strands behind the head are hidden and strands over it show.
- Colours: `depth` (dark = far, light = near, per view), `penetration` (segments touching a
  vertex whose signed distance is negative in red, drawn on top of everything so that they
  show even inside the body; the other hair shaded by depth as in `depth`, whose colours hold
  no red), or `strand` (a colour per strand, no reds either).

Views, camera looking at the body (y up, the body faces +z, its left at +x):
  "front" from +z, "back" from -z, "side" from -x (the body's right side, face to the right),
  "left" from +x (face to the left).

Time per frame on the shared 2-core development CPU, 1024 strands x 100 vertices on the
13 348-vertex default body: 1.2-1.6 s for two views at 100 dpi, 0.5-0.9 s for one; about
0.75 s a frame for a two-view GIF at 80 dpi (`tests/test_render.py` guards the order of it).
"""

from __future__ import annotations

import io
import os
from collections.abc import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.colors import LinearSegmentedColormap, to_rgba
from matplotlib.figure import Figure
from matplotlib.path import Path

from hairwarp.io._arrays import (
    body_pair,
    check_path,
    check_positive_number,
    ensure_parent,
    hair_frames,
    per_vertex_frames,
)

# Camera frames: rows are the screen's right, its up, and the direction toward the viewer.
VIEWS = {
    "front": ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    "back": ((-1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, -1.0)),
    "side": ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (-1.0, 0.0, 0.0)),
    "left": ((0.0, 0.0, -1.0), (0.0, 1.0, 0.0), (1.0, 0.0, 0.0)),
}
VIEW_LABELS = {
    "front": "front (from +z)",
    "back": "back (from -z)",
    "side": "side (from -x, face right)",
    "left": "left (from +x, face left)",
}
# World axis along the screen's right, for the axis label (the screen's up is always +y).
VIEW_AXES = {"front": "x [m]", "back": "\u2212x [m]", "side": "z [m]", "left": "\u2212z [m]"}
COLOR_MODES = ("depth", "penetration", "strand")

# Hair colours. None of them is red, so red pixels mean penetration and nothing else.
HAIR_DEPTH_CMAP = LinearSegmentedColormap.from_list(
    "hair_depth", [(0.20, 0.12, 0.06), (0.55, 0.36, 0.17), (0.96, 0.80, 0.50)]
)
PENETRATION_COLOR = (1.0, 0.0, 0.0, 1.0)
BODY_COLOR = np.array([0.72, 0.76, 0.82])  # a cool grey: brown hair and red stand out on it
# Light from the camera's upper left, in view coordinates (x right, y up, z toward viewer).
LIGHT = np.array([-0.35, 0.45, 0.82]) / np.linalg.norm([-0.35, 0.45, 0.82])
AMBIENT = 0.30

STRAND_PALETTE = (
    "#1f77b4", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22",
    "#17becf", "#ff7f0e", "#aec7e8", "#98df8a", "#c5b0d5", "#c49c94", "#dbdb8d",
)

# Line width [pt] of the strands; the triangles are stroked in their own colour with the same
# width (one width for the whole collection keeps matplotlib fast), which also hides the seams
# of background that anti-aliasing leaves between neighbours.
HAIR_LINEWIDTH = 0.45
PENETRATION_LINEWIDTH = 1.6
# A groom simulated through guides (`hairwarp.scene.guides`): the guides are drawn at
# HAIR_LINEWIDTH, the strands that follow them this thin [pt], and at most MAX_FOLLOWERS_DRAWN
# of those (evenly picked, every strand with a vertex inside kept), so 100 000 strands draw in
# seconds and still read as one head of hair.
FOLLOWER_LINEWIDTH = 0.12
MAX_FOLLOWERS_DRAWN = 20000
# Strands are drawn in pieces of consecutive segments (colour and depth order are per piece):
# one segment per piece while the hair has at most HAIR_PIECES of them, longer pieces beyond
# (matplotlib's cost is per piece: 1024 x 100 hair is drawn as about 25 000 pieces of 4).
HAIR_PIECES = 30000
# Margin around the hair's bounding box, as a fraction of its larger side, and at least this
# many metres (so that a single straight strand still shows its surroundings).
FRAME_MARGIN = 0.12
FRAME_MARGIN_MIN = 0.02
# Panel layout [inches]: axes inset, leaving room for tick labels and the view label.
PANEL_INCHES = (4.0, 5.0)
_MARGIN_LEFT, _MARGIN_BOTTOM, _MARGIN_RIGHT, _MARGIN_TOP = 0.55, 0.45, 0.1, 0.42
_TITLE_INCHES = 0.35


class _PiecesCollection(PolyCollection):
    """A PolyCollection of open paths from one (K, P, 2) array, built without matplotlib's
    per-path validation (our arrays are checked once, as a whole): a third of a frame's time
    otherwise, at 35 000 pieces per view.
    """

    def set_verts(self, verts, closed=False):
        make = getattr(Path, "_fast_from_codes_and_verts", None)
        if make is None or len(verts) == 0:  # a matplotlib without the private fast constructor
            self._paths = [Path(xy) for xy in verts]
        else:
            # Settings copied from one template path instead of read from rcParams per path.
            template = Path(verts[0])
            self._paths = [make(xy, None, internals_from=template) for xy in verts]
        self.stale = True


def _view_matrix(view: str) -> np.ndarray:
    return np.asarray(VIEWS[view], dtype=np.float64)


def _check_views(views) -> tuple[str, ...]:
    if isinstance(views, str):
        views = (views,)
    try:
        views = tuple(views)
    except TypeError:
        raise ValueError(f"views: expected a sequence of view names, got {views!r}") from None
    if not views:
        raise ValueError("views: expected at least one view")
    for v in views:
        if v not in VIEWS:
            raise ValueError(f"views: expected names among {sorted(VIEWS)}, got {v!r}")
    return views


def _check_color_by(color_by, signed_distance) -> str:
    if color_by is None:
        return "penetration" if signed_distance is not None else "depth"
    if color_by not in COLOR_MODES:
        raise ValueError(f"color_by: expected one of {COLOR_MODES}, got {color_by!r}")
    if color_by == "penetration" and signed_distance is None:
        raise ValueError("signed_distance: required when color_by='penetration'")
    return color_by


def _check_positive_int(name: str, value, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name}: expected an integer >= {minimum}, got {value!r}")
    return int(value)


def _frame_limits(hair: np.ndarray, views: Sequence[str], aspect: float) -> dict:
    """Per-view (xmin, xmax, ymin, ymax) framing every given frame of the hair, with a margin,
    stretched to the axes' aspect (width / height) so that one metre is as long on both axes.

    Args:
        hair: (T, M, N, 3) [m].
        views: view names.
        aspect: axes width / height in pixels.
    """
    limits = {}
    pts = hair.reshape(-1, 3).astype(np.float64)
    for view in views:
        p = pts @ _view_matrix(view)[:2].T
        lo, hi = p.min(axis=0), p.max(axis=0)
        centre, half = (lo + hi) / 2, (hi - lo) / 2
        pad = max(FRAME_MARGIN * 2 * float(half.max()), FRAME_MARGIN_MIN)
        hx, hy = half[0] + pad, half[1] + pad
        if hx / hy < aspect:
            hx = hy * aspect
        else:
            hy = hx / aspect
        limits[view] = (centre[0] - hx, centre[0] + hx, centre[1] - hy, centre[1] + hy)
    return limits


def _hair_colors(depth: np.ndarray, color_by: str) -> np.ndarray:
    """RGBA (M, C, 4) of the hair pieces of depths (M, C) [m] (larger = nearer the camera).

    "penetration" shades the hair by depth too; its red segments go on top separately.
    """
    m, c = depth.shape
    if color_by in ("depth", "penetration"):
        lo, hi = float(depth.min()), float(depth.max())
        return HAIR_DEPTH_CMAP((depth - lo) / (hi - lo) if hi > lo else np.full_like(depth, 0.5))
    if color_by == "strand":
        # A fixed palette without reds, cycled by strand index (deterministic across frames).
        palette = np.array([to_rgba(x) for x in STRAND_PALETTE])
    return np.broadcast_to(palette[np.arange(m) % len(palette)][:, None, :], (m, c, 4))


def _cluster_decimate(vertices: np.ndarray, faces: np.ndarray, target: int):
    """Fewer triangles by vertex clustering: vertices snapped to the mean of their grid cell,
    collapsed triangles dropped. Unlike dropping triangles it leaves no holes; the cell grows
    until at most `target` triangles remain. Returns (vertices, faces).
    """
    corner = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0]), axis=1).sum()
    cell = np.sqrt(2.0 * max(area, 1e-12) / max(target, 1))
    for _ in range(40):
        _, cluster, counts = np.unique(np.floor(vertices / cell).astype(np.int64), axis=0,
                                       return_inverse=True, return_counts=True)
        cluster = cluster.reshape(-1)
        f = cluster[faces]
        f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])]
        if len(f) <= target:
            merged = np.zeros((len(counts), 3))
            np.add.at(merged, cluster, vertices)
            return merged / counts[:, None], f
        cell *= 1.25
    return vertices, faces[:target]  # not reached for any mesh with a finite extent


def _body_triangles(vertices: np.ndarray, faces: np.ndarray, rot: np.ndarray, limits, max_triangles: int):
    """Visible body triangles of one view: (K, 3, 2) screen corners, (K,) depth, (K, 4) colour."""
    xmin, xmax, ymin, ymax = limits

    def visible(p, fa):
        tri = p[fa]  # (F, 3, 3)
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        lo, hi = tri[:, :, :2].min(axis=1), tri[:, :, :2].max(axis=1)
        keep = (
            (normal[:, 2] > 0)  # facing the camera (outward normals); back faces are hidden anyway
            & (hi[:, 0] >= xmin) & (lo[:, 0] <= xmax) & (hi[:, 1] >= ymin) & (lo[:, 1] <= ymax)
        )
        return tri[keep], normal[keep]

    p = vertices.astype(np.float64) @ rot.T
    tri, normal = visible(p, faces)
    if len(tri) > max_triangles:
        # Coarsen the whole mesh in proportion, then cull again.
        target = max(1, int(len(faces) * max_triangles / len(tri)))
        p, fa = _cluster_decimate(p, faces, target)
        tri, normal = visible(p, fa)
    length = np.linalg.norm(normal, axis=1)
    ok = length > 0
    tri, normal, length = tri[ok], normal[ok], length[ok]
    lambert = np.clip((normal / length[:, None]) @ LIGHT, 0.0, 1.0)
    shade = AMBIENT + (1.0 - AMBIENT) * lambert
    rgba = np.concatenate([shade[:, None] * BODY_COLOR[None], np.ones((len(tri), 1))], axis=1)
    return tri[:, :, :2], tri[:, :, 2].mean(axis=1), rgba


def _draw_panel(ax, hair, body_v, faces, inside, view, color_by, limits, max_triangles, widths=None):
    """Draw one frame of one view into `ax`; returns the number of vertices drawn in red.

    Args:
        hair: (M, N, 3) [m]; body_v: (V, 3) [m] or None; faces: (F, 3) or None;
        inside: (M, N) bool or None; widths: (M,) line widths [pt] or None (all
        HAIR_LINEWIDTH); the rest as in `render_drape`.
    """
    rot = _view_matrix(view)
    hv = hair.astype(np.float64) @ rot.T  # (M, N, 3): screen x, screen y, depth
    m, n = hv.shape[:2]
    # Hair and body share one collection sorted far to near, so that each hides the other
    # where it should. Strands go in as open polylines of k segments (see HAIR_PIECES),
    # triangles as closed paths (corners 0, 1, 2, 0); both padded to P points by repeating
    # their last point, so that all fit one array (matplotlib's fast path).
    k = max(1, -(-m * (n - 1) // HAIR_PIECES))
    num_points = max(k + 1, 4)
    chunks = -(-(n - 1) // k)
    idx = np.arange(chunks)[:, None] * k + np.minimum(np.arange(num_points), k)[None, :]
    idx = np.minimum(idx, n - 1)  # (C, P): the last piece may be shorter
    hair_verts = hv[:, idx, :2].reshape(-1, num_points, 2)
    hair_depth = hv[:, idx[:, : k + 1], 2].mean(axis=2)  # (M, C)
    hair_rgba = _hair_colors(hair_depth, color_by).reshape(-1, 4)
    verts, depth, edge, face = [hair_verts], [hair_depth.reshape(-1)], [hair_rgba], [np.zeros_like(hair_rgba)]
    line = [np.full(m * chunks, HAIR_LINEWIDTH) if widths is None else np.repeat(widths, chunks)]
    if body_v is not None:
        tv, td, tc = _body_triangles(body_v, faces, rot, limits, max_triangles)
        verts.append(tv[:, np.minimum(np.arange(num_points), 3) % 3])
        depth.append(td)
        edge.append(tc)
        face.append(tc)
        line.append(np.full(len(td), HAIR_LINEWIDTH))
    order = np.argsort(np.concatenate(depth), kind="stable")
    ax.add_collection(
        _PiecesCollection(
            np.concatenate(verts)[order], facecolors=np.concatenate(face)[order],
            edgecolors=np.concatenate(edge)[order],
            linewidths=HAIR_LINEWIDTH if widths is None else np.concatenate(line)[order],
        ),
        autolim=False,  # the frame is set below; measuring 35 000 paths costs 0.1 s a view
    )
    num_inside = 0
    if color_by == "penetration":
        red = inside[:, 1:] | inside[:, :-1]  # (M, N-1) segments touching an inside vertex
        num_inside = int(inside.sum())
        if red.any():
            # On top of everything, thicker: they must show even where the body hides them.
            segments = np.stack([hv[:, :-1, :2][red], hv[:, 1:, :2][red]], axis=1)
            ax.add_collection(
                LineCollection(segments, colors=[PENETRATION_COLOR], linewidths=PENETRATION_LINEWIDTH),
                autolim=False,
            )
    xmin, xmax, ymin, ymax = limits
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_aspect("equal", adjustable="box")
    ax.tick_params(labelsize=6, length=2, pad=1)
    ax.set_xlabel(VIEW_AXES[view], fontsize=6, labelpad=1)
    ax.set_ylabel("y [m]", fontsize=6, labelpad=1)
    return num_inside


def _panel_label(view: str, color_by: str, num_inside: int, prefix: str = "") -> str:
    label = prefix + VIEW_LABELS[view]
    if color_by == "penetration":
        label += f"  -  {num_inside} vertices inside (red)" if num_inside else "  -  no vertex inside"
    return label


def _make_figure(rows: int, cols: int, dpi: float, title: str | None):
    """A figure of rows x cols panels of PANEL_INCHES each (plus a title band) and its axes."""
    pw, ph = PANEL_INCHES
    top_band = _TITLE_INCHES if title else 0.0
    fw, fh = cols * pw, rows * ph + top_band
    fig = Figure(figsize=(fw, fh), dpi=dpi)
    FigureCanvasAgg(fig)
    axes = np.empty((rows, cols), dtype=object)
    for r in range(rows):
        for c in range(cols):
            left = (c * pw + _MARGIN_LEFT) / fw
            bottom = ((rows - 1 - r) * ph + _MARGIN_BOTTOM) / fh
            width = (pw - _MARGIN_LEFT - _MARGIN_RIGHT) / fw
            height = (ph - _MARGIN_BOTTOM - _MARGIN_TOP) / fh
            axes[r, c] = fig.add_axes((left, bottom, width, height))
    if title:
        fig.text(0.5, 1.0 - 0.5 * top_band / fh, title, ha="center", va="center", fontsize=10)
    aspect = (pw - _MARGIN_LEFT - _MARGIN_RIGHT) / (ph - _MARGIN_BOTTOM - _MARGIN_TOP)
    return fig, axes, aspect


def _followers_thin(hair_t, inside, guides):
    """(hair, inside, (M',) widths) with the followers thin and at most MAX_FOLLOWERS_DRAWN of them."""
    m = hair_t.shape[1]
    try:
        guide_index = np.asarray(guides, dtype=np.int64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"guides: expected strand indices, got {type(guides).__name__}") from None
    if guide_index.size and (guide_index.min() < 0 or guide_index.max() >= m):
        raise ValueError(f"guides: strand indices must lie in [0, {m}), got [{guide_index.min()}, {guide_index.max()}]")
    is_guide = np.zeros(m, dtype=bool)
    is_guide[guide_index] = True
    followers = np.nonzero(~is_guide)[0]
    keep = np.zeros(m, dtype=bool)
    keep[is_guide] = True
    keep[followers[:: max(1, -(-len(followers) // MAX_FOLLOWERS_DRAWN))]] = True
    if inside is not None:
        keep |= inside.any(axis=(0, 2))
    widths = np.where(is_guide[keep], HAIR_LINEWIDTH, FOLLOWER_LINEWIDTH)
    return hair_t[:, keep], None if inside is None else inside[:, keep], widths


def _prepare(hair, body_vertices, body_faces, signed_distance, views, color_by, dpi, frames_axis, guides=None):
    hair_t, _ = hair_frames("hair", hair, frames=frames_axis)
    body_v, faces = body_pair(
        body_vertices, body_faces, hair_t.shape[0], frames=None if frames_axis else False
    )
    inside = None
    if signed_distance is not None:
        inside = per_vertex_frames("signed_distance", signed_distance, hair_t.shape) < 0
    views = _check_views(views)
    color_by = _check_color_by(color_by, signed_distance)
    dpi = check_positive_number("dpi", dpi)
    widths = None
    if guides is not None:
        hair_t, inside, widths = _followers_thin(hair_t, inside, guides)
    return hair_t, body_v, faces, inside, views, color_by, dpi, widths


def _save(fig, path: str) -> None:
    ensure_parent(path)
    fig.savefig(path, format="png")


def render_drape(
    path: str | os.PathLike,
    hair,
    body_vertices=None,
    body_faces=None,
    signed_distance=None,
    views: Sequence[str] = ("front", "side"),
    color_by: str | None = None,
    title: str | None = None,
    dpi: float = 100,
    max_triangles: int = 20000,
    guides=None,
) -> str:
    """Draw one drape (hair on a body) from one or more orthographic views into a PNG.

    Args:
        path: output file, `.png`.
        hair: (M, N, 3) strand vertices [m], torch tensor (any device) or numpy array, y up.
        body_vertices: (V, 3) body vertices [m], or None for hair alone.
        body_faces: (F, 3) int triangles (counter-clockwise seen from outside), with
            `body_vertices`.
        signed_distance: (M, N) signed distance of each hair vertex to the body [m], negative
            inside; its negative vertices are drawn red.
        views: names among "front", "back", "side", "left" (see the module docstring), one panel
            each, left to right.
        color_by: "depth", "penetration" (needs `signed_distance`) or "strand"; None picks
            "penetration" when `signed_distance` is given, "depth" otherwise.
        title: text above the panels.
        dpi: pixels per inch; each panel is 4 x 5 inches (400 x 500 pixels at 100 dpi).
        max_triangles: most body triangles drawn per view (after culling those facing away or
            outside the frame); beyond it the body is coarsened by vertex clustering, for speed.
        guides: for a groom simulated through guides, the (K,) indices of the guide strands:
            they are drawn at full width, the other strands thin (at most MAX_FOLLOWERS_DRAWN).

    Returns:
        The path written. The image is `len(views) * 4 * dpi` by `5 * dpi (+ 0.35 * dpi with a
        title)` pixels.

    Raises:
        ValueError: naming the argument that is malformed (shape, dtype, NaN/Inf, empty,
            out-of-range face index, unknown view or colour mode, wrong file extension).
    """
    path = check_path("path", path, (".png",))
    hair_t, body_v, faces, inside, views, color_by, dpi, widths = _prepare(
        hair, body_vertices, body_faces, signed_distance, views, color_by, dpi, frames_axis=False, guides=guides
    )
    max_triangles = _check_positive_int("max_triangles", max_triangles)
    fig, axes, aspect = _make_figure(1, len(views), dpi, title)
    limits = _frame_limits(hair_t, views, aspect)
    for c, view in enumerate(views):
        k = _draw_panel(
            axes[0, c], hair_t[0], None if body_v is None else body_v[0], faces,
            None if inside is None else inside[0], view, color_by, limits[view], max_triangles, widths,
        )
        axes[0, c].set_title(_panel_label(view, color_by, k), fontsize=8)
    _save(fig, path)
    return path


def _frame_indices(num_frames: int, frames: int) -> np.ndarray:
    count = min(frames, num_frames)
    return np.unique(np.round(np.linspace(0, num_frames - 1, count)).astype(np.int64))


def render_sequence(
    path: str | os.PathLike,
    hair,
    body_vertices=None,
    body_faces=None,
    signed_distance=None,
    views: Sequence[str] = ("front", "side"),
    color_by: str | None = None,
    frames: int = 6,
    fps: float = 60,
    title: str | None = None,
    dpi: float = 80,
    max_triangles: int = 20000,
    guides=None,
) -> str:
    """Draw a strip of evenly spaced frames of a motion into one PNG (rows: views, columns: frames).

    All panels of a view share one framing (the hair's bounding box over the shown frames), so
    motion reads as motion.

    Args:
        path: output file, `.png`.
        hair: (T, M, N, 3) strand vertices per frame [m].
        body_vertices: (T, V, 3) (or (1, V, 3) for a still body) [m], or None.
        body_faces: (F, 3) int triangles, with `body_vertices`.
        signed_distance: (T, M, N) signed distances [m] (negative inside), or None.
        views: view names, one row each.
        color_by: as in `render_drape`.
        frames: number of frames shown (first and last included), at most T.
        fps: frame rate of the motion [1/s], for the time labels.
        title: text above the strip.
        dpi: pixels per inch; each panel is 4 x 5 inches.
        max_triangles: as in `render_drape`.
        guides: as in `render_drape`.

    Returns:
        The path written.

    Raises:
        ValueError: naming the malformed argument.
    """
    path = check_path("path", path, (".png",))
    hair_t, body_v, faces, inside, views, color_by, dpi, widths = _prepare(
        hair, body_vertices, body_faces, signed_distance, views, color_by, dpi, frames_axis=True, guides=guides
    )
    frames = _check_positive_int("frames", frames)
    fps = check_positive_number("fps", fps)
    max_triangles = _check_positive_int("max_triangles", max_triangles)
    idx = _frame_indices(hair_t.shape[0], frames)
    fig, axes, aspect = _make_figure(len(views), len(idx), dpi, title)
    limits = _frame_limits(hair_t[idx], views, aspect)
    for c, t in enumerate(idx):
        for r, view in enumerate(views):
            k = _draw_panel(
                axes[r, c], hair_t[t], None if body_v is None else body_v[min(t, len(body_v) - 1)], faces,
                None if inside is None else inside[t], view, color_by, limits[view], max_triangles, widths,
            )
            prefix = f"frame {t}, t = {t / fps:.2f} s\n"
            axes[r, c].set_title(_panel_label(view, color_by, k, prefix), fontsize=8)
    _save(fig, path)
    return path


def render_animation(
    path: str | os.PathLike,
    hair,
    body_vertices=None,
    body_faces=None,
    signed_distance=None,
    views: Sequence[str] = ("front", "side"),
    color_by: str | None = None,
    fps: float = 60,
    stride: int = 1,
    title: str | None = None,
    dpi: float = 80,
    max_triangles: int = 20000,
    guides=None,
) -> str:
    """Write the motion as an animated GIF (Pillow), one image per shown frame, looping.

    Args:
        path: output file, `.gif`.
        hair: (T, M, N, 3) strand vertices per frame [m].
        body_vertices: (T, V, 3) (or (1, V, 3) for a still body) [m], or None.
        body_faces: (F, 3) int triangles, with `body_vertices`.
        signed_distance: (T, M, N) signed distances [m] (negative inside), or None.
        views: view names, side by side in every image.
        color_by: as in `render_drape`.
        fps: frame rate of the motion [1/s]; the GIF plays in real time (GIF delays are whole
            centiseconds, so the speed is rounded).
        stride: show every `stride`-th frame.
        title: text above the panels.
        dpi: pixels per inch; each panel is 4 x 5 inches.
        max_triangles: as in `render_drape`.
        guides: as in `render_drape`.

    Returns:
        The path written.

    Raises:
        ValueError: naming the malformed argument.
    """
    path = check_path("path", path, (".gif",))
    hair_t, body_v, faces, inside, views, color_by, dpi, widths = _prepare(
        hair, body_vertices, body_faces, signed_distance, views, color_by, dpi, frames_axis=True, guides=guides
    )
    fps = check_positive_number("fps", fps)
    stride = _check_positive_int("stride", stride)
    max_triangles = _check_positive_int("max_triangles", max_triangles)
    idx = np.arange(0, hair_t.shape[0], stride)
    fig, axes, aspect = _make_figure(1, len(views), dpi, title)
    limits = _frame_limits(hair_t, views, aspect)
    images = []
    for t in idx:
        for c, view in enumerate(views):
            ax = axes[0, c]
            for artist in list(ax.collections):  # keep the axes (rebuilding ticks costs more)
                artist.remove()
            k = _draw_panel(
                ax, hair_t[t], None if body_v is None else body_v[min(t, len(body_v) - 1)], faces,
                None if inside is None else inside[t], view, color_by, limits[view], max_triangles, widths,
            )
            ax.set_title(_panel_label(view, color_by, k, f"frame {t}, t = {t / fps:.2f} s\n"), fontsize=8)
        images.append(_gif_image(fig))
    return _write_gif(path, images, 1000.0 * stride / fps)


def render_side_by_side(
    path: str | os.PathLike,
    hairs: dict,
    body_vertices=None,
    body_faces=None,
    signed_distances: dict | None = None,
    view: str = "front",
    frames: int = 6,
    fps: float = 60,
    stride: int = 1,
    title: str | None = None,
    dpi: float = 80,
    max_triangles: int = 20000,
) -> str:
    """Draw several methods' motions of the same scene side by side, in one framing.

    A `.png` is a strip: one row per method, one column per evenly spaced frame (one frame: the
    methods side by side in one row). A `.gif` shows
    every `stride`-th frame, one panel per method side by side, so a method and the physics move
    together.

    Args:
        path: output file, `.png` or `.gif`.
        hairs: label -> (T, M, N, 3) strand vertices per frame [m], the same T for all.
        body_vertices: (T, V, 3) (or (1, V, 3)) [m], or None.
        body_faces: (F, 3) int triangles, with `body_vertices`.
        signed_distances: label -> (T, M, N) signed distances [m] (negative inside: red), or None.
        view: one view name (see the module docstring).
        frames: `.png`: frames shown (first and last included), at most T.
        fps: frame rate [1/s] (labels; the GIF's speed).
        stride: `.gif`: show every `stride`-th frame.
        title: text above the panels.
        dpi: pixels per inch; each panel is 4 x 5 inches.
        max_triangles: as in `render_drape`.

    Returns:
        The path written.

    Raises:
        ValueError: naming the malformed argument (an empty `hairs`, motions of different
            lengths, and every check of `render_sequence`).
    """
    if not isinstance(hairs, dict) or not hairs:
        raise ValueError("hairs: expected a non-empty dict of label -> (T, M, N, 3) hair")
    path = check_path("path", path, (".png", ".gif"))
    prepared = {}
    for label, hair in hairs.items():
        sd = None if signed_distances is None else signed_distances.get(label)
        prepared[label] = _prepare(hair, body_vertices, body_faces, sd, (view,), None, dpi, frames_axis=True)
    lengths = {label: p[0].shape[0] for label, p in prepared.items()}
    if len(set(lengths.values())) != 1:
        raise ValueError(f"hairs: expected motions of one length, got {lengths}")
    fps = check_positive_number("fps", fps)
    max_triangles = _check_positive_int("max_triangles", max_triangles)
    labels = list(prepared)
    _, body_v, faces, _, (view,), color_by, dpi, _ = prepared[labels[0]]
    num_frames = lengths[labels[0]]
    gif = str(path).endswith(".gif")
    idx = np.arange(0, num_frames, _check_positive_int("stride", stride)) if gif else \
        _frame_indices(num_frames, _check_positive_int("frames", frames))
    everything = np.concatenate([prepared[label][0][idx] for label in labels], axis=1)
    across = gif or len(idx) == 1  # one panel per method, side by side (a GIF's image, one drape)
    rows, cols = (1, len(labels)) if across else (len(labels), len(idx))
    fig, axes, aspect = _make_figure(rows, cols, dpi, title)
    limits = _frame_limits(everything, (view,), aspect)[view]

    def draw(ax, label, t):
        hair_t, _, _, inside, _, mode, _, _ = prepared[label]
        for artist in list(ax.collections):
            artist.remove()
        k = _draw_panel(ax, hair_t[t], None if body_v is None else body_v[min(t, len(body_v) - 1)], faces,
                        None if inside is None else inside[t], view, mode, limits, max_triangles)
        ax.set_title(_panel_label(view, mode, k, f"{label}: frame {t}, t = {t / fps:.2f} s\n"), fontsize=8)

    if not gif:
        for r, label in enumerate(labels):
            for c, t in enumerate(idx):
                draw(axes[0, r] if across else axes[r, c], label, t)
        _save(fig, path)
        return path
    images = []
    for t in idx:
        for c, label in enumerate(labels):
            draw(axes[0, c], label, t)
        images.append(_gif_image(fig))
    return _write_gif(path, images, 1000.0 * stride / fps)


def _gif_image(fig):
    """The figure as a palette image: one adaptive palette per image; without dithering flat
    body shading stays flat.
    """
    from PIL import Image

    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3]
    return Image.fromarray(rgb).quantize(colors=255, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)


def _write_gif(path: str, images: list, frame_ms: float) -> str:
    """A looping GIF of `images`, `frame_ms` apart (GIF delays are whole centiseconds)."""
    duration_ms = max(20, int(round(frame_ms / 10.0)) * 10)
    ensure_parent(path)
    with io.BytesIO() as buf:
        images[0].save(buf, format="GIF", save_all=True, append_images=images[1:], duration=duration_ms,
                       loop=0, disposal=1)
        data = buf.getvalue()
    with open(path, "wb") as f:
        f.write(data)
    return path
