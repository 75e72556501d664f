"""The package as users get it: public names between modules, metadata, the sdist, and the wheel
installed on its own (non-editable) outside the repository."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE_FOLDERS = ("marl_render", "envs", "shaders")  # what the wheel's marl_render is built from


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
