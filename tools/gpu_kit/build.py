"""`make gpu-kit`: everything a GPU machine with Python 3.12, a CUDA torch and no network needs to
install marl-render and measure it, in one folder of at most 40 MiB (see README.md beside this file).

    python tools/gpu_kit/build.py --out .gpu-kit [--pybatchrender PATH] [--cache .gpu-kit-cache]

The kit holds:
- wheels/: this project's wheel; Panda3D 1.10.16 for CPython 3.12 manylinux x86-64, slimmed to
  what headless GL rendering loads (version 1.10.16+headless, see PANDA3D_KEEP); and the
  dependencies of the core and of `bench env` that the machine lacks (versions: constraints.txt,
  else those this environment runs);
- gl/: the GL dispatch libraries as Debian packages (libglvnd's libEGL, libGL, ...), which
  check.sh unpacks when the machine has no libEGL.so.1;
- tests/: the correctness subset check.sh runs (projection and pixels) and the interop's tests;
- pybatchrender/: a PyBatchRender clone, when --pybatchrender names one;
- PyOpenGL's wheel (in wheels/) and pbr_run.py (the `cuda.cudart` alias): PyBatchRender's GPU path;
- check.sh, report.py, README.md and MANIFEST.json (every file with its size and sha256).

Downloads (PyPI through pip, Debian through apt-get) are kept in --cache, so a second build runs
offline.
"""
from __future__ import annotations

import argparse
import base64
import csv
import fnmatch
import hashlib
import importlib.metadata
import io
import json
import re
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
LIMIT_BYTES = 40 * 2 ** 20

PYTHON_VERSION = "3.12"
PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64",
             "manylinux1_x86_64")
PANDA3D_VERSION = "1.10.16"
SLIM_LABEL = "headless"

# What headless rendering opens, read with `strace -f -e trace=openat` (and LD_DEBUG=files) from
# every task's make/reset/step, `bench render`, the renderer and transform tests (a model file
# included) and PyBatchRender's CartPole (ShowBase, its box model) on Panda3D 1.10.16 here:
PANDA3D_KEEP = (
    "panda3d/__init__.py",
    "panda3d/core.cpython-*.so",  # panda3d.core
    "panda3d/direct.cpython-*.so",  # panda3d.direct (ShowBase: PyBatchRender)
    "panda3d/libpanda.so.*", "panda3d/libpandaexpress.so.*", "panda3d/libp3dtool.so.*",
    "panda3d/libp3dtoolconfig.so.*", "panda3d/libp3interrogatedb.so.*", "panda3d/libp3direct.so.*",
    "panda3d/libCg.so", "panda3d/libCgGL.so",  # linked by libpanda and p3headlessgl: needed to load at all
    "panda3d/libp3headlessgl.so",  # the EGL display module
    "panda3d/libpandaegg.so.*", "panda3d/libp3ptloader.so",  # .egg files (load_model, PyBatchRender's box):
    # p3ptloader links pandaegg and is what makes the .egg loader known; without it no .egg loads (checked)
    "panda3d/libxcb.so.*", "panda3d/libXau.so.*",  # opened through libGL's X11 dependencies
    "panda3d/etc/*.prc",
    "panda3d/models/box.egg.pz", "panda3d/models/maps/noise.rgb",  # what PyBatchRender's CartPole loads
    "direct/*.py",  # ShowBase and what it imports (Python only)
    "panda3d-*.dist-info/*",
)
PANDA3D_DROP = ("*/__pycache__/*", "*.dist-info/RECORD", "*.dist-info/entry_points.txt", "*.dist-info/metadata.json")

# Configuration lines that name a library the slim build leaves out, and what replaces them
# (None: removed). Each must be found once: another Panda3D version fails the build here.
PRC_EDITS = {
    "panda3d/etc/Confauto.prc": {"load-file-type p3assimp": None, "load-audio-type * p3ffmpeg": None,
                                 "load-video-type * p3ffmpeg": None},
    "panda3d/etc/Config.prc": {"load-display pandagl": "load-display p3headlessgl", "aux-display p3headlessgl": None,
                               "audio-library-name p3openal_audio": "audio-library-name null"},
}

