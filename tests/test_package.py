"""The package as users get it: public names between modules, the built sdist and wheel, and the
wheel installed on its own (not editable) in a throwaway environment, used from outside the
repository.

The sdist is the whole source tree (MANIFEST.in says why): it must hold exactly the files of the
repository, and its tests run from it once it is installed as a clone is (editable). The builds
run offline with the installed setuptools (`python -m build --no-isolation`); the throwaway
environments reuse the installed dependencies through a .pth file, so only marl-render itself is
installed into them."""
import ast
import email.parser
import importlib.metadata
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import textwrap
import zipfile
from pathlib import Path
from types import SimpleNamespace

import pytest
from packaging.requirements import Requirement

from isolated_install import RED_BOX_PICTURE, throwaway_venv
from marl_render.envs import env_class, list_envs
from marl_render.extras import EXTRAS

ROOT = Path(__file__).resolve().parents[1]
PACKAGE_FOLDERS = ("marl_render", "envs", "shaders")  # what the wheel's marl_render is built from
GENERATED = {"PKG-INFO", "setup.cfg"}  # files setuptools adds to an sdist (besides the egg-info folder)
LOCAL_ONLY = ("__pycache__", "build", "dist", "out")  # folders never part of the source tree, nor hidden ones but .ci


def private_imports(folder: Path) -> list[str]:
    """Every `from module import _name` in the package's modules: what one module needs from
    another must be public there."""
    found = []
    for path in sorted(folder.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom):
                found += [f"{path.relative_to(ROOT)}:{node.lineno} imports {node.module}.{alias.name}"
                          for alias in node.names if alias.name.startswith("_") and not alias.name.startswith("__")]
    return found


def test_no_module_imports_a_private_name_of_another():
    found = [line for folder in PACKAGE_FOLDERS for line in private_imports(ROOT / folder)]
    assert found == []


def source_version() -> str:
    """marl_render.__version__ as written in marl_render/__init__.py, the one place it is set."""
    for node in ast.parse((ROOT / "marl_render" / "__init__.py").read_text()).body:
        if isinstance(node, ast.Assign) and [target.id for target in node.targets] == ["__version__"]:
            return node.value.value
    raise AssertionError("marl_render/__init__.py does not set __version__")


def source_files() -> set[str]:
    """The files of the source tree: git's (tracked, and new ones it does not ignore) in a
    checkout, else (an unpacked sdist) every file but generated and local ones."""
    if (ROOT / ".git").exists():
        listed = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                                capture_output=True, text=True, check=True).stdout.splitlines()
        return {name for name in listed if (ROOT / name).is_file()}
    files = set()
    for folder, subfolders, names in os.walk(ROOT):
        subfolders[:] = [s for s in subfolders if s not in LOCAL_ONLY and not s.endswith(".egg-info")
                         and (s == ".ci" or not s.startswith("."))]
        files |= {str((Path(folder) / name).relative_to(ROOT)) for name in names}
    return files - GENERATED


