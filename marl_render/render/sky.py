"""The appearance effect's sky: each world's background colour behind everything it draws.

A framebuffer holds the tiles of many worlds, and a GL clear has one colour for all of them. So a
renderer whose scene declares the "appearance" effect keeps, per framebuffer (pass), an RGBA8
image of its tiles, each filled with its world's sky colour, and copies it over the framebuffer's
colour texture (glCopyImageSubData) before the frame is drawn, in place of the colour clear.

Why a copy: the GL way, a quad per view drawn behind everything, runs llvmpipe's fragment pipeline
on every pixel of every tile; measured here at 1024 views of 64x64 it added about 8 ms of CPU time
to a frame, the copy (a memcpy) about 2 ms. The images cost 4 bytes per framebuffer pixel and are
uploaded again only over the views whose sky changed. MSAA resolves its own buffer over the
texture, so the effect refuses multisamples (supersample works).

The copy for the next frame is made as soon as a framebuffer has been read (`refill`), while
llvmpipe still rasterises the framebuffers after it: the main thread would otherwise wait for them.
A frame whose framebuffer was not refilled, or whose sky changed since, copies first (`fill`).

The GL objects are made and used with the renderer's context current (inside its render).
"""
from __future__ import annotations

import ctypes

import torch

from .readback import GL_RGBA, GL_UNSIGNED_BYTE, gl_functions
from .tiling import TileLayout

GL_TEXTURE_2D = 0x0DE1
GL_TEXTURE_2D_ARRAY = 0x8C1A
GL_RGBA8 = 0x8058
GL_PIXEL_UNPACK_BUFFER = 0x88EC
GL_PIXEL_UNPACK_BUFFER_BINDING = 0x88EF
GRAY_WEIGHTS = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)  # shaders.GRAY_WEIGHTS


class SkyImages:
    """One image per pass of `layout` (tile_width x views * tile_height, RGBA8) with each view's tile
    in its world's sky colour (gray: its BT.601 luma, as the gray output reads the red channel).
    layered: one array texture per pass instead, a layer per view (BatchRenderer(layered=True))."""

    def __init__(self, layout: TileLayout, agents: int, gray: bool, layered: bool = False):
        self.layout, self.agents, self.gray, self.layered = layout, agents, gray, layered
        self.target = GL_TEXTURE_2D_ARRAY if layered else GL_TEXTURE_2D
        self.names: list[int] = []  # GL textures, one per pass
        self._uploaded = torch.zeros(layout.num_passes, dtype=torch.bool)  # passes that have been uploaded once
        self._held = torch.zeros(layout.num_views, 4, dtype=torch.uint8)  # [views, 4]: what the images hold
        self._bytes = self._held.clone()  # [views, 4]: what they should hold (set_sky)
        self._stale = [True] * layout.num_passes  # set_sky was called since the pass's image was last updated
        self._ready = [False] * layout.num_passes  # the pass's framebuffer holds the current sky (refill)
        functions = gl_functions()
        for index in range(layout.num_passes):
            name = ctypes.c_uint()
            functions["glCreateTextures"](self.target, 1, ctypes.byref(name))
            if not name.value:
                raise RuntimeError("the GL made no texture for the appearance effect's sky")
            self.names.append(name.value)
            views = layout.pass_views(index)
            if layered:
                functions["glTextureStorage3D"](name.value, 1, GL_RGBA8, layout.tile_width, layout.tile_height,
                                                len(views))
            else:
                functions["glTextureStorage2D"](name.value, 1, GL_RGBA8, layout.tile_width,
                                                len(views) * layout.tile_height)

    def set_sky(self, sky: torch.Tensor) -> None:
        """Each world's sky colour, sky [W, 3] float in [0, 1] (uploaded at the next copy)."""
        rgb = sky.to(torch.float64)
        if self.gray:
            rgb = (rgb @ GRAY_WEIGHTS)[:, None].expand(-1, 3)
        world_bytes = torch.cat((torch.round(rgb.clamp(0, 1) * 255), torch.full_like(rgb[:, :1], 255)), -1)
        self._bytes = world_bytes.to(torch.uint8).repeat_interleave(self.agents, dim=0)  # [views, 4]
        self._ready = [False] * self.layout.num_passes
        self._stale = [True] * self.layout.num_passes

    def fill(self, index: int, target: int) -> None:
        """Before pass `index` is drawn: its colour texture `target` shows the current sky."""
        if not self._ready[index]:
            self.copy_into(index, target)
        self._ready[index] = False  # the frame draws over it

    def refill(self, index: int, target: int) -> None:
        """After pass `index` was read: the sky for the next frame, copied now."""
        self.copy_into(index, target)
        self._ready[index] = True

    def copy_into(self, index: int, target: int) -> None:
        """Bring pass `index`'s image up to date, then copy it over the colour texture `target`."""
        views = self.layout.pass_views(index)
        functions = gl_functions()
        self._upload(index, views, functions)
        height, depth = (self.layout.tile_height, len(views)) if self.layered else \
            (len(views) * self.layout.tile_height, 1)
        functions["glCopyImageSubData"](self.names[index], self.target, 0, 0, 0, 0, target, self.target, 0, 0, 0,
                                        0, self.layout.tile_width, height, depth)

    def _upload(self, index: int, views: range, functions: dict) -> None:
        """The rows of the views (first to last) whose colour changed since the last upload."""
        if not self._stale[index]:  # every frame between resets: no comparison either (it cost 0.2 ms a pass)
            return
        self._stale[index] = False
        wanted = self._bytes[views.start:views.stop]
        if self._uploaded[index]:
            changed = (wanted != self._held[views.start:views.stop]).any(-1)
            if not bool(changed.any()):
                return
        else:  # a new texture holds no defined pixels
            changed = torch.ones(len(views), dtype=torch.bool)
            self._uploaded[index] = True
        where = changed.nonzero()[:, 0]
        first, last = int(where[0]), int(where[-1]) + 1
        th, tw = self.layout.tile_height, self.layout.tile_width
        rows = wanted[first:last, None, None, :].expand(-1, th, tw, 4).contiguous()
        unpack = ctypes.c_int()
        functions["glGetIntegerv"](GL_PIXEL_UNPACK_BUFFER_BINDING, ctypes.byref(unpack))
        if unpack.value:  # a bound buffer would turn the pointer into an offset into it
            functions["glBindBuffer"](GL_PIXEL_UNPACK_BUFFER, 0)
        try:
            if self.layered:
                functions["glTextureSubImage3D"](self.names[index], 0, 0, 0, first, tw, th, last - first, GL_RGBA,
                                                 GL_UNSIGNED_BYTE, rows.data_ptr())
            else:
                functions["glTextureSubImage2D"](self.names[index], 0, 0, first * th, tw, (last - first) * th,
                                                 GL_RGBA, GL_UNSIGNED_BYTE, rows.data_ptr())
        finally:
            if unpack.value:
                functions["glBindBuffer"](GL_PIXEL_UNPACK_BUFFER, unpack.value)
        self._held[views.start + first:views.start + last] = wanted[first:last]

    def close(self) -> None:
        """Delete the GL textures (with the context current)."""
        if self.names:
            names = (ctypes.c_uint * len(self.names))(*self.names)
            gl_functions()["glDeleteTextures"](len(self.names), names)
        self.names = []