# The dependencies to bring: marl-render's own (panda3d apart), resolved to what they need in turn,
# less what the machine has (/work/.library/device/KINDS.md, "Python packages already there").
KIT_REQUIREMENTS = ("pettingzoo", "gymnasium", "torchrl", "tensordict")
ON_THE_MACHINE = {
    "torch", "numpy", "pillow", "cloudpickle", "typing-extensions", "packaging", "zipp", "psutil", "tqdm", "tabulate",
    "matplotlib", "pytest", "hypothesis", "filelock", "fsspec", "jinja2", "markupsafe", "networkx", "sympy", "mpmath",
    "triton", "setuptools", "pyyaml", "imageio", "cupy-cuda13x",
}
GL_PACKAGES = ("libegl1", "libglvnd0", "libgl1", "libglx0", "libopengl0", "libgles2")  # as the device notes list
CORRECTNESS_TESTS = ("conftest.py", "test_renderer.py", "test_transforms.py", "test_interop.py", "test_interop_gpu.py",
                     "test_multiprocess_gpu.py")
# PyBatchRender's GPU frame grabber imports PyOpenGL (pure Python, checked with `pip download --no-deps
# pyopengl==3.1.10`: one py3-none-any wheel of 3.1 MB) and `cuda.cudart`, which pbr_run.py aliases to the
# machine's cuda.bindings.runtime (cuda-python 12.9.0 exists on PyPI too, but would bring a second set of
# CUDA bindings, about 11 MB of cuda-bindings 12.9, beside the machine's 13).
PYOPENGL = "pyopengl==3.1.10"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=ROOT / ".gpu-kit", help="the kit's folder (emptied first)")
    parser.add_argument("--cache", type=Path, default=ROOT / ".gpu-kit-cache", help="downloads, kept between builds")
    parser.add_argument("--pybatchrender", type=Path, help="a PyBatchRender clone to include, if it exists")
    args = parser.parse_args(argv)
    kit = args.out.resolve()
    shutil.rmtree(kit, ignore_errors=True)
    for folder in ("wheels", "gl", "tests"):
        (kit / folder).mkdir(parents=True)
    args.cache.mkdir(parents=True, exist_ok=True)

    project_wheel = build_project_wheel(kit / "wheels")
    panda3d = download(f"panda3d=={PANDA3D_VERSION}", args.cache)
    slim = slim_panda3d(panda3d, kit / "wheels")
    for wheel in dependency_wheels(args.cache):
        shutil.copy2(wheel, kit / "wheels")
    shutil.copy2(download(PYOPENGL, args.cache), kit / "wheels")
    for deb in gl_packages(args.cache):
        shutil.copy2(deb, kit / "gl")
    for name in CORRECTNESS_TESTS:
        shutil.copy2(ROOT / "tests" / name, kit / "tests" / name)
    for name in ("check.sh", "report.py", "pbr_run.py", "README.md"):
        shutil.copy2(HERE / name, kit / name)
    pybatchrender = None
    if args.pybatchrender and args.pybatchrender.is_dir():
        pybatchrender = copy_clone(args.pybatchrender, kit / "pybatchrender")

    manifest = write_manifest(kit, project_wheel=project_wheel.name, panda3d=slim, pybatchrender=pybatchrender)
    size = manifest["total_bytes"]
    print(f"gpu kit: {kit} holds {len(manifest['files'])} files, {size / 2 ** 20:.1f} MiB "
          f"(limit {LIMIT_BYTES / 2 ** 20:.0f} MiB)")
    if size > LIMIT_BYTES:
        print(f"error: the kit is {size / 2 ** 20:.1f} MiB, over the {LIMIT_BYTES / 2 ** 20:.0f} MiB limit",
              file=sys.stderr)
        return 1
    return 0


def run(command: list, **kwargs) -> subprocess.CompletedProcess:
    done = subprocess.run([str(c) for c in command], capture_output=True, text=True, **kwargs)
    if done.returncode != 0:
        raise SystemExit(f"error: {' '.join(map(str, command))} failed:\n{done.stdout[-2000:]}{done.stderr[-2000:]}")
    return done


