"""A focal-only env: the driver simulates every slot, bots play the background ones, and only the
focal agents are exposed (agent names, groups, spec, observations, rewards, dones).

    from marl_render.envs import make_env
    env = make_env("tag", num_worlds=64, heldout="tag/prey_vs_interceptors")   # a held-out scenario
    env = make_env("tag", num_worlds=64, background=Population({"prey": [make_bot("tag", "heuristic")]}))
    env.agent_names                  # the focal agents only (here the predators)
    obs = env.reset(seed=0)          # obs[key]: [W, F, ...] for the F focal agents
    obs, reward, terminated, truncated, info = env.step(actions)    # actions [W, F]
    info["background_reward"]        # float32 [W]: the background slots' mean reward of the step

Every front end takes the same keywords (``make_parallel_env("tag", heldout=...)``,
``make_vec_env``, ``make_torchrl_env``, ``make_sb3_env``, RLlib's env_config): they see a
``FocalEnv`` where they would see the driver, with the same methods and attributes.

At every reset of a world (reset, reset_worlds, or an autoreset inside step) the world samples one
bot per background slot, with replacement, from the bots of the slot's team (its role): with
levels on (envs/levels.py) as a pure function of the world's level id, so a level plays with the
same bots in any world slot and batch; else with the env's own generator ("background_rng"):
deterministic for a seed, different across worlds. A seeded reset re-seeds that generator and each
bot's own (its ``generator`` attribute, a torch.Generator) with the seed plus the offset the bot's
seed had from the env's when the env was built, so ``reset(seed=s)`` replays the same bots' draws.
A step calls each distinct bot once, over every (world, slot) pair it plays (``bot_calls`` counts
the calls); what a bot returns is checked, and a bad action is named as that bot's. Background
bots see their own slots' observations or read the simulation state; the frames of background
slots are still rendered (the renderer draws every agent's view in the same pass). A call that
raises, in the core or in a bot's act or reset, leaves the env as it was.
"""
from __future__ import annotations

import contextlib
import dataclasses
import threading

import torch

from marl_render.util.keyed_random import KeyedRandom, derive_keys
from marl_render.util.validation import describe

from . import levels as level_sets
from . import masking
from .atomic import AllOrNothing, one_at_a_time
from .core import BatchedEnv

# The driver's attributes a focal-only env shares unchanged (settings of the whole batch).
SHARED = ("name", "num_worlds", "resolution", "continuous", "num_actions", "action_dim", "action_meanings",
          "obs_keys", "state_dim", "max_steps", "dt", "device", "seed", "autoreset", "pixel_channels", "depth",
          "far", "state_obs", "lidar_rays", "lidar_range", "grayscale", "enforce_action_mask", "scenario",
          "renderer", "physics", "physics_compiled", "context", "agent_range", "background", "fov_y", "near",
          "overview_resolution", "overview_fov_y", "arena_half_extent", "appearance", "appearance_ids",
          "torch_threads", "generator", "step_count", "sim", "closed", "levels", "level_ids", "needs_reset")


def _check_generator_state(name: str, state) -> None:
    """ValueError naming `name` unless `state` loads into a torch.Generator (tried on a scratch one,
    so that nothing changes before every part of a state was checked)."""
    try:
        torch.Generator().set_state(state)
    except (TypeError, RuntimeError) as error:
        raise ValueError(f"{name} must be a torch.Generator state (a uint8 tensor from get_state()), got "
                         f"{describe(state)}: {error}") from None


def _agent_names(focal) -> tuple:
    """Population's `focal`: one agent name, or several (a list or tuple of str)."""
    if isinstance(focal, str):
        return (focal,)
    if not isinstance(focal, (list, tuple)) or not all(isinstance(name, str) for name in focal):
        raise TypeError(f"focal must be an agent name (str) or a list of them, got {describe(focal)}")
    return tuple(focal)


