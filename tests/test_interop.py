"""Reads through the GL pixel-pack buffer, and the CUDA-OpenGL interop's control flow with fake
CUDA runtimes (marl_render/readback.py, marl_render/interop.py). The real interop: test_interop_gpu.py."""
import ctypes
import os
import subprocess
import sys
import warnings

import pytest
import torch

import marl_render as mr
from marl_render import backend, interop
from marl_render import renderer as renderer_module
from marl_render.readback import gl_functions

BACKGROUND = (0.2, 0.4, 0.6)


def scene(effects=("lighting",), worlds=3, agents=2, resolution=(12, 20)):
    result = mr.Scene(num_worlds=worlds, agents_per_world=agents, resolution=resolution, effects=effects,
                      background=BACKGROUND)
    result.add_static("floor", "plane", position=[0, 0, 0], scale=[20, 20, 1], color=[0.3, 0.6, 0.3])
    result.add_group("boxes", "box", capacity=2)
    return result


def render(the_scene, **options):
    """The frame of `the_scene` with boxes in view of every camera, and the renderer's pass count."""
    W, A = the_scene.num_worlds, the_scene.agents_per_world
    with mr.BatchRenderer(the_scene, **options) as renderer:
        generator = torch.Generator().manual_seed(3)
        renderer.set_cameras(position=torch.tensor([0, 0, 1.0]).repeat(W, A, 1) + 0.2 * torch.rand(W, A, 3,
                                                                                                generator=generator),
                             look_at=torch.tensor([0, 3, 0.3]).repeat(W, A, 1))
        renderer.update("boxes", position=torch.tensor([[-0.6, 3, 0.5], [0.7, 4, 0.5]]).repeat(W, 1, 1)
                        + torch.rand(W, 2, 3, generator=generator) * 0.5,
                        color=torch.rand(W, 2, 3, generator=generator), active=torch.ones(W, 2, dtype=torch.bool))
        frame = renderer.render()
        return frame, renderer.layout.num_passes, dict(renderer.last_timings)


