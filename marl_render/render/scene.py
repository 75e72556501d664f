"""Declarative scene description: what exists, not how it is drawn.

A Scene holds W worlds of A agents each. It has
- static geometry, shared by all worlds and stored once;
- instance groups: one mesh, a capacity per world, per-instance pose/scale/colour/active
  mask/owner, updated every step by the environment;
- cameras: A per world, free or mounted on instances (egocentric);
- the effects it declares; only those are compiled into the shaders.

Names used for sizes throughout the project (code, docstrings, docs):
  W    worlds                          Scene(num_worlds=), make_env(num_worlds=)
  A    agents per world                Scene(agents_per_world=), make_env(num_agents=): the same
                                       number; each agent has one camera
  V    views = W * A                   Scene.num_views; view v = w * A + a (world-major)
  H    image height in pixels          resolution = (H, Wpx); an int R means (R, R)
  Wpx  image width in pixels           (not W, which is always worlds)
  C    capacity of an instance group   add_group(capacity=): instance slots per world
  K    count of a static group         StaticGroup.count: instances shared by all worlds
  N    agents of one TorchRL group     a subset of the A agents
So pixels are [W, A, H, Wpx, 3] uint8, in words [worlds, agents, height, width, 3].
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np
import torch

from ..assets import meshes as mesh_lib
from ..assets.images import texture_pixels
from ..util.validation import (
    as_tensor,
    boolean,
    check_finite,
    check_host,
    check_range,
    check_shape,
    describe,
    finite_float,
    positive_float,
    positive_int,
    resolution_hw,
)
from .shaders import EFFECTS

# far / near beyond which the depth buffer (24 bits, perspective depth) cannot tell distances apart:
# measured here, a box at half the far distance vanished at 1e7 and was drawn at 3e6.
MAX_DEPTH_RATIO = 1e6


def check_depth_range(near, far, log_depth: bool) -> None:
    """near / far (floats or tensors) that the depth buffer can resolve, unless log_depth is on."""
    if log_depth:
        return
    ratio = float((torch.as_tensor(far, dtype=torch.float64) / torch.as_tensor(near, dtype=torch.float64)).max())
    if ratio > MAX_DEPTH_RATIO:
        raise ValueError(f"far / near must be at most {MAX_DEPTH_RATIO:g} without the log_depth effect (the depth "
                         f"buffer cannot tell distances apart beyond that: frames would come out blank), got a "
                         f"ratio of {ratio:.3g}; raise near, lower far, or add 'log_depth' to the scene's effects")


# Roles of surfaces under the "appearance" effect: a floor or wall instance takes its world's floor
# or wall colour and pattern; every other instance keeps its own colour, jittered per world.
ROLES = {None: 0, "floor": 1, "wall": 2}

MIN_DIRECTION_LENGTH, MAX_DIRECTION_LENGTH = 1e-30, 1e30  # Lighting.direction's length (see there)


@dataclass(frozen=True)
class Lighting:
    """Ambient plus one directional light (Lambert)."""

    direction: tuple = (-0.3, 0.4, -1.0)  # from the light, world frame
    color: tuple = (0.75, 0.75, 0.75)
    ambient: tuple = (0.35, 0.35, 0.35)

    def __post_init__(self):
        direction = _numbers("lighting.direction", self.direction, (3,))
        if not any(direction):
            raise ValueError(f"lighting.direction must be a non-zero vector, got {direction}")
        # Its length is squared on the way to a unit vector (here in float64, in the shader in
        # float32): one that underflows or overflows there would reach the shader as NaN or 0.
        length = math.hypot(*direction)
        if not MIN_DIRECTION_LENGTH <= length <= MAX_DIRECTION_LENGTH:
            raise ValueError(f"lighting.direction must have a length in [{MIN_DIRECTION_LENGTH:g}, "
                             f"{MAX_DIRECTION_LENGTH:g}] (scale it), got {direction} of length {length:g}")
        object.__setattr__(self, "direction", direction)
        # Light colours may exceed 1 (a bright light); they only must not be negative.
        object.__setattr__(self, "color", _color("lighting.color", self.color, high=None))
        object.__setattr__(self, "ambient", _color("lighting.ambient", self.ambient, high=None))


@dataclass(frozen=True)
class Fog:
    """Exponential distance fog: colour = mix(fog, colour, exp(-density * depth))."""

    color: tuple = (0.6, 0.65, 0.7)
    density: float = 0.05

    def __post_init__(self):
        object.__setattr__(self, "color", _color("fog.color", self.color))
        object.__setattr__(self, "density", positive_float("fog.density", self.density, allow_zero=True))


@dataclass(frozen=True)
class Shadows:
    """Shadow maps of the directional light (Scene.lighting.direction), drawn where the
    scene declares the "shadows" effect.

    resolution: texels per side of each world's shadow map (2-4x the views' resolution
    over the bounds is plenty; larger maps cost more to draw and to read). pcf: soften
    edges by percentage-closer filtering (4 depth compares, bilinearly weighted; about a
    third more shading time); off, every pixel is fully lit or fully shadowed. bounds:
    ((x0, y0, z0), (x1, y1, z1)), the world-frame box that receives shadows (casters above
    it, towards the light, cast too); None fits it to the static geometry. Outside the box
    everything is lit.
    """

    resolution: int = 256
    pcf: bool = False
    bounds: tuple | None = None

    def __post_init__(self):
        object.__setattr__(self, "resolution", positive_int("shadows.resolution", self.resolution))
        object.__setattr__(self, "pcf", boolean("shadows.pcf", self.pcf))
        if self.bounds is not None:
            object.__setattr__(self, "bounds", _box("shadows.bounds", self.bounds))


@dataclass
class StaticGroup:
    name: str
    mesh: object  # MeshData or a Panda3D NodePath from load_model
    position: torch.Tensor  # [K, 3] float64
    rotation: torch.Tensor  # [K, 4]
    scale: torch.Tensor  # [K, 3]
    color: torch.Tensor  # [K, 4]
    texture: object = None
    segment_base: int = 0
    role: torch.Tensor | None = None  # [K] int64 ROLES codes (None: all 0, no role)

    @property
    def count(self) -> int:
        """K: instances of this static group, drawn in every world."""
        return self.position.shape[0]


@dataclass
class InstanceGroup:
    name: str
    mesh: object
    capacity: int  # C: instance slots per world (inactive slots are not drawn)
    texture: object = None
    segment_base: int = 0
    role: str | None = None  # a key of ROLES: the role of every instance


@dataclass(frozen=True)
class CameraMount:
    """Agent a's camera rides on instance `instance[a]` of `group` (egocentric)."""

    group: str
    instance: tuple  # one instance index per agent
    offset: tuple = (0.0, 0.0, 0.0)  # in the instance's frame (metres)
    pitch: float = 0.0  # radians, positive looks up
    hide_owner: bool = True


