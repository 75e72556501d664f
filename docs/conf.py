"""Sphinx configuration of the marl-render site: `make docs` builds it offline into out/docs.

The pages are the Markdown files of docs/ (MyST); the API reference is autodoc of the public
names. No intersphinx: the build never touches the network.
"""
import marl_render

project = "marl-render"
author = "The marl-render developers"
copyright = "the marl-render developers, MIT licence"  # noqa: A001 (Sphinx's name)
release = version = marl_render.__version__

extensions = ["myst_parser", "sphinx_design", "sphinx.ext.autodoc", "sphinx.ext.napoleon", "sphinx_copybutton"]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
# Tables the benchmarks write without a title are shown inside performance.md ({include}); learning_notes.md
# is part of accuracy/learning.md, which learning_accuracy writes with it; generalisation/example.md is
# part of generalisation.md, whose report() copies it in.
exclude_patterns = ["_build", "**/train.log", "bench/floor*.md", "effects/effects.md", "scale/scale.md",
                    "accuracy/learning_notes.md", "generalisation/example.md", "bench/profile*/*.md",
                    "bench/accuracy_geometry*/*.md", "bench/peers_impostors/*.md", "bench/peers_perf2/*.md",
                    "bench/peers_quiet*/*.md", "bench/floor*/*.md"]
suppress_warnings = ["myst.header"]  # generated notes (baselines/notes.md) start at a lower heading level

myst_enable_extensions = ["colon_fence", "attrs_inline"]
myst_heading_anchors = 3  # `[spread](#spread)`: links to headings, as on GitHub

autodoc_member_order = "bysource"
autodoc_inherit_docstrings = False  # the libraries' own docstrings (gymnasium, torchrl) are not Sphinx-clean
autodoc_typehints = "description"
# No default "members": on Sphinx 9 it overrode each automodule's own :members: list (api.md), and
# every function of a module (main, write, HelpFormatter) was listed; the lists say what is public.
autodoc_default_options = {"undoc-members": False, "show-inheritance": True}
napoleon_google_docstring = True
napoleon_numpy_docstring = False

html_theme = "furo"
html_title = f"marl-render {release}"
copybutton_prompt_text = r"\$ |>>> "
copybutton_prompt_is_regexp = True

# Nitpicky (-n): every cross-reference must resolve, except to other projects' classes (no intersphinx:
# the build is offline) and to internal classes that the public API returns but does not export.
nitpicky = True
nitpick_ignore_regex = [
    ("py:class", r"(torch|numpy|jax|jaxlib|argparse|abc|gymnasium|spaces|pettingzoo|torchrl|tensordict"
                 r"|stable_baselines3)(\..*)?"),
    ("py:class", r"marl_render\.(render\.backend\.(GLInfo|Settings)|render\.scene\.(StaticGroup|InstanceGroup)"
                 r"|render\.frame_reads\.FrameReads"  # BatchRenderer's base class: its reads
                 r"|envs\.planar\.(Obstacles|BodyState)|envs\.levels\.Draws|baselines\.(ppo\.MAPPO|policy\.GreedyPolicy))"),
    ("py:class", r"Actor"),  # marl_render.baselines.networks.Actor, held by ActorPolicy
    ("py:class", r"marl_render\.envs\.atomic\.AllOrNothing"),  # the base of BatchedEnv and FocalEnv (envs/atomic.py)
]
