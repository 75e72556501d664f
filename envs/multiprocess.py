"""One env over several worker processes: ``make_env(name, num_worlds=W, num_processes=N)``.

Each of the N workers is a process started with ``spawn`` (never fork: a GL context does not
survive it, docs/distributed.md) that builds its own ``BatchedEnv`` (so its own GL context, on
the same device) over a contiguous slice of the W worlds: worker k owns worlds
``bounds[k]:bounds[k + 1]`` (the slices differ by at most one world). The parent owns ONE
tensor per output (pixels, depth, the other observations, reward, flags, info, alive, step
counts) of all W worlds, shared with the workers (``torch.multiprocessing``: shared memory on
the CPU, CUDA IPC on a GPU), and each worker writes its worlds into its slice of it. A call
sends the command to every worker, waits for all of them and hands back copies of the shared
outputs, so what a call returns is the caller's memory (as the single-process env's outputs
are: the next call does not write into it).

On a CUDA device the host never waits for the GPU: the parent records an interprocess
``torch.cuda.Event`` per worker after writing the actions (and after copying the previous
outputs out), on which the worker's stream waits before it writes; the worker records another
once its outputs are written, on which the parent's current stream waits before its copies.
The only host waits are the pipes' messages (a worker answers once its work is queued).

Randomness: worker 0's generator is seeded with the env's seed, worker k > 0 with a key derived
from (seed, k) (``worker_seed``); ``reset(seed=s)`` re-seeds each worker the same way. So
``num_processes=1`` is bit-identical to the single-process env with the same seed, and with
N > 1 the default path's draws differ from it (each worker draws its own slice from its own
stream). With ``levels=`` a reset to given levels (``reset_to_level``) is a pure function of the
level ids and is bit-identical at any N; steps are as well for tasks whose step draws nothing
from the generator (cartpole, spread, push, tag, ...), so frames, rewards and states are then
bit-identical to the single-process env. ``get_state()["rng"]`` is the workers' generator
states, uint8 [N, bytes].

A worker's exception is raised in the parent as the same type with the same message, chained
from ``WorkerTraceback`` (the worker's traceback text). A call that failed in one worker is
undone in the others (each kept its state from before the call), so the env is as before the
call and stays usable. A worker that dies, or a call interrupted while the workers run, closes
the env (RuntimeError on later use). ``close()`` (also at garbage collection and at exit) stops
and joins every worker.
"""
from __future__ import annotations

import dataclasses
import functools
import multiprocessing.connection
import pickle
import signal
import threading
import traceback
import weakref

import numpy as np
import torch
import torch.multiprocessing

from marl_render.keyed_random import derive_keys
from marl_render.validation import describe, positive_int, unpicklable

from . import levels as level_sets
from . import masking
from . import options as check
from .core import BatchedEnv
from .options import EnvOptions

JOIN_TIMEOUT_S = 30.0  # a worker that has not exited this long after "close" is killed
_MUTATING = frozenset({"reset", "reset_worlds", "reset_to_level", "step", "set_state"})


class WorkerTraceback(Exception):
    """The traceback text of an exception raised in a worker process (the ``__cause__`` of the
    exception the parent raises)."""


def check_num_processes(value, num_worlds: int) -> int:
    """`value` as a process count: an int in [1, num_worlds] (every worker owns at least one world)."""
    return positive_int("num_processes", value, maximum=num_worlds)


def world_bounds(num_worlds: int, num_processes: int) -> list:
    """[0, ..., num_worlds]: worker k owns worlds bounds[k]:bounds[k + 1]; the first W mod N workers
    own one world more than the others."""
    base, extra = divmod(num_worlds, num_processes)
    sizes = [base + (k < extra) for k in range(num_processes)]
    return [int(b) for b in np.concatenate(([0], np.cumsum(sizes)))]


