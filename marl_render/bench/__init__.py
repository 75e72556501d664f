"""Benchmarks: `python -m marl_render.bench SUBCOMMAND ... [--json]`.

Each subcommand lives in its own module exposing `add_arguments(parser)` and
`run(args) -> dict` (and, when an option needs another extra, `check_extras(args)`). Speed is
measured here, never asserted in tests. Modules that are not subcommands: common.py (timing,
memory, the arena scene, report files), figures.py (matplotlib, for the benchmarks that draw),
naive.py (the plain Panda3D renderer the batched one is measured against), floor_gl.py (the
independent raw-GL floor of `floor`) and accuracy_report.py (the recommendations, tables and
plot of `accuracy`).
"""
