"""Headless OpenGL through Panda3D: configuration, the shared GL context, diagnostics.

Panda3D's `p3headlessgl` opens an EGL context without a display: a GPU's driver when
one is present, Mesa's llvmpipe (CPU) otherwise. All renderers of a process share one
host context, created on first use.

Threads: an EGL context can be current in only one thread at a time, and Panda3D leaves
it current in whichever thread drew last, so a draw from another thread would fail
(EGL_BAD_ACCESS) and silently keep the old pixels. Every piece of GL work therefore runs
inside `_Context.current()`: under one process-wide lock, with the context made current
in the calling thread and released (the caller's own binding restored) afterwards.
"""
from __future__ import annotations

import ctypes
import logging
import numbers
import os
import threading
from contextlib import contextmanager
from dataclasses import dataclass

from . import triton_guard

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

_lock = threading.Lock()
_context = None


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


class _Context:
    """Panda3D engine, pipe and a 1x1 host buffer whose GSG all render targets share."""

    def __init__(self, egl_device_index: int | None):
        from panda3d.core import (FrameBufferProperties, GraphicsEngine, GraphicsPipe,
                                  GraphicsPipeSelection, WindowProperties, loadPrcFileData)

        triton_guard.install()  # before Mesa's LLVM is loaded: see triton_guard.py
        config = _CONFIG
        if egl_device_index is not None:
            config += f"egl-device-index {int(egl_device_index)}\n"
        loadPrcFileData("marl_render", config)
        # llvmpipe splits rasterisation into bins over LP_NUM_THREADS threads (default: one
        # per core); twice as many threads balance uneven tiles better (~10% faster frames
        # measured on 2 cores). Only a default: a value the user set is kept.
        os.environ.setdefault("LP_NUM_THREADS", str(min(16, 2 * (os.cpu_count() or 1))))
        self.pid = os.getpid()
        # Panda3D's log (shader compiler output among it) is captured so that errors can
        # carry it; every line is forwarded to the "marl_render.gl" logger.
        from panda3d.core import LineStream, Notify

        self.log = LineStream()
        Notify.ptr().set_ostream_ptr(self.log, False)
        self.recent_log: list[str] = []
        self.engine = GraphicsEngine.get_global_ptr()
        selection = GraphicsPipeSelection.get_global_ptr()
        self.pipe = selection.make_module_pipe("p3headlessgl")
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
        self.device_index = egl_device_index
        self.lock = threading.RLock()
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

    @contextmanager
    def current(self):
        """Hold the GL lock with this context current in the calling thread; afterwards the
        thread's previous binding (usually none) is restored. Reentrant."""
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
        """New lines of Panda3D's log since the last call (also kept in recent_log)."""
        lines = []
        while self.log.is_text_available():
            line = self.log.get_line()
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


def _forget_in_child():
    # The child shares the parent's GL handles but not its driver threads: mark them stale.
    if _context is not None:
        _context.pid = -1
        _context.lock = threading.RLock()  # another thread may have held it at fork time


os.register_at_fork(after_in_child=_forget_in_child)


def context(egl_device_index: int | None = None) -> _Context:
    """The process-wide GL context, created on first use on EGL device `egl_device_index`
    (None: $MARL_RENDER_EGL_DEVICE, else the default display). Once it exists, asking for
    another device is an error: a process renders on one device."""
    global _context
    if egl_device_index is not None and (isinstance(egl_device_index, bool)
                                         or not isinstance(egl_device_index, numbers.Integral)):
        raise TypeError(f"egl_device_index must be an int >= 0 or None, got {type(egl_device_index).__name__} "
                        f"{egl_device_index!r}")
    if egl_device_index is not None and egl_device_index < 0:
        raise ValueError(f"egl_device_index must be an int >= 0 or None, got {egl_device_index}")
    with _lock:
        if _context is not None and _context.pid != os.getpid():
            raise ForkedContextError(
                "this process was forked after OpenGL was initialised in its parent; GL contexts do not "
                "survive fork(). Start workers with the 'spawn' start method "
                "(multiprocessing.set_start_method('spawn'), or TorchRL's ParallelEnv default).")
        if egl_device_index is not None:
            egl_device_index = int(egl_device_index)
        if _context is None:
            _context = _Context(egl_device_index if egl_device_index is not None else _env_device_index())
        elif egl_device_index is not None and egl_device_index != _context.device_index:
            in_use = ("the default EGL display" if _context.device_index is None
                      else f"EGL device {_context.device_index}")
            raise ValueError(f"egl_device_index={egl_device_index} was given, but this process's GL context already "
                             f"uses {in_use} (egl_device_index={_context.device_index}); one process renders on one "
                             "device: pass the same index everywhere, or use one process per device")
        return _context


def _env_device_index() -> int | None:
    value = os.environ.get("MARL_RENDER_EGL_DEVICE", "").strip()
    if value == "":
        return None
    if not value.isdigit():
        raise ValueError(f"MARL_RENDER_EGL_DEVICE must be an EGL device index (an int >= 0), got {value!r}")
    return int(value)


def gl_info() -> GLInfo:
    return context().info()
