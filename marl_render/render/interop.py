"""CUDA-OpenGL interop: the renderer's pixel-pack buffer copied device to device into torch.

On a CUDA device the renderer reads every texture of a frame into one GL pixel-pack buffer
(readback.PackBuffer) and, instead of copying it to the host, hands it to CUDA: the buffer
is registered once (read-only), and every frame it is mapped, its device pointer taken,
copied with cudaMemcpyAsync (device to device) into torch CUDA tensors on the current
stream, and unmapped. No byte crosses to the host.

`Backend` is the few CUDA runtime calls this needs. `CudaRuntime` makes them through
ctypes on the libcudart that torch itself loaded, rather than through cuda-bindings: no
new dependency, and the very runtime (and primary context) torch uses, so torch's stream
handles and device pointers are valid in it as they are. It is made on first use only:
`import marl_render` loads no CUDA library of its own. Tests put fakes behind the same
interface (tests/test_interop.py).

`open_interop(readback, device, ...)` decides for a renderer: "host" never uses interop;
"gpu" uses it or raises with the reason; "auto" uses it where it works (a CUDA device whose
GL context renders on that same device) and otherwise reads through the host, with one
warning per reason per process. A GL context on another CUDA device than `device` is an
error in both modes, naming the two devices: the frames would cross devices silently.
"""
from __future__ import annotations

import ctypes
import warnings

import torch

from ..util.validation import describe

READBACKS = ("auto", "gpu", "host")  # what users choose; the renderer has two more for benchmarks

CUDA_GL_DEVICE_LIST_ALL = 1  # cudaGLDeviceListAll
CUDA_GRAPHICS_REGISTER_FLAGS_READ_ONLY = 1  # cudaGraphicsRegisterFlagsReadOnly
CUDA_MEMCPY_DEVICE_TO_DEVICE = 3  # cudaMemcpyDeviceToDevice


class InteropUnavailable(RuntimeError):
    """CUDA-OpenGL interop cannot be used here; the message says why."""


class Backend:
    """The CUDA runtime calls of the interop (every one raises RuntimeError on a CUDA error).
    `resource` is whatever register() returned; `stream` a cudaStream_t as an int."""

    def gl_devices(self) -> list[int]:
        """cudaGLGetDevices: the CUDA devices of the GL context current in this thread ([]: none)."""
        raise NotImplementedError

    def register(self, buffer: int):
        """cudaGraphicsGLRegisterBuffer of GL buffer `buffer`, read-only."""
        raise NotImplementedError

    def unregister(self, resource) -> None:
        raise NotImplementedError

    def map(self, resource, stream: int) -> None:
        raise NotImplementedError

    def pointer(self, resource) -> tuple[int, int]:
        """cudaGraphicsResourceGetMappedPointer: (device address, bytes) of a mapped resource."""
        raise NotImplementedError

    def copy(self, destination: int, source: int, size: int, stream: int) -> None:
        """cudaMemcpyAsync device to device, on `stream`."""
        raise NotImplementedError

    def unmap(self, resource, stream: int) -> None:
        raise NotImplementedError


