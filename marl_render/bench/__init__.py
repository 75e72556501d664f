"""Benchmarks: `python -m marl_render.bench SUBCOMMAND ... [--json]`.

Each subcommand lives in its own module exposing `add_arguments(parser)` and
`run(args) -> dict`. Speed is measured here, never asserted in tests.
"""
