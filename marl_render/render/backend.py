"""Headless OpenGL through Panda3D: configuration, GL contexts, diagnostics.

Panda3D's `p3headlessgl` opens an EGL context without a display: a GPU's driver when
one is present, Mesa's llvmpipe (CPU) otherwise. A `GLContext` owns one host context
and every renderer made on it, and releases them all in `close()` (or at the end of a
`with` block). Renderers given no context share the default one, created on first use
and kept for the life of the process.

$MARL_RENDER_PRC, read when the first context is made, adds Panda3D configuration lines
that take precedence over marl-render's own (lines split by newlines or a literal "\\n"; e.g. "gl-debug #t", which
has the GL driver say which call failed and why). It is for diagnostics.

Process-wide settings (`configure()`): the first context sets LP_NUM_THREADS (llvmpipe's
rasteriser threads) unless the user set it, and sends Panda3D's log, which carries
shader compiler errors, to the "marl_render.gl" logger instead of stderr. Both can be
switched off before the first context is made. Torch's thread count is left to the
callers: the renderer runs its small tensor ops on one thread inside its calls and
restores the caller's setting after (threads.py); the envs do the same with their
`torch_threads` (None: torch is left alone).

Threads: an EGL context can be current in only one thread at a time, and Panda3D leaves
it current in whichever thread drew last, so a draw from another thread would fail
(EGL_BAD_ACCESS) and silently keep the old pixels. Every piece of GL work therefore runs
inside `GLContext.current()`: under one process-wide lock (Panda3D's engine is one per
process), with the context made current in the calling thread and released (the
caller's own binding restored) afterwards.
"""
from __future__ import annotations

import atexit
import ctypes
import logging
import numbers
import os
import threading
import weakref
from contextlib import contextmanager
from dataclasses import dataclass

from ..util import triton_guard

_CONFIG = """
load-display p3headlessgl
window-type offscreen
audio-library-name null
sync-video false
framebuffer-srgb false
framebuffer-multisample false
textures-power-2 none
gl-coordinate-system default
notify-level-display error
notify-level-glgsg error
notify-level-egldisplay error
notify-level-gobj error
# Without ShowBase nobody garbage-collects render states: keep them reference-counted.
garbage-collect-states false
"""

INSTALL_HINT = (
    "marl-render needs a headless OpenGL 4.1+ driver reachable through EGL. On Debian/Ubuntu: "
    "`apt-get install libegl1 libgl1 libgl1-mesa-dri libgles2` (Mesa, CPU) or an NVIDIA driver "
    "with its EGL vendor file (GPU)."
)

_lock = threading.Lock()  # guards the default context and the settings below
_gl_lock = threading.RLock()  # held for all GL work: Panda3D's engine is shared by every context
_context = None  # the default context (see context())
_open_contexts: set = set()  # contexts not yet closed (the device check, the fork guard)
_process_device: list = []  # [egl_device_index] once the first context was made: one device per process
_panda_log = None  # Panda3D's log when captured: a LineStream shared by every context


@dataclass
class Settings:
    """Process-wide effects of marl-render, applied when the first GLContext is made.

    set_lp_num_threads: set LP_NUM_THREADS (llvmpipe's rasteriser threads) to twice the
        cores, at most 16, when the user has not set it (about 10% faster frames measured on
        2 cores); False leaves os.environ alone.
    capture_panda_log: send Panda3D's log (Notify) to the "marl_render.gl" logger and
        keep its recent lines, so shader errors can carry the compiler log; False leaves
        Panda3D's log stream as it is (on stderr), and errors then say so."""

    set_lp_num_threads: bool = True
    capture_panda_log: bool = True


SETTINGS = Settings()


def configure(*, set_lp_num_threads: bool | None = None, capture_panda_log: bool | None = None) -> Settings:
    """Change the process-wide settings (see Settings); None keeps one as it is. They take
    effect when the first GLContext is made: after that, a change raises RuntimeError."""
    changes = {"set_lp_num_threads": set_lp_num_threads, "capture_panda_log": capture_panda_log}
    for name, value in changes.items():
        if value is not None and not isinstance(value, bool):
            raise TypeError(f"{name} must be a bool or None, got {type(value).__name__} {value!r}")
    with _lock:
        changes = {k: v for k, v in changes.items() if v is not None and v != getattr(SETTINGS, k)}
        if changes and _process_device:
            raise RuntimeError(f"marl_render.configure({', '.join(f'{k}={v}' for k, v in changes.items())}) must be "
                               "called before the first GL context is made (the first renderer or env)")
        for name, value in changes.items():
            setattr(SETTINGS, name, value)
        return SETTINGS