def build_project_wheel(out: Path) -> Path:
    with tempfile.TemporaryDirectory() as folder:
        run([sys.executable, "-m", "build", "--wheel", "--no-isolation", "--outdir", folder, ROOT])
        (wheel,) = Path(folder).glob("*.whl")
        return Path(shutil.copy2(wheel, out))


def download(requirement: str, cache: Path) -> Path:
    """The CPython 3.12 manylinux x86-64 wheel of `requirement` (name==version), from the cache or PyPI."""
    name, version = requirement.split("==")
    stem = f"{canonicalize_name(name).replace('-', '_')}-{version}-"
    cached = [path for path in cache.glob("*.whl") if path.name.lower().startswith(stem)]
    if not cached:
        platforms = [option for platform in PLATFORMS for option in ("--platform", platform)]
        run([sys.executable, "-m", "pip", "download", "--quiet", "--disable-pip-version-check", "--no-deps",
             "--only-binary=:all:", "--python-version", PYTHON_VERSION, "--implementation", "cp", *platforms,
             "--dest", cache, requirement])
        cached = [path for path in cache.glob("*.whl") if path.name.lower().startswith(stem)]
    if len(cached) != 1:
        raise SystemExit(f"error: expected one wheel of {requirement} in {cache}, found {[p.name for p in cached]}")
    return cached[0]


def pinned_version(name: str) -> str:
    """The version constraints.txt pins, else the one this environment runs (the tested one)."""
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        match = re.match(r"^([A-Za-z0-9_.-]+)==([^\s#]+)", line)
        if match and canonicalize_name(match[1]) == canonicalize_name(name):
            return match[2]
    return importlib.metadata.version(name)


def wheel_requirements(wheel: Path) -> list[Requirement]:
    """The Requires-Dist of a wheel that apply on CPython 3.12 Linux without extras."""
    with zipfile.ZipFile(wheel) as archive:
        (metadata,) = [n for n in archive.namelist() if re.fullmatch(r"[^/]+\.dist-info/METADATA", n)]
        lines = archive.read(metadata).decode().splitlines()
    environment = {"python_version": PYTHON_VERSION, "python_full_version": f"{PYTHON_VERSION}.3",
                   "sys_platform": "linux", "platform_system": "Linux", "platform_machine": "x86_64",
                   "implementation_name": "cpython", "os_name": "posix", "extra": ""}
    requirements = [Requirement(line.split(":", 1)[1].strip()) for line in lines if line.startswith("Requires-Dist:")]
    return [r for r in requirements if r.marker is None or r.marker.evaluate(environment)]


def dependency_wheels(cache: Path) -> list[Path]:
    """KIT_REQUIREMENTS and what they need, transitively, less what the machine has."""
    wanted, seen, wheels = list(KIT_REQUIREMENTS), set(), []
    while wanted:
        name = canonicalize_name(wanted.pop(0))
        if name in seen or name in ON_THE_MACHINE:
            continue
        seen.add(name)
        wheel = download(f"{name}=={pinned_version(name)}", cache)
        wheels.append(wheel)
        wanted += [r.name for r in wheel_requirements(wheel)]
    return wheels


def slim_members(names: list[str]) -> list[str]:
    """The members of Panda3D's wheel that the slim build keeps (PANDA3D_KEEP less PANDA3D_DROP)."""
    return [name for name in names if any(fnmatch.fnmatch(name, keep) for keep in PANDA3D_KEEP)
            and not any(fnmatch.fnmatch(name, drop) for drop in PANDA3D_DROP)]


def slim_prc(member: str, text: str) -> str:
    """Panda3D's configuration file `member` without the libraries the slim build leaves out."""
    edits = PRC_EDITS.get(member, {})
    lines = text.splitlines(keepends=True)
    for old, new in edits.items():
        found = [i for i, line in enumerate(lines) if line.strip() == old]
        if len(found) != 1:
            raise SystemExit(f"error: {member}: expected the line {old!r} once, found it {len(found)} times")
        lines[found[0]] = "" if new is None else new + "\n"
    return "".join(lines)


def record_line(name: str, data: bytes) -> list:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return [name, f"sha256={digest}", str(len(data))]