@dataclass
class Scene:
    num_worlds: int
    agents_per_world: int
    resolution: object = 64  # int or (H, Wpx) of each agent's view
    effects: tuple = ("lighting",)
    background: tuple = (0.55, 0.65, 0.75)
    lighting: Lighting = field(default_factory=Lighting)
    fog: Fog = field(default_factory=Fog)
    fov_y: float = math.radians(70.0)
    near: float = 0.05
    far: float = 100.0
    shadows: Shadows = field(default_factory=Shadows)  # settings of the "shadows" effect
    # The "appearance" effect's floor and wall patterns: compiled into the variants of groups with
    # roles (a fragment-shader cost, appearance.py); False leaves them out (the patterns must be plain).
    surface_patterns: bool = True
    static: dict = field(default_factory=dict, init=False)
    groups: dict = field(default_factory=dict, init=False)
    camera_mount: CameraMount | None = field(default=None, init=False)

    def __post_init__(self):
        self.num_worlds = positive_int("num_worlds", self.num_worlds)
        self.agents_per_world = positive_int("agents_per_world", self.agents_per_world)
        self.resolution = resolution_hw(self.resolution)
        self.effects = _effect_names(self.effects)
        self.near = positive_float("near", self.near)
        self.far = positive_float("far", self.far)
        if not self.far > self.near:
            raise ValueError(f"far must be greater than near, got near={self.near}, far={self.far}")
        check_depth_range(self.near, self.far, "log_depth" in self.effects)
        self.fov_y = finite_float("fov_y", self.fov_y)
        if not 0 < self.fov_y < math.pi:
            raise ValueError(f"fov_y must be in (0, pi) radians, got {self.fov_y}")
        self.background = _color("background", self.background, sizes=(3, 4))
        self.surface_patterns = boolean("surface_patterns", self.surface_patterns)
        for name, kind in (("lighting", Lighting), ("fog", Fog), ("shadows", Shadows)):
            if not isinstance(getattr(self, name), kind):
                raise TypeError(f"{name} must be a marl_render.{kind.__name__}, got {describe(getattr(self, name))}")
        if "shadows" in self.effects and "lighting" not in self.effects:
            raise ValueError(f"effects: 'shadows' darkens the directional light, so it needs 'lighting' too, "
                             f"got {list(self.effects)}")

    @property
    def num_views(self) -> int:
        """The number of views, V = W * A (one per agent of every world)."""
        return self.num_worlds * self.agents_per_world

    def _check_name(self, name: str) -> None:
        if not isinstance(name, str) or not name:
            raise TypeError(f"group name must be a non-empty str, got {describe(name)}")
        if name in self.static or name in self.groups:
            raise ValueError(f"group name {name!r} is already used in this scene")

    def _next_segment_base(self) -> int:
        used = [g.segment_base + g.count for g in self.static.values()]
        used += [g.segment_base + g.capacity for g in self.groups.values()]
        return max(used, default=1)

    def add_static(self, name: str, mesh, position, rotation=None, scale=None, color=None, texture=None,
                   role=None) -> StaticGroup:
        """Geometry identical in every world (floor, walls): stored and uploaded once.

        position [K, 3] or [3]; rotation [K|1, 4] quaternions (w, x, y, z); scale [K|1, 3],
        [K|1, 1] or a number; color [K|1, 3|4] in [0, 1]; texture an image file path or a
        uint8 array [h, w, 3|4] (shown where the scene declares the "texture" effect);
        role None, "floor" or "wall" for all instances, or one of those per instance: under the
        "appearance" effect such instances take their world's floor / wall colour and pattern."""
        self._check_name(name)
        position = as_tensor("position", position)
        check_host("position", position)
        position = position.detach().to(torch.float64)
        if position.ndim == 1:
            position = position[None]
        check_shape("position", position, (None, 3))
        count = position.shape[0]
        rotation, scale, color = _pose_defaults(count, rotation, scale, color)
        for label, value in (("position", position), ("rotation", rotation), ("scale", scale), ("color", color)):
            check_finite(label, value)
        if bool((scale < 0).any()):
            raise ValueError("scale must be >= 0 (mirrored instances are not supported), "
                             f"got minimum {scale.min().item()}")
        check_range("color", color, 0.0, 1.0)  # the same bounds as BatchRenderer.update
        rotation = _unit(rotation)
        role = _roles(role, count)
        texture = _resolve_texture(texture)
        mesh = _resolve_mesh(mesh)  # last: a model file is parsed in a child process
        group = StaticGroup(name, mesh, position, rotation, scale, color, texture, self._next_segment_base(), role)
        self.static[name] = group
        return group

    def add_group(self, name: str, mesh, capacity: int, texture=None, role=None) -> InstanceGroup:
        """A mesh drawn up to `capacity` times per world, posed per step. role: None, "floor" or
        "wall" (under the "appearance" effect its instances take their world's floor / wall look)."""
        self._check_name(name)
        capacity = positive_int("capacity", capacity)
        _role_code("role", role)
        texture = _resolve_texture(texture)
        group = InstanceGroup(name, _resolve_mesh(mesh), capacity, texture, self._next_segment_base(), role)
        self.groups[name] = group
        return group

    def mount_cameras(self, group: str, instance, offset=(0.0, 0.0, 0.0), pitch: float = 0.0,
                      hide_owner: bool = True) -> CameraMount:
        """Egocentric cameras: agent a looks out of instance `instance[a]` of `group`.

        instance: one integer index per agent; offset: 3 numbers (metres, in the
        instance's frame); pitch: radians, positive looks up; hide_owner: bool."""
        if not isinstance(group, str):
            raise TypeError(f"group must be the name (str) of an instance group, got {describe(group)}")
        if group not in self.groups:
            raise ValueError(f"group must name an instance group of this scene ({sorted(self.groups)}), got {group!r}")
        indices = as_tensor("instance", np.asarray(instance) if isinstance(instance, range) else instance,
                            dtype_kind="int")
        check_host("instance", indices)
        indices = indices.reshape(-1)
        if len(indices) != self.agents_per_world:
            raise ValueError(f"instance must give one index per agent ({self.agents_per_world}), got {len(indices)}")
        capacity = self.groups[group].capacity
        instance = tuple(int(i) for i in indices.tolist())
        if any(not 0 <= i < capacity for i in instance):
            raise ValueError(f"instance indices must be in [0, {capacity}), got {list(instance)}")
        offset = _numbers("offset", offset, (3,))
        pitch = finite_float("pitch", pitch)
        hide_owner = boolean("hide_owner", hide_owner)
        self.camera_mount = CameraMount(group, instance, offset, pitch, hide_owner)
        return self.camera_mount

    def segment_ids(self, name: str) -> range:
        """Segmentation ids of a group's instances (same in every world); 0 is background."""
        group = self.static.get(name) or self.groups.get(name)
        if group is None:
            raise KeyError(f"no group named {name!r}; known: {sorted(self.static) + sorted(self.groups)}")
        count = group.count if isinstance(group, StaticGroup) else group.capacity
        return range(group.segment_base, group.segment_base + count)