LOG = logging.getLogger("marl_render.gl")


class ShaderCompileError(RuntimeError):
    """A shader variant failed to compile or link; the message carries the GL log."""


class GLUnavailableError(RuntimeError):
    """No usable headless OpenGL context could be created."""


class ForkedContextError(RuntimeError):
    """GL state was inherited through fork(); it cannot be used in the child."""


@dataclass(frozen=True)
class GLInfo:
    vendor: str
    renderer: str
    gl_version: str
    glsl_version: str
    max_texture_size: int
    max_framebuffer_size: int

    def as_dict(self) -> dict:
        return dict(self.__dict__)


_EGL_DRAW, _EGL_READ = 0x3059, 0x305A  # eglGetCurrentSurface's argument


class _EGLBinding:
    """What eglMakeCurrent binds in one thread: display, draw and read surfaces, context
    (all None: nothing current)."""

    def __init__(self, library):
        self._egl = library
        for name in ("eglGetCurrentDisplay", "eglGetCurrentContext", "eglGetCurrentSurface"):
            getattr(library, name).restype = ctypes.c_void_p
        library.eglMakeCurrent.argtypes = [ctypes.c_void_p] * 4
        library.eglMakeCurrent.restype = ctypes.c_uint
        library.eglGetError.restype = ctypes.c_int

    def get(self) -> tuple:
        egl = self._egl
        return (egl.eglGetCurrentDisplay(), egl.eglGetCurrentSurface(_EGL_DRAW), egl.eglGetCurrentSurface(_EGL_READ),
                egl.eglGetCurrentContext())

    def set(self, binding: tuple, display_for_release) -> None:
        """Bind `binding` in this thread; a binding without display releases this thread's
        context on `display_for_release`."""
        display, draw, read, context = binding
        if display is None:
            display, draw, read, context = display_for_release, None, None, None
        if not self._egl.eglMakeCurrent(display, draw, read, context):
            raise RuntimeError(f"eglMakeCurrent failed with EGL error 0x{self._egl.eglGetError():04x}; the GL "
                               "context may be current in a thread that holds it outside marl-render")


