"""One layer per folder (docs/architecture.md): a module imports its own layer and the layers below,
never one above. Read from the source with ast, every import (lazy ones inside functions too);
an old path of a moved module (marl_render/aliases.py) counts as the module it names."""
import ast
from pathlib import Path

import pytest

from marl_render import aliases

ROOT = Path(__file__).resolve().parents[1]

# The layers, lowest first: (rank, name, the dotted prefixes of its modules). A module's layer is
# that of its longest matching prefix (the package root, "marl_render", matches only itself: a new
# module at the top of marl_render/ belongs in a layer's folder, or here); layers of one rank may
# import each other.
LAYERS = (
    (0, "util", ("marl_render.util", "marl_render.aliases")),
    (1, "assets", ("marl_render.assets",)),
    (2, "render", ("marl_render.render", "marl_render")),  # the package root re-exports the renderer's names
    (3, "envs", ("marl_render.envs",)),
    (4, "populations", ("marl_render.populations",)),
    (4, "front ends", ("marl_render.wrappers",)),
    (5, "tools", ("marl_render.baselines", "marl_render.bench")),
)

def package_modules() -> dict[str, Path]:
    """Dotted name -> file of every module of the package (envs/ is marl_render.envs)."""
    modules = {}
    for folder, package in ((ROOT / "marl_render", "marl_render"), (ROOT / "envs", "marl_render.envs")):
        for path in folder.rglob("*.py"):
            parts = list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            modules[".".join([package, *parts])] = path
    return modules


MODULES = package_modules()


def layer(module: str) -> tuple[int, str]:
    best = max(((len(prefix), rank, name) for rank, name, prefixes in LAYERS for prefix in prefixes
                if module == prefix or (prefix != "marl_render" and module.startswith(prefix + "."))), default=None)
    assert best is not None, f"{module} is in no layer: move it into a layer's folder or add it to LAYERS"
    return best[1], best[2]


def is_package(module: str) -> bool:
    return MODULES[module].name == "__init__.py"


def imported_names(module: str) -> list[str]:
    """The dotted names `module`'s imports spell (relative ones made absolute), as written."""
    package = module if is_package(module) else module.rpartition(".")[0]
    spelled = []
    for node in ast.walk(ast.parse(MODULES[module].read_text(), str(MODULES[module]))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{anchor}.{base}" if base else anchor
            # `from package import module` imports the module; `from module import name`, the module
            names = [f"{base}.{alias.name}" for alias in node.names
                     if aliases.resolve(f"{base}.{alias.name}") in MODULES] or [base]
        else:
            continue
        spelled.extend(names)
    return spelled


def imported_modules(module: str) -> set[str]:
    """The package's modules that `module` imports (real names: old paths resolved)."""
    found = set()
    for name in imported_names(module):
        real = aliases.resolve(name)
        while real not in MODULES and "." in real:  # `import marl_render.envs.spread.Spread`-like paths
            real = real.rpartition(".")[0]
        if real in MODULES:
            found.add(real)
    return found


def upward_imports() -> list[str]:
    found = []
    for module in sorted(MODULES):
        rank, _ = layer(module)
        for imported in sorted(imported_modules(module)):
            if layer(imported)[0] > rank:
                found.append(f"{module} -> {imported}")
    return found


def test_no_module_imports_a_higher_layer():
    upward = sorted(upward_imports())
    assert upward == [], "a lower layer imports a higher one (docs/architecture.md: where each change goes)"


def test_the_package_imports_its_modules_by_their_real_paths():
    """Old paths (marl_render/aliases.py) are for users' code, pickles and docs: the package's own
    imports name the modules where they live, so that reading an import tells where to look."""
    through_alias = sorted(f"{module} imports {name}" for module in MODULES for name in imported_names(module)
                           if aliases.resolve(name) != name)
    assert through_alias == []


def test_every_module_is_in_a_layer():
    layers = {module: layer(module)[1] for module in MODULES}  # raises for a module in none
    assert layers["marl_render"] == "render" and layers["marl_render.aliases"] == "util"
    assert layers["marl_render.render.renderer"] == "render" and layers["marl_render.envs.core"] == "envs"
    with pytest.raises(AssertionError, match="marl_render.new_module is in no layer"):
        layer("marl_render.new_module")


@pytest.mark.parametrize("source, expected", [
    ("from ..render import renderer", "marl_render.util.threads -> marl_render.render.renderer"),
    ("import marl_render.layout", "marl_render.util.threads -> marl_render.render.row_layouts"),  # an old path
    ("def lazy():\n    from marl_render.envs import make_env", "marl_render.util.threads -> marl_render.envs"),
    ("import marl_render", "marl_render.util.threads -> marl_render"),  # the root imports the renderer
])
def test_the_check_finds_an_upward_import(monkeypatch, tmp_path, source, expected):
    """The check itself: a util module given one import of a higher layer is caught."""
    path = tmp_path / "threads.py"
    path.write_text(MODULES["marl_render.util.threads"].read_text() + "\n" + source + "\n")
    monkeypatch.setitem(MODULES, "marl_render.util.threads", path)
    assert expected in upward_imports()
