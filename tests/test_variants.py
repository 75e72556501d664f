"""docs/variants.md runs as written: a built-in task's variant by keyword and by a registered subclass
(the task it registers leaves with the module: conftest restores the registry)."""
import pathlib
import re

DOC = pathlib.Path(__file__).resolve().parents[1] / "docs" / "variants.md"


def test_the_variants_page_runs_as_written(capsys):
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)
    assert len(blocks) == 1
    exec(compile(blocks[0], str(DOC), "exec"), {"__name__": "variants_page"})
    lines = capsys.readouterr().out.splitlines()
    assert lines == ["['action_mask', 'inventory', 'pixels'] (4, 8, 2)", "True (4, 4)"]
