"""num_processes=: one env over several worker processes (envs/multiprocess.py).

Each worker process costs an interpreter start and the imports (seconds), so the tests share a
few small envs (5 worlds at 16x16 over 2 workers: an uneven split, 3 + 2)."""
import os

import pytest
import torch
from tensordict import TensorDict

from marl_render.envs import MultiProcessEnv, make_env
from marl_render.envs.multiprocess import WorkerTraceback, output_layout, worker_seed, world_bounds
from marl_render.envs.spec import ActionSpec, ArraySpec, EnvSpec
from marl_render.wrappers.torchrl import make_torchrl_env
from multiprocess_task import FailingCartPole

W = 5
KWARGS = dict(num_worlds=W, resolution=16, seed=3, levels=100, depth=True, state_obs=True)
LEVELS = torch.tensor([7, 3, 99, 0, 42])
ALL = torch.ones(W, dtype=torch.bool)


@pytest.fixture(scope="module")
def envs():
    """(the env over 2 worker processes, the same env in this process), both reset to LEVELS."""
    multi = make_env(FailingCartPole, num_processes=2, **KWARGS)
    single = make_env(FailingCartPole, **KWARGS)
    for env in (multi, single):
        env.reset(seed=0)
        env.reset_to_level(ALL, LEVELS)
    yield multi, single
    multi.close()
    single.close()


def assert_same(a, b):
    """Equal bit for bit: tensors, or dicts of them with the same keys."""
    if isinstance(a, dict):
        assert sorted(a) == sorted(b)
        for key in a:
            assert_same(a[key], b[key])
    else:
        assert a.dtype == b.dtype and a.shape == b.shape and a.device == b.device
        assert torch.equal(a, b)


def without_rng(state: dict) -> dict:
    return {key: value for key, value in state.items() if key != "rng"}


def actions_of(step: int) -> torch.Tensor:
    """Never all ones in a worker's worlds (FailingCartPole would refuse them)."""
    return torch.tensor([[step % 2], [1], [0], [(step + 1) % 2], [step % 2]])


def test_worlds_are_split_in_contiguous_slices_differing_by_at_most_one():
    assert world_bounds(5, 2) == [0, 3, 5]
    assert world_bounds(8, 4) == [0, 2, 4, 6, 8]
    assert world_bounds(7, 3) == [0, 3, 5, 7]
    assert world_bounds(3, 3) == [0, 1, 2, 3]


def test_worker_0_keeps_the_seed_and_the_others_get_distinct_ones():
    assert worker_seed(3, 0) == 3
    seeds = {worker_seed(3, rank) for rank in range(8)}
    assert len(seeds) == 8 and all(0 <= seed < 2 ** 63 for seed in seeds)
    assert worker_seed(3, 1) == worker_seed(3, 1) != worker_seed(4, 1)


@pytest.mark.parametrize("value, error, text", [
    (0, ValueError, "num_processes must be an int in [1, 4], got 0"),
    (-1, ValueError, "num_processes must be an int in [1, 4], got -1"),
    (5, ValueError, "num_processes must be an int in [1, 4], got 5"),
    (2.0, TypeError, "num_processes must be an int in [1, 4], got 2.0"),
    (True, TypeError, "num_processes must be an int in [1, 4], got True"),
])
def test_a_bad_num_processes_is_refused_before_any_worker_starts(value, error, text):
    before = _children()
    with pytest.raises(error) as caught:
        make_env("cartpole", num_worlds=4, num_processes=value)
    assert str(caught.value) == text
    assert _children() == before


def _parent_of(pid: str) -> str:
    """The "PPid:" line of process `pid` ("" if it is gone)."""
    try:
        with open(f"/proc/{pid}/status") as status:
            return next((line for line in status if line.startswith("PPid:")), "")
    except OSError:
        return ""


def _children() -> list:
    """Live or zombie child processes of this process, but multiprocessing's resource tracker (started
    with the first spawned process, it lives as long as this process)."""
    return sorted(pid for pid in os.listdir("/proc")
                  if pid.isdigit() and _parent_of(pid).split()[1:] == [str(os.getpid())]
                  and "resource_tracker" not in _command_line(pid))


def _command_line(pid: str) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as cmdline:
            return cmdline.read().decode(errors="replace")
    except OSError:
        return ""


