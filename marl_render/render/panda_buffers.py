"""Panda3D objects the renderer and the shadow pass share: buffer textures and their
writable memory, shader inputs, image textures.

`TextureMemory` is how packed tensors reach the GL without a copy of their own: the packer
(packing.py) writes into a torch view of the texture's RAM image, which Panda3D uploads
at the next draw.
"""
from __future__ import annotations

import functools

import numpy as np
import torch

from ..assets.images import texture_pixels


def buffer_texture(name: str, texels: int, integer: bool = False):
    """A dynamic buffer texture of `texels` RGBA32F texels (R32I when `integer`)."""
    from panda3d.core import GeomEnums, Texture

    texture = Texture(name)
    kind, fmt = (Texture.T_int, Texture.F_r32i) if integer else (Texture.T_float, Texture.F_rgba32)
    texture.setup_buffer_texture(max(texels, 1), kind, fmt, GeomEnums.UH_dynamic)
    return texture


def array_view(array, dtype) -> torch.Tensor:
    """A flat torch tensor of `dtype` on the memory of a Panda3D array (a PTA_uchar): one
    buffer request, and with it the 32 bytes Panda3D does not give back (TextureMemory)."""
    return torch.from_numpy(np.frombuffer(memoryview(array), dtype=dtype))


class TextureMemory:
    """A texture's RAM image as a flat writable torch tensor of `dtype`.

    Calling it marks the texture for upload at the next draw and returns the view. The view
    is made once and kept while Panda3D hands back the same array: every buffer request on
    a Panda3D PTA_uchar leaves a 32-byte heap block behind (Panda3D 1.10 never frees the
    shape it reports), so views made per frame, about ten per step of an env with shadows,
    grew a process by 0.3-0.6 MB per 1,000 steps for as long as it ran."""

    def __init__(self, texture, dtype):
        self.texture, self.dtype = texture, dtype
        self._array = self._tensor = None  # the PTA_uchar the view was made of, and the view

    def __call__(self) -> torch.Tensor:
        array = self.texture.modify_ram_image()  # marks the texture for upload
        # PTAs compare by the vector they point to; a resize would keep it, hence the length too.
        if self._tensor is None or array != self._array or len(array) != self._tensor.numel() * self._itemsize:
            self._tensor = array_view(array, self.dtype)
            self._array = array
        return self._tensor

    @property
    def _itemsize(self) -> int:
        return np.dtype(self.dtype).itemsize

    def release(self) -> None:
        """Drop the view (and with it Panda3D's array, which the view keeps alive)."""
        self._array = self._tensor = None


def int_input(value: int):
    """An int shader input that can be changed in place (a new one would make a new render state)."""
    from panda3d.core import PTA_int

    return PTA_int([int(value)])


@functools.cache
def clip_distances(count: int):
    """A ClipPlaneAttrib whose one job is to make Panda3D enable GL_CLIP_DISTANCE0..count-1.

    The shaders write gl_ClipDistance themselves (each view clipped to its own tile); the GL
    applies those only where the distances are enabled. Mesa's llvmpipe clips without the
    enable, the NVIDIA driver does not, and geometry spilled into neighbouring tiles (found on
    the first lent GPU). The planes keep every point (z + 1e30 >= 0), so Panda3D's culling on
    the CPU removes nothing. One attrib per count for the process, its planes under a node of
    their own: planes under a renderer's root made a cycle (root -> attrib -> plane -> root)
    that kept every closed renderer's scene graph alive."""
    from panda3d.core import ClipPlaneAttrib, LPlane, NodePath, PlaneNode

    planes = NodePath("clip_distances")
    attrib = ClipPlaneAttrib.make()
    for index in range(count):
        attrib = attrib.add_on_plane(planes.attach_new_node(PlaneNode(f"clip_distance_{index}", LPlane(0, 0, 1, 1e30))))
    return attrib


def vec3_input(values):
    from panda3d.core import LVecBase3f

    return LVecBase3f(*(float(v) for v in values))


def panda_texture(texture, name):
    """A Panda3D Texture from a Texture, or from pixels: an image path or a uint8 array [h, w, 3|4].

    Image files are decoded by Pillow (images.py), never by Panda3D's own readers, which
    end the process on some corrupt files."""
    from panda3d.core import SamplerState, Texture

    if type(texture).__name__ == "Texture":
        return texture
    try:
        array = texture_pixels(texture, name="texture")
    except (TypeError, ValueError) as error:
        raise type(error)(f"texture of group {name!r}: {error}") from None
    h, w, channels = array.shape
    result = Texture(f"texture:{name}")
    result.setup_2d_texture(w, h, Texture.T_unsigned_byte, Texture.F_rgb if channels == 3 else Texture.F_rgba)
    # Panda3D stores images bottom-up in BGR(A) order.
    swizzled = array[::-1, :, [2, 1, 0, 3][:channels]]
    result.set_ram_image(np.ascontiguousarray(swizzled).tobytes())
    result.set_minfilter(SamplerState.FT_linear_mipmap_linear)
    result.set_magfilter(SamplerState.FT_linear)
    return result
