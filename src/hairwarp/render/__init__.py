"""Preview pictures of hair drapes and motions (matplotlib Agg, no screen needed)."""

from hairwarp.render.preview import VIEWS, render_animation, render_drape, render_sequence, render_side_by_side

__all__ = ["VIEWS", "render_animation", "render_drape", "render_sequence", "render_side_by_side"]
