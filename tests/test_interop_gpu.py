"""The real CUDA-OpenGL interop (marl_render/interop.py) on a GPU: frames copied device to device
equal the host reads bit for bit in every mode. Marked `gpu`: skipped unless CUDA is present and the GL
driver is NVIDIA's (tests/conftest.py); the GPU kit runs them (tools/gpu_kit/check.sh)."""
import pytest
import torch

import marl_render as mr
from marl_render import backend, interop
from test_interop import MODES, assert_same_frames, render, scene

pytestmark = pytest.mark.gpu


@pytest.mark.parametrize("effects, options", MODES)
@pytest.mark.parametrize("split", [False, True])
def test_interop_frames_are_the_host_frames_bit_for_bit(effects, options, split):
    the_scene = scene(effects, worlds=5)
    k = options.get("supersample", 1)
    layout = {"max_framebuffer_size": 12 * k * 2} if split else {}
    host, _, _ = render(the_scene, readback="host", device="cuda", **options, **layout)
    gpu, _, timings = render(the_scene, readback="gpu", device="cuda", **options, **layout)
    assert gpu.rgb.device.type == "cuda" and host.rgb.device.type == "cuda"
    assert set(timings) == {"pack", "cull", "draw", "read", "copy"}
    assert_same_frames(host, gpu)


def test_the_gl_context_is_on_the_cuda_device_of_the_frames():
    with mr.BatchRenderer(scene(), readback="gpu", device="cuda") as renderer:
        assert isinstance(renderer._interop, interop.PackBufferInterop)
        with renderer._context.current():
            devices = interop.load_cuda_runtime().gl_devices()
        assert torch.cuda.current_device() in devices
        index = backend.egl_device_for_cuda(torch.cuda.current_device(), backend.egl_cuda_devices())
        assert index is not None, "no EGL device reports the CUDA device (EGL_CUDA_DEVICE_NV)"


def test_env_pixels_are_born_on_the_device_and_equal_the_host_ones():
    from marl_render.envs import make_env

    pixels = []
    for readback in ("host", "gpu"):
        with make_env("spread", num_worlds=8, resolution=16, seed=0, device="cuda", readback=readback,
                      depth=True) as env:
            obs = env.reset(seed=0)
            step = env.step(env.random_actions(torch.Generator().manual_seed(0)).to("cuda"))[0]
            pixels.append((obs["pixels"], step["pixels"], step["depth"]))
            assert obs["pixels"].device.type == "cuda"
    for host, gpu in zip(*pixels, strict=True):
        assert torch.equal(host, gpu)