class CudaRuntime(Backend):
    """The Backend through ctypes on the libcudart that torch loaded (see the module docstring)."""

    def __init__(self, library: ctypes.CDLL):
        self._cuda = library
        vp, uint, sint, size_t = ctypes.c_void_p, ctypes.c_uint, ctypes.c_int, ctypes.c_size_t
        signatures = {
            "cudaGLGetDevices": [ctypes.POINTER(uint), ctypes.POINTER(sint), uint, sint],
            "cudaGraphicsGLRegisterBuffer": [ctypes.POINTER(vp), uint, uint],
            "cudaGraphicsUnregisterResource": [vp],
            "cudaGraphicsMapResources": [sint, ctypes.POINTER(vp), vp],
            "cudaGraphicsResourceGetMappedPointer": [ctypes.POINTER(vp), ctypes.POINTER(size_t), vp],
            "cudaGraphicsUnmapResources": [sint, ctypes.POINTER(vp), vp],
            "cudaMemcpyAsync": [vp, vp, size_t, sint, vp],
        }
        for name, argtypes in signatures.items():
            function = getattr(library, name)
            function.argtypes, function.restype = argtypes, sint
        library.cudaGetErrorString.argtypes, library.cudaGetErrorString.restype = [sint], ctypes.c_char_p

    def _check(self, call: str, status: int) -> None:
        if status:
            text = self._cuda.cudaGetErrorString(status).decode(errors="replace")
            raise RuntimeError(f"{call} failed with CUDA error {status} ({text})")

    def gl_devices(self) -> list[int]:
        count, devices = ctypes.c_uint(0), (ctypes.c_int * 16)()
        status = self._cuda.cudaGLGetDevices(ctypes.byref(count), devices, 16, CUDA_GL_DEVICE_LIST_ALL)
        if status:  # cudaErrorNoDevice and the like: the context is not on a CUDA device
            return []
        return list(devices[:count.value])

    def register(self, buffer: int):
        resource = ctypes.c_void_p()
        self._check(f"cudaGraphicsGLRegisterBuffer(GL buffer {buffer})",
                    self._cuda.cudaGraphicsGLRegisterBuffer(ctypes.byref(resource), buffer,
                                                            CUDA_GRAPHICS_REGISTER_FLAGS_READ_ONLY))
        return resource

    def unregister(self, resource) -> None:
        self._check("cudaGraphicsUnregisterResource", self._cuda.cudaGraphicsUnregisterResource(resource))

    def map(self, resource, stream: int) -> None:
        self._check("cudaGraphicsMapResources",
                    self._cuda.cudaGraphicsMapResources(1, ctypes.byref(resource), ctypes.c_void_p(stream)))

    def pointer(self, resource) -> tuple[int, int]:
        address, size = ctypes.c_void_p(), ctypes.c_size_t()
        self._check("cudaGraphicsResourceGetMappedPointer",
                    self._cuda.cudaGraphicsResourceGetMappedPointer(ctypes.byref(address), ctypes.byref(size),
                                                                    resource))
        return int(address.value or 0), int(size.value)

    def copy(self, destination: int, source: int, size: int, stream: int) -> None:
        self._check("cudaMemcpyAsync", self._cuda.cudaMemcpyAsync(
            ctypes.c_void_p(destination), ctypes.c_void_p(source), size, CUDA_MEMCPY_DEVICE_TO_DEVICE,
            ctypes.c_void_p(stream)))

    def unmap(self, resource, stream: int) -> None:
        self._check("cudaGraphicsUnmapResources",
                    self._cuda.cudaGraphicsUnmapResources(1, ctypes.byref(resource), ctypes.c_void_p(stream)))


def torch_cudart_path() -> str | None:
    """The file of the libcudart mapped into this process (torch's, once CUDA is initialised)."""
    with open("/proc/self/maps") as maps:
        for line in maps:
            fields = line.split(maxsplit=5)  # address, perms, offset, dev, inode[, path]
            path = fields[5].strip() if len(fields) == 6 else ""
            if "libcudart" in path.rsplit("/", 1)[-1]:
                return path
    return None


def load_cuda_runtime() -> Backend:
    """CudaRuntime on torch's libcudart; InteropUnavailable with the reason where there is none."""
    if not torch.cuda.is_available():
        raise InteropUnavailable("torch has no usable CUDA device")
    torch.cuda.init()  # torch loads its libcudart here at the latest
    path = torch_cudart_path()
    if path is None:
        raise InteropUnavailable("torch's CUDA runtime library (libcudart) is not mapped into this process "
                                 "(a torch linked statically against CUDA has none to share)")
    try:
        return CudaRuntime(ctypes.CDLL(path))
    except (OSError, AttributeError) as error:
        raise InteropUnavailable(f"{path} lacks the CUDA-OpenGL interop calls: {error}") from None


