"""Optional extras: the core needs none of them, and every feature whose extra is missing fails
at once (before any work) with one line that names the extra to install.

A missing package is simulated in a child process by a sitecustomize that puts None in
sys.modules for it, which makes every import of it fail as if it were not installed."""
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from marl_render.extras import EXTRAS, MissingExtraError, needs_extra, require

ROOT = Path(__file__).resolve().parents[1]
EVERY_OPTIONAL_MODULE = sorted({module for modules in EXTRAS.values() for module in modules})

BLOCKER = """\
import os, sys
for name in filter(None, os.environ.get("MARL_RENDER_TEST_MISSING", "").split(",")):
    sys.modules[name] = None  # 'import name' now fails with ModuleNotFoundError, as if not installed
"""


def message(feature: str, module: str, extra: str) -> str:
    return f"{feature} needs {module}, which is not installed: pip install 'marl-render[{extra}]'"


def run_without(missing, code: str, tmp_path: Path, **env) -> dict:
    """Runs `code` (which prints one JSON object last) with the modules `missing` uninstalled."""
    (tmp_path / "blocker").mkdir(exist_ok=True)
    (tmp_path / "blocker" / "sitecustomize.py").write_text(BLOCKER)
    environment = {**env, "PYTHONPATH": str(tmp_path / "blocker"), "MARL_RENDER_TEST_MISSING": ",".join(missing)}
    done = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=300,
                          cwd=tmp_path, env={**_inherited(), **environment})
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def _inherited() -> dict:
    import os

    return {key: value for key, value in os.environ.items() if key not in ("PYTHONPATH", "DISPLAY")}


# ---------------------------------------------------------------------- needs_extra, require
def test_a_missing_module_of_the_extra_is_one_line_naming_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "tabulate", None)
    with pytest.raises(MissingExtraError) as caught:
        with needs_extra("bench", "the table"):
            import tabulate  # noqa: F401
    assert str(caught.value) == message("the table", "tabulate", "bench")
    assert isinstance(caught.value, ModuleNotFoundError) and caught.value.name == "tabulate"
    assert caught.value.extra == "bench" and caught.value.__cause__ is None


def test_other_import_errors_pass_through_unchanged(monkeypatch):
    monkeypatch.setitem(sys.modules, "jax", None)
    with pytest.raises(ModuleNotFoundError) as caught:
        with needs_extra("bench", "the table"):  # jax is not a module of the bench extra
            import jax  # noqa: F401
    assert not isinstance(caught.value, MissingExtraError)
    with pytest.raises(ImportError, match="^broken inside$"):
        with needs_extra("jax", "make_jax_env"):
            raise ImportError("broken inside")  # an installed package that fails to import is not "missing"
    with pytest.raises(ValueError, match=r"extra must be one of \['bench', .*\], got 'plot'"):
        with needs_extra("plot", "a figure"):
            pass


def test_require_checks_without_importing(monkeypatch):
    monkeypatch.setitem(sys.modules, "gltf", None)
    with pytest.raises(MissingExtraError, match=r"^a glTF skin needs gltf, which is not installed: pip install "
                                                r"'marl-render\[gltf\]'$"):
        require("gltf", "a glTF skin", "gltf")
    require("bench", "the table", "tabulate")  # installed: nothing happens
    with pytest.raises(ValueError, match=r"module must be one of extra 'sb3''s modules \['stable_baselines3'\], "
                                         r"got 'sb3'"):
        require("sb3", "make_sb3_env", "sb3")


# ---------------------------------------------------------------------- no extra installed
LIBRARY_WITHOUT_EXTRAS = """
    import contextlib, io, json, warnings
    import torch
    import marl_render as mr
    from marl_render.envs import list_envs, make_env, make_parallel_env, make_torchrl_env, make_vec_env
    from marl_render.wrappers import window

    core = {}
    env = make_env("spread", num_worlds=2, resolution=8)
    env.reset(seed=0)
    core["core"] = list(env.step(env.random_actions())[0]["pixels"].shape)
    env.close()
    parallel = make_parallel_env("cartpole", resolution=8)
    observations, _ = parallel.reset(seed=0)
    core["parallel"] = list(observations["agent_0"].shape)
    parallel.close()
    trl = make_torchrl_env("cartpole", num_worlds=2, resolution=8)
    core["torchrl"] = list(trl.rollout(2)["agents", "pixels"].shape)
    trl.close()
    vec = make_vec_env("cartpole", num_worlds=2, resolution=8)
    core["vec"] = list(vec.reset(seed=0)[0].shape)
    vec.close()

    def refusal(call):
        try:
            call()
        except ImportError as error:
            return [type(error).__name__, str(error)]
        return None

    import marl_render.envs as envs
    features = {
        "jax": refusal(lambda: envs.make_jax_env),
        "sb3": refusal(lambda: envs.make_sb3_env),
        "gltf": refusal(lambda: mr.load_skinned_model("walker.glb")),
        "human": window.window_unavailable(),
    }

    from marl_render.bench.__main__ import SUBCOMMANDS, main
    bench = {}
    for name in SUBCOMMANDS:
        stderr = io.StringIO()
        with contextlib.redirect_stderr(stderr):
            status = main([name, "--json"])
        bench[name] = [status, stderr.getvalue()]
    print(json.dumps({"core": core, "features": features, "bench": bench}))
"""