def _effect_names(effects) -> tuple:
    if isinstance(effects, str) or not isinstance(effects, (tuple, list, set, frozenset)):
        raise TypeError(f"effects must be a collection of names (tuple, list or set) drawn from {list(EFFECTS)}, "
                        f"got {describe(effects)}")
    not_names = [e for e in effects if not isinstance(e, str)]
    if not_names:
        raise TypeError(f"effects must be names (str) drawn from {list(EFFECTS)}, got {not_names}")
    unknown = sorted(set(effects) - set(EFFECTS))
    if unknown:
        raise ValueError(f"effects must be drawn from {list(EFFECTS)}, got unknown {unknown}")
    return tuple(sorted(set(effects)))


def _role_code(name: str, role) -> int:
    if role is not None and not isinstance(role, str) or role not in ROLES:
        raise ValueError(f"{name} must be one of {list(ROLES)}, got {describe(role)}")
    return ROLES[role]


def _roles(role, count: int) -> torch.Tensor:
    """[count] int64 role codes from one role for all instances or a sequence of one per instance."""
    if role is None or isinstance(role, str):
        return torch.full((count,), _role_code("role", role), dtype=torch.int64)
    if not isinstance(role, (tuple, list)) or len(role) != count:
        raise ValueError(f"role must be one of {list(ROLES)} or a list of {count} of them (one per instance), "
                         f"got {describe(role)}")
    return torch.tensor([_role_code(f"role[{i}]", r) for i, r in enumerate(role)], dtype=torch.int64)