class GLContext:
    """A headless GL context: Panda3D's engine, a pipe and a 1x1 host buffer whose GSG all
    render targets of the renderers made on it share.

    It owns those renderers: close() (or leaving a `with` block) closes each of them, then
    the host buffer; a closed context raises RuntimeError when used. Pass it to
    BatchRenderer(scene, context=ctx) or to an env (context=ctx); without one they share
    the default context (context()). One process renders on one EGL device
    (egl_device_index; None: $MARL_RENDER_EGL_DEVICE, else the default display)."""

    def __reduce__(self):  # copy.copy, copy.deepcopy and pickle all come here
        raise TypeError("a marl_render GLContext cannot be pickled or copied: it is this process's EGL context; "
                        "make one where it is needed (marl_render.GLContext()) or use the default")

    def __init__(self, egl_device_index: int | None = None):
        from panda3d.core import FrameBufferProperties, GraphicsEngine, GraphicsPipe, WindowProperties

        egl_device_index = _device_index(egl_device_index)
        if egl_device_index is None:
            egl_device_index = _env_device_index()
        _check_not_forked()
        with _lock:
            _setup_process(egl_device_index)
        self.pid = os.getpid()
        self.device_index = egl_device_index
        self.lock = _gl_lock
        self.closed = False
        self.host = None
        self._owned = weakref.WeakSet()  # renderers made on this context, closed with it
        self.recent_log: list[str] = []
        self.engine = GraphicsEngine.get_global_ptr()
        self.pipe = _pipe()
        if self.pipe is None or not self.pipe.is_valid():
            raise GLUnavailableError("no EGL display could be initialised through Panda3D's p3headlessgl "
                                     "(libEGL or a GL driver is missing). " + INSTALL_HINT + self._log_tail())
        props = FrameBufferProperties()
        props.set_rgba_bits(8, 8, 8, 8)
        props.set_depth_bits(24)
        self.host = self.engine.make_output(self.pipe, "marl_render_host", -100, props,
                                            WindowProperties.size(1, 1), GraphicsPipe.BF_refuse_window)
        if self.host is None:
            raise GLUnavailableError("could not create a headless OpenGL context through EGL. " + INSTALL_HINT
                                     + self._log_tail())
        self.engine.open_windows()
        self.gsg = self.host.get_gsg()
        # Opening the host left its context current in this thread: remember that binding
        # and release it, so that any thread can take it through current().
        self._egl = _EGLBinding(ctypes.CDLL("libEGL.so.1"))  # the library p3headlessgl is linked to
        self._binding = self._egl.get()
        if self._binding[3] is None:
            raise GLUnavailableError("Panda3D opened its headless buffer but left no EGL context current. "
                                     + INSTALL_HINT + self._log_tail())
        self._egl.set((None,) * 4, self._binding[0])
        if not self.gsg.get_supports_glsl() or self.gsg.get_driver_shader_version_major() < 4:
            raise GLUnavailableError(
                f"OpenGL driver {self.gsg.get_driver_renderer()!r} lacks GLSL 4.x "
                f"(has {self.gsg.get_driver_shader_version_major()}.{self.gsg.get_driver_shader_version_minor()}). "
                + INSTALL_HINT)
        with _lock:
            _open_contexts.add(self)

    def __enter__(self) -> GLContext:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def check_usable(self) -> None:
        """RuntimeError once closed; ForkedContextError in a process forked after it was made."""
        if self.closed:
            raise RuntimeError("this GLContext is closed; make a new one (or use the default context)")
        if self.pid != os.getpid():
            raise ForkedContextError(FORKED_MESSAGE)

    def own(self, resource) -> None:
        """Close `resource` (anything with close()) when this context closes."""
        self.check_usable()
        self._owned.add(resource)

    def close(self) -> None:
        """Close every renderer made on this context, then free the host buffer; safe to
        call twice. In a forked child nothing of the parent's GL is touched."""
        if self.closed:
            return
        for resource in list(self._owned):  # while the context can still be made current
            resource.close()
        self._owned.clear()
        self.closed = True
        with _lock:
            _open_contexts.discard(self)
        if self.host is not None and self.pid == os.getpid():
            with self.lock:
                self.engine.remove_window(self.host)
        self.host = self.gsg = None

    @contextmanager
    def current(self):
        """Hold the GL lock with this context current in the calling thread; afterwards the
        thread's previous binding (usually none) is restored. Reentrant."""
        self.check_usable()
        with self.lock:
            previous = self._egl.get()
            self._egl.set(self._binding, None)
            try:
                yield self
            finally:
                self._egl.set(previous, self._binding[0])

    def drop_render_texture_events(self) -> None:
        """Remove the "render-texture-targets-changed" events that Panda3D queues whenever a
        buffer's render textures change. Without ShowBase nothing consumes the global event
        queue, so they would pile up for the life of the process (two per renderer, each a
        small block that keeps a heap page from being returned). Other events are put back
        in order."""
        from panda3d.core import EventQueue

        queue = EventQueue.get_global_event_queue()
        if queue.is_queue_empty():
            return
        kept = []
        while not queue.is_queue_empty():
            event = queue.dequeue_event()
            if event.name != "render-texture-targets-changed":
                kept.append(event)
        for event in kept:
            queue.queue_event(event)

    def _log_tail(self) -> str:
        lines = self.drain_log()
        return ("\nGL log:\n" + "\n".join(lines)) if lines else ""

    def drain_log(self) -> list[str]:
        """New lines of Panda3D's log since the last call (also kept in recent_log); none
        when the log is not captured (configure(capture_panda_log=False))."""
        lines = []
        while _panda_log is not None and _panda_log.is_text_available():
            line = _panda_log.get_line()
            lines.append(line)
            LOG.warning("%s", line)
        if lines:
            self.recent_log = (self.recent_log + lines)[-200:]
        return lines

    def info(self) -> GLInfo:
        gsg = self.gsg
        max_size = int(gsg.get_max_texture_dimension())
        return GLInfo(
            vendor=gsg.get_driver_vendor(),
            renderer=gsg.get_driver_renderer(),
            gl_version=gsg.get_driver_version(),
            glsl_version=f"{gsg.get_driver_shader_version_major()}.{gsg.get_driver_shader_version_minor()}",
            max_texture_size=max_size,
            max_framebuffer_size=max_size,
        )


