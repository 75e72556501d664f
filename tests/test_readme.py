"""Every ```python block of README.md runs as written (in a fresh namespace, in one child
process, from a scratch directory). Blocks that train get smaller budgets through BUDGETS,
exact substitutions that must match; blocks marked `# side venv: .venv-NAME` run in
`make test-NAME` instead (tests/test_benchmarl.py, tests/test_rllib.py)."""
import json
import os
import subprocess
import sys

import pytest

from readme_snippets import SIDE_VENV, snippets

SIDE_VENVS = {"benchmarl", "rllib"}  # the side venvs whose tests run their blocks
BUDGETS = {  # text in a block -> the same with a budget that runs in seconds
    "n_steps=128, batch_size=256, device=\"cpu\").learn(100_000)":
        "n_steps=8, batch_size=256, device=\"cpu\").learn(256)",
}

# Runs each block given on stdin (a JSON list of code) in a fresh namespace; prints a JSON
# list of None (ran) or the error with its traceback, one per block.
DRIVER = """
import json, sys, traceback
results = []
for code in json.loads(sys.stdin.read()):
    try:
        exec(compile(code, "README.md block", "exec"), {"__name__": "__main__"})
        results.append(None)
    except BaseException:
        results.append(traceback.format_exc())
print(json.dumps(results))
"""

MAIN_BLOCKS = [(line, code) for line, code, venv in snippets() if venv is None]


def test_the_readme_has_blocks_and_every_side_venv_block_is_run_by_its_make_target():
    assert len(MAIN_BLOCKS) >= 8
    side = [venv for _, _, venv in snippets() if venv is not None]
    assert set(side) == SIDE_VENVS, side
    for line, code, _ in snippets():  # a misspelt marker would run the block in the main venv
        assert "side venv" not in code or SIDE_VENV.match(code), f"README.md line {line}: unrecognised marker"


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    blocks = []
    for _, code in MAIN_BLOCKS:
        for text, small in BUDGETS.items():
            code = code.replace(text, small)
        blocks.append(code)
    used = [text for text in BUDGETS if any(text in code for _, code in MAIN_BLOCKS)]
    assert used == list(BUDGETS), f"README.md no longer contains {set(BUDGETS) - set(used)}: update BUDGETS"
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    done = subprocess.run([sys.executable, "-c", DRIVER], input=json.dumps(blocks), env=env, capture_output=True,
                          cwd=tmp_path_factory.mktemp("readme"), text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("index", range(len(MAIN_BLOCKS)), ids=[f"line{line}" for line, _ in MAIN_BLOCKS])
def test_block_runs_as_written(index, results):
    line, code = MAIN_BLOCKS[index]
    assert results[index] is None, f"README.md block at line {line}:\n{code}\n{results[index]}"
