"""Command line of the benchmarks; see `python -m marl_render.bench --help`.

The benchmarks need the `bench` extra; a subcommand whose packages are missing stays listed
and, when chosen, fails at once with one line naming the extra to install."""
from __future__ import annotations

import argparse
import importlib
import json
import sys

from marl_render.util.extras import MissingExtraError, needs_extra

# subcommand -> (module, one-line help). Each module is imported to list its options.
SUBCOMMANDS = {
    "render": ("marl_render.bench.render", "batched renderer vs the plain Panda3D way (views/s, ratio)"),
    "env": ("marl_render.bench.env", "environment steps/s and agent-frames/s"),
    "floor": ("marl_render.bench.floor", "throughput as a fraction of a raw OpenGL floor"),
    "accuracy": ("marl_render.bench.accuracy", "error against time: resolution, AA, substeps, precision"),
    "effects": ("marl_render.bench.effects", "cost of each effect and the batching ablation"),
    "scale": ("marl_render.bench.scale", "scaling with views and resolution"),
    "soak": ("marl_render.bench.soak", "long run: memory over time, non-finite values"),
    "parallel": ("marl_render.bench.parallel", "one process against TorchRL ParallelEnv / collectors with 2 workers"),
    "profile": ("marl_render.bench.profile", "the GL stage split into vertex and fragment work per task"),
    "accuracy-geometry": ("marl_render.bench.accuracy_geometry", "impostors' pixel and depth error against meshes"),
    "peers": ("marl_render.bench.peers", "against Melting Pot, MPE and PyBatchRender in their own venvs (ratios)"),
}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m marl_render.bench", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, metavar="SUBCOMMAND")
    modules, missing = {}, {}
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        try:
            with needs_extra("bench", f"python -m marl_render.bench {name}"):
                module = importlib.import_module(module_name)
        except MissingExtraError as error:
            # Listed, and refused in one line when chosen, before any work.
            missing[name] = str(error)
            sub.add_parser(name, help=f"{help_text} [not installed: needs the '{error.extra}' extra]", add_help=False)
            continue
        except ModuleNotFoundError as error:
            if error.name != module_name:
                raise
            continue  # not part of this build
        modules[name] = module
        command = sub.add_parser(name, help=help_text, description=module.__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
        command.add_argument("--json", action="store_true", help="print one JSON object on stdout")
        module.add_arguments(command)
    args, unknown = parser.parse_known_args(argv)
    if args.command in missing:
        print(f"error: {missing[args.command]}", file=sys.stderr)
        return 2
    if unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    module = modules[args.command]
    try:  # options that need another extra (bench env --api jax) are refused before any work too
        getattr(module, "check_extras", lambda args: None)(args)
    except MissingExtraError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    result = module.run(args)
    if args.json:
        print(json.dumps(result, indent=None, default=str))
    else:
        print(json.dumps(result, indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