def test_num_processes_is_refused_with_bots_and_with_a_given_context():
    with pytest.raises(ValueError, match="num_processes applies to the batched core"):
        make_env("tag", num_worlds=2, num_processes=2, heldout="tag/prey_vs_interceptors")
    with pytest.raises(ValueError, match="context must be None with num_processes .* got 'mine'"):
        make_env("cartpole", num_worlds=2, num_processes=2, context="mine")


@pytest.mark.parametrize("front_end", ["make_vec_env", "make_gym_env", "make_sb3_env", "make_parallel_env",
                                       "make_aec_env", "make_jax_env"])
def test_the_other_front_ends_refuse_num_processes_before_any_worker_starts(front_end):
    import marl_render.envs as envs

    before = _children()
    with pytest.raises(TypeError, match=r"does not accept 'num_processes': only marl_render.envs.make_env and "
                                        r"make_torchrl_env split the worlds over worker processes"):
        getattr(envs, front_end)("cartpole", num_processes=2)
    assert _children() == before


def test_a_cuda_device_without_cuda_is_refused_before_any_worker_starts():
    if torch.cuda.is_available():
        pytest.skip("CUDA is available here: tests/test_multiprocess_gpu.py covers device='cuda'")
    before = _children()
    with pytest.raises(ValueError, match="device 'cuda' was asked for but torch sees no CUDA device"):
        make_env("cartpole", num_worlds=2, num_processes=2, device="cuda")
    assert _children() == before


def test_the_output_layout_has_every_output_of_every_call():
    env_spec = EnvSpec(name="t", num_worlds=1, agent_names=("a", "b"), groups={"t": ["a", "b"]},
                       observations={"pixels": ArraySpec((4, 6, 3), torch.uint8, 0, 255)},
                       action=ActionSpec(continuous=False, num_actions=3), info={"score": torch.float32},
                       max_steps=10, dt=0.1)
    layout = output_layout(env_spec, 2, "same_step", has_levels=True)
    assert layout["obs/pixels"] == ((2, 4, 6, 3), torch.uint8)
    assert layout["final_obs/pixels"] == ((2, 4, 6, 3), torch.uint8)
    assert layout["reward"] == ((2,), torch.float32)
    assert layout["info/score"] == ((), torch.float32)
    assert {"info/final_level", "info/level", "info/autoreset_worlds", "state/level_ids"} <= set(layout)
    plain = output_layout(env_spec, 2, False, has_levels=False)
    assert not any(name.startswith("final_obs/") or "level" in name or "autoreset" in name for name in plain)


def test_frames_rewards_and_states_equal_the_single_process_env_bit_for_bit(envs):
    multi, single = envs
    assert isinstance(multi, MultiProcessEnv) and multi.bounds == [0, 3, 5]
    assert_same(multi.get_state()["qstate"], single.get_state()["qstate"])
    for step in range(4):
        got, want = multi.step(actions_of(step)), single.step(actions_of(step))
        for a, b in zip(got, want, strict=True):
            assert_same(a, b)
    assert_same(without_rng(multi.get_state()), without_rng(single.get_state()))
    assert multi.get_state()["rng"].shape == (2, single.get_state()["rng"].numel())
    assert_same(multi.alive, single.alive)
    assert_same(multi.step_count, single.step_count)
    assert_same(multi.level_ids, single.level_ids)


def test_the_outputs_are_the_callers_memory(envs):
    multi, _ = envs
    obs, reward, *_ = multi.step(actions_of(0))
    kept = obs["pixels"].clone(), reward.clone()
    multi.step(actions_of(1))
    assert torch.equal(obs["pixels"], kept[0]) and torch.equal(reward, kept[1])
    assert obs["pixels"].untyped_storage().data_ptr() != multi._outputs["obs/pixels"].untyped_storage().data_ptr()


def test_partial_resets_and_set_state_match_the_single_process_env(envs):
    multi, single = envs
    multi.set_state({**single.get_state(), "rng": multi.get_state()["rng"]})  # the same worlds
    mask = torch.tensor([False, True, False, True, False])  # one world in each worker
    chosen = torch.tensor([0, 11, 0, 12, 0])
    assert_same(multi.reset_to_level(mask, chosen), single.reset_to_level(mask, chosen))
    assert_same(without_rng(multi.get_state()), without_rng(single.get_state()))
    saved = multi.get_state()
    first = [multi.step(actions_of(step))[0] for step in range(2)]
    multi.set_state(saved)
    again = [multi.step(actions_of(step))[0] for step in range(2)]
    want = [single.step(actions_of(step))[0] for step in range(2)]
    for a, b, c in zip(first, again, want, strict=True):
        assert_same(a, b)
        assert_same(b, c)
    # reset_worlds draws from each worker's own generator: the reset world restarts, the others stay
    before = multi.get_state()
    obs = multi.reset_worlds(torch.tensor([True, False, False, False, False]))
    assert obs["pixels"].shape == (W, 1, 16, 16, 3) and obs["depth"].shape == (W, 1, 16, 16)
    after = multi.get_state()
    assert torch.equal(after["qstate"][1:], before["qstate"][1:])
    assert after["step_count"].tolist() == [0, *before["step_count"][1:].tolist()] and before["step_count"][0] > 0