def assert_same_frames(a: mr.Frame, b: mr.Frame):
    for name in ("rgb", "depth", "segmentation"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.dtype == y.dtype and x.shape == y.shape and x.device == y.device, name
            assert torch.equal(x, y), f"{name} differs"


MODES = [  # (effects, renderer options): every byte layout the reads produce
    (("lighting",), {}),
    (("lighting",), {"color": "gray"}),
    (("lighting",), {"channels_first": True}),
    (("lighting",), {"color": "gray", "channels_first": True}),
    (("lighting", "depth", "segmentation"), {}),
    (("lighting", "depth", "segmentation"), {"supersample": 2, "channels_first": True}),
    (("lighting",), {"supersample": 2, "color": "gray"}),
]


@pytest.mark.parametrize("effects, options", MODES)
@pytest.mark.parametrize("split", [False, True])
def test_pack_buffer_reads_are_the_direct_reads_bit_for_bit(effects, options, split):
    the_scene = scene(effects)
    k = options.get("supersample", 1)
    layout = {"max_framebuffer_size": 12 * k * 2} if split else {}  # two 12-row tiles a pass: three passes
    direct, passes, _ = render(the_scene, readback="host", **options, **layout)
    packed, _, timings = render(the_scene, readback="pbo", **options, **layout)
    assert passes == (3 if split else 1)
    assert set(timings) == {"pack", "cull", "draw", "read", "copy"}
    assert_same_frames(direct, packed)
    assert (direct.rgb != direct.rgb[0, 0, 0, 0, 0]).any(), "the frame shows more than the background"


def test_unknown_readback_is_refused_before_any_gl_work(framebuffers_made):
    for value in ("zero_copy", 3, None):
        with pytest.raises(ValueError, match=r"readback must be one of \['auto', 'gpu', 'host', 'pbo', 'copy'\], got"):
            mr.BatchRenderer(scene(), readback=value)
    with pytest.raises(ValueError, match=r"readback='gpu' copies frames device to device and needs a CUDA device, "
                                         r"got device='cpu'"):
        mr.BatchRenderer(scene(), readback="gpu")
    with pytest.raises(TypeError, match=r"device must be a str or torch.device"):
        mr.BatchRenderer(scene(), device=0)
    assert framebuffers_made == []


def test_env_takes_readback_and_refuses_a_bad_one():
    from marl_render.envs import make_env

    with pytest.raises(ValueError, match=r"readback must be one of \['auto', 'gpu', 'host', 'pbo', 'copy'\], "
                                         r"got 'fast'"):
        make_env("cartpole", num_worlds=1, resolution=8, readback="fast")
    frames = []
    for readback in ("auto", "pbo"):
        env = make_env("cartpole", num_worlds=2, resolution=8, readback=readback, seed=1)
        try:
            assert env.readback == readback and env.renderer.readback == readback
            frames.append(env.reset(seed=1)["pixels"])
        finally:
            env.close()
    assert torch.equal(frames[0], frames[1])


# ---------------------------------------------------------------------------------------------- fakes

class RecordingBackend(interop.Backend):
    """A CUDA runtime that records the calls and copies host memory (the device pointers are host ones)."""

    def __init__(self, devices=(0,), memory: bytes = bytes(range(64))):
        self.devices, self.calls = list(devices), []
        self.memory = ctypes.create_string_buffer(memory, len(memory))
        self.registered: set = set()

    def gl_devices(self):
        self.calls.append(("gl_devices",))
        return self.devices

    def register(self, buffer):
        self.calls.append(("register", buffer))
        self.registered.add(buffer)
        return ("resource", buffer)

    def unregister(self, resource):
        self.calls.append(("unregister", resource[1]))
        self.registered.discard(resource[1])

    def map(self, resource, stream):
        self.calls.append(("map", resource[1], stream))

    def pointer(self, resource):
        return ctypes.addressof(self.memory), len(self.memory)

    def copy(self, destination, source, size, stream):
        self.calls.append(("copy", source - ctypes.addressof(self.memory), size))
        ctypes.memmove(destination, source, size)

    def unmap(self, resource, stream):
        self.calls.append(("unmap", resource[1], stream))


class GLMappingBackend(RecordingBackend):
    """The interop's path on llvmpipe: the pack buffer mapped for reading by the GL stands in for
    CUDA's mapping (the renderer calls it with its GL context current)."""

    GL_MAP_READ_BIT, GL_BUFFER_SIZE = 0x0001, 0x8764

    def __init__(self):
        super().__init__()
        egl = ctypes.CDLL("libEGL.so.1")
        egl.eglGetProcAddress.restype, egl.eglGetProcAddress.argtypes = ctypes.c_void_p, [ctypes.c_char_p]
        function = ctypes.CFUNCTYPE
        self.map_range = function(ctypes.c_void_p, ctypes.c_uint, ctypes.c_ssize_t, ctypes.c_ssize_t, ctypes.c_uint)(
            egl.eglGetProcAddress(b"glMapNamedBufferRange"))
        self.unmap_buffer = function(ctypes.c_ubyte, ctypes.c_uint)(egl.eglGetProcAddress(b"glUnmapNamedBuffer"))
        self.parameter = function(None, ctypes.c_uint, ctypes.c_uint, ctypes.POINTER(ctypes.c_int))(
            egl.eglGetProcAddress(b"glGetNamedBufferParameteriv"))
        self.mapped = None

    def map(self, resource, stream):
        super().map(resource, stream)
        size = ctypes.c_int()
        self.parameter(resource[1], self.GL_BUFFER_SIZE, ctypes.byref(size))
        self.mapped = (self.map_range(resource[1], 0, size.value, self.GL_MAP_READ_BIT), size.value)
        assert self.mapped[0], f"glMapNamedBufferRange failed: GL error 0x{gl_functions()['glGetError']():04x}"

    def pointer(self, resource):
        return self.mapped

    def copy(self, destination, source, size, stream):
        self.calls.append(("copy", source - self.mapped[0], size))
        ctypes.memmove(destination, source, size)

    def unmap(self, resource, stream):
        super().unmap(resource, stream)
        assert self.unmap_buffer(resource[1])
        self.mapped = None


@pytest.fixture
def fake_interop(monkeypatch):
    """Renderers made with readback="gpu" (device cpu) copy through a GLMappingBackend: [backends made]."""
    made = []

    def open_interop(readback, device, load=None):
        made.append(GLMappingBackend())
        return interop.PackBufferInterop(made[-1], torch.device("cpu"))

    monkeypatch.setattr(renderer_module.interop, "open_interop", open_interop)
    monkeypatch.setattr(renderer_module.interop, "check_device", lambda readback, device: None)
    return made


@pytest.mark.parametrize("effects, options", [MODES[0], MODES[3], MODES[5]])
def test_interop_path_gives_the_host_frames_bit_for_bit(fake_interop, effects, options):
    the_scene = scene(effects)
    host, _, _ = render(the_scene, readback="host", **options, max_framebuffer_size=48)
    through_interop, passes, timings = render(the_scene, readback="gpu", **options, max_framebuffer_size=48)
    assert passes > 1
    assert_same_frames(host, through_interop)
    backend_calls = fake_interop[0].calls
    kinds = [call[0] for call in backend_calls]
    # One register, then per frame: map, one copy per output, unmap; unregister at close.
    outputs = 1 + 2 * ("depth" in effects)
    assert kinds == ["register", "map", *["copy"] * outputs, "unmap", "unregister"]
    assert timings["copy"] >= 0 and timings["read"] > 0


def test_interop_registers_once_and_again_when_the_buffer_changes():
    fake = RecordingBackend()
    pipe = interop.PackBufferInterop(fake, torch.device("cpu"))
    out = torch.zeros(8, dtype=torch.uint8)
    pipe.copy(7, [(4, out)])
    pipe.copy(7, [(4, out), (16, out[:4])])
    assert out.tolist() == [16, 17, 18, 19, 8, 9, 10, 11]
    assert [c[0] for c in fake.calls] == ["register", "map", "copy", "unmap", "map", "copy", "copy", "unmap"]
    pipe.copy(9, [(0, out)])  # a new GL buffer: the old registration goes, the new one comes
    assert [c for c in fake.calls if c[0] in ("register", "unregister")] == [
        ("register", 7), ("unregister", 7), ("register", 9)]
    with pytest.raises(ValueError, match=r"cannot copy 8 bytes at offset 60 of a 64-byte mapped buffer"):
        pipe.copy(9, [(60, out)])
    assert fake.calls[-1] == ("unmap", 9, 0), "unmapped after a failed copy too"
    pipe.close()
    pipe.close()
    assert fake.registered == set() and [c for c in fake.calls if c[0] == "unregister"] == [
        ("unregister", 7), ("unregister", 9)]


def test_closing_the_renderer_or_its_context_unregisters_before_the_buffer_goes(fake_interop):
    deleted = []
    with mr.GLContext() as context:
        renderer = mr.BatchRenderer(scene(), readback="gpu", context=context)
        renderer.render()
        fake = fake_interop[-1]
        pack = renderer._pack
        delete = pack.delete
        pack.delete = lambda: (deleted.append(set(fake.registered)), delete())
        assert fake.registered == {pack.name}
    # the context's close closed the renderer: unregistered first, then the GL buffer deleted
    assert renderer._closed and fake.registered == set() and deleted == [set()]
    assert [c[0] for c in fake.calls][-1] == "unregister"


def test_auto_falls_back_with_one_warning_and_gpu_raises_when_gl_has_no_cuda_device(monkeypatch):
    monkeypatch.setattr(interop, "_warned", set())
    fake = RecordingBackend(devices=[])
    cuda = torch.device("cuda", 0)
    with pytest.warns(RuntimeWarning, match=r"readback='auto': CUDA-OpenGL interop is unavailable \(the GL context is "
                                            r"on no CUDA device .*frames are read through the host"):
        assert interop.open_interop("auto", cuda, load=lambda: fake) is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # one warning per reason and process: the second is silent
        assert interop.open_interop("auto", cuda, load=lambda: fake) is None
    with pytest.raises(interop.InteropUnavailable, match=r"readback='gpu' cannot use CUDA-OpenGL interop: the GL "
                                                         r"context is on no CUDA device"):
        interop.open_interop("gpu", cuda, load=lambda: fake)

    def no_runtime():
        raise interop.InteropUnavailable("torch has no usable CUDA device")

    with pytest.raises(interop.InteropUnavailable, match="torch has no usable CUDA device"):
        interop.open_interop("gpu", cuda, load=no_runtime)
    assert fake.registered == set()


def test_a_gl_context_on_another_cuda_device_is_an_error_naming_both():
    fake = RecordingBackend(devices=[1])
    for readback in ("auto", "gpu"):
        with pytest.raises(ValueError, match=r"the GL context renders on CUDA device\(s\) \[1\] but device='cuda:0' "
                                             r"is CUDA device 0"):
            interop.open_interop(readback, torch.device("cuda", 0), load=lambda: fake)
    chosen = interop.open_interop("gpu", torch.device("cuda", 1), load=lambda: fake)
    assert isinstance(chosen, interop.PackBufferInterop) and chosen.device == torch.device("cuda", 1)
    assert fake.registered == set(), "registered only at the first frame"


def test_host_and_cpu_devices_never_load_a_cuda_runtime():
    def load():
        raise AssertionError("loaded")

    assert interop.open_interop("host", torch.device("cuda", 0), load=load) is None
    assert interop.open_interop("auto", torch.device("cpu"), load=load) is None


def test_importing_marl_render_loads_no_cuda_runtime():
    # torch itself may map a libcudart (a CUDA build links one): marl-render must add none, nor cuda-bindings.
    code = ("import sys, torch\n"
            "def cudart():\n"
            "    return sorted(l.split()[-1] for l in open('/proc/self/maps') if 'libcudart' in l)\n"
            "def bindings():\n"
            "    return sorted(name for name in sys.modules if name == 'cuda' or name.startswith('cuda.'))\n"
            "before = cudart(), bindings()\n"
            "import marl_render, marl_render.envs, marl_render.interop\n"
            "assert (cudart(), bindings()) == before, (before, cudart(), bindings())\n"
            "assert not torch.cuda.is_initialized()\n"
            "print('ok')\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stderr


# ---------------------------------------------------------------------------------------------- EGL device

def test_egl_device_is_the_one_whose_cuda_device_matches():
    assert backend.egl_device_for_cuda(0, [None, 1, 0]) == 2
    assert backend.egl_device_for_cuda(1, [None, 1, 0]) == 1
    assert backend.egl_device_for_cuda(3, [None, 1, 0]) is None
    assert backend.egl_device_for_cuda(0, []) is None


def test_first_context_for_a_cuda_device_opens_its_egl_device(monkeypatch):
    asked = []
    monkeypatch.setattr(backend, "context", lambda index=None: asked.append(index) or "context")
    monkeypatch.setattr(backend, "_process_device", [])
    monkeypatch.delenv("MARL_RENDER_EGL_DEVICE", raising=False)
    devices = [None, 1, 0]
    assert backend.context_for_cuda(0, query=lambda: devices) == "context"
    backend.context_for_cuda(1, query=lambda: devices)
    backend.context_for_cuda(5, query=lambda: devices)  # none matches: the default display
    backend.context_for_cuda(None, query=lambda: pytest.fail("queried for a CPU device"))
    assert asked == [2, 1, None, None]
    monkeypatch.setenv("MARL_RENDER_EGL_DEVICE", "1")  # the user's choice stands
    backend.context_for_cuda(0, query=lambda: pytest.fail("queried despite MARL_RENDER_EGL_DEVICE"))
    monkeypatch.delenv("MARL_RENDER_EGL_DEVICE")
    monkeypatch.setattr(backend, "_process_device", [None])  # the process's device is fixed already
    backend.context_for_cuda(0, query=lambda: pytest.fail("queried after the first context"))
    assert asked == [2, 1, None, None, None, None]


def test_egl_cuda_devices_name_cuda_devices_of_nvidia_ones_only():
    devices = backend.egl_cuda_devices()
    assert isinstance(devices, list) and all(device is None or device >= 0 for device in devices)
    if "Mesa" in backend.context().info().vendor:  # llvmpipe's EGL devices are no CUDA devices
        assert all(device is None for device in devices)


def test_marl_render_prc_adds_panda3d_configuration_that_wins():
    code = ("import marl_render as mr\n"
            "from panda3d.core import ConfigVariableBool, ConfigVariableString\n"
            "mr.backend.context()\n"
            "print(ConfigVariableBool('gl-debug').get_value(),\n"
            "      ConfigVariableString('notify-level-glgsg').get_value())\n")
    environment = {**os.environ, "MARL_RENDER_PRC": r"gl-debug #t\nnotify-level-glgsg warning"}
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=environment)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["True", "warning"]  # marl-render's own says notify-level-glgsg error