class PackBufferInterop:
    """One renderer's use of CUDA on its pack buffer: registered once, again when the buffer's
    GL name changes (a new buffer), unregistered by close() (before the buffer is deleted)."""

    def __init__(self, backend: Backend, device: torch.device):
        self.backend, self.device = backend, device
        self.buffer = 0  # the GL name registered (0: none)
        self._resource = None

    def copy(self, buffer: int, regions: list) -> None:
        """Copy each (byte offset, destination tensor) of GL buffer `buffer` device to device into
        its destination, contiguous on `device`, on torch's current stream of that device."""
        if buffer != self.buffer:
            self.unregister()
            self._resource = self.backend.register(buffer)
            self.buffer = buffer
        stream = torch.cuda.current_stream(self.device).cuda_stream if self.device.type == "cuda" else 0
        self.backend.map(self._resource, stream)
        try:
            address, size = self.backend.pointer(self._resource)
            for offset, destination in regions:
                count = destination.numel() * destination.element_size()
                if not destination.is_contiguous() or destination.device != self.device or offset + count > size:
                    raise ValueError(f"cannot copy {count} bytes at offset {offset} of a {size}-byte mapped buffer "
                                     f"into a tensor of shape {tuple(destination.shape)} on {destination.device}")
                self.backend.copy(destination.data_ptr(), address + offset, count, stream)
        finally:
            self.backend.unmap(self._resource, stream)

    def unregister(self) -> None:
        """Let go of the registration (inside the GL context, before its buffer goes); safe twice."""
        if self._resource is not None:
            resource, self._resource, self.buffer = self._resource, None, 0
            self.backend.unregister(resource)

    close = unregister


_warned: set[str] = set()  # the reasons "auto" has already warned of in this process


def check_readback(readback, allowed=READBACKS) -> str:
    """`readback` if it is one of `allowed`, else a ValueError naming them."""
    if not isinstance(readback, str) or readback not in allowed:
        raise ValueError(f"readback must be one of {list(allowed)}, got {describe(readback)}")
    return readback


def check_device(readback: str, device: torch.device) -> None:
    """ValueError for readback "gpu" with a device that is not a CUDA one (before any GL work)."""
    if readback == "gpu" and device.type != "cuda":
        raise ValueError(f"readback='gpu' copies frames device to device and needs a CUDA device, got "
                         f"device={str(device)!r}; use readback='host' or 'auto'")


def open_interop(readback: str, device: torch.device, load=load_cuda_runtime) -> PackBufferInterop | None:
    """The interop for a renderer whose GL context is current in this thread, or None (the host
    path). readback "gpu" raises InteropUnavailable (or ValueError for a non-CUDA device) where
    "auto" warns once and returns None; a GL context on another CUDA device than `device` is a
    ValueError either way. `load` makes the Backend (tests pass fakes)."""
    check_device(readback, device)
    if readback == "host" or device.type != "cuda":
        return None
    index = torch.cuda.current_device() if device.index is None else device.index
    try:
        backend = load()
        gl_devices = backend.gl_devices()
        if not gl_devices:
            raise InteropUnavailable("the GL context is on no CUDA device (cudaGLGetDevices reports none: the GL "
                                     "driver is not NVIDIA's, e.g. Mesa llvmpipe)")
    except InteropUnavailable as error:
        if readback == "gpu":
            raise InteropUnavailable(f"readback='gpu' cannot use CUDA-OpenGL interop: {error}") from None
        reason = str(error)
        if reason not in _warned:
            _warned.add(reason)
            warnings.warn(f"readback='auto': CUDA-OpenGL interop is unavailable ({reason}); frames are read "
                          f"through the host and copied to {device}", RuntimeWarning, stacklevel=3)
        return None
    if index not in gl_devices:
        raise ValueError(f"the GL context renders on CUDA device(s) {gl_devices} but device={str(device)!r} is CUDA "
                         f"device {index}: open the GL context on the EGL device of CUDA device {index} "
                         f"(marl_render.backend.egl_device_for_cuda; MARL_RENDER_EGL_DEVICE or egl_device_index "
                         "name EGL's own order), or pass device='cuda:" f"{gl_devices[0]}'")
    return PackBufferInterop(backend, torch.device("cuda", index))
