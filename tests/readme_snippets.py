"""The ```python blocks of README.md and of the docs pages (docs/*.md), as a user copies them.

A block whose first line is `# side venv: .venv-NAME ...` needs a side venv (BenchMARL,
RLlib pin their own torchrl / gymnasium): test_readme.py leaves it to `make test-NAME`,
whose tests run it with `side_venv_snippets("NAME")`. A page whose blocks another test runs
(with its own fixtures) is listed in TESTED_ELSEWHERE; a block whose first line is
`# fragment: ...` is a piece of a larger program (it says what is missing) and is not run."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
SIDE_VENV = re.compile(r"# side venv: \.venv-(\w+)\b")
FRAGMENT = "# fragment: "
TESTED_ELSEWHERE = {  # page -> the test that runs its blocks
    "docs/authoring.md": "tests/test_authoring.py",
    "docs/training.md": "tests/test_baselines.py",
    "docs/populations.md": "tests/test_heldout.py",
    "docs/levels.md": "tests/test_levels.py",
}


def pages() -> list[Path]:
    """README.md, then every Markdown page of the site (docs/ and its folders), in a fixed order."""
    return [README] + sorted(DOCS.rglob("*.md"))


def snippets(path: Path = README) -> list[tuple[int, str, str | None]]:
    """(line of the opening fence, code, side venv name or None) for every ```python block of `path`."""
    found = []
    lines = path.read_text().splitlines()
    start = None
    for number, line in enumerate(lines, 1):
        if start is None and line.strip() == "```python":
            start = number
        elif start is not None and line.strip() == "```":
            code = "\n".join(lines[start:number - 1]) + "\n"
            marker = SIDE_VENV.match(code)
            found.append((start, code, marker.group(1) if marker else None))
            start = None
    assert start is None, f"{path.name}: the ```python block at line {start} is not closed"
    return found


def page_snippets() -> list[tuple[str, int, str, str | None]]:
    """(page relative to the repository, line, code, side venv or None) of every page's blocks but
    those of TESTED_ELSEWHERE and the fragments."""
    found = []
    for path in pages():
        page = str(path.relative_to(ROOT))
        if page not in TESTED_ELSEWHERE:
            found += [(page, line, code, venv) for line, code, venv in snippets(path) if not code.startswith(FRAGMENT)]
    return found


def side_venv_snippets(name: str) -> list[tuple[str, str]]:
    """("page line N", code) of the blocks that need the side venv `name`."""
    return [(f"{page} line {line}", code) for page, line, code, venv in page_snippets() if venv == name]


def run_snippet(code: str, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    """Runs `code` as a script in a fresh interpreter (this one's venv) in `cwd`."""
    script = cwd / "snippet.py"
    script.write_text(code)
    return subprocess.run([sys.executable, str(script)], cwd=cwd, capture_output=True, text=True, timeout=timeout)
