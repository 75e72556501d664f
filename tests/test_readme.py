"""Every ```python block of README.md and of the docs pages runs as written (in a fresh namespace,
in one child process, from a scratch directory; readme_snippets.py says which blocks
other tests run instead). Blocks that train get smaller budgets through BUDGETS, exact
substitutions that must match; blocks marked `# side venv: .venv-NAME` run in `make test-NAME`
instead (tests/test_benchmarl.py, tests/test_rllib.py)."""
import json
import os
import subprocess
import sys

import pytest

from readme_snippets import FRAGMENT, README, ROOT, SIDE_VENV, TESTED_ELSEWHERE, page_snippets, pages, snippets

SIDE_VENVS = {"benchmarl", "rllib"}  # the side venvs whose tests run their blocks
BUDGETS = {  # text in a block -> the same with a budget that runs in seconds
    "n_steps=128, batch_size=256, device=\"cpu\").learn(100_000)":
        "n_steps=8, batch_size=256, device=\"cpu\").learn(256)",
    '"--updates", "20",': '"--updates", "1",',  # docs/evaluate.md's run, to have a folder to load
}

# Runs each block given on stdin (a JSON list of [name, code]) in a fresh namespace; prints a JSON
# list of None (ran) or the error with its traceback, one per block.
DRIVER = """
import json, sys, traceback
results = []
for name, code in json.loads(sys.stdin.read()):
    try:
        exec(compile(code, name, "exec"), {"__name__": "__main__"})
        results.append(None)
    except BaseException:
        results.append(traceback.format_exc())
print(json.dumps(results))
"""

MAIN_BLOCKS = [(page, line, code) for page, line, code, venv in page_snippets() if venv is None]


def test_the_readme_has_blocks_and_every_side_venv_block_is_run_by_its_make_target():
    assert len([block for block in MAIN_BLOCKS if block[0] == "README.md"]) >= 1
    assert len(MAIN_BLOCKS) >= 12
    side = [venv for _, _, _, venv in page_snippets() if venv is not None]
    assert sorted(side) == sorted(SIDE_VENVS), side  # one block each
    for path in pages():  # a misspelt marker would run the block in the main venv
        for line, code, _ in snippets(path):
            assert "side venv" not in code or SIDE_VENV.match(code), f"{path.name} line {line}: unrecognised marker"
    assert {str(page) for page in TESTED_ELSEWHERE} <= {str(p.relative_to(ROOT)) for p in pages()}
    fragments = [(path.name, line) for path in pages() for line, code, _ in snippets(path) if code.startswith(FRAGMENT)]
    assert fragments == [("distributed.md", fragments[0][1])], fragments  # the one sketch of a cluster job
    assert README in pages()


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """Every block in page order in one child process (one interpreter start for all)."""
    used = [text for text in BUDGETS if any(text in code for _, _, code in MAIN_BLOCKS)]
    assert used == list(BUDGETS), f"the pages no longer contain {set(BUDGETS) - set(used)}: update BUDGETS"
    blocks = []
    for page, line, code in MAIN_BLOCKS:
        for text, small in BUDGETS.items():
            code = code.replace(text, small)
        blocks.append((f"{page} block at line {line}", code))
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    done = subprocess.run([sys.executable, "-c", DRIVER], input=json.dumps(blocks), env=env, capture_output=True,
                          cwd=tmp_path_factory.mktemp("pages"), text=True, timeout=400)
    assert done.returncode == 0, done.stderr[-3000:]
    return dict(zip((name for name, _ in blocks), json.loads(done.stdout.strip().splitlines()[-1]), strict=True))


@pytest.mark.parametrize("index", range(len(MAIN_BLOCKS)), ids=[f"{page}:{line}" for page, line, _ in MAIN_BLOCKS])
def test_block_runs_as_written(index, results):
    page, line, code = MAIN_BLOCKS[index]
    name = f"{page} block at line {line}"
    assert results[name] is None, f"{name}:\n{code}\n{results[name]}"
