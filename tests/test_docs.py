"""The docs site (docs/conf.py, `make docs`) builds: Sphinx reads every page and every public
docstring (autodoc), resolves every reference (nitpicky) and fails on any warning, as `make docs`
does. The test uses Sphinx's dummy builder, which does all of that but write HTML (half the time
of the full build); the HTML writer itself is Sphinx's and furo's own code."""
from pathlib import Path

import pytest

pytest.importorskip("sphinx", reason="the docs extra: pip install -c constraints.txt -e '.[docs]'")
from sphinx.cmd.build import build_main  # noqa: E402

DOCS = Path(__file__).resolve().parents[1] / "docs"


def build(tmp_path: Path, source: Path = DOCS) -> int:
    return build_main(["-b", "dummy", "-n", "-W", "--keep-going", "-q", "-E", "-d", str(tmp_path / "doctrees"),
                       str(source), str(tmp_path / "out")])


@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::PendingDeprecationWarning")  # myst on Sphinx 9
def test_the_site_builds_without_a_warning(tmp_path, capsys):
    code = build(tmp_path)
    assert code == 0, capsys.readouterr().err[-5000:]
