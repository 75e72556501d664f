"""The renderer-facing part of the driver: a scenario's states as pixels.

``EnvRenderer`` builds the agents' renderer from the scenario's scene binding (and, on first
use, the overview renderer), hands it the instance data of a state, and reads the frames
back. It knows nothing of episodes, counters or actions: the driver (envs/core.py) decides
when to draw and what to return.
"""
from __future__ import annotations

import torch

import marl_render as mr
from marl_render.render import memory
from marl_render.util.transforms import quat_from_yaw_pitch_roll, quat_multiply
from marl_render.util.validation import resolution_hw


class EnvRenderer:
    """The agents' views (one renderer, a camera per agent) and the overview (one per world)."""

    def __init__(self, scenario, *, resolution: tuple, effects: tuple, shadows, grayscale: bool,
                 context: mr.GLContext, device: torch.device, multisamples: int = 0, supersample: int = 1,
                 appearance: mr.Appearance | None = None, readback: str = "auto",
                 layered: bool = False, exact_tiles: bool = False, impostors="auto"):
        self.scenario, self.resolution, self.shadows = scenario, resolution, shadows
        self.appearance = appearance  # the looks' distribution ("appearance" is then in effects)
        self._look = None  # the AppearanceParams of the current worlds (set_appearance)
        self._free_cameras = None  # the agents' free cameras as place_cameras left them (camera jitter)
        self.multisamples, self.supersample = multisamples, supersample  # the agents' views only
        # The agents' views only: the overview has one tile per world.
        self.layered, self.exact_tiles = layered, exact_tiles
        self.grayscale, self.context, self.device = grayscale, context, device
        self.impostors = impostors  # both renderers: spheres as impostors where they can (BatchRenderer's)
        self.readback = readback  # the frames are born on `device` (BatchRenderer's readback and device)
        self.overview_renderer = None
        self.renderer = None
        # The next sync must send everything: set before any change that a pose update does not
        # carry (a reset) and kept until a sync has finished, so an interrupted one (a caught
        # Ctrl-C) cannot leave the renderer's copy of the scene half old.
        self._needs_full = True
        scene = self._scene(overview=False, resolution=resolution, effects=effects)
        check_memory(scene, scenario.num_worlds, scenario.num_agents, resolution)
        self.renderer = self._renderer(scene, overview=False)

    def sync(self, state, full: bool) -> None:
        """Hand the agents' renderer the instance data of `state` (full: everything, else poses;
        everything anyway after invalidate() or an interrupted sync)."""
        full = full or self._needs_full
        self._needs_full = True
        self._sync(self.renderer, state, full)
        self._needs_full = False

    def set_appearance(self, ids: torch.Tensor, worlds: torch.Tensor | None = None) -> None:
        """The looks of the worlds where `worlds` ([W] bool, None: all) is True, from their ids ([W]
        int64): the renderers' appearance rows and the agents' camera jitter (fov_y, and the height
        and pitch of the mounted or free cameras). Only those worlds are sampled (a reset of a few
        worlds costs a few draws); the others keep theirs."""
        if worlds is None or self._look is None:
            self._look = self.appearance.sample(ids)
        else:
            fresh = self.appearance.sample(ids[worlds])
            self._look = mr.AppearanceParams(**{
                name: torch.index_put(value, (worlds,), getattr(fresh, name))
                for name, value in vars(self._look).items()})
        for renderer in (self.renderer, self.overview_renderer):
            if renderer is not None:
                renderer.set_appearance(**self._look.renderer_kwargs())
        if self.appearance.camera:
            self._jitter_cameras(self.renderer, self._look)

    def _jitter_cameras(self, renderer: mr.BatchRenderer, look) -> None:
        scene = renderer.scene
        W, A = scene.num_worlds, scene.agents_per_world
        fov_y = (scene.fov_y * look.fov_scale[:, None]).expand(W, A)
        up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        height = look.camera_height[:, None, None] * up  # [W, 1, 3]
        mount = scene.camera_mount
        if mount is not None:  # in the body's frame: bodies stand upright (yaw only)
            offset = torch.tensor(mount.offset, dtype=torch.float64) + height.expand(W, A, 3)
            renderer.set_cameras(fov_y=fov_y, mount_offset=offset,
                                 mount_pitch=(mount.pitch + look.camera_pitch[:, None]).expand(W, A))
            return
        position, rotation = self._free_cameras
        tilt = quat_from_yaw_pitch_roll(torch.zeros(W, A, dtype=torch.float64),
                                        look.camera_pitch[:, None].expand(W, A))  # about the camera's x axis
        renderer.set_cameras(position=position + height, fov_y=fov_y,
                             rotation=quat_multiply(rotation.to(torch.float64), tilt))

    def invalidate(self) -> None:
        """The state is about to change beyond poses: the next sync sends everything."""
        self._needs_full = True

    def render(self) -> mr.Frame:
        return self.renderer.render()

    def overview(self, state, resolution=None) -> torch.Tensor:
        """uint8 [W, H2, W2, 3] of `state` from the overview camera of every world; the overview
        renderer is built on first use and rebuilt when `resolution` changes."""
        resolution = resolution_hw(self.scenario.overview_resolution if resolution is None else resolution)
        current = self.overview_renderer
        if current is None or current.scene.resolution != resolution:
            effects = ("lighting", "shadows") if self.shadows else ("lighting",)
            effects += ("appearance",) if self.appearance is not None else ()
            scene = self._scene(overview=True, resolution=resolution, effects=effects)
            replaced = 0 if current is None else memory.renderer_bytes(current.scene)
            memory.check_fits(memory.renderer_bytes(scene) - replaced,
                              f"render_overview(resolution={resolution}) with num_worlds={self.scenario.num_worlds}",
                              "lower the overview's resolution")
            if current is not None:
                current.close()
                self.overview_renderer = None
            self.overview_renderer = self._renderer(scene, overview=True)
            if self._look is not None:  # the worlds' looks; the overview camera is not jittered
                self.overview_renderer.set_appearance(**self._look.renderer_kwargs())
        self._sync(self.overview_renderer, state, full=True)
        return self.overview_renderer.render().rgb[:, 0].to(self.device)

    def close(self) -> None:
        for renderer in (self.renderer, self.overview_renderer):
            if renderer is not None:
                renderer.close()
        self.overview_renderer = None

    # ------------------------------------------------------------------ internals
    def _scene(self, overview: bool, resolution, effects) -> mr.Scene:
        s = self.scenario
        scene = mr.Scene(num_worlds=s.num_worlds, agents_per_world=1 if overview else s.num_agents,
                         resolution=resolution, effects=effects, background=s.background,
                         fov_y=s.overview_fov_y if overview else s.fov_y, near=s.near, far=s.far,
                         shadows=self.shadows or mr.Shadows(),
                         surface_patterns=self.appearance is not None and self.appearance.textures)
        s.build_scene(scene, overview)
        return scene

    def _renderer(self, scene: mr.Scene, overview: bool) -> mr.BatchRenderer:
        antialias = {} if overview else dict(multisamples=self.multisamples, supersample=self.supersample,
                                             layered=self.layered, exact_tiles=self.exact_tiles)
        renderer = mr.BatchRenderer(scene, color="gray" if self.grayscale and not overview else "rgb",
                                    context=self.context, device=self.device, readback=self.readback,
                                    impostors=self.impostors, **antialias)
        try:
            self.scenario.place_cameras(renderer, overview)
        except BaseException:
            renderer.close()
            raise
        if not overview and scene.camera_mount is None:  # the poses camera jitter starts from
            self._free_cameras = (renderer.camera_position.clone(), renderer.camera_rotation.clone())
        return renderer

    def _sync(self, renderer: mr.BatchRenderer, state, full: bool) -> None:
        on_cpu = self.device.type == "cpu"
        overview = renderer is not self.renderer
        for group, kwargs in self.scenario.instances(state, full).items():
            if overview and "owner" in kwargs:  # owners hide bodies from agent views; the overview has none
                kwargs = {k: v for k, v in kwargs.items() if k != "owner"}
            if not on_cpu:
                kwargs = {k: v.cpu() for k, v in kwargs.items()}
            renderer.update(group, **kwargs)


def check_memory(scene: mr.Scene, num_worlds: int, num_agents: int, resolution) -> None:
    """Refuse a batch whose renderer, observations and env state would not fit in this machine's
    memory before they are allocated (torch would fail late with a raw allocator error, or the
    OOM killer would strike). See marl_render/memory.py for what is counted."""
    height, width = resolution
    needed = memory.renderer_bytes(scene) + num_worlds * memory.ENV_WORLD_BYTES
    memory.check_fits(needed, f"num_worlds={num_worlds} x num_agents={num_agents} at resolution {height}x{width}",
                      "lower num_worlds, num_agents or resolution")
