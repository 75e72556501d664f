"""How far a GL driver's pixels are from the exact comparisons of tests/test_renderer.py: the same
scenes (its render_* functions), with counts instead of pass/fail: leaked pixels, differing pixels,
coverage, depth, segmentation ids.

    python tools/gpu_kit/renderer_probe.py tests out.json      # here, or with the kit's tests on a GPU

docs/bench/gpu/h200_renderer_probe_*.json are its output on the lent H200 before and after the
clip-distance fix (docs/bench/gpu.md)."""
import json
import sys

import torch

sys.path.insert(0, sys.argv[1])
import test_renderer  # noqa: E402  (the scenes, from the tests folder given)


def differences(a: torch.Tensor, b: torch.Tensor) -> dict:
    """Per pixel (the largest difference over its channels): how many differ, by more than 2 and 8
    levels, and where one side is finite and the other not (depth)."""
    a, b = a.float(), b.float()
    finite_mismatch = int((torch.isfinite(a) != torch.isfinite(b)).sum())
    d = torch.nan_to_num((a - b).abs(), nan=0.0, posinf=0.0)
    per_pixel = d.reshape(-1, d.shape[-1]).amax(-1)
    return dict(max=float(d.max()), mean=float(d.mean()), differing=int((per_pixel > 0).sum()),
                over2=int((per_pixel > 2).sum()), over8=int((per_pixel > 8).sum()), total=int(per_pixel.numel()),
                finite_mismatch=finite_mismatch)


def main(out_path: str) -> dict:
    out = {}
    for resolution, worlds, agents in [((24, 40), 3, 2), ((40, 24), 2, 3), ((32, 32), 5, 1)]:
        rgb = test_renderer.render_leak_scene(resolution, worlds, agents)
        green = (rgb == torch.tensor([0, 255, 0], dtype=torch.uint8)).all(-1)
        leaked = ~test_renderer.is_background(rgb[[w for w in range(worlds) if w != 1]])
        out[f"leaks_{resolution}_{worlds}_{agents}"] = dict(
            world1_not_green=int((~green[1]).sum()), world1_pixels=int(green[1].numel()),
            others_leaked=int(leaked.sum()), others_leaked_at=leaked.nonzero()[:8].tolist())
    for seed in (0, 1, 2):
        batched, plain = test_renderer.render_batched_and_plain(seed)
        result = differences(batched, plain)
        result["error_per_channel"] = (batched.float() - plain.float()).abs().mean(dim=(0, 1, 2, 3)).tolist()
        result["coverage_mismatch"] = int((test_renderer.is_background(batched)
                                           != test_renderer.is_background(plain)).sum())
        out[f"plain_{seed}"] = result
    seg, ids, floor_id, active, cols = test_renderer.render_segmentation_scene()
    out["segmentation"] = dict(ids=[int(i) for i in ids], floor=int(floor_id), dtype=str(seg.dtype),
                               active=active.tolist(), centre=[[int(seg[w, 0, 16, c]) for c in cols] for w in range(2)],
                               row16=[seg[w, 0, 16].tolist() for w in range(2)], unique=seg.unique().tolist()[:20])
    for effects, supersample in [(("lighting", "depth", "segmentation"), 1),
                                 (("lighting", "fog", "depth", "log_depth"), 1), (("depth",), 2)]:
        (_, one), (_, many) = test_renderer.render_in_one_pass_and_split(effects, supersample)
        result = dict(rgb=differences(one.rgb, many.rgb),
                      depth=differences(one.depth.unsqueeze(-1), many.depth.unsqueeze(-1)))
        if one.segmentation is not None:
            result["segmentation_differing"] = int((one.segmentation != many.segmentation).sum())
        out[f"split_{'+'.join(effects)}_{supersample}"] = result
    with open(out_path, "w") as f:
        json.dump(out, f, indent=1)
    return out


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[2]))[:3000])