def worker_seed(seed: int, rank: int) -> int:
    """The seed of worker `rank`'s generator: `seed` itself for worker 0, a key derived from (seed,
    rank) for the others, in [0, 2**63)."""
    if rank == 0:
        return seed
    return int(derive_keys(torch.tensor([seed], dtype=torch.int64), "process", rank)[0]) & (2 ** 63 - 1)


def output_layout(spec, num_agents: int, autoreset, has_levels: bool) -> dict:
    """{name: (shape after the worlds, dtype)} of every output a call can produce: the observations,
    the step's reward, flags and info, and the state the parent reports (alive, step counts, levels)."""
    A = num_agents
    obs = {key: ((A, *entry.shape), entry.dtype) for key, entry in spec.observations.items()}
    layout = {f"obs/{key}": value for key, value in obs.items()}
    layout.update({"reward": ((A,), torch.float32), "terminated": ((A,), torch.bool),
                   "truncated": ((A,), torch.bool), "state/alive": ((A,), torch.bool),
                   "state/step_count": ((), torch.int64), "state/episode_over": ((), torch.bool),
                   "info/step_count": ((), torch.int64), "info/done_worlds": ((), torch.bool)})
    layout.update({f"info/{key}": ((), dtype) for key, dtype in spec.info.items() if key != "level"})
    if autoreset:
        layout["info/autoreset_worlds"] = ((), torch.bool)
    if autoreset == "same_step":
        layout.update({f"final_obs/{key}": value for key, value in obs.items()})
    if has_levels:
        layout["state/level_ids"] = ((), torch.int64)
        layout["info/level"] = ((), torch.int64)
        if autoreset == "same_step":
            layout["info/final_level"] = ((), torch.int64)
    return layout


def _env_call(method):
    """A call of the env's public API: one at a time, outside inference mode and without grad (as
    BatchedEnv's calls)."""
    @functools.wraps(method)
    def call(self, *args, **kwargs):
        with self._lock, torch.inference_mode(False), torch.no_grad():
            return method(self, *args, **kwargs)
    return call


