"""marl-render: batched egocentric rendering for multi-agent RL from pixels."""
from .appearance import Appearance, AppearanceParams
from .backend import GLContext, configure
from .meshes import MeshData, box, capsule, cone, cylinder, load_model, plane, sphere
from .renderer import BatchRenderer, Frame
from .scene import CameraMount, Fog, Lighting, Scene, Shadows
from .skinning import SkinnedMesh, load_skinned_model, skinned_character, skinned_limb
from .transforms import look_at_quat, quat_from_yaw_pitch_roll, yaw_pitch_roll_from_quat

__version__ = "0.1.0"

__all__ = [
    "BatchRenderer", "Frame", "GLContext", "configure", "Appearance", "AppearanceParams",
    "Scene", "Lighting", "Fog", "Shadows", "CameraMount", "MeshData",
    "box", "capsule", "cone", "cylinder", "plane", "sphere", "load_model",
    "SkinnedMesh", "skinned_character", "skinned_limb", "load_skinned_model",
    "look_at_quat", "quat_from_yaw_pitch_roll", "yaw_pitch_roll_from_quat",
]
