"""Host memory: what a batch of worlds will need, and what this machine can give.

Sizes are checked before the bulk is allocated, so that a batch too large for the
machine is a ValueError naming its sizes, not a raw allocator error halfway through a
step, nor the OOM killer.

The estimate counts everything that grows with the batch, in five units. Per view:
camera state, view and projection matrices, culling planes and the view buffer texture.
Per (view, instance) pair: the culling products and the visible-pair list. Per instance
row (world x dynamic instance): pose state, its packing and the instance buffer texture.
Per pixel: the output tensor and the tiled framebuffer (GL colour and depth; the frame is
read straight into the output, with no copy in between); depth and segmentation outputs
add their own target and tensor. Per shadow-map texel (worlds x Shadows.resolution^2, with
the "shadows" effect): the atlas's depth texture and the rest of its framebuffer, as
llvmpipe holds them. An environment adds a constant per world (its state, the step's
temporaries, the observation dict).

The bytes per unit were fitted (least squares on the relative error) to the peak RSS of
22 batches and checked on 11 more (torch 2.13 CPU, Mesa llvmpipe, 2 cores; each batch in a
fresh process, its peak above the process after a 1-world warm-up, after building and 2
renders, or reset and 5 steps): renderers of the bench's arena scene (1-8 views per world,
10 or 40 instances, 1x1 to 128x128 pixels, depth, Shadows(64) to Shadows(512)) and all
nine built-in envs (1x1 to 64x64, 128-30,000 worlds, Shadows(128) to Shadows(1024),
depth). The env term is rounded up from the fit's 0.9 KB for speaker_listener, whose own
temporaries are larger. The peaks, 116 MiB to 3.0 GiB, were 0.84-1.28 times the estimate
(37 readings; the four of speaker_listener 1.19-1.28). Under about 100 MB, constant costs
of a first renderer (shader variants, GL objects) that no unit counts make the ratio
larger (1.3 for rooms at 86 MiB). A batch is refused when its estimate exceeds the
memory available now: within that accuracy, it would not have fitted.
"""
from __future__ import annotations

import os

VIEW_BYTES = 1792
PAIR_BYTES = 128
INSTANCE_BYTES = 320
PIXEL_BYTES = 14
EXTRA_TARGET_PIXEL_BYTES = 13  # each of the depth and segmentation outputs
SKY_PIXEL_BYTES = 4  # the "appearance" effect's sky images: RGBA8 per framebuffer pixel (sky.py), not fitted
# Per texel of the shadow atlas: 11.4 B measured (4,096 worlds x Shadows(256): 3.1 GiB),
# against the 8 B (4-byte depth, 4-byte colour target) counted before.
SHADOW_TEXEL_BYTES = 12
ENV_WORLD_BYTES = 1536
# Per joint of every instance of a skinned group: its quaternion, and the forward-kinematics
# temporaries of a render ([W, C, J, 3, 4] matrices and their products). Fitted to a 300-joint
# glTF at W=512, C=8: about 275 MB more peak RSS than at W=16, 231 B per (world, instance, joint).
JOINT_BYTES = 240


def renderer_bytes(scene, supersample: int = 1) -> int:
    """Host bytes a BatchRenderer of `scene` holds at its peak, one render included
    (supersample=k draws k x k samples per pixel; the appearance effect's sky images add
    SKY_PIXEL_BYTES per framebuffer pixel; a shadow atlas holds W maps of
    Shadows.resolution^2 texels; skinned groups hold their joints and the forward-kinematics
    temporaries of a render)."""
    height, width = scene.resolution
    views = scene.num_views
    dynamic = sum(group.capacity for group in scene.groups.values())
    static = sum(group.count for group in scene.static.values())
    extra_targets = sum(effect in scene.effects for effect in ("depth", "segmentation"))
    per_pixel = PIXEL_BYTES + extra_targets * EXTRA_TARGET_PIXEL_BYTES
    per_pixel += SKY_PIXEL_BYTES if "appearance" in scene.effects else 0
    shadow_maps = getattr(scene, "shadows", None)
    atlas = (scene.num_worlds * shadow_maps.resolution ** 2 * SHADOW_TEXEL_BYTES
             if "shadows" in scene.effects and shadow_maps else 0)
    joints = sum(group.capacity * getattr(group.mesh, "num_joints", 0) for group in scene.groups.values())
    return (views * VIEW_BYTES + views * (dynamic + static) * PAIR_BYTES
            + scene.num_worlds * dynamic * INSTANCE_BYTES + views * height * width * per_pixel * supersample ** 2
            + atlas + scene.num_worlds * joints * JOINT_BYTES)


def available_bytes() -> int:
    """Memory this process can still take: the kernel's MemAvailable (free memory plus
    reclaimable caches), capped by the memory limit of the process's cgroup (container)."""
    available = _meminfo_available()
    if available is None:
        available = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    limit = _cgroup_limit()
    return min(available, limit) if limit is not None else available


def check_fits(needed: int, what: str, remedy: str) -> None:
    """ValueError when `needed` bytes exceed available_bytes(); `what` names the sizes."""
    available = available_bytes()
    if needed > available:
        raise ValueError(f"{what} needs about {_gib(needed)} of host memory, more than the {_gib(available)} "
                         f"available ({needed} > {available} bytes); {remedy}")


def _gib(count: int) -> str:
    return f"{count / 2 ** 30:.2f} GiB"


def _meminfo_available() -> int | None:
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _cgroup_limit() -> int | None:
    """cgroup v2 memory.max or v1 memory.limit_in_bytes; None where there is no limit."""
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            with open(path) as file:
                text = file.read().strip()
        except OSError:
            continue
        if text.isdigit() and int(text) < 2 ** 60:  # "max" or a page-rounded 2**63: no limit
            return int(text)
    return None
