"""Installs checked in isolation: a throwaway virtual environment that reuses this environment's
packages (what a test installs into it, a wheel or a slimmed Panda3D, comes first on its path;
everything else is found here), and a picture that tests render there."""
import subprocess
import sys
import sysconfig
from pathlib import Path
from types import SimpleNamespace


def throwaway_venv(home: Path) -> SimpleNamespace:
    """A venv at `home` without pip: .python, and .site (its site-packages), whose .pth file names
    this process's site-packages folders (this environment's, and those it reaches through .pth
    files of its own, as a throwaway venv does). Path lines only: the .pth files in those folders
    (this checkout's editable install among them) are not run."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(home)], check=True, timeout=120)
    python = home / "bin" / "python"
    site = Path(subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                               capture_output=True, text=True, check=True).stdout.strip())
    reached = [path for path in sys.path if path.endswith("site-packages") and Path(path).is_dir()]
    folders = dict.fromkeys([sysconfig.get_path("purelib"), *reached])
    (site / "a_dependencies.pth").write_text("".join(f"{folder}\n" for folder in folders))
    return SimpleNamespace(python=python, site=site)


# Python code (for `python -c`, after `import torch` and `import marl_render as mr`) that renders a red
# unit box 3.5 m in front of the camera on a blue background into `rgb` [16, 16, 3]: the centre
# pixel [8, 8] is [255, 0, 0] and the corner [0, 0] is [0, 0, 255].
RED_BOX_PICTURE = """
scene = mr.Scene(num_worlds=1, agents_per_world=1, resolution=(16, 16), effects=(), background=(0.0, 0.0, 1.0))
scene.add_group("boxes", "box", capacity=1)
with mr.BatchRenderer(scene) as renderer:
    renderer.set_cameras(position=torch.zeros(1, 1, 3), rotation=torch.tensor([[[1.0, 0, 0, 0]]]))
    renderer.update("boxes", position=torch.tensor([[[0.0, 4.0, 0.0]]]), color=torch.tensor([[[1.0, 0, 0]]]),
                    active=torch.ones(1, 1, dtype=torch.bool))
    rgb = renderer.render().rgb[0, 0]
"""
