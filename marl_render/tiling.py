"""Where each view lives in the framebuffer, and how tiles become a batch.

Views are laid out row-major in a grid of tiles. When all views do not fit the largest
framebuffer the GL allows, they are split into passes of one grid each. The renderer
flips every view vertically in the vertex shader, so in the bottom-up memory that
glReadPixels returns, tile row r is memory row block r and image rows run top to bottom.
A tile copy is then one strided copy, with no flip and no channel swizzle.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import torch


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


def framebuffer_tiles(ram_image, dtype, channels: int, layout: TileLayout) -> torch.Tensor:
    """Zero-copy torch view [rows, columns, H, W(, C)] of a Panda3D RAM image.

    The view aliases memory that Panda3D overwrites on the next render.
    """
    with warnings.catch_warnings():
        # Panda3D hands out its RAM image read-only; we only ever read from this view.
        warnings.simplefilter("ignore", UserWarning)
        flat = torch.from_numpy(np.frombuffer(memoryview(ram_image), dtype=dtype))
    th, tw, cols, rows = layout.tile_height, layout.tile_width, layout.columns, layout.rows
    shape = (rows, th, cols, tw) + ((channels,) if channels > 1 else ())
    return flat.view(shape).transpose(1, 2)


def copy_tiles(tiles: torch.Tensor, destination: torch.Tensor) -> None:
    """Copy the first len(destination) tiles of a [rows, columns, H, W, ...] view, in grid order.

    Rows and columns cannot merge into one strided axis, so whole tile rows are copied
    through a [rows, columns, ...] view of the destination, then the partial last row.
    """
    count, columns = destination.shape[0], tiles.shape[1]
    full_rows, rest = divmod(count, columns)
    if full_rows:
        destination[: full_rows * columns].view((full_rows, columns) + tuple(destination.shape[1:])).copy_(
            tiles[:full_rows])
    if rest:
        destination[full_rows * columns:].copy_(tiles[full_rows, :rest])