def _device_index(value) -> int | None:
    if value is not None and (isinstance(value, bool) or not isinstance(value, numbers.Integral)):
        raise TypeError(f"egl_device_index must be an int >= 0 or None, got {type(value).__name__} {value!r}")
    if value is not None and value < 0:
        raise ValueError(f"egl_device_index must be an int >= 0 or None, got {value}")
    return None if value is None else int(value)


def _setup_process(egl_device_index: int | None) -> None:
    """Once per process, before the first context: Panda3D's configuration, the settings
    of SETTINGS; afterwards, check that a new context asks for the same device."""
    global _panda_log
    if _process_device:
        if egl_device_index is not None and egl_device_index != _process_device[0]:
            in_use = "the default EGL display" if _process_device[0] is None else f"EGL device {_process_device[0]}"
            raise ValueError(f"egl_device_index={egl_device_index} was given, but this process's GL context already "
                             f"uses {in_use} (egl_device_index={_process_device[0]}); one process renders on one "
                             "device: pass the same index everywhere, or use one process per device")
        return
    from panda3d.core import LineStream, Notify, loadPrcFileData

    triton_guard.install()  # before Mesa's LLVM is loaded: see triton_guard.py
    # Diagnostics only: Panda3D configuration lines of the user's, before marl-render's own so that they
    # win (a page's first value of a variable counts); the GPU kit runs once with "gl-debug #t".
    config = os.environ.get("MARL_RENDER_PRC", "").replace("\\n", "\n") + "\n" + _CONFIG
    if egl_device_index is not None:
        config += f"egl-device-index {egl_device_index}\n"
    loadPrcFileData("marl_render", config)
    if SETTINGS.set_lp_num_threads:
        # llvmpipe splits rasterisation into bins over LP_NUM_THREADS threads (default: one
        # per core); twice as many threads balance uneven tiles better (~10% faster frames
        # measured on 2 cores). Only a default: a value the user set is kept.
        os.environ.setdefault("LP_NUM_THREADS", str(min(16, 2 * (os.cpu_count() or 1))))
    if SETTINGS.capture_panda_log:
        # Panda3D's log (shader compiler output among it) is captured so that errors can
        # carry it; every line is forwarded to the "marl_render.gl" logger.
        _panda_log = LineStream()
        Notify.ptr().set_ostream_ptr(_panda_log, False)
    _process_device.append(egl_device_index)


def _pipe():
    """The p3headlessgl pipe, one per process (made with the first context)."""
    global _pipe_instance
    if _pipe_instance is None:
        from panda3d.core import GraphicsPipeSelection

        _pipe_instance = GraphicsPipeSelection.get_global_ptr().make_module_pipe("p3headlessgl")
    return _pipe_instance


_pipe_instance = None

FORKED_MESSAGE = (
    "this process was forked after OpenGL was initialised in its parent; GL contexts do not "
    "survive fork(). Start workers with the 'spawn' start method "
    "(multiprocessing.set_start_method('spawn'), or TorchRL's ParallelEnv default).")


def _check_not_forked() -> None:
    if any(c.pid != os.getpid() for c in list(_open_contexts)):
        raise ForkedContextError(FORKED_MESSAGE)


def _forget_in_child():
    # The child shares the parent's GL handles but not its driver threads: mark them stale.
    global _gl_lock
    _gl_lock = threading.RLock()  # another thread may have held it at fork time
    for c in list(_open_contexts):
        c.pid = -1
        c.lock = _gl_lock


os.register_at_fork(after_in_child=_forget_in_child)


def _close_at_exit():
    # While the interpreter is still whole, close every context of this process and with it
    # every renderer made on it. A finaliser that closes an env later in the teardown, after
    # module globals were cleared (RLlib's env runners do), then finds nothing left to free,
    # instead of failing in an 'Exception ignored in ... __del__' message.
    for c in list(_open_contexts):
        if c.pid == os.getpid():
            try:
                c.close()
            except Exception:  # exit goes on; nothing here may be left half-closed for long
                pass


atexit.register(_close_at_exit)


