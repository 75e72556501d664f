"""Play a task by keyboard: one agent is yours, the others play a policy.

    python -m marl_render.play spread                            # drive agent 0 in a window
    python -m marl_render.play tag --agent prey_0 --others random
    python -m marl_render.play commons --keys "w w a a 5 d" --frames out/   # scripted, no window needed
    python -m marl_render.play my_tasks:HideAndSeek              # a task of your own, by module:Class

The window shows the agent's egocentric view (what its policy would see, scaled up) beside the
overview camera. Keys: w forward, s backward, a turn left, d turn right (for tasks with those
actions), a digit takes the action of that number (a task's own actions: commons' zap is 5, a
cartpole force level 0-4), space or nothing held is action 0 (noop); q or escape quits. In the
window the env runs at its own pace, 1 / dt steps a second, taking the key held down, as VMAS's
``render_interactively`` and Melting Pot's human players do. ``--keys`` plays a scripted sequence
instead, one step per key ("." or "space": action 0), offscreen, and prints one JSON line with the
agent's actions, positions and headings after each step (``--frames DIR`` also writes every frame
as a PNG). The other agents play ``--others``: the task's scripted heuristic (the default, where the
task has one; else random), random valid actions, or noop. An episode that ends starts again.

The window is matplotlib's (the ``human`` extra; the same as ``render_mode="human"``); without a
display, or without matplotlib, the command prints one line saying why and exits with status 2.
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import os
import sys

import numpy as np
import torch
from PIL import Image

from marl_render.envs import Scenario, env_class, make_env
from marl_render.envs.evaluation import random_policy
from marl_render.util.validation import positive_int
from marl_render.wrappers.window import window_unavailable

# Keys by the meaning of the action they take, where the task's action has that meaning.
KEYS_BY_MEANING = {"forward": "w", "backward": "s", "turn_left": "a", "turn_right": "d", "left": "a", "right": "d"}
NOOP_KEYS = ("space", ".", " ")
QUIT_KEYS = ("q", "escape")
OTHERS = ("heuristic", "random", "noop")
GAP = 4  # pixels between the egocentric view and the overview


@dataclasses.dataclass
class Turn:
    """One step of play: the key, the action it took, the reward and the frame shown after it."""

    key: str
    action: int
    reward: float
    frame: np.ndarray  # uint8 [H, W, 3]: the agent's view (scaled up) beside the overview


class Player:
    """One world of task `name` (a registered name, a Scenario subclass or "module:Class") with agent
    `agent` (index or name) driven by keys: ``frame()`` is what the window shows, ``step(key)`` plays
    one step. Keyword arguments go to make_env."""

    def __init__(self, name, *, agent=0, others: str | None = None, resolution=64, overview=256, seed=0,
                 **kwargs):
        overview = positive_int("overview", overview)  # before the env is built
        self.env = make_env(task_class(name), num_worlds=1, resolution=resolution, seed=seed, **kwargs)
        try:
            self.agent = self._agent_index(agent)
            self.others = self._others(others)
            self.keys = self._key_table()
        except BaseException:
            self.env.close()
            raise
        self.overview = overview
        self.generator = torch.Generator().manual_seed(seed)
        self.obs = self.env.reset()
        self.episode_return = 0.0

    def action_for(self, key: str) -> int:
        """The action `key` takes; ValueError naming the key and the known ones."""
        if key in self.keys:
            return self.keys[key]
        known = sorted(k for k in self.keys if k.strip())
        raise ValueError(f"key {key!r} takes no action in {self.env.name}; keys: {known} "
                         f"(and {', '.join(QUIT_KEYS)} to quit)")

    def step(self, key: str) -> Turn:
        action = self.action_for(key)
        actions = self._others_actions()
        actions[0, self.agent] = action
        self.obs, reward, *_ = self.env.step(actions)
        self.episode_return += float(reward[0, self.agent])
        if bool(self.env.episode_over()[0]):
            self.obs = self.env.reset()
            self.episode_return = 0.0
        return Turn(key, action, float(reward[0, self.agent]), self.frame())

    def frame(self) -> np.ndarray:
        """uint8 [H, W, 3]: the agent's view, scaled up by a whole factor, beside the overview."""
        overview = self.env.render_overview(self.overview)[0].cpu().numpy()
        view = self.obs["pixels"][0, self.agent].cpu().numpy()
        if view.shape[-1] == 1:  # grayscale=True
            view = np.repeat(view, 3, -1)
        scale = max(1, overview.shape[0] // view.shape[0])
        view = view.repeat(scale, 0).repeat(scale, 1)
        height = max(view.shape[0], overview.shape[0])
        canvas = np.full((height, view.shape[1] + GAP + overview.shape[1], 3), 24, dtype=np.uint8)
        canvas[:view.shape[0], :view.shape[1]] = view
        canvas[:overview.shape[0], view.shape[1] + GAP:] = overview
        return canvas

    def pose(self) -> dict:
        """The agent's position and heading, for tasks whose state has them (arena tasks)."""
        sim = self.env.sim
        if not (hasattr(sim, "pos") and hasattr(sim, "yaw")):
            return {}
        return {"position": sim.pos[0, self.agent].tolist(), "yaw": float(sim.yaw[0, self.agent])}

    def close(self) -> None:
        self.env.close()

    def _agent_index(self, agent) -> int:
        names = self.env.agent_names
        if isinstance(agent, str) and agent in names:
            return names.index(agent)
        if isinstance(agent, str) and agent.isdigit():
            agent = int(agent)
        if isinstance(agent, int) and 0 <= agent < len(names):
            return agent
        raise ValueError(f"agent must be an agent's index in [0, {len(names)}) or name {names}, got {agent!r}")

    def _others(self, others):
        if others is None:
            return "heuristic" if self._has_heuristic() else "random"
        if others not in OTHERS:
            raise ValueError(f"others must be one of {list(OTHERS)}, got {others!r}")
        if others == "heuristic" and not self._has_heuristic():
            raise ValueError(f"others='heuristic': {self.env.name} has no scripted heuristic; use random or noop")
        return others

    def _has_heuristic(self) -> bool:
        return type(self.env.scenario).heuristic is not Scenario.heuristic

    def _key_table(self) -> dict:
        if self.env.continuous:
            raise ValueError("play drives discrete actions (continuous=False)")
        table = {key: 0 for key in NOOP_KEYS}
        table.update({str(i): i for i in range(min(self.env.num_actions, 10))})
        for action, meaning in enumerate(self.env.action_meanings):
            if meaning in KEYS_BY_MEANING:
                table.setdefault(KEYS_BY_MEANING[meaning], action)
        return table

    def _others_actions(self) -> torch.Tensor:
        if self.others == "heuristic":
            return self.env.heuristic_actions().clone()
        if self.others == "random":
            return random_policy(self.env, self.obs, self.generator)
        return torch.zeros(1, self.env.num_agents, dtype=torch.int64)


def task_class(name):
    """The task of a registered name, or the Scenario subclass a "module:Class" string names."""
    if not (isinstance(name, str) and name.count(":") == 1):
        return env_class(name)
    module, attribute = name.split(":")
    try:
        task = getattr(importlib.import_module(module), attribute)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"task {name!r} names no importable class: {exc}") from None
    if not (isinstance(task, type) and issubclass(task, Scenario)):
        raise ValueError(f"task {name!r} must name a Scenario subclass, got {task!r}")
    return task


