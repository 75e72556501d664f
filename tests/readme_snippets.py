"""The ```python blocks of README.md, as a user copies them.

A block whose first line is `# side venv: .venv-NAME ...` needs a side venv (BenchMARL,
RLlib pin their own torchrl / gymnasium): test_readme.py leaves it to `make test-NAME`,
whose tests run it with `side_venv_snippets("NAME")`."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"
SIDE_VENV = re.compile(r"# side venv: \.venv-(\w+)\b")


def snippets() -> list[tuple[int, str, str | None]]:
    """(line of the opening fence, code, side venv name or None) for every ```python block."""
    found = []
    lines = README.read_text().splitlines()
    start = None
    for number, line in enumerate(lines, 1):
        if start is None and line.strip() == "```python":
            start = number
        elif start is not None and line.strip() == "```":
            code = "\n".join(lines[start:number - 1]) + "\n"
            marker = SIDE_VENV.match(code)
            found.append((start, code, marker.group(1) if marker else None))
            start = None
    assert start is None, f"README.md: the ```python block at line {start} is not closed"
    return found


def side_venv_snippets(name: str) -> list[tuple[int, str]]:
    return [(line, code) for line, code, venv in snippets() if venv == name]


def run_snippet(code: str, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    """Runs `code` as a script in a fresh interpreter (this one's venv) in `cwd`."""
    script = cwd / "snippet.py"
    script.write_text(code)
    return subprocess.run([sys.executable, str(script)], cwd=cwd, capture_output=True, text=True, timeout=timeout)