def test_the_version_citation_and_changelog_agree():
    """One version, set in marl_render/__init__.py: the citation cites it and the changelog has its
    entry below the Unreleased one (CITATION.cff is checked against its schema with cffconvert by
    `make dist`)."""
    version = source_version()
    citation = dict(re.findall(r"^([a-z-]+): \"?([^\"\n]*)\"?$", (ROOT / "CITATION.cff").read_text(), flags=re.M))
    assert citation["cff-version"] == "1.2.0" and citation["license"] == "MIT"
    assert citation["version"] == version and citation["type"] == "software"
    headings = re.findall(r"^## \[([^\]]+)\]", (ROOT / "CHANGELOG.md").read_text(), flags=re.M)
    assert headings[:2] == ["Unreleased", version]


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """The sdist and the wheel `python -m build` makes from a copy of the source tree (as from a
    fresh clone: setuptools would also pack whatever an old marl_render.egg-info/SOURCES.txt here
    lists), the wheel from the unpacked sdist; and the build's log."""
    source, out = tmp_path_factory.mktemp("source"), tmp_path_factory.mktemp("dist")
    for name in source_files():
        (source / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, source / name)
    done = subprocess.run([sys.executable, "-m", "build", "--no-isolation", "--outdir", str(out), str(source)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    (sdist,), (wheel,) = out.glob("*.tar.gz"), out.glob("*.whl")
    return SimpleNamespace(sdist=sdist, wheel=wheel, log=done.stdout + done.stderr)


def test_the_build_gives_no_deprecation_warning(built):
    # setuptools warned that a TOML-table `license` is deprecated (it is an SPDX expression now)
    assert "deprecat" not in built.log.lower() and "!!" not in built.log, built.log
    assert built.sdist.name == f"marl_render-{source_version()}.tar.gz"
    assert built.wheel.name == f"marl_render-{source_version()}-py3-none-any.whl"


def test_the_wheel_holds_the_package_its_license_and_metadata(built):
    with zipfile.ZipFile(built.wheel) as wheel:
        names = set(wheel.namelist())
        info = f"marl_render-{source_version()}.dist-info"
        metadata = email.parser.Parser().parsestr(wheel.read(f"{info}/METADATA").decode())
        license_text = wheel.read(f"{info}/licenses/LICENSE").decode()
    assert metadata["Name"] == "marl-render" and metadata["Version"] == source_version()
    assert metadata["License-Expression"] == "MIT" and metadata.get_all("License-File") == ["LICENSE"]
    assert metadata["License"] is None and not any("License ::" in c for c in metadata.get_all("Classifier") or [])
    assert license_text == (ROOT / "LICENSE").read_text() and license_text.startswith("MIT License")
    package = ROOT / "marl_render"
    expected = {f"marl_render/{path.relative_to(package)}" for path in package.rglob("*.py")}
    expected |= {f"marl_render/envs/{path.name}" for path in (ROOT / "envs").glob("*.py")}
    expected |= {f"marl_render/glsl/{path.name}" for path in (ROOT / "shaders").iterdir() if path.is_file()}
    assert {name for name in names if not name.startswith(info)} == expected


def test_the_extras_table_lists_the_modules_of_the_wheels_extras(built):
    """marl_render.extras.EXTRAS names, for each extra the wheel declares, the modules that the
    extra's distributions provide: no more, no fewer (its one-line errors name the right extra)."""
    with zipfile.ZipFile(built.wheel) as wheel:
        text = wheel.read(f"marl_render-{source_version()}.dist-info/METADATA").decode()
    metadata = email.parser.Parser().parsestr(text)
    extras = set(metadata.get_all("Provides-Extra")) - {"test"}
    assert set(EXTRAS) == extras
    requirements = [Requirement(line) for line in metadata.get_all("Requires-Dist")]
    providers = importlib.metadata.packages_distributions()  # top-level module -> distributions (installed)
    canonical = lambda name: name.lower().replace("_", "-")  # noqa: E731
    for extra in extras:
        listed = {canonical(r.name) for r in requirements if r.marker and r.marker.evaluate({"extra": extra})}
        provided = {canonical(dist) for module in EXTRAS[extra] for dist in providers.get(module, [])}
        assert provided == listed, f"extra {extra!r}: its modules {EXTRAS[extra]} come from {provided}, not {listed}"


def test_the_sdist_is_the_source_tree(built):
    with tarfile.open(built.sdist) as sdist:
        prefix = f"marl_render-{source_version()}/"
        members = {m.name.removeprefix(prefix) for m in sdist.getmembers() if m.isfile()}
    generated = {name for name in members if name in GENERATED or name.startswith("marl_render.egg-info/")}
    models = {name for name in source_files() if name.startswith("docs/") and name.endswith("/actor.pt")}
    assert not {name for name in members if name.endswith("actor.pt")}, "the published actors stay out of the sdist"
    source = source_files() - models  # MANIFEST.in leaves the published runs' actors out
    assert sorted(source - members) == [], "left out of the sdist: add them to MANIFEST.in"
    assert sorted(members - generated - source) == [], "in the sdist but not in the source tree: prune them"


@pytest.fixture(scope="module")
def installed(built, tmp_path_factory):
    """The python of a throwaway venv into which the wheel is installed (not editable); the
    dependencies come from this environment's site-packages through a .pth file."""
    venv = throwaway_venv(tmp_path_factory.mktemp("venv"))
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-index",
                    "--disable-pip-version-check", "--target", str(venv.site), str(built.wheel)],
                   check=True, capture_output=True, timeout=300)
    return venv