class MultiProcessEnv:
    """W worlds of one task over N worker processes; see the module docstring.

    The attributes and calls of BatchedEnv that a front end reads: name, spec, num_worlds,
    num_agents, agent_names, groups, continuous, num_actions, action_dim, action_meanings,
    obs_keys, info_keys, state_dim, max_steps, dt, device, readback, resolution, seed, autoreset,
    enforce_action_mask, levels, level_ids, alive, step_count, closed; reset, reset_worlds,
    reset_to_level, step, check_actions, episode_over, random_actions, render_overview,
    get_state, set_state, close. Also num_processes, bounds (worker k owns worlds
    bounds[k]:bounds[k + 1]) and pids."""

    check_actions = BatchedEnv.check_actions  # reads only the attributes this class has too

    def __init__(self, scenario, options: EnvOptions, params, num_processes):
        self._lock = threading.RLock()
        self._closed = True  # until fully built
        if not isinstance(options, EnvOptions):
            raise TypeError(f"options must be an EnvOptions, got {describe(options)}")
        self.num_worlds = positive_int("num_worlds", options.num_worlds)
        self.num_processes = check_num_processes(num_processes, self.num_worlds)
        if options.context is not None:
            raise ValueError(f"context must be None with num_processes (each worker process opens its own GL "
                             f"context), got {describe(options.context)}")
        self.device = check.device(options.device)
        if self.device.type not in ("cpu", "cuda"):
            raise ValueError(f"device must be a CPU or CUDA device with num_processes, got {self.device}")
        seed = check.seed("seed", options.seed)
        self.seed = int(torch.Generator().seed() % 2 ** 63) if seed is None else seed
        self.levels = level_sets.as_sampler(options.levels)
        self.bounds = world_bounds(self.num_worlds, self.num_processes)
        self._sync = _CudaSync(self.num_processes) if self.device.type == "cuda" else _HostSync()
        self._connections, self._processes = [], []
        # Closes the workers when the env is collected or at exit, without holding the env alive.
        self._finalizer = weakref.finalize(self, _stop_workers, self._connections, self._processes)
        context = torch.multiprocessing.get_context("spawn")
        try:
            for rank in range(self.num_processes):
                size = self.bounds[rank + 1] - self.bounds[rank]
                worker_options = dataclasses.replace(options, num_worlds=size, seed=worker_seed(self.seed, rank))
                parent_end, worker_end = context.Pipe()
                process = context.Process(target=_serve, name=f"marl_render-worker-{rank}",
                                          args=(worker_end, rank, scenario, worker_options, params))
                process.start()
                worker_end.close()
                self._connections.append(parent_end)
                self._processes.append(process)
            descriptions = self._gather(self._receive_all())
            self._describe(descriptions[0])
            self._outputs = {name: self._shared((self.num_worlds, *shape), dtype)
                             for name, (shape, dtype) in output_layout(self.spec, self.num_agents, self.autoreset,
                                                                       self.levels is not None).items()}
            action_shape = (self.num_agents, self.action_dim) if self.continuous else (self.num_agents,)
            self._actions = self._shared((self.num_worlds, *action_shape),
                                         torch.float32 if self.continuous else torch.int64)
            for rank, connection in enumerate(self._connections):
                connection.send(("buffers", (self._outputs, self._actions, self.bounds[rank],
                                             self.bounds[rank + 1], self._sync.worker_events(rank))))
            self._gather(self._receive_all())
        except BaseException:
            self._finalizer()
            raise
        self._started = False
        self._closed = False

    def _describe(self, description: dict) -> None:
        for name, value in description.items():
            setattr(self, name, value)
        self.spec = dataclasses.replace(self.spec, num_worlds=self.num_worlds)

    def _shared(self, shape: tuple, dtype: torch.dtype) -> torch.Tensor:
        tensor = torch.zeros(shape, dtype=dtype, device=self.device)
        return tensor.share_memory_() if self.device.type == "cpu" else tensor  # CUDA: IPC when sent

    @property
    def pids(self) -> list:
        return [process.pid for process in self._processes]

    # ================================================================== public API
    @_env_call
    def reset(self, seed: int | None = None) -> dict:
        """Reset every world (BatchedEnv.reset); `seed` re-seeds every worker (worker_seed)."""
        self._check_open()
        seed = check.seed("seed", seed)
        self._call("reset", [None if seed is None else worker_seed(seed, k) for k in range(self.num_processes)])
        self._started = True
        if seed is not None:
            self.seed = seed
        return self._copies("obs/")

    @_env_call
    def reset_worlds(self, mask, seed: int | None = None) -> dict:
        """Reset the worlds where mask [W] (bool) is True (BatchedEnv.reset_worlds); obs of all worlds."""
        self._check_open()
        self._check_started()
        mask = self._world_mask(mask)
        seed = check.seed("seed", seed)
        self._call("reset_worlds", [(mask[lo:hi], None if seed is None else worker_seed(seed, k))
                                    for k, (lo, hi) in enumerate(self._slices())])
        return self._copies("obs/")

    @_env_call
    def reset_to_level(self, mask, level_ids, seed: int | None = None) -> dict:
        """Reset the worlds where mask is True to level_ids [W] (BatchedEnv.reset_to_level)."""
        self._check_open()
        self._check_started()
        level_sets.require_levels(self, "reset_to_level")
        mask = self._world_mask(mask)
        from_user = level_ids.detach() if isinstance(level_ids, torch.Tensor) else level_ids
        chosen = level_sets.check_level_ids("level_ids", from_user, self.num_worlds, where=mask)
        seed = check.seed("seed", seed)
        self._call("reset_to_level", [(mask[lo:hi], chosen[lo:hi].numpy(),
                                       None if seed is None else worker_seed(seed, k))
                                      for k, (lo, hi) in enumerate(self._slices())])
        return self._copies("obs/")

    @_env_call
    def step(self, actions):
        """Advance all worlds one step (BatchedEnv.step): (obs, reward, terminated, truncated, info)."""
        self._check_open()
        self._check_started()
        self._actions.copy_(self.check_actions(actions))
        self._call("step", [None] * self.num_processes)
        obs = self._copies("obs/")
        info = self._copies("info/")
        reward, terminated, truncated = (self._outputs[name].clone() for name in ("reward", "terminated", "truncated"))
        if self.autoreset == "same_step":
            info["final_obs"] = self._copies("final_obs/")
            if "final_level" in info and not bool(info["done_worlds"].any()):
                del info["final_level"]  # as the single-process env: only when a world was reset
        return obs, reward, terminated, truncated, info

    def episode_over(self) -> torch.Tensor:
        """bool [W]: worlds whose episode has ended (every agent terminated or truncated)."""
        return self._outputs["state/episode_over"].clone()  # the workers' (random episode ends: envs/episodes.py)

    def random_actions(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """Uniformly random valid actions (BatchedEnv.random_actions)."""
        W, A = self.num_worlds, self.num_agents
        if self.continuous:
            return torch.rand(W, A, self.action_dim, generator=generator) * 2 - 1
        if self.enforce_action_mask:
            return masking.sample_allowed(self._outputs["obs/action_mask"].clone(), generator)
        return torch.randint(self.num_actions, (W, A), generator=generator)

    @property
    def alive(self) -> torch.Tensor:
        """bool [W, A] (a copy)."""
        return self._outputs["state/alive"].clone()

    @property
    def step_count(self) -> torch.Tensor:
        """int64 [W] (a copy)."""
        return self._outputs["state/step_count"].clone()

    @property
    def level_ids(self) -> torch.Tensor | None:
        """int64 [W] on the CPU (a copy) with levels on, else None."""
        return None if self.levels is None else self._outputs["state/level_ids"].cpu().clone()

    @_env_call
    def render_overview(self, resolution=None) -> torch.Tensor:
        """uint8 [W, H2, W2, 3] (BatchedEnv.render_overview), gathered from the workers."""
        self._check_open()
        self._check_started()
        parts = self._call("render_overview", [resolution] * self.num_processes)
        return torch.cat([torch.from_numpy(part) for part in parts]).to(self.device)

    @_env_call
    def get_state(self) -> dict:
        """The whole state (BatchedEnv.get_state) of all worlds; "rng" is uint8 [N, bytes], the workers'
        generator states in order."""
        self._check_open()
        self._check_started()
        parts = self._call("get_state", [None] * self.num_processes)
        devices = parts[0][1]  # each key where the single-process env keeps it (level ids on the CPU, ...)
        state = {key: torch.cat([torch.from_numpy(arrays[key]) for arrays, _ in parts]).to(devices[key])
                 for key in devices if key != "rng"}
        state["rng"] = torch.stack([torch.from_numpy(arrays["rng"]) for arrays, _ in parts])
        return state

    @_env_call
    def set_state(self, state: dict) -> None:
        """Restore a state from get_state() of an env with the same arguments and num_processes; checked
        by the workers (BatchedEnv.set_state's checks), undone everywhere if one of them refuses it."""
        self._check_open()
        if not isinstance(state, dict):
            raise TypeError(f"state must be a dict of tensors as returned by get_state(), got {describe(state)}")
        for key, value in state.items():
            if not isinstance(value, torch.Tensor):
                raise TypeError(f"state[{key!r}] must be a torch.Tensor, got {describe(value)}")
        rng = state.get("rng")
        want = (self.num_processes,)
        if rng is None or rng.ndim != 2 or tuple(rng.shape[:1]) != want:
            raise ValueError(f"state['rng'] must be the workers' generator states, uint8 [{self.num_processes}, "
                             f"bytes] (get_state() of an env with num_processes={self.num_processes}), got "
                             f"{describe(rng)}")
        worlds = {key: value for key, value in state.items() if key != "rng"}
        bad = sorted(key for key, value in worlds.items() if value.ndim == 0 or value.shape[0] != self.num_worlds)
        if bad:
            raise ValueError(f"state[{bad[0]!r}] must have the worlds first ({self.num_worlds}), got "
                             f"{describe(worlds[bad[0]])}")
        parts = [{**{key: _wire(value[lo:hi]) for key, value in worlds.items()}, "rng": _wire(rng[k])}
                 for k, (lo, hi) in enumerate(self._slices())]
        devices = {key: str(value.device) for key, value in worlds.items()}
        self._call("set_state", [(part, devices) for part in parts])
        self._started = True

    def close(self) -> None:
        """Stop and join every worker; safe to call twice. Any later use raises RuntimeError."""
        with self._lock:
            self._closed = True
            self._finalizer()

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __reduce__(self):
        raise unpicklable(f"a marl_render {type(self).__name__}", "marl_render.envs.make_env")

    def __repr__(self):
        return (f"{type(self).__name__}(name={getattr(self, 'name', '?')!r}, num_worlds={self.num_worlds}, "
                f"num_processes={self.num_processes}, device={self.device})")

    # ================================================================== internals
    def _slices(self) -> list:
        return list(zip(self.bounds[:-1], self.bounds[1:], strict=True))

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"this {type(self).__name__} is closed (close() was called, or a worker process "
                               f"died or a call was interrupted); create a new one")

    def _check_started(self) -> None:
        if not self._started:
            raise RuntimeError("call reset() before using this environment")

    def _world_mask(self, mask) -> np.ndarray:
        tensor = mask.detach() if isinstance(mask, torch.Tensor) else torch.as_tensor(np.asarray(mask))
        if tensor.dtype != torch.bool:
            raise TypeError(f"mask must be a bool tensor of shape [{self.num_worlds}] (num_worlds), got "
                            f"{describe(mask)}")
        if tuple(tensor.shape) != (self.num_worlds,):
            raise ValueError(f"mask must be a bool tensor of shape [{self.num_worlds}] (num_worlds), "
                             f"got shape {list(tensor.shape)}")
        return tensor.cpu()

    def _copies(self, prefix: str) -> dict:
        """Copies of the shared outputs named prefix + key, as {key: tensor} (the caller's memory)."""
        return {name[len(prefix):]: value.clone() for name, value in self._outputs.items()
                if name.startswith(prefix)}

    def _call(self, command: str, arguments: list) -> list:
        """Send `command` with arguments[k] to worker k, wait for every answer and return them. A worker's
        error is raised here (after the others undid the call, for a call that changes the env); a dead
        worker or an interruption closes the env."""
        try:
            self._sync.parent_release()
            for connection, argument in zip(self._connections, arguments, strict=True):
                connection.send((command, _wire_all(argument)))
            replies = self._receive_all()
        except BaseException:
            self.close()
            raise
        failed = [rank for rank, (status, _) in enumerate(replies) if status == "error"]
        if failed and command in _MUTATING:
            # Every worker goes back to its state from before the call: those that failed too, in case
            # one failed after its env had changed (undoing an unchanged env changes nothing).
            undo = range(self.num_processes)
            try:
                for rank in undo:
                    self._connections[rank].send(("undo", None))
                self._gather([self._receive(rank) for rank in undo])
            except BaseException:
                self.close()
                raise
        results = self._gather(replies)
        self._sync.parent_acquire()
        return results

    def _receive_all(self) -> list:
        return [self._receive(rank) for rank in range(self.num_processes)]

    def _receive(self, rank: int):
        """Worker `rank`'s answer ("ok", result) or ("error", payload); RuntimeError (the env closed) if
        the worker exits without one."""
        connection, process = self._connections[rank], self._processes[rank]
        multiprocessing.connection.wait([connection, process.sentinel])
        try:
            return connection.recv()
        except (EOFError, OSError):
            process.join(1.0)
            self.close()
            raise RuntimeError(f"worker process {rank} (pid {process.pid}) exited with code {process.exitcode} "
                               f"without answering; the env is closed") from None

    def _gather(self, replies: list) -> list:
        for rank, (status, payload) in enumerate(replies):
            if status == "error":
                raise _rebuilt(rank, *payload)
        return [payload for _, payload in replies]


