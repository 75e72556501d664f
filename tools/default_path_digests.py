"""Digests of the default (no levels) path of every built-in task: a few steps' state and pixels.

    python tools/default_path_digests.py > tests/data/default_path_digests.json

The reset draws of every task come from the env's torch.Generator unless ``levels=`` is given;
tests/test_levels.py compares these digests (recorded before levels existed) with today's code, so
the default path stays bit-identical for runs that were made before levels existed.
"""
from __future__ import annotations

import hashlib
import json
import sys

import torch

from marl_render.envs import env_class, list_envs, make_env

BUILT_IN = ("capture_flag", "cartpole", "clean_up", "commons", "cooking", "coop_mining", "forage", "matrix",
            "push", "rooms", "speaker_listener", "spread", "tag", "territory")


def digest(name: str, **kwargs) -> str:
    """sha256 of the pixels and the state of reset, a partial reset and 4 random steps (4 worlds, 8 px)."""
    sha = hashlib.sha256()
    actions = torch.Generator().manual_seed(1)
    if env_class(name).mixed_motive:  # their random ends and social tallies came later: off, as recorded
        kwargs = {"episode_end": False, "social_metrics": False, **kwargs}
    with make_env(name, num_worlds=4, resolution=8, seed=3, autoreset="same_step", max_steps=3, **kwargs) as env:
        frames = [env.reset()["pixels"], env.reset_worlds(torch.tensor([False, True, False, True]))["pixels"]]
        for _ in range(4):
            frames.append(env.step(env.random_actions(actions))[0]["pixels"])
        for frame in frames:
            sha.update(frame.numpy().tobytes())
        for key, value in sorted(env.get_state().items()):
            sha.update(key.encode())
            sha.update(value.contiguous().view(torch.uint8).numpy().tobytes() if value.numel() else b"")
    return sha.hexdigest()


def main() -> None:
    assert set(BUILT_IN) <= set(list_envs())
    digests = {name: digest(name) for name in BUILT_IN}
    digests.update({f"{name}+appearance": digest(name, appearance="train") for name in ("rooms", "spread")})
    json.dump({"torch": torch.__version__, "digests": digests}, sys.stdout, indent=1, sort_keys=True)
    print()


if __name__ == "__main__":
    main()
