"""How far a GL driver's pixels are from the exact comparisons of tests/test_renderer.py: the same
scenes, with counts instead of pass/fail (leaked pixels, differing pixels, coverage, depth).

    python tools/gpu_kit/renderer_probe.py tests out.json      # here, or with the kit's tests on a GPU

docs/bench/gpu/h200_renderer_probe_*.json are its output on the lent H200 before and after the
clip-distance fix (docs/bench/gpu.md)."""
import json
import math
import sys

import torch

sys.path.insert(0, sys.argv[1])
import marl_render as mr  # noqa: E402
import test_renderer as T  # noqa: E402

out = {}


def diff_stats(a, b):
    a, b = a.float(), b.float()
    d = (a - b).abs()
    finite = torch.isfinite(d)
    d = torch.where(finite, d, torch.zeros_like(d))
    mism_inf = int((torch.isfinite(a) != torch.isfinite(b)).sum())
    px = d.reshape(-1, d.shape[-1]).amax(-1) if d.dim() == 5 else d.reshape(-1)
    return dict(max=float(d.max()), mean=float(d.mean()), differing=int((px > 0).sum()), over2=int((px > 2).sum()),
                over8=int((px > 8).sum()), total=int(px.numel()), finite_mismatch=mism_inf)


for resolution, worlds, agents in [((24, 40), 3, 2), ((40, 24), 2, 3), ((32, 32), 5, 1)]:
    scene = T.box_scene(worlds=worlds, agents=agents, resolution=resolution, capacity=1)
    with mr.BatchRenderer(scene) as renderer:
        T.cameras_at_origin(renderer, worlds, agents)
        position = torch.zeros(worlds, 1, 3)
        position[:, 0, 1] = -50.0
        position[1, 0] = torch.tensor([0.0, 30.0, 0.0])
        scale = torch.ones(worlds, 1, 3)
        scale[1, 0] = torch.tensor([400.0, 2.0, 400.0])
        renderer.update("boxes", position=position, scale=scale, active=torch.ones(worlds, 1, dtype=torch.bool),
                        color=torch.tensor([0.0, 1.0, 0.0]).repeat(worlds, 1, 1))
        rgb = renderer.render().rgb
    green = (rgb == torch.tensor([0, 255, 0], dtype=torch.uint8)).all(-1)
    others = [w for w in range(worlds) if w != 1]
    leak = ~T.is_background(rgb[others])
    notgreen = (~green[1]).nonzero()[:8].tolist()
    out[f"leaks_{resolution}_{worlds}_{agents}"] = dict(
        world1_not_green=int((~green[1]).sum()), world1_pixels=int(green[1].numel()),
        world1_not_green_at=notgreen, world1_not_green_colours=[rgb[1][tuple(i)].tolist() for i in notgreen],
        others_leaked=int(leak.sum()), others_leaked_at=leak.nonzero()[:8].tolist())

for seed in (0, 1, 2):
    worlds, agents, capacity = 2, 3, 5
    scene = mr.Scene(num_worlds=worlds, agents_per_world=agents, resolution=(36, 48), effects=("lighting",),
                     background=T.BACKGROUND)
    scene.add_static("floor", "plane", position=[0, 0, 0], scale=[30, 30, 1], color=[0.3, 0.6, 0.3])
    scene.add_group("boxes", "box", capacity=capacity)
    instances, camera, target = T.random_scene_inputs(torch.Generator().manual_seed(seed), worlds, agents, capacity)
    images = []
    for cls in (mr.BatchRenderer, T.NaiveRenderer):
        renderer = cls(scene)
        renderer.update("boxes", **instances)
        renderer.set_cameras(position=camera, look_at=target)
        images.append(renderer.render().rgb)
        renderer.close()
    s = diff_stats(images[0], images[1])
    s["error_per_channel"] = (images[0].float() - images[1].float()).abs().mean(dim=(0, 1, 2, 3)).tolist()
    s["coverage_mismatch"] = int((T.is_background(images[0]) != T.is_background(images[1])).sum())
    out[f"plain_{seed}"] = s

scene = mr.Scene(num_worlds=2, agents_per_world=1, resolution=(32, 64), effects=("segmentation",),
                 background=T.BACKGROUND)
scene.add_static("floor", "plane", position=[0, 0, -1], scale=[50, 50, 1])
scene.add_group("boxes", "box", capacity=3)
ids = list(scene.segment_ids("boxes"))
floor_id = scene.segment_ids("floor")[0]
with mr.BatchRenderer(scene) as renderer:
    T.cameras_at_origin(renderer, 2, 1)
    position = torch.tensor([[-1.2, 4.0, 0.0], [0.0, 4.0, 0.0], [1.2, 4.0, 0.0]]).repeat(2, 1, 1)
    active = torch.tensor([[True, True, True], [True, False, True]])
    renderer.update("boxes", position=position, scale=torch.full((2, 3, 3), 0.8), active=active)
    seg = renderer.render().segmentation
cols = [64 // 2 + round(x / 3.6 * (16 / math.tan(scene.fov_y / 2))) for x in (-1.2, 0.0, 1.2)]
out["segmentation"] = dict(ids=[int(i) for i in ids], floor=int(floor_id), dtype=str(seg.dtype),
                           centre=[[int(seg[w, 0, 16, c]) for c in cols] for w in range(2)],
                           corner=int(seg[0, 0, 0, 0]), bottom=int(seg[0, 0, 31, 0]), unique=seg.unique().tolist()[:20])

for effects, supersample in [(("lighting", "depth", "segmentation"), 1), (("lighting", "fog", "depth", "log_depth"), 1),
                             (("depth",), 2)]:
    worlds, agents, capacity = 3, 3, 4
    scene = mr.Scene(num_worlds=worlds, agents_per_world=agents, resolution=(20, 30), effects=effects,
                     background=T.BACKGROUND)
    scene.add_static("floor", "plane", position=[0, 0, 0], scale=[30, 30, 1], color=[0.3, 0.6, 0.3])
    scene.add_group("boxes", "box", capacity=capacity)
    scene.add_group("balls", "sphere", capacity=1)
    instances, camera, target = T.random_scene_inputs(torch.Generator().manual_seed(5), worlds, agents, capacity)
    frames = []
    for max_size in (None, 40 * supersample):
        with mr.BatchRenderer(scene, max_framebuffer_size=max_size, supersample=supersample) as renderer:
            renderer.update("boxes", **instances)
            renderer.update("balls", position=torch.tensor([0.3, 2.5, 0.6]).expand(worlds, 1, 3),
                            active=torch.ones(worlds, 1, dtype=torch.bool))
            renderer.set_cameras(position=camera, look_at=target)
            frames.append(renderer.render())
    one, many = frames
    r = dict(rgb=diff_stats(one.rgb, many.rgb), depth=diff_stats(one.depth.unsqueeze(-1), many.depth.unsqueeze(-1)))
    if one.segmentation is not None:
        r["segmentation_differing"] = int((one.segmentation != many.segmentation).sum())
    out[f"split_{'+'.join(effects)}_{supersample}"] = r

json.dump(out, open(sys.argv[2], "w"), indent=1)
print(json.dumps(out)[:3000])
