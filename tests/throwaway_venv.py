"""A throwaway virtual environment that reuses this environment's packages: what a test installs
into it (a wheel, a slimmed Panda3D) comes first on its path, everything else is found here."""
import subprocess
import sys
import sysconfig
from pathlib import Path
from types import SimpleNamespace


def throwaway_venv(home: Path) -> SimpleNamespace:
    """A venv at `home` without pip: .python, and .site (its site-packages), which ends with a .pth
    line naming this environment's site-packages. Only a path line: the .pth files there (this
    checkout's editable install among them) are not run."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(home)], check=True, timeout=120)
    python = home / "bin" / "python"
    site = Path(subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                               capture_output=True, text=True, check=True).stdout.strip())
    (site / "a_dependencies.pth").write_text(sysconfig.get_path("purelib") + "\n")
    return SimpleNamespace(python=python, site=site)