class Population:
    """Background bots by role: ``{team: [Policy, ...]}`` (marl_render/policies.py; each bot has act
    and reset). The slots of those teams are background, unless `focal` (an agent name, or a list of
    them) says which agents are focal; every other slot must belong to a team listed here."""

    def __init__(self, bots_by_role: dict, focal=None):
        if not isinstance(bots_by_role, dict) or not bots_by_role:
            raise TypeError(f"bots_by_role must be a non-empty dict {{team: [policies]}}, got {describe(bots_by_role)}")
        for team, bots in bots_by_role.items():
            if not isinstance(bots, (list, tuple)) or not bots or not all(hasattr(b, "act") for b in bots):
                raise TypeError(f"bots_by_role[{team!r}] must be a non-empty list of policies (objects with act), "
                                f"got {describe(bots)}")
            for j, bot in enumerate(bots):  # reset runs at every reset of a world: a bot without it would fail there
                missing = [method for method in ("act", "reset") if not callable(getattr(bot, method, None))]
                if missing:
                    raise TypeError(f"bots_by_role[{team!r}][{j}] ({type(bot).__name__} "
                                    f"{getattr(bot, 'name', None)!r}) must be a policy with act and reset "
                                    f"(marl_render.policies.Policy); it lacks {missing}")
        self.bots_by_role = {team: list(bots) for team, bots in bots_by_role.items()}
        self.focal = None if focal is None else _agent_names(focal)

    def __repr__(self):
        roles = {team: [getattr(b, "name", type(b).__name__) for b in bots] for team, bots in self.bots_by_role.items()}
        return f"Population({roles}, focal={self.focal})"