EVERY_TASK_FROM_THE_WHEEL = """
    import importlib.metadata, json, sys
    import torch
    import marl_render as mr
    from marl_render.envs import list_envs, make_env

    tasks = {}
    for name in list_envs():
        env = make_env(name, num_worlds=2, resolution=8, seed=0)
        env.reset(seed=0)
        observation, reward, terminated, truncated, info = env.step(env.random_actions())
        pixels = observation["pixels"]
        tasks[name] = [list(pixels.shape), str(pixels.dtype), list(reward.shape), float(pixels.float().std())]
        env.close()

    {picture}
    print(json.dumps({"tasks": tasks, "centre": rgb[8, 8].tolist(), "corner": rgb[0, 0].tolist(),
                      "files": [mr.__file__, mr.envs.__file__, sys.executable],
                      "version": [mr.__version__, importlib.metadata.version("marl-render")]}))
"""


def test_the_wheel_installed_alone_makes_every_task_and_renders_from_outside_the_repository(installed, tmp_path):
    code = textwrap.dedent(EVERY_TASK_FROM_THE_WHEEL).replace("{picture}", RED_BOX_PICTURE)
    done = subprocess.run([installed.python, "-I", "-c", code], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    package_file, envs_file, python = result["files"]
    assert Path(package_file).is_relative_to(installed.site) and Path(envs_file).is_relative_to(installed.site)
    assert Path(python).parent == installed.python.parent
    assert result["version"] == [source_version(), source_version()]
    assert sorted(result["tasks"]) == list_envs()
    for name, (shape, dtype, reward_shape, spread) in result["tasks"].items():
        low, high = env_class(name).agent_range
        assert shape[0] == 2 and low <= shape[1] <= high and shape[2:] == [8, 8, 3], name
        assert dtype == "torch.uint8" and reward_shape == shape[:2], name
        assert spread > 0, f"{name}: every pixel has one colour"
    assert result["centre"] == [255, 0, 0] and result["corner"] == [0, 0, 255]


def test_the_sdists_tests_run_from_it(built, tmp_path):
    """As from a clone: the unpacked sdist installed editable (what `make test` does there), then
    tests that read its conftest.py, docs and sources. (Run from the source tree, an installed wheel
    would be shadowed by the tree's marl_render/ folder, which lacks envs/ and the shaders: the
    layout maps them in at install time.)"""
    with tarfile.open(built.sdist) as sdist:
        sdist.extractall(tmp_path, filter="data")
    unpacked = tmp_path / f"marl_render-{source_version()}"
    venv = throwaway_venv(tmp_path / "venv")
    subprocess.run([venv.python, "-m", "pip", "install", "--quiet", "--no-deps", "--no-index", "--no-build-isolation",
                    "--disable-pip-version-check", "--editable", str(unpacked)],
                   check=True, capture_output=True, timeout=300)
    where = subprocess.run([venv.python, "-c", "import marl_render.envs as e; print(e.__file__)"], cwd=tmp_path,
                           capture_output=True, text=True, check=True).stdout.strip()
    assert Path(where) == unpacked / "envs" / "__init__.py"
    done = subprocess.run([venv.python, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           "tests/test_authoring.py::test_tutorial_usage_block_runs_as_written",
                           "tests/test_package.py::test_no_module_imports_a_private_name_of_another",
                           "-W", "ignore::DeprecationWarning", "--override-ini", "addopts="],
                          cwd=unpacked, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "2 passed" in done.stdout