# ====================================================================== synchronisation
class _HostSync:
    """CPU outputs: the pipes' messages order the writes; nothing else to do."""

    def parent_release(self) -> None:
        pass

    def parent_acquire(self) -> None:
        pass

    def worker_events(self, rank: int):
        return None


class _CudaSync:
    """CUDA outputs: per worker, an interprocess event the parent records once the actions are written
    and the previous outputs copied out ("free"), and one the worker records once its outputs are
    written ("ready"); each side's stream waits on the other's, so the host never blocks."""

    def __init__(self, num_processes: int):
        self.free = [torch.cuda.Event(interprocess=True) for _ in range(num_processes)]
        self.ready = [torch.cuda.Event(interprocess=True) for _ in range(num_processes)]

    def parent_release(self) -> None:
        for event in self.free:
            event.record()

    def parent_acquire(self) -> None:
        stream = torch.cuda.current_stream()
        for event in self.ready:
            stream.wait_event(event)

    def worker_events(self, rank: int):
        return self.free[rank], self.ready[rank]


# ====================================================================== messages
def _wire(value):
    """A tensor as a numpy array for the pipe (a CPU tensor sent as it is would be moved into shared
    memory, the caller's tensor included); anything else as it is."""
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().numpy()
    return value


def _wire_all(argument):
    if isinstance(argument, tuple):
        return tuple(_wire(value) for value in argument)
    return _wire(argument)