def context(egl_device_index: int | None = None) -> GLContext:
    """The default GL context, shared by every renderer and env given none: made on first
    use on EGL device `egl_device_index` (None: $MARL_RENDER_EGL_DEVICE, else the default
    display), and again after it was closed. A process renders on one device: asking for
    another is a ValueError."""
    global _context
    egl_device_index = _device_index(egl_device_index)
    _check_not_forked()
    with _lock:
        current = _context if _context is not None and not _context.closed else None
    if current is None:
        current = GLContext(egl_device_index)
        with _lock:
            if _context is None or _context.closed:
                _context = current
            else:  # another thread made one meanwhile
                current.close()
                current = _context
    elif egl_device_index is not None and egl_device_index != current.device_index:
        in_use = ("the default EGL display" if current.device_index is None
                  else f"EGL device {current.device_index}")
        raise ValueError(f"egl_device_index={egl_device_index} was given, but this process's GL context already "
                         f"uses {in_use} (egl_device_index={current.device_index}); one process renders on one "
                         "device: pass the same index everywhere, or use one process per device")
    return current


EGL_CUDA_DEVICE_NV = 0x323A  # eglQueryDeviceAttribEXT: the CUDA device index of an NVIDIA EGL device


def egl_cuda_devices() -> list:
    """The CUDA device of each EGL device, in EGL's own order (the order egl_device_index and
    MARL_RENDER_EGL_DEVICE count in): an int, or None for a device that is not a CUDA one
    (Mesa's). [] where EGL cannot enumerate its devices (EGL_EXT_device_enumeration)."""
    egl = ctypes.CDLL("libEGL.so.1")
    egl.eglGetProcAddress.restype, egl.eglGetProcAddress.argtypes = ctypes.c_void_p, [ctypes.c_char_p]
    query_devices = egl.eglGetProcAddress(b"eglQueryDevicesEXT")
    query_attribute = egl.eglGetProcAddress(b"eglQueryDeviceAttribEXT")
    if not query_devices or not query_attribute:
        return []
    query_devices = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_int, ctypes.POINTER(ctypes.c_void_p),
                                     ctypes.POINTER(ctypes.c_int))(query_devices)
    query_attribute = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_void_p, ctypes.c_int,
                                       ctypes.POINTER(ctypes.c_ssize_t))(query_attribute)  # EGLAttrib: intptr_t
    count = ctypes.c_int(0)
    if not query_devices(0, None, ctypes.byref(count)) or count.value <= 0:
        return []
    devices = (ctypes.c_void_p * count.value)()
    if not query_devices(count.value, devices, ctypes.byref(count)):
        return []
    result = []
    for device in devices[:count.value]:
        value = ctypes.c_ssize_t(-1)
        result.append(int(value.value) if query_attribute(device, EGL_CUDA_DEVICE_NV, ctypes.byref(value)) else None)
    return result


def egl_device_for_cuda(cuda_index: int, devices: list) -> int | None:
    """The index, in EGL's order, of the EGL device whose EGL_CUDA_DEVICE_NV is `cuda_index`
    (`devices` as egl_cuda_devices() gives them); None where no EGL device is that CUDA device."""
    matches = [index for index, cuda in enumerate(devices) if cuda == cuda_index]
    return matches[0] if matches else None


def context_for_cuda(cuda_index: int | None, query=egl_cuda_devices) -> GLContext:
    """The default context for frames on CUDA device `cuda_index` (None: not a CUDA device). The
    first context of a process asked for with a CUDA device opens the EGL device that is that CUDA
    device (EGL's order need not be CUDA's), unless MARL_RENDER_EGL_DEVICE names one; where none
    matches, or the process has a context already, the default one is used as it is (the interop's
    cudaGLGetDevices check, interop.py, then names a mismatch). `query`: egl_cuda_devices (tests
    pass fakes)."""
    with _lock:
        chosen = bool(_process_device)  # the first context fixed the process's device already
    if cuda_index is None or chosen or _env_device_index() is not None:
        return context()
    return context(egl_device_for_cuda(cuda_index, query()))


def _env_device_index() -> int | None:
    value = os.environ.get("MARL_RENDER_EGL_DEVICE", "").strip()
    if value == "":
        return None
    if not value.isdigit():
        raise ValueError(f"MARL_RENDER_EGL_DEVICE must be an EGL device index (an int >= 0), got {value!r}")
    return int(value)


def gl_info() -> GLInfo:
    return context().info()
