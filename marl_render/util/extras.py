"""The optional extras of pyproject.toml and the one-line error of a feature whose extra is missing.

A feature that needs an optional package imports it where the feature starts (a front end at
the top of its module, a command before it does any work), inside ``needs_extra``:

    with needs_extra("jax", "make_jax_env"):
        import jax

If the package is missing, the import fails there and then with MissingExtraError, whose
message is one line that names the extra to install:

    make_jax_env needs jax, which is not installed: pip install 'marl-render[jax]'

MissingExtraError is a ModuleNotFoundError (``name`` is the missing module), so code that
catches ImportError keeps working. A module that is installed but fails to import for another
reason is not reported as missing: its own error goes through unchanged.
"""
from __future__ import annotations

import importlib.util
from contextlib import contextmanager

# extra -> the top-level modules it installs that marl-render imports (pyproject.toml's extras;
# tests/test_package.py checks that the two agree).
EXTRAS = {
    "bench": ("psutil", "tabulate", "tqdm", "matplotlib", "moderngl"),
    "plots": ("matplotlib", "tqdm"),
    "video": ("imageio",),
    "jax": ("jax", "jaxlib"),
    "sb3": ("stable_baselines3",),
    "tensorboard": ("tensorboard",),  # python -m marl_render.baselines --tensorboard
    "gltf": ("gltf",),
    "human": ("matplotlib",),
    "docs": ("sphinx", "myst_parser", "furo", "sphinx_copybutton", "sphinx_design"),  # make docs
}


class MissingExtraError(ModuleNotFoundError):
    """A feature's optional dependency is not installed; the message names the extra to install."""

    def __init__(self, feature: str, extra: str, module: str):
        super().__init__(f"{feature} needs {module}, which is not installed: pip install 'marl-render[{extra}]'",
                         name=module)
        self.feature, self.extra = feature, extra


@contextmanager
def needs_extra(extra: str, feature: str):
    """Imports inside the block that fail for a module of `extra` raise MissingExtraError
    (naming `feature` and the extra); other errors pass through unchanged."""
    if extra not in EXTRAS:
        raise ValueError(f"extra must be one of {sorted(EXTRAS)}, got {extra!r}")
    try:
        yield
    except MissingExtraError:
        raise
    except ModuleNotFoundError as error:
        missing = (error.name or "").partition(".")[0]
        if missing not in EXTRAS[extra]:
            raise
        raise MissingExtraError(feature, extra, missing) from None


def require(extra: str, feature: str, module: str) -> None:
    """Raise MissingExtraError at once if `module` (one of `extra`'s) cannot be found, without
    importing it: for features that import it later or in another process."""
    if module not in EXTRAS.get(extra, ()):
        raise ValueError(f"module must be one of extra {extra!r}'s modules {list(EXTRAS.get(extra, ()))}, "
                         f"got {module!r}")
    if importlib.util.find_spec(module) is None:
        raise MissingExtraError(feature, extra, module)


@contextmanager
def command_needs_extra(extra: str, command: str):
    """needs_extra for a command-line program: a missing module ends the program at once with
    the one line (``error: ...``) on stderr and exit status 1, instead of a traceback."""
    try:
        with needs_extra(extra, command):
            yield
    except MissingExtraError as error:
        raise SystemExit(f"error: {error}") from None
