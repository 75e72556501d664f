"""num_processes= on a GPU (envs/multiprocess.py): the workers write into slices of CUDA tensors the
parent owns (CUDA IPC), ordered by interprocess events. Marked `gpu`: skipped unless CUDA is present and
the GL driver is NVIDIA's (tests/conftest.py); the GPU kit runs them (tools/gpu_kit/check.sh)."""
import pytest
import torch

from marl_render.envs import make_env

pytestmark = pytest.mark.gpu

KWARGS = dict(num_worlds=5, resolution=16, seed=3, levels=100, depth=True, state_obs=True, device="cuda")
LEVELS = torch.tensor([7, 3, 99, 0, 42])


@pytest.mark.parametrize("readback", ["gpu", "host"])
def test_cuda_outputs_over_two_workers_equal_the_single_process_env_bit_for_bit(readback):
    multi = make_env("cartpole", num_processes=2, readback=readback, **KWARGS)
    single = make_env("cartpole", readback=readback, **KWARGS)
    try:
        everywhere = torch.ones(5, dtype=torch.bool)
        for env in (multi, single):
            env.reset(seed=0)
        got, want = multi.reset_to_level(everywhere, LEVELS), single.reset_to_level(everywhere, LEVELS)
        assert got["pixels"].device.type == "cuda"
        assert all(torch.equal(got[key], want[key]) for key in want)
        # Many steps back to back, no host sync in between: a missing event wait would let the parent
        # copy a slice before its worker wrote it, or a worker overwrite one the parent had not copied.
        results = []
        for step in range(12):
            actions = torch.tensor([[step % 2], [1], [0], [(step + 1) % 2], [step % 2]], device="cuda")
            results.append((multi.step(actions), single.step(actions)))
        for got_step, want_step in results:
            obs, reward = got_step[:2]
            assert obs["pixels"].device.type == "cuda" and reward.device.type == "cuda"
            assert all(torch.equal(obs[key], want_step[0][key]) for key in want_step[0])
            for got_value, want_value in zip(got_step[1:4], want_step[1:4], strict=True):
                assert torch.equal(got_value, want_value)
            assert all(torch.equal(got_step[4][key], want_step[4][key]) for key in want_step[4])
        state, reference = multi.get_state(), single.get_state()
        assert all(torch.equal(state[key], reference[key]) for key in reference if key != "rng")
    finally:
        multi.close()
        single.close()


def test_the_parent_returns_its_own_copies_on_the_device():
    with make_env("cartpole", num_processes=2, **KWARGS) as env:
        env.reset(seed=0)
        obs, reward, *_ = env.step(torch.zeros(5, 1, dtype=torch.int64, device="cuda"))
        kept = obs["pixels"].clone()
        env.step(torch.ones(5, 1, dtype=torch.int64, device="cuda"))
        assert torch.equal(obs["pixels"], kept)
        assert obs["pixels"].data_ptr() != env._outputs["obs/pixels"].data_ptr()