def slim_panda3d(wheel: Path, out: Path) -> dict:
    """Rebuilds Panda3D's wheel with the members slim_members keeps, as version
    <version>+headless (so that `pip list` says what it is); returns what was kept and dropped."""
    version = f"{PANDA3D_VERSION}+{SLIM_LABEL}"
    old_info, new_info = f"panda3d-{PANDA3D_VERSION}.dist-info", f"panda3d-{version}.dist-info"
    target = out / wheel.name.replace(f"-{PANDA3D_VERSION}-", f"-{version}-")
    with zipfile.ZipFile(wheel) as source, zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as dest:
        infos = source.infolist()
        kept = slim_members([info.filename for info in infos])
        records = []
        for info in infos:
            if info.filename not in kept:
                continue
            data = source.read(info)
            name = info.filename.replace(old_info, new_info)
            if info.filename in PRC_EDITS:
                data = slim_prc(info.filename, data.decode()).encode()
            if name == f"{new_info}/METADATA":
                data = re.sub(rb"^Version: .*$", f"Version: {version}".encode(), data, count=1, flags=re.M)
            copy = zipfile.ZipInfo(name, date_time=info.date_time)
            copy.external_attr, copy.compress_type = info.external_attr, zipfile.ZIP_DEFLATED
            dest.writestr(copy, data)
            records.append(record_line(name, data))
        text = io.StringIO()
        csv.writer(text, lineterminator="\n").writerows(records + [[f"{new_info}/RECORD", "", ""]])
        dest.writestr(f"{new_info}/RECORD", text.getvalue())
        dropped = [info for info in infos if info.filename not in kept]
    return {"wheel": target.name, "from": wheel.name, "from_bytes": wheel.stat().st_size,
            "bytes": target.stat().st_size, "kept_members": len(kept), "dropped_members": len(dropped),
            "dropped_unpacked_bytes": sum(info.file_size for info in dropped)}


def gl_packages(cache: Path) -> list[Path]:
    """The Debian packages of GL_PACKAGES for amd64, from the cache or apt-get download."""
    folder = cache / "gl"
    folder.mkdir(exist_ok=True)
    debs = {package: sorted(folder.glob(f"{package}_*_amd64.deb")) for package in GL_PACKAGES}
    missing = [package for package, found in debs.items() if not found]
    if missing:
        run(["apt-get", "download", *(f"{package}:amd64" for package in missing)], cwd=folder)
        debs = {package: sorted(folder.glob(f"{package}_*_amd64.deb")) for package in GL_PACKAGES}
    if any(len(found) != 1 for found in debs.values()):
        raise SystemExit(f"error: expected one .deb of each of {GL_PACKAGES} in {folder}, found {debs}")
    return [found[0] for found in debs.values()]


def copy_clone(clone: Path, target: Path) -> dict:
    """A clone's tracked files at its checked-out commit (the whole folder if it is not a git repository)."""
    git = subprocess.run(["git", "-C", str(clone), "rev-parse", "HEAD"], capture_output=True, text=True)
    if git.returncode != 0:
        shutil.copytree(clone, target, ignore=shutil.ignore_patterns(".git", "__pycache__"))
        return {"source": str(clone), "commit": None}
    target.mkdir()
    archive = subprocess.run(["git", "-C", str(clone), "archive", "HEAD"], capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(target)], input=archive.stdout, check=True)
    return {"source": str(clone), "commit": git.stdout.strip()}


def write_manifest(kit: Path, **about) -> dict:
    """MANIFEST.json: every file of the kit with its size and sha256, and what the kit was built from.
    Returns it, with total_bytes: the kit's size on disk, the manifest included."""
    files = {}
    for path in sorted(p for p in kit.rglob("*") if p.is_file()):
        data = path.read_bytes()
        files[str(path.relative_to(kit))] = {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True)
    manifest = {"marl_render_commit": commit.stdout.strip() or None, "python": PYTHON_VERSION, **about,
                "files": files}
    (kit / "MANIFEST.json").write_text(json.dumps(manifest, indent=1) + "\n")
    return {**manifest, "total_bytes": sum(p.stat().st_size for p in kit.rglob("*") if p.is_file())}


if __name__ == "__main__":
    sys.exit(main())
