"""``render_mode="human"``: frames shown in a matplotlib window, paced at ``render_fps``.

Matplotlib draws the window because it is already the project's plotting library, needs
no GL context of its own (the renderer's context is headless EGL and cannot open a
window) and picks whatever GUI toolkit the machine has. Where no window can be opened (no
display, no matplotlib, or only a non-interactive matplotlib backend) the first frame
gives one warning that says why, and nothing is shown; nothing else changes.
"""
from __future__ import annotations

import os
import sys
import warnings


def window_unavailable() -> str | None:
    """Why no window can be opened here, or None when one can."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return "this machine has no display (neither DISPLAY nor WAYLAND_DISPLAY is set)"
    try:
        import matplotlib
        import matplotlib.pyplot  # noqa: F401  (selects the backend)
        from matplotlib.backends import BackendFilter, backend_registry
    except ImportError:
        return "matplotlib (3.9 or newer) is not installed: pip install 'marl-render[human]'"
    backend = matplotlib.get_backend()
    if backend.lower() in backend_registry.list_builtin(BackendFilter.NON_INTERACTIVE):
        return f"matplotlib's backend {backend!r} cannot open windows (install a GUI toolkit such as tkinter)"
    return None


class Window:
    """A window that shows uint8 [H, W, 3] frames, at most `fps` a second.

    ``available()`` says whether it can (and warns once when it cannot); ``show(frame)``
    draws a frame; ``close()`` closes the window."""

    def __init__(self, title: str, fps: float):
        self.title = title
        self.fps = float(fps)
        self._figure = None
        self._image = None
        self._checked = False
        self.unavailable: str | None = None  # the reason, once the first frame found no window

    def available(self) -> bool:
        """Whether frames can be shown; the first call that finds they cannot warns why (once)."""
        if not self._checked:
            self._checked = True
            self.unavailable = window_unavailable()
            if self.unavailable:
                warnings.warn(f"render_mode='human' shows nothing: {self.unavailable}. Use render_mode='rgb_array' "
                              f"to get the frames as arrays.", UserWarning, stacklevel=4)
        return self.unavailable is None

    def show(self, frame) -> None:
        """Show `frame` (call only when `available()`); waits 1 / fps seconds while the window redraws."""
        import matplotlib.pyplot as plt

        if self._figure is None or not plt.fignum_exists(self._figure.number):  # first frame, or closed by the user
            height, width = frame.shape[:2]
            self._figure = plt.figure(self.title, figsize=(width / 50, height / 50))  # 2x the frame at 100 dpi
            axes = self._figure.add_axes((0, 0, 1, 1))
            axes.set_axis_off()
            self._image = axes.imshow(frame, interpolation="nearest")
            self._figure.show()
        else:
            self._image.set_data(frame)
        self._figure.canvas.draw_idle()
        self._figure.canvas.start_event_loop(1.0 / self.fps)  # draws, handles events, paces the episode

    def close(self) -> None:
        if self._figure is not None:
            import matplotlib.pyplot as plt

            plt.close(self._figure)
            self._figure = self._image = None
