"""marl-render: batched egocentric rendering for multi-agent RL from pixels.

One folder per layer (docs/architecture.md): util < assets < render < envs < populations and the
front ends (wrappers) < baselines and bench. Modules that moved keep their old import paths
(aliases.py)."""
from . import aliases

aliases.install()  # before anything else: an old path imported from here on is the moved module

from .assets.meshes import MeshData, box, capsule, cone, cylinder, load_model, plane, sphere  # noqa: E402
from .assets.skinning import SkinnedMesh, load_skinned_model, skinned_character, skinned_limb  # noqa: E402
from .render.appearance import Appearance, AppearanceParams  # noqa: E402
from .render.backend import GLContext, configure  # noqa: E402
from .render.renderer import BatchRenderer, Frame  # noqa: E402
from .render.scene import CameraMount, Fog, Lighting, Scene, Shadows  # noqa: E402
from .util.transforms import look_at_quat, quat_from_yaw_pitch_roll, yaw_pitch_roll_from_quat  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "BatchRenderer", "Frame", "GLContext", "configure", "Appearance", "AppearanceParams",
    "Scene", "Lighting", "Fog", "Shadows", "CameraMount", "MeshData",
    "box", "capsule", "cone", "cylinder", "plane", "sphere", "load_model",
    "SkinnedMesh", "skinned_character", "skinned_limb", "load_skinned_model",
    "look_at_quat", "quat_from_yaw_pitch_roll", "yaw_pitch_roll_from_quat",
]


def __getattr__(name: str):
    """`marl_render.<old module name>` read as an attribute: the moved module (aliases.MOVED)."""
    module = aliases.moved_attribute(__name__, name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return module
