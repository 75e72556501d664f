"""Fixtures shared by several test modules, and the `gpu` marker's skip."""
import functools
import sys

import pytest
import torch


@functools.cache
def gpu_unavailable() -> str | None:
    """Why the `gpu` tests cannot run here (None: CUDA is present and the GL driver is NVIDIA's)."""
    if not torch.cuda.is_available():
        return "needs CUDA (torch sees no CUDA device)"
    import marl_render as mr  # a GL context only where CUDA is there

    vendor = mr.backend.context_for_cuda(torch.cuda.current_device()).info().vendor
    return None if "NVIDIA" in vendor.upper() else f"needs NVIDIA's GL driver (the GL vendor is {vendor!r})"


def pytest_collection_modifyitems(config, items):
    gpu_items = [item for item in items if item.get_closest_marker("gpu") is not None]
    reason = gpu_unavailable() if gpu_items else None
    for item in gpu_items if reason else ():
        item.add_marker(pytest.mark.skip(reason=reason))


@pytest.fixture(scope="module", autouse=True)
def registered_tasks_restored():
    """A test module that registers a user's task (tests/selfplay_user_task.py registers beacon_duel
    when imported) leaves none behind: other modules count the registered tasks."""
    from marl_render.envs import registry  # the library only once a test module runs

    before = dict(registry._REGISTRY)
    yield
    if registry._REGISTRY != before:
        registry._REGISTRY.clear()
        registry._REGISTRY.update(before)
    sys.modules.pop("selfplay_user_task", None)


@pytest.fixture
def registries():
    """The bot and held-out scenario registries as they were, restored after the test (they are
    module-global: register_bot and register_heldout write into them; the tasks' own bots and
    scenarios are on their classes)."""
    from marl_render import bots, heldout  # the library only once a test asks for it

    registered_bots, registered_scenarios = dict(bots._REGISTERED), list(heldout._REGISTERED)
    yield
    bots._REGISTERED.clear()
    bots._REGISTERED.update(registered_bots)
    heldout._REGISTERED[:] = registered_scenarios


@pytest.fixture(scope="module")
def single_torch_thread():
    """Tiny tensors on a shared 2-core machine: one torch thread for the module's own ops."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture
def check_only_declared_terms(monkeypatch):
    """A checker: steps `env` and asserts that each physics term it declares ran once per
    step and that no other term ran at all (undeclared ones raise if called)."""
    from marl_render.envs import planar

    def check(env, steps=3):
        declared = env.physics_terms
        assert env.physics is None or env.physics.terms == declared
        calls = dict.fromkeys(planar.TERM_NAMES, 0)

        def counted(name, builder):
            def term(*args, **kwargs):
                calls[name] += 1
                return builder(*args, **kwargs)
            return term

        def forbidden(name):
            def term(*args, **kwargs):
                raise AssertionError(f"undeclared term {name!r} was computed")
            return term

        with monkeypatch.context() as patch:
            for name in planar.TERM_NAMES:
                wrapped = counted(name, planar.TERMS[name]) if name in declared else forbidden(name)
                patch.setitem(planar.TERMS, name, wrapped)
            env.reset(seed=0)
            generator = torch.Generator().manual_seed(0)
            for _ in range(steps):
                env.step(env.random_actions(generator))
        assert all(calls[name] == steps for name in declared), calls
        assert all(calls[name] == 0 for name in planar.TERM_NAMES - declared), calls

    return check


@pytest.fixture
def framebuffers_made(monkeypatch):
    """A list that records every framebuffer a BatchRenderer allocates while the test runs (a
    pass's tiles, or the shadow atlas): a call refused before any GL allocation leaves it empty.
    This is what "fails fast" means, checked without a clock."""
    from marl_render import renderer, shadows

    made = []
    make_pass, shadow_pass = renderer.BatchRenderer._make_pass, shadows.ShadowPass.__init__

    def counted_pass(self, views):
        made.append(f"pass of {len(views)} views")
        return make_pass(self, views)

    def counted_shadows(self, *args, **kwargs):
        made.append("shadow atlas")
        return shadow_pass(self, *args, **kwargs)

    monkeypatch.setattr(renderer.BatchRenderer, "_make_pass", counted_pass)
    monkeypatch.setattr(shadows.ShadowPass, "__init__", counted_shadows)
    return made
