"""Where each view lives in the framebuffer.

The batch renderer stacks its views in ONE column of tiles, as many as the GL's largest
framebuffer holds (`column_layout`); more views take more framebuffers (passes), all
drawn before any is read. Every view is flipped vertically in the vertex shader, so in
the bottom-up rows GL reads back, tile t is rows [t * H, (t + 1) * H) top to bottom:
the framebuffer's memory is exactly the [views, H, W, C] batch, and the readback lands
in it with no rearranging copy. `plan_layout` makes a near-square grid, for the plain
Panda3D baseline (one display region per view) and the shadow atlas (shadows.py).
"""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class TileLayout:
    num_views: int
    tile_height: int
    tile_width: int
    columns: int  # tiles per row in one pass
    rows: int  # tile rows in one pass

    @property
    def views_per_pass(self) -> int:
        return self.columns * self.rows

    @property
    def num_passes(self) -> int:
        return math.ceil(self.num_views / self.views_per_pass)

    @property
    def framebuffer_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.columns * self.tile_width, self.rows * self.tile_height

    def pass_views(self, index: int) -> range:
        start = index * self.views_per_pass
        return range(start, min(start + self.views_per_pass, self.num_views))


def column_layout(num_views: int, tile_height: int, tile_width: int, max_size: int) -> TileLayout:
    """One column of as many tiles as fit in max_size rows (fewer if there are fewer views)."""
    if tile_height > max_size or tile_width > max_size:
        raise ValueError(f"resolution must be at most {max_size} pixels per side (framebuffer limit), "
                         f"got {(tile_height, tile_width)}")
    return TileLayout(num_views, tile_height, tile_width, 1, min(num_views, max_size // tile_height))


def layer_layout(num_views: int, tile_height: int, tile_width: int, max_size: int, max_layers: int) -> TileLayout:
    """One view per layer of an array texture, as many layers per framebuffer as the GL allows
    (BatchRenderer(layered=True)); `rows` counts the layers of one pass."""
    if tile_height > max_size or tile_width > max_size:
        raise ValueError(f"resolution must be at most {max_size} pixels per side (framebuffer limit), "
                         f"got {(tile_height, tile_width)}")
    return TileLayout(num_views, tile_height, tile_width, 1, min(num_views, max_layers))


def plan_layout(num_views: int, tile_height: int, tile_width: int, max_size: int) -> TileLayout:
    """A near-square grid of tiles no larger than max_size x max_size pixels."""
    if tile_height > max_size or tile_width > max_size:
        raise ValueError(f"resolution must be at most {max_size} pixels per side (framebuffer limit), "
                         f"got {(tile_height, tile_width)}")
    max_columns = max_size // tile_width
    max_rows = max_size // tile_height
    in_first_pass = min(num_views, max_columns * max_rows)
    columns = math.ceil(math.sqrt(in_first_pass * tile_height / tile_width))
    columns = min(max_columns, max(columns, math.ceil(in_first_pass / max_rows), 1))
    rows = math.ceil(in_first_pass / columns)
    return TileLayout(num_views, tile_height, tile_width, columns, rows)