class KeyboardWindow:
    """A matplotlib window that shows frames and remembers the key held down (None: none)."""

    def __init__(self, title: str, fps: float):
        import matplotlib.pyplot as plt

        for name in [k for k in plt.rcParams if k.startswith("keymap.")]:  # our keys, not matplotlib's shortcuts
            plt.rcParams[name] = [k for k in plt.rcParams[name] if k not in ("w", "a", "s", "d", "q", *"0123456789")]
        self.fps = fps
        self.held: str | None = None
        self.closed = False
        self.figure = plt.figure(title)
        self.axes = self.figure.add_axes((0, 0, 1, 1))
        self.axes.set_axis_off()
        self.image = None
        canvas = self.figure.canvas
        canvas.mpl_connect("key_press_event", self._press)
        canvas.mpl_connect("key_release_event", self._release)
        canvas.mpl_connect("close_event", self._close)

    def show(self, frame: np.ndarray) -> None:
        """Draw `frame`, then handle events for 1 / fps seconds (the pace of the game)."""
        if self.image is None:
            height, width = frame.shape[:2]
            self.figure.set_size_inches(width / 50, height / 50)  # 2x the frame at 100 dpi
            self.image = self.axes.imshow(frame, interpolation="nearest")
            self.figure.show()
        else:
            self.image.set_data(frame)
        self.figure.canvas.draw_idle()
        self.figure.canvas.start_event_loop(1.0 / self.fps)

    def _press(self, event) -> None:
        if event.key in QUIT_KEYS:
            self.closed = True
        else:
            self.held = event.key

    def _release(self, event) -> None:
        if event.key == self.held:
            self.held = None

    def _close(self, event) -> None:
        self.closed = True


