"""The task that the round-4 reliability tests (issue 24) break on purpose, and their helpers: shared
by tests/test_reliability_author_traps.py and tests/isolated_crash_cases.py."""
from __future__ import annotations

import collections
import dataclasses

import torch

from marl_render.envs import ArenaScenario, ArenaState, Prop, list_envs, make_env, numbered

W = 2
RES = 8
ENVS = list_envs()
LOOKS = {"appearance": "train", "lidar": 3}  # the options of the worlds' looks (drawn at each reset) and lidar

# ---------------------------------------------------------------------- a small task to break on purpose
@dataclasses.dataclass(frozen=True)
class ProbeState(ArenaState):
    seen: torch.Tensor  # [W, A, 3] float32: handed out by observation() as it is
    flag: torch.Tensor  # [W, 1, 2] a prop's place


class Probe(ArenaScenario):
    """Two agents; observation() returns a state field as it is, action_mask() one constant tensor,
    and the reward reads the field. ``fail = (hook, n)`` makes the n-th call of that hook raise."""

    name, State, physics_terms = "probe", ProbeState, frozenset({"walls", "drag"})
    default_num_agents, agent_range, default_max_steps = 2, (2, 2), 3  # episodes end at the third step
    info_keys = {"seen_sum": torch.float32}
    fail = None

    def setup(self):
        self.setup_arena({"agents": numbered("agent", 2)}, state_dim=3, radius=0.15, max_speed=2.0)
        self.calls = collections.Counter()
        self.everything = torch.ones(self.num_worlds, 2, self.num_actions, dtype=torch.bool)

    def check(self, hook):
        self.calls[hook] += 1
        if self.fail == (hook, self.calls[hook]):
            raise RuntimeError(f"{hook} failed on purpose")

    def initial_state(self):
        W, N = self.num_worlds, self.num_agents
        return self.at_rest(torch.zeros(W, N, 2), torch.zeros(W, N), seen=torch.zeros(W, N, 3),
                            flag=torch.zeros(W, 1, 2))

    def props(self):
        return [Prop("flag", "box", count=1, position="flag", height=0.2, scale=(0.2, 0.2, 0.4), moves=False)]

    def spawn(self, generator):
        self.check("spawn")
        W, N = self.num_worlds, self.num_agents
        pos = torch.rand(W, N, 2, generator=generator) * 2 - 1
        return self.at_rest(pos, torch.zeros(W, N), seen=torch.rand(W, N, 3, generator=generator) + 1,
                            flag=torch.rand(W, 1, 2, generator=generator) - 0.5)

    def rules(self, before, moved, actions, alive, generator):
        self.check("rules")
        noise = torch.rand(self.num_worlds, generator=generator)  # draws: a failed step must not lose them
        reward = before.seen.sum(-1) + noise[:, None]
        return moved, reward, torch.zeros_like(alive), {"seen_sum": before.seen.sum((1, 2))}

    def observation(self, state, alive):
        self.check("observation")
        return state.seen

    def action_mask(self, state, alive):
        self.check("action_mask")
        return self.everything

    def instances(self, state, full):
        self.check("instances")
        return super().instances(state, full)

    def frozen(self, state):
        self.check("frozen")
        return None

    def lidar(self, state, rays, reach):
        self.check("lidar")
        return super().lidar(state, rays, reach)


def probe(task=Probe, **kwargs):
    return make_env(task, **{"num_worlds": W, "resolution": RES, "seed": 0, **kwargs})


def assert_same(a, b, where=""):
    """Nested dicts / tuples of tensors are equal, bit for bit."""
    if isinstance(a, torch.Tensor):
        assert torch.equal(a, b), where
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            assert_same(a[key], b[key], f"{where}[{key!r}]")
    else:
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")


def tensors(value):
    if isinstance(value, torch.Tensor):
        yield value
    elif isinstance(value, dict):
        for item in value.values():
            yield from tensors(item)
    elif isinstance(value, (list, tuple)):
        for item in value:
            yield from tensors(item)


def scribble(value) -> None:
    """Write into every tensor of `value`, as a caller that owns them may."""
    for tensor in tensors(value):
        if tensor.dtype == torch.bool:
            tensor.logical_not_()
        else:
            tensor.fill_(3)