def _send_error(connection, error: BaseException) -> None:
    """Send ("error", (type, message, traceback text)); a type the parent could not unpickle (a class
    local to a function, say) goes as RuntimeError naming it."""
    text = "".join(traceback.format_exception(error))
    try:
        payload = pickle.dumps((type(error), str(error), text))
    except Exception:
        payload = pickle.dumps((RuntimeError, f"{type(error).__qualname__}: {error}", text))
    connection.send(("error", pickle.loads(payload)))


def _rebuilt(rank: int, kind: type, message: str, text: str) -> BaseException:
    """The worker's exception as the parent raises it: the same type and message where the type can be
    built from a message, else a RuntimeError; chained from its traceback text."""
    try:
        error = kind(message)
    except Exception:
        error = RuntimeError(f"{kind.__name__}: {message}")
    error.__cause__ = WorkerTraceback(f"in worker process {rank}:\n{text}")
    return error


def _stop_workers(connections: list, processes: list) -> None:
    """Ask every worker to exit, join it (killing one that hangs) and close the pipes."""
    for connection in connections:
        try:
            connection.send(("close", None))
        except (OSError, ValueError):
            pass
    for process in processes:
        process.join(JOIN_TIMEOUT_S)
        if process.is_alive():
            process.kill()
            process.join()
    for connection in connections:
        connection.close()


