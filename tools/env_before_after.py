"""`bench env` of two checkouts in one run: whole `python -m marl_render.bench env ... --json`
processes of the "before" and "after" checkouts take turns (the order alternating each round), so
both see the same machine; per (env, worlds) the median env-steps/s over the rounds and the ratio
after / before.

    python tools/env_before_after.py BEFORE_DIR AFTER_DIR --rounds 3 --out docs/bench/env_before_after.json \\
        -- --env all --worlds 16 64 256 --steps 30

Each checkout runs with PYTHONPATH set to itself, and a sitecustomize that points this venv's
editable install (setuptools' finder, which maps marl_render.envs and marl_render.glsl to folders
of the checkout it was installed from) at the checkout instead. Tasks that only one side has are
reported for that side alone.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

from marl_render.util.cpu import cpu_model_and_flags

# Run at start-up in each checkout's process: the editable finder's folders, moved to the checkout.
SITECUSTOMIZE = """import sys
for _module in list(sys.modules.values()):
    _mapping = getattr(_module, "MAPPING", None)
    if getattr(_module, "__name__", "").startswith("__editable__") and isinstance(_mapping, dict):
        for _name, _folder in _mapping.items():
            _mapping[_name] = _folder.replace({installed!r}, {checkout!r}, 1)
"""


def installed_root() -> str:
    """The checkout this venv's editable install points at (its marl_render folder's parent)."""
    for module in list(sys.modules.values()):
        mapping = getattr(module, "MAPPING", None)
        if getattr(module, "__name__", "").startswith("__editable__") and isinstance(mapping, dict):
            return os.path.dirname(mapping["marl_render"])
    raise RuntimeError("this venv has no editable install of marl_render to redirect")


def bench(checkout: str, bench_args: list[str]) -> list[dict]:
    checkout = os.path.abspath(checkout)
    with tempfile.TemporaryDirectory() as site:
        with open(os.path.join(site, "sitecustomize.py"), "w") as f:
            f.write(SITECUSTOMIZE.format(installed=installed_root(), checkout=checkout))
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([site, checkout])}
        done = subprocess.run([sys.executable, "-m", "marl_render.bench", "env", "--json", *bench_args],
                              cwd=checkout, env=env, capture_output=True, text=True)
    if done.returncode:
        raise RuntimeError(f"bench env in {checkout} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout)["results"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("before")
    parser.add_argument("after")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", default=None, help="write the JSON here too")
    argv = sys.argv[1:]
    split = argv.index("--") if "--" in argv else len(argv)
    args = parser.parse_args(argv[:split])
    bench_args = argv[split + 1:]  # bench env's own arguments
    rates = {"before": {}, "after": {}}
    for round_index in range(args.rounds):
        sides = ("before", "after") if round_index % 2 == 0 else ("after", "before")
        for side in sides:
            started = time.perf_counter()
            results = bench(getattr(args, side), bench_args)
            for row in results:
                rates[side].setdefault(f"{row['env']}@{row['worlds']}", []).append(row["env_steps_per_s"])
            print(f"round {round_index + 1}/{args.rounds} {side}: {len(results)} rows in "
                  f"{time.perf_counter() - started:.0f} s", file=sys.stderr, flush=True)
    rows = []
    for key in sorted(set(rates["before"]) | set(rates["after"])):
        env, worlds = key.rsplit("@", 1)
        before = statistics.median(rates["before"][key]) if key in rates["before"] else None
        after = statistics.median(rates["after"][key]) if key in rates["after"] else None
        rows.append({"env": env, "worlds": int(worlds), "before_env_steps_per_s": before,
                     "after_env_steps_per_s": after, "ratio": after / before if before and after else None,
                     "before_runs": rates["before"].get(key, []), "after_runs": rates["after"].get(key, [])})
    out = {"benchmark": "env_before_after", "cpu_model": cpu_model_and_flags()[0], "before": args.before,
           "after": args.after, "rounds": args.rounds, "bench_args": bench_args,
           "load_average_end": os.getloadavg(), "rows": rows}
    text = json.dumps(out, indent=1)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
