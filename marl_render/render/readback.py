"""Reading Panda3D's render textures straight into torch memory with one GL call each.

Panda3D's own readback (RTM_copy_ram) reads a framebuffer into a RAM image Panda3D owns,
right after drawing it; the batch then needs one more full copy, and llvmpipe cannot
rasterise one framebuffer while the next is being drawn. The renderer instead renders
into textures (RTM_bind_or_copy) and, once every pass is drawn, reads each texture with
`glGetTextureSubImage` into the caller's tensor: the driver converts RGBA to the
requested components itself (measured: several times cheaper than dropping alpha in
torch) and the bytes land where the batch wants them.

The calls must run inside `backend.GLContext.current()` (the renderer reads within the
same block as its frame), which makes the shared context current in the calling thread;
they touch no binding Panda3D tracks (direct state access) and restore the pack
alignment and pixel-pack buffer binding they change.

`PackBuffer` is the other way to read: every texture of a frame is read into one GL
pixel-pack buffer (PBO), each at its own offset, in the bytes a direct read would give;
the batch then takes them from there in one copy per output, to the host
(`PackBuffer.download`) or, on a CUDA device, device to device (interop.py).
"""
from __future__ import annotations

import ctypes
import ctypes.util

import torch

from .backend import INSTALL_HINT, GLUnavailableError

GL_RED, GL_RGB, GL_RGBA = 0x1903, 0x1907, 0x1908
GL_UNSIGNED_BYTE = 0x1401
GL_PACK_ALIGNMENT = 0x0D05
GL_PIXEL_PACK_BUFFER = 0x88EB
GL_PIXEL_PACK_BUFFER_BINDING = 0x88ED
GL_STREAM_READ = 0x88E1
GL_MAX_ARRAY_TEXTURE_LAYERS = 0x88FF
FORMATS = {1: GL_RED, 3: GL_RGB, 4: GL_RGBA}

_functions = None


def gl_functions() -> dict:
    """GL entry points through eglGetProcAddress (they dispatch to the current context): those of
    the reads here and of the appearance effect's sky images (sky.py)."""
    global _functions
    if _functions is None:
        name = ctypes.util.find_library("EGL")
        if name is None:
            raise GLUnavailableError("libEGL not found: the renderer reads its textures through EGL. " + INSTALL_HINT)
        egl = ctypes.CDLL(name)
        egl.eglGetProcAddress.restype = ctypes.c_void_p
        egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
        uint, sint, ptr = ctypes.c_uint, ctypes.c_int, ctypes.c_void_p
        signatures = {
            "glGetTextureSubImage": (None, [uint, sint, sint, sint, sint, sint, sint, sint, uint, uint, sint, ptr]),
            "glGetIntegerv": (None, [uint, ctypes.POINTER(sint)]),
            "glPixelStorei": (None, [uint, sint]),
            "glBindBuffer": (None, [uint, uint]),
            "glGetError": (uint, []),
            "glCreateTextures": (None, [uint, sint, ctypes.POINTER(uint)]),
            "glTextureStorage2D": (None, [uint, sint, uint, sint, sint]),
            "glTextureSubImage2D": (None, [uint, sint, sint, sint, sint, sint, uint, uint, ptr]),
            "glTextureStorage3D": (None, [uint, sint, uint, sint, sint, sint]),
            "glTextureSubImage3D": (None, [uint, sint, sint, sint, sint, sint, sint, sint, uint, uint, ptr]),
            "glCopyImageSubData": (None, [uint, uint, sint, sint, sint, sint, uint, uint, sint, sint, sint, sint,
                                          sint, sint, sint]),
            "glDeleteTextures": (None, [sint, ctypes.POINTER(uint)]),
            "glCreateBuffers": (None, [sint, ctypes.POINTER(uint)]),
            "glNamedBufferData": (None, [uint, ctypes.c_ssize_t, ptr, uint]),
            "glGetNamedBufferSubData": (None, [uint, ctypes.c_ssize_t, ctypes.c_ssize_t, ptr]),
            "glDeleteBuffers": (None, [sint, ctypes.POINTER(uint)]),
        }
        functions = {}
        for function, (restype, argtypes) in signatures.items():
            address = egl.eglGetProcAddress(function.encode())
            if not address:
                raise GLUnavailableError(f"the GL driver has no {function} (OpenGL 4.5 is needed). " + INSTALL_HINT)
            functions[function] = ctypes.CFUNCTYPE(restype, *argtypes)(address)
        _functions = functions
    return _functions


def texture_id(texture, gsg) -> int:
    """The GL name of a Panda3D texture that `gsg` has created (rendered into at least once)."""
    context = texture.prepare_now(0, gsg.get_prepared_objects(), gsg)
    name = context.get_native_id() if context is not None else 0
    if not name:
        raise RuntimeError(f"texture {texture.get_name()!r} has no GL object yet; render a frame first")
    return int(name)


def _get_integer(functions, name: int) -> int:
    value = ctypes.c_int()
    functions["glGetIntegerv"](name, ctypes.byref(value))
    return value.value


def max_array_texture_layers() -> int:
    """GL_MAX_ARRAY_TEXTURE_LAYERS of the current context."""
    return _get_integer(gl_functions(), GL_MAX_ARRAY_TEXTURE_LAYERS)