class FocalEnv(AllOrNothing):
    """The driver `core` with its background slots played by `population`; see the module docstring."""

    def __init__(self, core: BatchedEnv, population: Population):
        if not isinstance(core, BatchedEnv):
            raise TypeError(f"core must be a BatchedEnv (marl_render.envs.make_env), got {describe(core)}")
        if not isinstance(population, Population):
            raise TypeError(f"background must be a marl_render.envs.Population, got {describe(population)}")
        team_of = {name: team for team, names in core.groups.items() for name in names}
        unknown = sorted(set(population.bots_by_role) - set(core.groups))
        if unknown:
            raise ValueError(f"background names teams {unknown} that {core.name} does not have; its teams: "
                             f"{list(core.groups)}")
        focal = population.focal
        if focal is None:
            focal = [n for n in core.agent_names if team_of[n] not in population.bots_by_role]
        unknown = [n for n in focal if n not in team_of]
        if unknown or len(set(focal)) != len(focal):
            raise ValueError(f"focal must name distinct agents of {core.name} {list(core.agent_names)}, "
                             f"got {list(focal)}")
        background = [n for n in core.agent_names if n not in focal]
        if not focal or not background:
            raise ValueError(f"a focal-only env needs at least one focal and one background agent; focal "
                             f"{list(focal)}, background {background}")
        unplayed = sorted({team_of[n] for n in background} - set(population.bots_by_role))
        if unplayed:
            raise ValueError(f"background has no bots for team(s) {unplayed}, whose agents "
                             f"{[n for n in background if team_of[n] in unplayed]} are not focal")
        self.core, self.population = core, population
        index = {name: i for i, name in enumerate(core.agent_names)}
        self.agent_names = [n for n in core.agent_names if n in focal]  # in the task's order
        self.focal_slots = torch.tensor([index[n] for n in self.agent_names])
        self.background_names = background
        self.background_slots = torch.tensor([index[n] for n in background])
        self.num_agents = len(self.agent_names)
        self.groups = {team: [n for n in names if n in focal] for team, names in core.groups.items()
                       if any(n in focal for n in names)}
        # Distinct bots, and for each background slot the bots of its role (padded; counts say how many).
        self.bots = []
        for bots in population.bots_by_role.values():
            self.bots += [b for b in bots if not any(b is known for known in self.bots)]
        roles = [[next(k for k, known in enumerate(self.bots) if known is b)
                  for b in population.bots_by_role[team_of[n]]] for n in background]
        width = max(len(r) for r in roles)
        self._candidates = torch.tensor([r + [r[0]] * (width - len(r)) for r in roles])  # [B, K]
        self._counts = torch.tensor([len(r) for r in roles])  # [B]
        self.info_keys = {**core.info_keys, "background_reward": torch.float32}
        self.spec = dataclasses.replace(core.spec, agent_names=tuple(self.agent_names), groups=self.groups,
                                        info={**core.spec.info, "background_reward": torch.float32})
        self.bot_generator = torch.Generator().manual_seed(core.seed + 1)
        # Each bot's seed relative to the env's when the env was built (None: a bot without a generator):
        # reset(seed=s) re-seeds it with s plus this, so reset(seed=env.seed) puts it back where it began.
        self._seed_offsets = [(b.generator.initial_seed() - core.seed) % 2 ** 64
                              if isinstance(getattr(b, "generator", None), torch.Generator) else None
                              for b in self.bots]
        team_of_bot = [[team for team, bots in population.bots_by_role.items() if any(b is bot for b in bots)]
                       for bot in self.bots]
        self._bot_labels = [f"background bot {getattr(bot, 'name', type(bot).__name__)!r} "
                            f"({f'team {teams[0]!r}' if len(teams) == 1 else f'teams {teams}'})"
                            for bot, teams in zip(self.bots, team_of_bot, strict=True)]
        self.assignment = torch.zeros(core.num_worlds, len(background), dtype=torch.int64)  # [W, B] bot index
        self.bot_calls = 0  # act calls made on bots (a step makes at most one per distinct bot)
        self._pairs = []
        self._obs = None  # the full obs the bots act on (None: before reset, or after set_state)
        self._lock = threading.RLock()

    def __getattr__(self, name):
        if name in SHARED:
            return getattr(self.core, name)
        raise AttributeError(f"{type(self).__name__} has no attribute {name!r}")

    # ------------------------------------------------------------------ the driver's API, focal slots only
    @property
    def alive(self) -> torch.Tensor:
        return self.core.alive[:, self.focal_slots]

    @one_at_a_time
    def reset(self, seed: int | None = None) -> dict:
        with self.kept():
            obs = self.core.reset(seed=seed)  # checks the seed before anything changes
            return self._after_reset(torch.ones(self.num_worlds, dtype=torch.bool), obs, seed)

    @one_at_a_time
    def reset_worlds(self, mask, seed: int | None = None) -> dict:
        with self.kept():
            obs = self.core.reset_worlds(mask, seed=seed)
            return self._after_reset(torch.as_tensor(mask).cpu(), obs, seed)

    @one_at_a_time
    def reset_to_level(self, mask, level_ids, seed: int | None = None) -> dict:
        """The core's reset_to_level (envs/levels.py), then new bots for those worlds."""
        with self.kept():
            obs = self.core.reset_to_level(mask, level_ids, seed=seed)
            return self._after_reset(torch.as_tensor(mask).cpu(), obs, seed)

    @one_at_a_time
    def step(self, actions):
        actions = self.check_actions(actions)
        if self._obs is None:
            self._check_bots_can_act()
        with self.kept():  # a bot that raises, in act or in an autoreset's reset, changes nothing
            full = self._background_actions()
            full[:, self.focal_slots] = actions
            obs, reward, terminated, truncated, info = self.core.step(full)
            info["background_reward"] = reward[:, self.background_slots].mean(1)
            if "final_obs" in info:
                info["final_obs"] = self._focal(info["final_obs"])
            if "autoreset_worlds" in info and bool(info["autoreset_worlds"].any()):
                self._restart(info["autoreset_worlds"].cpu(), obs)
            self._commit(obs=obs)
        focal = self.focal_slots
        return self._focal(obs), reward[:, focal], terminated[:, focal], truncated[:, focal], info

    def check_actions(self, actions) -> torch.Tensor:
        """Focal actions [W, F] (or [W, F, action_dim]) checked as the driver checks its own."""
        W, F = self.num_worlds, self.num_agents
        shape = (W, F, self.action_dim) if self.continuous else (W, F)
        given = tuple(getattr(actions, "shape", ()))
        if not isinstance(actions, (torch.Tensor, list, tuple)) and not hasattr(actions, "shape"):
            raise TypeError(f"actions must be a tensor of shape {list(shape)} (worlds, focal agents "
                            f"{self.agent_names}), got {describe(actions)}")
        actions = torch.as_tensor(actions).detach()
        if tuple(actions.shape) != shape:
            raise ValueError(f"actions must have shape {list(shape)} (worlds, focal agents {self.agent_names}), "
                             f"got {list(given or actions.shape)}")
        full = torch.zeros((W, self.core.num_agents, *shape[2:]), dtype=actions.dtype)
        full[:, self.focal_slots] = actions
        return self.core.check_actions(full)[:, self.focal_slots]

    def episode_over(self) -> torch.Tensor:
        return self.core.episode_over()

    def action_mask(self) -> torch.Tensor:
        return self.core.action_mask()[:, self.focal_slots]

    def random_actions(self, generator: torch.Generator | None = None) -> torch.Tensor:
        return self.core.random_actions(generator)[:, self.focal_slots]

    def heuristic_actions(self) -> torch.Tensor:
        return self.core.heuristic_actions()[:, self.focal_slots]

    def state_observation(self) -> torch.Tensor:
        return self.core.state_observation()[:, self.focal_slots]

    def render_overview(self, resolution=None) -> torch.Tensor:
        return self.core.render_overview(resolution)

    def get_state(self) -> dict:
        """The driver's state plus the worlds' bots ("background_bots" [W, B]), the generator that
        draws them ("background_rng") and each distinct bot's own generator ("bot_rngs", None for a
        bot without one: a bot's random state is its ``generator`` attribute, if a torch.Generator).
        Bots' own memories (an actor's frame stack) are not part of it."""
        return {**self.core.get_state(), "background_bots": self.assignment.clone(),
                "background_rng": self.bot_generator.get_state(), "bot_rngs": self._bot_rngs()}

    @one_at_a_time
    def set_state(self, state: dict) -> None:
        keys = ("background_bots", "background_rng", "bot_rngs")
        if not isinstance(state, dict) or any(k not in state for k in keys):
            raise ValueError(f"state must be a dict from this focal-only env's get_state(), with {list(keys)}")
        state = dict(state)
        bots, rng, bot_rngs = (state.pop(k) for k in keys)
        if not (isinstance(bots, torch.Tensor) and bots.shape == self.assignment.shape and bots.dtype == torch.int64
                and bool(((bots >= 0) & (bots < len(self.bots))).all())):
            raise ValueError(f"state['background_bots'] must be int64 {list(self.assignment.shape)} in "
                             f"[0, {len(self.bots)}), got {describe(bots)}")
        _check_generator_state("state['background_rng']", rng)
        self._check_bot_rngs(bot_rngs)
        self.core.set_state(state)
        self.bot_generator.set_state(rng)
        self._set_bot_rngs(bot_rngs)
        # obs None: no observation of this state yet (bots that read the simulation state act on)
        self._commit(assignment=bots.clone(), pairs=self._pairs_of(bots), obs=None)

    def close(self) -> None:
        self.core.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __repr__(self):
        return f"FocalEnv({self.core!r}, focal={self.agent_names}, background={self.population!r})"

    # ------------------------------------------------------------------ internals
    def sampled_bots(self) -> list:
        """[W][B] names of the bots playing each world's background slots."""
        names = [getattr(b, "name", type(b).__name__) for b in self.bots]
        return [[names[k] for k in row] for row in self.assignment.tolist()]

    # ------------------------------------------------------------------ all or nothing (envs/atomic.py)
    # A call that raises (in the core, or in a bot's act or reset after the core committed) leaves the env
    # as it was: the core's state and generator, the bots' assignment, the generator that draws them and
    # the bots' own generators. Bots' memories (an actor's frame stack) are the bots': a failed call may
    # have cleared some of them.
    _committed = {"assignment": "assignment", "pairs": "_pairs", "obs": "_obs"}

    def _generators(self) -> list:
        return [self.bot_generator, *(b.generator for b in self.bots
                                      if isinstance(getattr(b, "generator", None), torch.Generator))]

    @contextlib.contextmanager
    def kept(self):
        """AllOrNothing.kept, the core's part included."""
        with self.core.kept(), super().kept():
            yield

    def _after_reset(self, worlds: torch.Tensor, obs: dict, seed: int | None) -> dict:
        """After the core reset the worlds of mask [W] (re-seeded with `seed`, if given): the bots'
        generators re-seeded alike, new bots there; the focal observations."""
        if seed is not None:
            seed = int(seed)  # the core took it (an int or numpy integer in [0, 2**63)): a numpy one would overflow
            self.bot_generator.manual_seed(seed + 1)
            for bot, offset in zip(self.bots, self._seed_offsets, strict=True):
                if offset is not None:
                    bot.generator.manual_seed((seed + offset) % 2 ** 64)
        self._restart(worlds, obs)
        return self._focal(obs)

    def _restart(self, worlds: torch.Tensor, obs: dict) -> None:
        """New bots for the worlds of mask [W], sampled per slot from its role (one draw per world
        and slot: with levels on, a pure function of the world's level id, else from bot_generator);
        their memories cleared, then (once every bot's reset has passed) the new bots committed."""
        W, B = self.assignment.shape
        if self.core.levels is not None:  # the same level samples the same bots in any slot and batch
            core = self.core
            keys = level_sets.level_keys(core.level_ids, core.name, core.scenario.params, core.num_agents)
            unit = KeyedRandom(derive_keys(keys, "background bots")).uniform("bots", (B,))
        else:
            unit = torch.rand(W, B, generator=self.bot_generator)
        fresh = self._candidates.gather(1, (unit * self._counts).long().T).T  # [W, B]
        assignment = torch.where(worlds[:, None], fresh, self.assignment)
        for bot in self.bots:
            bot.reset(self.core, worlds)
        self._commit(assignment=assignment, pairs=self._pairs_of(assignment), obs=obs)

    def _bot_rngs(self) -> list:
        """[K] each distinct bot's generator state (a uint8 tensor), None for a bot without one."""
        return [b.generator.get_state() if isinstance(getattr(b, "generator", None), torch.Generator) else None
                for b in self.bots]

    def _check_bot_rngs(self, rngs) -> None:
        expected = ["None" if r is None else "generator state" for r in self._bot_rngs()]
        if not isinstance(rngs, list) or len(rngs) != len(self.bots) or any(
                (r is None) != (e == "None") for r, e in zip(rngs, expected, strict=True)):
            raise ValueError(f"state['bot_rngs'] must be a list of {len(self.bots)} entries ({expected}), "
                             f"got {describe(rngs)}")
        for k, r in enumerate(rngs):
            if r is not None:
                _check_generator_state(f"state['bot_rngs'][{k}]", r)

    def _set_bot_rngs(self, rngs: list) -> None:
        for bot, r in zip(self.bots, rngs, strict=True):
            if r is not None:
                bot.generator.set_state(r)

    def _check_bots_can_act(self) -> None:
        """Before the first reset, or after set_state with bots that read observations: RuntimeError."""
        if self.core.needs_reset:
            raise RuntimeError(f"call reset() before using this focal-only {self.name} env")
        seeing = [getattr(b, "name", repr(b)) for b in self.bots if set(getattr(b, "needs", ())) - {"sim"}]
        if seeing:
            raise RuntimeError(f"after set_state the bots {seeing} have no observation to act on; call reset() or "
                               f"use bots that read the simulation state")

    def _pairs_of(self, assignment: torch.Tensor) -> list:
        """[(k, bot, worlds [P], slots [P])] for each distinct bot k that plays somewhere."""
        pairs = []
        for k, bot in enumerate(self.bots):
            worlds, column = (assignment == k).nonzero(as_tuple=True)
            if len(worlds):
                pairs.append((k, bot, worlds, self.background_slots[column]))
        return pairs

    def _background_actions(self) -> torch.Tensor:
        """Actions [W, A, ...] with every background slot's bot action (focal slots 0)."""
        W, A = self.num_worlds, self.core.num_agents
        if self.continuous:
            full = torch.zeros(W, A, self.action_dim)
        else:
            full = torch.zeros(W, A, dtype=torch.int64)
        for k, bot, worlds, slots in self._pairs:
            needs = getattr(bot, "needs", ())
            seen = {key: value[worlds, slots] for key, value in (self._obs or {}).items() if key in needs}
            actions = bot.act(self.core, seen, worlds, slots)
            self.bot_calls += 1
            full[worlds, slots] = self._checked(k, actions, worlds, slots).to(full.dtype)
        return full

    def _checked(self, k: int, actions, worlds: torch.Tensor, slots: torch.Tensor) -> torch.Tensor:
        """Bot k's actions for its pairs, else TypeError / ValueError naming the bot (not the focal
        actions): a tensor of one action per pair, integers in [0, num_actions) the mask allows under
        enforce_action_mask, or finite floats in [-1, 1] [P, action_dim]."""
        label, core = self._bot_labels[k], self.core
        if not isinstance(actions, torch.Tensor):
            raise TypeError(f"{label} must return a torch.Tensor of actions, got {describe(actions)}")
        shape = [len(worlds), self.action_dim] if self.continuous else [len(worlds)]
        integer = not (actions.is_floating_point() or actions.is_complex() or actions.dtype == torch.bool)
        if self.continuous != actions.is_floating_point() or not self.continuous and not integer:
            kind = "float" if self.continuous else "integer"  # a float action is refused, never truncated
            raise TypeError(f"{label} must return {kind} actions, got {describe(actions)}")
        if list(actions.shape) != shape:
            raise ValueError(f"{label} must return actions of shape {shape}, got {list(actions.shape)} (one per "
                             f"(world, slot) pair it plays)")
        if not actions.numel():
            return actions
        if self.continuous:
            if not bool((torch.isfinite(actions) & (actions.abs() <= 1)).all()):
                raise ValueError(f"{label} must return finite actions in [-1, 1], got values in "
                                 f"[{actions.min().item():.4g}, {actions.max().item():.4g}]")
            return actions
        low, high = (value.item() for value in torch.aminmax(actions.to(torch.int64)))
        if low < 0 or high >= self.num_actions:
            raise ValueError(f"{label} must return actions in [0, {self.num_actions}), got values in [{low}, {high}]")
        if core.enforce_action_mask:
            self._check_allowed(label, actions.to(torch.int64).cpu(), worlds, slots)
        return actions

    def _check_allowed(self, label: str, actions: torch.Tensor, worlds: torch.Tensor, slots: torch.Tensor) -> None:
        """enforce_action_mask: ValueError naming the bot where it took a forbidden action (for the agents
        the step acts for, as the core counts them)."""
        core = self.core
        mask, acting = core.action_mask()[worlds, slots].cpu(), masking.acting(core)[worlds, slots].cpu()
        refused = masking.forbidden(mask, actions, acting)
        if bool(refused.any()):
            i = int(refused.nonzero()[0, 0])
            allowed = mask[i].nonzero()[:, 0].tolist()
            raise ValueError(f"{label} must take actions the action mask allows (enforce_action_mask=True), got "
                             f"{int(refused.sum())} forbidden, e.g. world {int(worlds[i])} agent "
                             f"{core.agent_names[int(slots[i])]!r} took {int(actions[i])}, allowed: {allowed}")

    def _focal(self, obs: dict) -> dict:
        return {key: value[:, self.focal_slots] for key, value in obs.items()}
