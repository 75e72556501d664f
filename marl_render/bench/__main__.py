"""Command line of the benchmarks; see `python -m marl_render.bench --help`."""
from __future__ import annotations

import argparse
import importlib
import json
import sys

# subcommand -> (module, one-line help). Modules are imported only when chosen.
SUBCOMMANDS = {
    "render": ("marl_render.bench.render", "batched renderer vs the plain Panda3D way (views/s, ratio)"),
    "env": ("marl_render.bench.env", "environment steps/s and agent-frames/s"),
    "floor": ("marl_render.bench.floor", "throughput as a fraction of a raw OpenGL floor"),
    "accuracy": ("marl_render.bench.accuracy", "error against time: resolution, AA, substeps, precision"),
    "effects": ("marl_render.bench.effects", "cost of each effect and the batching ablation"),
    "scale": ("marl_render.bench.scale", "scaling with views and resolution"),
    "soak": ("marl_render.bench.soak", "long run: memory over time, non-finite values"),
    "parallel": ("marl_render.bench.parallel", "one process against TorchRL ParallelEnv / collectors with 2 workers"),
    "peers": ("marl_render.bench.peers", "against Melting Pot, MPE and PyBatchRender in their own venvs (ratios)"),
}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m marl_render.bench", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, metavar="SUBCOMMAND")
    modules = {}
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as error:
            if error.name != module_name:
                raise
            continue  # not part of this build
        modules[name] = module
        command = sub.add_parser(name, help=help_text, description=module.__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
        command.add_argument("--json", action="store_true", help="print one JSON object on stdout")
        module.add_arguments(command)
    args = parser.parse_args(argv)
    result = modules[args.command].run(args)
    if args.json:
        print(json.dumps(result, indent=None, default=str))
    else:
        print(json.dumps(result, indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