def read_texture(name: int, width: int, height: int, components: int, destination: torch.Tensor,
                 layers: int = 1) -> None:
    """Rows [0, height) of texture `name` (of each of its first `layers` layers, for an array
    texture), bottom-up as GL stores them, as 8-bit `components` (1: red, 3: RGB, 4: RGBA)
    per pixel into `destination`, a contiguous CPU tensor of exactly
    layers * width * height * components bytes."""
    size = layers * width * height * components
    if not destination.is_contiguous() or destination.numel() * destination.element_size() != size:
        raise ValueError(f"destination must be a contiguous tensor of {size} bytes, got shape "
                         f"{tuple(destination.shape)} of {destination.dtype}")
    _get_texture(name, width, height, components, 0, destination.data_ptr(), layers)


def _get_texture(name: int, width: int, height: int, components: int, pack_buffer: int, pixels: int,
                 layers: int = 1) -> None:
    """glGetTextureSubImage of texture `name` (its first `layers` layers, for an array texture) into
    client memory at address `pixels` (pack_buffer 0) or into GL buffer `pack_buffer` at byte offset
    `pixels`."""
    size = layers * width * height * components
    functions = gl_functions()
    while functions["glGetError"]():  # errors of earlier calls are not ours to report
        pass
    alignment = _get_integer(functions, GL_PACK_ALIGNMENT)
    bound = _get_integer(functions, GL_PIXEL_PACK_BUFFER_BINDING)
    if bound != pack_buffer:
        functions["glBindBuffer"](GL_PIXEL_PACK_BUFFER, pack_buffer)
    functions["glPixelStorei"](GL_PACK_ALIGNMENT, 1)
    try:
        # bufSize counts from the start of the buffer when one is bound (the offset plus the bytes).
        functions["glGetTextureSubImage"](name, 0, 0, 0, 0, width, height, layers, FORMATS[components],
                                          GL_UNSIGNED_BYTE, size + (pixels if pack_buffer else 0), pixels)
        error = functions["glGetError"]()
    finally:
        functions["glPixelStorei"](GL_PACK_ALIGNMENT, alignment)
        if bound != pack_buffer:
            functions["glBindBuffer"](GL_PIXEL_PACK_BUFFER, bound)
    if error:
        raise RuntimeError(f"reading back GL texture {name} ({width}x{height}, {components} components) failed "
                           f"with GL error 0x{error:04x}")


class PackBuffer:
    """One GL pixel-pack buffer (PBO) that a frame's textures are read into, each at its own
    byte offset. Its GL name changes when it grows (a new buffer): `name` is what CUDA
    registers (interop.py). Every call runs inside `GLContext.current()`."""

    def __init__(self):
        self.name = 0  # GL buffer name; 0 until the first reserve()
        self.size = 0

    def reserve(self, size: int) -> None:
        """At least `size` bytes; a larger need makes a new buffer (a new name)."""
        if size <= self.size:
            return
        self.delete()
        functions = gl_functions()
        name = ctypes.c_uint()
        functions["glCreateBuffers"](1, ctypes.byref(name))
        # GL_STREAM_READ: written by the GL once a frame, read by the application (or CUDA) once.
        functions["glNamedBufferData"](name.value, size, None, GL_STREAM_READ)
        error = functions["glGetError"]()
        if error or not name.value:
            if name.value:
                functions["glDeleteBuffers"](1, ctypes.byref(name))
            raise RuntimeError(f"could not make a GL pixel-pack buffer of {size} bytes (GL error 0x{error:04x})")
        self.name, self.size = name.value, size

    def read_texture(self, texture: int, width: int, height: int, components: int, offset: int) -> None:
        """Texture `texture` as read_texture would give it, into this buffer from byte `offset`."""
        if offset < 0 or offset + width * height * components > self.size:
            raise ValueError(f"a read of {width * height * components} bytes at offset {offset} does not fit a "
                             f"pack buffer of {self.size} bytes")
        _get_texture(texture, width, height, components, self.name, offset)

    def download(self, offset: int, destination: torch.Tensor) -> None:
        """Bytes [offset, offset + destination's bytes) of the buffer into `destination`, a
        contiguous CPU tensor (the host copy; the GL waits for the reads into the buffer)."""
        size = destination.numel() * destination.element_size()
        if not destination.is_contiguous() or destination.device.type != "cpu":
            raise ValueError(f"destination must be a contiguous CPU tensor, got shape {tuple(destination.shape)} "
                             f"on {destination.device}")
        if offset < 0 or offset + size > self.size:
            raise ValueError(f"{size} bytes at offset {offset} are not within the pack buffer's {self.size} bytes")
        functions = gl_functions()
        functions["glGetNamedBufferSubData"](self.name, offset, size, destination.data_ptr())
        error = functions["glGetError"]()
        if error:
            raise RuntimeError(f"copying {size} bytes out of GL pack buffer {self.name} failed with GL error "
                               f"0x{error:04x}")

    def delete(self) -> None:
        """Free the GL buffer (inside the context that made it); safe to call twice."""
        if self.name:
            name = ctypes.c_uint(self.name)
            gl_functions()["glDeleteBuffers"](1, ctypes.byref(name))
        self.name = self.size = 0