def test_the_core_runs_without_any_extra_and_each_feature_names_its_extra(tmp_path):
    result = run_without(EVERY_OPTIONAL_MODULE, LIBRARY_WITHOUT_EXTRAS, tmp_path, DISPLAY=":0")
    assert result["core"] == {"core": [2, 3, 8, 8, 3], "parallel": [8, 8, 3], "torchrl": [2, 2, 1, 8, 8, 3],
                              "vec": [2, 8, 8, 3]}
    features = result["features"]
    assert features["jax"] == ["MissingExtraError", message("make_jax_env", "jax", "jax")]
    assert features["sb3"] == ["MissingExtraError", message("make_sb3_env", "stable_baselines3", "sb3")]
    assert features["gltf"] == ["MissingExtraError", message("load_skinned_model of a glTF file", "gltf", "gltf")]
    assert features["human"] == "matplotlib (3.9 or newer) is not installed: pip install 'marl-render[human]'"
    for name, (status, stderr) in result["bench"].items():
        first_missing = {"accuracy": "tqdm", "effects": "tabulate", "scale": "tabulate"}.get(name, "psutil")
        command = f"python -m marl_render.bench {name}"
        assert (status, stderr) == (2, f"error: {message(command, first_missing, 'bench')}\n"), name


BENCH_ENV_FRONT_ENDS = """
    import contextlib, io, json
    from marl_render.bench.__main__ import main
    replies = {}
    for api in ("jax", "sb3"):
        stderr = io.StringIO()
        with contextlib.redirect_stderr(stderr):
            replies[api] = [main(["env", "--api", "core", api, "--worlds", "2", "--json"]), stderr.getvalue()]
    print(json.dumps(replies))
"""


def test_bench_env_refuses_a_front_end_whose_extra_is_missing_before_measuring(tmp_path):
    replies = run_without(["jax", "stable_baselines3"], BENCH_ENV_FRONT_ENDS, tmp_path)
    assert replies == {"jax": [2, f"error: {message('bench env --api jax', 'jax', 'jax')}\n"],
                       "sb3": [2, f"error: {message('bench env --api sb3', 'stable_baselines3', 'sb3')}\n"]}


EXAMPLES_WITHOUT_EXTRAS = """
    import contextlib, io, json, os, runpy, sys
    replies = {}
    for script in ("record_video.py", "train_mappo.py", "ppo_cartpole_pixels.py", "jax_policy_gradient.py"):
        sys.argv = [script, "--out", os.path.join("out", script)]
        stderr = io.StringIO()
        try:
            with contextlib.redirect_stderr(stderr):
                runpy.run_path(os.path.join(EXAMPLES, script), run_name="__main__")
            replies[script] = "ran"
        except SystemExit as stop:
            replies[script] = [str(stop.code), stderr.getvalue(), os.path.exists("out")]
    print(json.dumps(replies))
"""


def test_examples_stop_before_any_work_when_their_extra_is_missing(tmp_path):
    code = f"EXAMPLES = {str(ROOT / 'examples')!r}\n" + textwrap.dedent(EXAMPLES_WITHOUT_EXTRAS)
    replies = run_without(EVERY_OPTIONAL_MODULE, code, tmp_path)
    expected = {"record_video.py": ("imageio", "video"), "train_mappo.py": ("matplotlib", "plots"),
                "ppo_cartpole_pixels.py": ("matplotlib", "plots"), "jax_policy_gradient.py": ("jax", "jax")}
    for script, (module, extra) in expected.items():
        # SystemExit's message is printed by the interpreter as the one line on stderr (exit status 1)
        assert replies[script] == [f"error: {message(f'examples/{script}', module, extra)}", "", False], script