def play_window(player: Player) -> None:
    """Play in a window until it is closed or q / escape is pressed."""
    window = KeyboardWindow(f"marl_render.play {player.env.name}: {player.env.agent_names[player.agent]}",
                            1.0 / player.env.dt)
    window.show(player.frame())
    while not window.closed:
        key = window.held if window.held in player.keys else "space"  # unknown keys: noop
        window.show(player.step(key).frame)


def play_keys(player: Player, keys: list, frames: str | None) -> dict:
    """Play the scripted `keys` (one step each) offscreen; the record printed as JSON."""
    for key in keys:  # every key is known before anything is played
        player.action_for(key)
    record = {"task": player.env.name, "agent": player.env.agent_names[player.agent], "keys": keys,
              "actions": [], "rewards": [], "poses": [player.pose()]}
    images = [player.frame()]
    for key in keys:
        turn = player.step(key)
        record["actions"].append(turn.action)
        record["rewards"].append(turn.reward)
        record["poses"].append(player.pose())
        images.append(turn.frame)
    if frames is not None:
        os.makedirs(frames, exist_ok=True)
        for i, image in enumerate(images):
            Image.fromarray(image).save(os.path.join(frames, f"frame_{i:04d}.png"))
    record["frames"] = len(images)
    return record


def frames_folder_problem(folder: str) -> str | None:
    """Why the frames cannot be written into `folder` (made if missing), or None: checked before
    anything is played, so that a bad --frames does not lose a played sequence."""
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as exc:
        return f"cannot be made a folder ({exc.strerror})"
    if not os.access(folder, os.W_OK | os.X_OK):
        return "is a folder this process cannot write into"
    return None


def parse_args(argv=None):
    parser = argparse.ArgumentParser(prog="python -m marl_render.play", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("task", help="a registered task (marl_render.envs.list_envs()) or module:Class")
    parser.add_argument("--agent", default="0", help="the agent you drive: its index or name (default 0)")
    parser.add_argument("--others", choices=OTHERS, default=None,
                        help="what the other agents play (default: heuristic where the task has one, else random)")
    parser.add_argument("--keys", default=None,
                        help='a scripted key sequence, e.g. "w w a d": one step per key, no window')
    parser.add_argument("--frames", default=None, help="with --keys: a folder for the frames as PNGs")
    parser.add_argument("--resolution", type=int, default=64, help="the agents' views (pixels a side)")
    parser.add_argument("--overview", type=int, default=256, help="the overview's pixels a side")
    parser.add_argument("--seed", type=int, default=0, help="the env's and the random policy's seed")
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.frames is not None and args.keys is None:
        print("marl_render.play: --frames needs --keys (a scripted sequence)", file=sys.stderr)
        return 2
    if args.frames is not None and (problem := frames_folder_problem(args.frames)):
        print(f"marl_render.play: --frames {args.frames!r}: {problem}", file=sys.stderr)
        return 2
    if args.keys is None:
        reason = window_unavailable()
        if reason is not None:
            print(f"marl_render.play: cannot open a window: {reason}; --keys \"w a d ...\" plays a scripted "
                  f"sequence without one", file=sys.stderr)
            return 2
    try:
        player = Player(args.task, agent=args.agent, others=args.others, resolution=args.resolution,
                        overview=args.overview, seed=args.seed)
    except (ValueError, TypeError) as exc:
        print(f"marl_render.play: {exc}", file=sys.stderr)
        return 2
    try:
        if args.keys is None:
            play_window(player)
            return 0
        try:
            record = play_keys(player, args.keys.split(), args.frames)
        except ValueError as exc:
            print(f"marl_render.play: {exc}", file=sys.stderr)
            return 2
        print(json.dumps(record))
        return 0
    finally:
        player.close()


if __name__ == "__main__":
    sys.exit(main())