def _resolve_mesh(mesh):
    if isinstance(mesh, mesh_lib.MeshData):
        return mesh
    if isinstance(mesh, str) and mesh in mesh_lib.PROCEDURAL:
        return mesh_lib.PROCEDURAL[mesh]()
    if isinstance(mesh, (str, os.PathLike)):
        try:
            return mesh_lib.load_model(mesh, name="mesh")
        except FileNotFoundError as error:
            raise FileNotFoundError(f"{error} (and it is not one of the procedural meshes "
                                    f"{sorted(mesh_lib.PROCEDURAL)})") from None
    if type(mesh).__name__ == "NodePath":
        return mesh
    raise TypeError(f"mesh must be a MeshData, a procedural name {sorted(mesh_lib.PROCEDURAL)}, a model path "
                    f"or a Panda3D NodePath, got {describe(mesh)}")


def _resolve_texture(texture):
    """None, a Panda3D Texture as it is, or checked pixels the scene owns (files decoded now)."""
    if texture is None or type(texture).__name__ == "Texture":
        return texture
    return texture_pixels(texture, name="texture")


def _pose_defaults(count, rotation, scale, color):
    rotation = torch.tensor([[1.0, 0, 0, 0]]).expand(count, 4) if rotation is None else as_tensor("rotation", rotation)
    scale = torch.ones(count, 3) if scale is None else as_tensor("scale", scale)
    color = torch.tensor([[0.8, 0.8, 0.8, 1.0]]).expand(count, 4) if color is None else as_tensor("color", color)
    for label, value in (("rotation", rotation), ("scale", scale), ("color", color)):
        check_host(label, value)
    rotation, scale, color = (t.detach() for t in (rotation, scale, color))
    scale = scale.reshape(1, 1) if scale.ndim == 0 else scale  # one number: uniform scale
    for label, value, width in (("rotation", rotation, "4"), ("scale", scale, "3|1"), ("color", color, "4|3")):
        if value.ndim not in (1, 2):
            raise ValueError(f"{label} must have shape [{count}, {width}], [1, {width}] or [{width}], "
                             f"got {list(value.shape)}")
    rotation, scale, color = (t[None] if t.ndim == 1 else t for t in (rotation, scale, color))
    if scale.shape[-1] == 1:
        scale = scale.expand(count, 3)
    if color.shape[-1] == 3:
        color = torch.cat((color, torch.ones(color.shape[0], 1, dtype=color.dtype)), -1)
    rotation, scale, color = (t.expand(count, t.shape[-1]) if t.shape[0] == 1 else t for t in (rotation, scale, color))
    check_shape("rotation", rotation, (count, 4))
    check_shape("scale", scale, (count, 3))
    check_shape("color", color, (count, 4))
    return rotation.to(torch.float32), scale.to(torch.float32), color.to(torch.float32)