# ====================================================================== the worker
def _serve(connection, rank: int, scenario, options: EnvOptions, params) -> None:
    """A worker's life: build its env, receive the shared buffers, then answer commands until "close"."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle: it closes the workers
    try:
        env = BatchedEnv(scenario, options, params)
    except BaseException as error:
        _send_error(connection, error)
        connection.close()
        return
    try:
        connection.send(("ok", _description(env)))
        command, argument = connection.recv()
        if command != "buffers":  # "close": the parent gave up (another worker failed to build)
            return
        outputs, actions, lo, hi, events = argument
        if env.device.type == "cuda" and env.device.index is not None:  # the events' and copies' device
            torch.cuda.set_device(env.device)
        if options.torch_threads is not None:  # the copies outside env calls too: N workers share the cores
            torch.set_num_threads(options.torch_threads)
        worker = _Worker(env, {name: value[lo:hi] for name, value in outputs.items()}, actions[lo:hi], events)
        connection.send(("ok", None))
        while True:
            command, argument = connection.recv()
            if command == "close":
                return
            try:
                result = worker.run(command, argument)
            except Exception as error:
                _send_error(connection, error)
            else:
                connection.send(("ok", result))
    except (EOFError, OSError):  # the parent went away
        return
    finally:
        env.close()
        connection.close()


def _description(env: BatchedEnv) -> dict:
    """What the parent copies from worker 0's env (its spec names this worker's worlds; the parent fixes it)."""
    names = ("name", "spec", "num_agents", "agent_names", "groups", "continuous", "num_actions", "action_dim",
             "action_meanings", "obs_keys", "info_keys", "state_dim", "max_steps", "dt", "readback", "resolution",
             "autoreset", "enforce_action_mask", "far")
    return {name: getattr(env, name) for name in names}


class _Worker:
    """One worker's env and its slices of the shared outputs and actions."""

    def __init__(self, env: BatchedEnv, outputs: dict, actions: torch.Tensor, events):
        self.env, self.outputs, self.actions = env, outputs, actions
        self.free, self.ready = events if events is not None else (None, None)
        self.before = None  # the state before the last call that changes the env (None: not started)

    def run(self, command: str, argument):
        if command == "undo":  # another worker refused the call this one made: back to the state before it
            if self.before is not None:
                self.env.set_state(self.before)
                self._write_state()
            return None
        if command in _MUTATING:
            self.before = self.env.get_state() if not self.env._needs_reset else None
        if self.free is not None:  # the parent's writes (actions) and reads (last outputs) come first
            torch.cuda.current_stream().wait_event(self.free)
        result = getattr(self, command)(argument)
        if command in _MUTATING:
            self._write_state()
        if self.ready is not None:
            self.ready.record()
        return result

    def reset(self, seed):
        self._write("obs/", self.env.reset(seed=seed))

    def reset_worlds(self, argument):
        mask, seed = argument
        self._write("obs/", self.env.reset_worlds(torch.from_numpy(mask), seed=seed))

    def reset_to_level(self, argument):
        mask, level_ids, seed = argument
        self._write("obs/", self.env.reset_to_level(torch.from_numpy(mask), torch.from_numpy(level_ids), seed=seed))

    def step(self, _):
        obs, reward, terminated, truncated, info = self.env.step(self.actions)
        self._write("obs/", obs)
        for name, value in (("reward", reward), ("terminated", terminated), ("truncated", truncated)):
            self.outputs[name].copy_(value)
        final_obs = info.pop("final_obs", None)
        if final_obs is not None:
            self._write("final_obs/", final_obs)
        if "info/final_level" in self.outputs:  # no world of this worker was reset: its levels stayed
            info.setdefault("final_level", info["level"])
        self._write("info/", info)

    def set_state(self, argument):
        part, devices = argument
        self.env.set_state({key: torch.from_numpy(value).to(devices.get(key, "cpu")) for key, value in part.items()})

    def get_state(self, _):
        state = self.env.get_state()
        return {key: _wire(value) for key, value in state.items()}, {key: str(value.device) for key, value in
                                                                      state.items()}

    def render_overview(self, resolution):
        return _wire(self.env.render_overview(resolution))

    def _write(self, prefix: str, values: dict) -> None:
        for key, value in values.items():
            self.outputs[prefix + key].copy_(value)

    def _write_state(self) -> None:
        self.outputs["state/alive"].copy_(self.env.alive)
        self.outputs["state/step_count"].copy_(self.env.step_count)
        self.outputs["state/episode_over"].copy_(self.env.episode_over())
        if "state/level_ids" in self.outputs:
            self.outputs["state/level_ids"].copy_(self.env._level_ids)