def test_a_worker_error_is_raised_with_its_traceback_and_the_other_worker_is_undone(envs):
    multi, single = envs
    multi.set_state({**single.get_state(), "rng": multi.get_state()["rng"]})  # the same worlds
    before = multi.get_state()
    failing = torch.tensor([[0], [1], [0], [1], [1]])  # worker 1's worlds (3, 4) all 1: only it fails
    with pytest.raises(ValueError, match="refuses a batch of all-ones actions") as caught:
        multi.step(failing)
    cause = caught.value.__cause__
    assert isinstance(cause, WorkerTraceback)
    assert str(cause).startswith("in worker process 1:")
    assert "multiprocess_task.py" in str(cause) and "in step" in str(cause)
    assert_same(multi.get_state(), before)  # worker 0 stepped, then was undone
    assert_same(multi.step_count, before["step_count"])
    # still usable, and on the single env's trajectory
    for step in range(2):
        got, want = multi.step(actions_of(step)), single.step(actions_of(step))
        assert_same(got[0], want[0])
        assert_same(got[1], want[1])


def test_bad_input_is_refused_in_the_parent_and_changes_nothing(envs):
    multi, _ = envs
    before = multi.get_state()
    with pytest.raises(ValueError, match=r"actions must be an integer tensor of shape \[5, 1\]"):
        multi.step(torch.zeros(4, 1, dtype=torch.int64))
    with pytest.raises(ValueError, match=r"mask must be a bool tensor of shape \[5\]"):
        multi.reset_worlds(torch.ones(4, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"state\['rng'\] must be the workers' generator states"):
        multi.set_state({**before, "rng": before["rng"][0]})
    with pytest.raises(ValueError, match=r"state\['qstate'\] must have shape"):  # the worker's own check
        multi.set_state({**before, "qstate": before["qstate"][:, :2]})
    assert_same(multi.get_state(), before)


def test_a_build_error_in_the_workers_is_raised_and_leaves_no_process():
    before = _children()
    with pytest.raises(ValueError, match="num_agents must be an int in") as caught:
        make_env("cartpole", num_worlds=2, num_processes=1, num_agents=3)
    assert isinstance(caught.value.__cause__, WorkerTraceback)
    assert _children() == before


def test_torchrl_front_end_over_workers_equals_the_single_process_one_and_closes_cleanly():
    kwargs = dict(num_worlds=4, resolution=16, seed=1, levels=50, group_map="one_group")
    multi, single = make_torchrl_env("cartpole", num_processes=2, **kwargs), make_torchrl_env("cartpole", **kwargs)
    pids = multi.core.pids
    assert len(pids) == 2 and all(os.path.exists(f"/proc/{pid}") for pid in pids)
    levels = TensorDict({"level_ids": torch.tensor([5, 6, 7, 8])}, batch_size=[4])
    got, want = multi.reset(levels.clone()), single.reset(levels.clone())
    assert torch.equal(got["agents", "pixels"], want["agents", "pixels"])
    for step in range(3):
        action = torch.tensor([[step % 2], [1], [0], [1]])
        got = multi.step(got.set(("agents", "action"), action))["next"]
        want = single.step(want.set(("agents", "action"), action))["next"]
        for key in (("agents", "pixels"), ("agents", "reward"), ("agents", "done"), "done"):
            assert torch.equal(got[key], want[key]), key
    multi.close()
    single.close()
    assert all(not os.path.exists(f"/proc/{pid}") for pid in pids)  # joined: exited and reaped, no zombie
    with pytest.raises(RuntimeError, match="is closed"):
        multi.core.step(torch.zeros(4, 1, dtype=torch.int64))


def test_one_worker_is_the_single_process_env_on_the_default_path_with_autoreset_outputs():
    """num_processes=1: worker 0 keeps the seed, so even the default path's draws (no levels) are the
    single-process env's; same_step autoreset's final_obs and autoreset_worlds come through too."""
    kwargs = dict(num_worlds=2, resolution=8, seed=5, max_steps=2, autoreset="same_step")
    with make_env("cartpole", num_processes=1, **kwargs) as multi, make_env("cartpole", **kwargs) as single:
        assert_same(multi.reset(), single.reset())
        for step in range(3):
            actions = torch.tensor([[step % 2], [1]])
            got, want = multi.step(actions), single.step(actions)
            assert "final_obs" in got[4] and set(got[4]) == set(want[4])
            for a, b in zip(got, want, strict=True):
                assert_same(a, b)
        assert got[4]["autoreset_worlds"].tolist() == [False, False]  # steps 2, then 1 of the new episode
        assert_same(without_rng(multi.get_state()), without_rng(single.get_state()))
        assert torch.equal(multi.get_state()["rng"][0], single.get_state()["rng"])


def test_a_dead_worker_closes_the_env_with_a_clear_error_and_no_zombie():
    env = make_env("cartpole", num_worlds=2, num_processes=2, resolution=8)
    env.reset(seed=0)
    pids = env.pids
    os.kill(pids[1], 9)
    with pytest.raises(RuntimeError, match=r"worker process 1 \(pid \d+\) exited with code -9 without answering"):
        env.step(torch.zeros(2, 1, dtype=torch.int64))
    assert env.closed
    with pytest.raises(RuntimeError, match="is closed"):
        env.reset()
    assert all(not os.path.exists(f"/proc/{pid}") for pid in pids)
    env.close()  # twice: nothing


class _Logged:
    """A fake CUDA event / stream that logs what is done with it."""

    def __init__(self, name: str, log: list):
        self.name, self.log = name, log

    def record(self):
        self.log.append(f"record {self.name}")

    def wait_event(self, event):
        self.log.append(f"wait {event.name}")


class _FakeEnv:
    """Just enough of a BatchedEnv for a worker's step: it logs its step and returns fixed outputs."""

    def __init__(self, log: list):
        self.log, self.needs_reset = log, False
        self.alive, self.step_count = torch.ones(2, 1, dtype=torch.bool), torch.tensor([4, 5])

    def get_state(self):
        return {}

    def episode_over(self):
        return torch.zeros(2, dtype=torch.bool)

    def step(self, actions):
        self.log.append(f"step {actions.tolist()}")
        obs = {"pixels": torch.full((2, 1, 2, 2, 3), 7, dtype=torch.uint8)}
        info = {"step_count": self.step_count, "done_worlds": torch.zeros(2, dtype=torch.bool)}
        return obs, torch.ones(2, 1), torch.zeros(2, 1, dtype=torch.bool), torch.zeros(2, 1, dtype=torch.bool), info


def test_a_cuda_worker_waits_for_the_parents_event_before_it_writes_and_records_its_own_after(monkeypatch):
    """The CUDA path's ordering, with fakes (no GPU here): the worker's stream waits on "free" (the
    parent's actions written, its last copies done) before stepping and writing its slice, and records
    "ready" (which the parent's stream waits on) only once every output is written."""
    from marl_render.envs.multiprocess import _Worker

    log = []
    layout = {"obs/pixels": ((1, 2, 2, 3), torch.uint8), "reward": ((1,), torch.float32),
              "terminated": ((1,), torch.bool), "truncated": ((1,), torch.bool), "state/alive": ((1,), torch.bool),
              "state/step_count": ((), torch.int64), "state/episode_over": ((), torch.bool),
              "info/step_count": ((), torch.int64), "info/done_worlds": ((), torch.bool)}

    class Watched(torch.Tensor):  # logs every write into the worker's slice of an output
        def copy_(self, source, non_blocking=False):
            log.append("write")
            return super().copy_(source)

    outputs = {name: torch.zeros((2, *shape), dtype=dtype).as_subclass(Watched) for name, (shape, dtype)
               in layout.items()}
    monkeypatch.setattr(torch.cuda, "current_stream", lambda: _Logged("stream", log))
    worker = _Worker(_FakeEnv(log), outputs, torch.tensor([[1], [0]]), (_Logged("free", log), _Logged("ready", log)))
    worker.run("step", None)
    writes = len(layout)
    assert log == ["wait free", "step [[1], [0]]", *["write"] * writes, "record ready"]
    assert torch.equal(outputs["obs/pixels"], torch.full((2, 1, 2, 2, 3), 7, dtype=torch.uint8))
    assert outputs["state/step_count"].tolist() == [4, 5]