def _unit(rotation: torch.Tensor) -> torch.Tensor:
    from ..util.transforms import normalize_quat

    return normalize_quat(rotation.to(torch.float64)).to(torch.float32)


def _numbers(name: str, value, sizes: tuple) -> tuple:
    """A short vector of finite numbers (its length one of `sizes`) as a tuple of floats."""
    if isinstance(value, (str, bytes)) or not isinstance(value, (tuple, list, np.ndarray, torch.Tensor)):
        raise TypeError(f"{name} must be a sequence of {' or '.join(map(str, sizes))} numbers, got {describe(value)}")
    vector = as_tensor(name, value)
    check_host(name, vector)
    vector = vector.detach().to(torch.float64)
    if vector.ndim != 1 or len(vector) not in sizes:
        raise ValueError(f"{name} must be {' or '.join(map(str, sizes))} numbers, got {describe(value)}")
    check_finite(name, vector)
    return tuple(float(v) for v in vector.tolist())


def _box(name: str, value) -> tuple:
    """An axis-aligned box ((x0, y0, z0), (x1, y1, z1)) of finite numbers with min <= max."""
    if isinstance(value, (str, bytes)) or not isinstance(value, (tuple, list, np.ndarray, torch.Tensor)):
        raise TypeError(f"{name} must be ((x0, y0, z0), (x1, y1, z1)), got {describe(value)}")
    box = as_tensor(name, value)
    check_host(name, box)
    if box.shape != (2, 3):
        raise ValueError(f"{name} must be ((x0, y0, z0), (x1, y1, z1)), shape [2, 3], got shape {list(box.shape)}")
    check_finite(name, box)
    low, high = box.to(torch.float64).tolist()
    if any(a > b for a, b in zip(low, high, strict=True)):
        raise ValueError(f"{name} must have min <= max on every axis, got min {low} and max {high}")
    return tuple(low), tuple(high)


def _color(name: str, value, *, sizes: tuple = (3,), high: float | None = 1.0) -> tuple:
    """An RGB(A) colour: numbers in [0, high] (high=None: any finite number >= 0)."""
    color = _numbers(name, value, sizes)
    if min(color) < 0 or (high is not None and max(color) > high):
        bounds = f"in [0, {high:g}]" if high is not None else ">= 0"
        raise ValueError(f"{name} must be {' or '.join(map(str, sizes))} numbers {bounds}, got {value}")
    return color
