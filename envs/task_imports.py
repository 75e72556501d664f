"""Tasks a user registered, made known to a command line before it parses its task names.

    python -m marl_render.baselines --import my_tasks --env my_task --self-play
    python -m marl_render.baselines --env my_tasks:MyTask --self-play
    python -m marl_render.evaluate --import my_tasks --crossplay my_task --roster random out/my_task

``--import MODULE`` (repeatable) imports a module whose import calls ``register_env``; a task
option given as ``module:Class`` registers that Scenario subclass under the name "module:Class".
Both happen before the real parser runs, so its ``choices`` list the user's tasks. The current
folder is on ``sys.path`` as it is for ``python -m``.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from marl_render.envs import Scenario, list_envs, register_env
from marl_render.util.validation import describe


def add_import_option(parser: argparse.ArgumentParser) -> None:
    """The ``--import MODULE`` option, so that it shows in --help and the full parser accepts it."""
    parser.add_argument("--import", dest="imports", action="append", default=[], metavar="MODULE",
                        help="import MODULE first: a module that registers tasks with register_env (repeatable)")


def load_user_tasks(argv, prog: str, task_options: tuple = ("--env",)) -> None:
    """Import every ``--import`` module of `argv` and register every ``module:Class`` value of
    `task_options`; a module that does not import, or a ``module:Class`` that names no Scenario
    subclass, exits with status 2 and one line naming the option, as argparse does."""
    pre = argparse.ArgumentParser(prog=prog, add_help=False)
    add_import_option(pre)
    for option in task_options:  # every value an option is given (python -m marl_render.envs.evaluation --env a b)
        pre.add_argument(option, nargs="*", default=[])
    known, _ = pre.parse_known_args(sys.argv[1:] if argv is None else argv)
    if "" not in sys.path and "." not in sys.path:  # as python -m does: modules of the current folder import
        sys.path.insert(0, "")
    for module in known.imports:
        try:
            importlib.import_module(module)
        except Exception as error:  # any error of the user's module: name it, do not print a traceback
            pre.error(f"--import {module}: the module did not import ({type(error).__name__}: {error})")
    for option in task_options:
        for value in getattr(known, option.lstrip("-").replace("-", "_")):
            register_task_option(pre, option, value)


def register_task_option(pre: argparse.ArgumentParser, option: str, value: str) -> None:
    """Register `value` of `option` if it is a ``module:Class`` not registered yet."""
    if ":" not in value or value in list_envs():
        return
    if value.count(":") != 1 or not all(value.split(":")):
        pre.error(f"{option} must be a registered task or module:Class, got {value!r}")
    module, name = value.split(":")
    try:
        scenario = getattr(importlib.import_module(module), name)
    except Exception as error:
        pre.error(f"{option} {value}: could not import it ({type(error).__name__}: {error})")
    if not (isinstance(scenario, type) and issubclass(scenario, Scenario)):
        pre.error(f"{option} {value}: expected module:Class naming a Scenario subclass "
                  f"(marl_render.envs.Scenario), got {describe(scenario)}")
    register_env(value, scenario)
