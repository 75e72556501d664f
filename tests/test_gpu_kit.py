"""The GPU kit (tools/gpu_kit): check.sh's CPU dry run writes its one JSON and keeps to its time
budget; the slimmed Panda3D layout renders here; the slimmed wheel is a valid wheel.

Building the kit itself needs the network (PyPI, Debian) and is `make gpu-kit`, not a test."""
import base64
import csv
import hashlib
import importlib.metadata
import importlib.util
import io
import json
import shutil
import subprocess
import sys
import sysconfig
import textwrap
import zipfile
from pathlib import Path

import pytest

from isolated_install import RED_BOX_PICTURE, throwaway_venv

ROOT = Path(__file__).resolve().parents[1]
KIT = ROOT / "tools" / "gpu_kit"


def load(name: str):
    spec = importlib.util.spec_from_file_location(f"gpu_kit_{name}", KIT / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


build, report = load("build"), load("report")


def check(tmp_path: Path, *arguments: str, python: str = sys.executable, cwd: Path | None = None) -> dict:
    """check.sh --cpu with this environment's python (or `python`), started in `cwd`; its JSON."""
    target = tmp_path / "check.json"
    done = subprocess.run(["bash", str(KIT / "check.sh"), "--cpu", "--python", python, "--json", str(target),
                           *arguments], capture_output=True, text=True, timeout=600, cwd=cwd or tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(target.read_text())


def test_the_dry_run_writes_one_json_with_every_stage(tmp_path):
    # Started from the checkout's root, as the device tool starts it: every stage's Python must run
    # elsewhere, or `python -m marl_render` imports the checkout's marl_render/ (without envs/ and glsl/,
    # which only an install maps in) instead of the kit's install. A wrapper records where it ran.
    where = tmp_path / "where.log"
    python = tmp_path / "python"
    python.write_text(f'#!/bin/sh\npwd >> "{where}"\nexec "{sys.executable}" "$@"\n')
    python.chmod(0o755)
    report = check(tmp_path, "--sizes", "4", "--more", "0 8", "--steps", "2",
                   "--tests", f"{ROOT}/tests/test_renderer.py::test_box_projects_where_a_pinhole_camera_puts_it",
                   "--interop-tests", f"{ROOT}/tests/test_interop_gpu.py::test_the_gl_context_is_on_the_cuda_device_"
                   f"of_the_frames {ROOT}/tests/test_interop.py::test_egl_device_is_the_one_whose_cuda_device_matches",
                   "--gl-debug-worlds", "2",
                   "--render-args", "--worlds 2 --agents 2 --resolution 16 --steps 2 --baseline-steps 1",
                   "--processes", "2", "--processes-worlds", "3", python=str(python), cwd=ROOT)
    directories = where.read_text().splitlines()
    assert len(directories) >= 7 and not any(Path(d).is_relative_to(ROOT) for d in directories), directories
    stages = {stage["name"]: stage for stage in report["stages"]}
    # The GPU-only stages are skipped; a failed size ends its task's larger sizes (0 worlds: refused,
    # so 8 is not tried), and the check goes on to write its JSON.
    assert list(stages) == ["gl-libraries", "install", "nvidia-smi", "gpu", "requirements", "gl-info", "tests",
                            "interop-tests", "env-cartpole-4", "pybatchrender", "env-spread:4-4", "gl-debug", "render",
                            "processes", "env-cartpole-0", "env-spread:4-0"]
    assert [stages[name]["status"] for name in ("gl-libraries", "install", "nvidia-smi", "gpu", "pybatchrender")] == \
        ["skipped"] * 5
    assert stages["pybatchrender"]["reason"] == "no PyBatchRender clone in the kit"
    for name in ("requirements", "gl-info", "tests", "interop-tests", "env-cartpole-4", "env-spread:4-4", "gl-debug",
                 "render", "processes"):
        assert stages[name]["status"] == "ok" and stages[name]["exit_status"] == 0, stages[name]["stderr_tail"]
        assert 0 < stages[name]["seconds"] <= stages[name]["limit_seconds"] + 5
    for name in ("env-cartpole-0", "env-spread:4-0"):
        assert stages[name]["status"] == "failed" and "argument --worlds: expected an int >= 1, got 0" in \
            stages[name]["stderr_tail"]
    assert report["mode"] == "cpu" and report["ok"] is False  # the two refused sizes
    requirements = stages["requirements"]["result"]
    assert requirements["unmet"] == [] and all(entry["ok"] for entry in requirements["imports"].values())
    assert requirements["versions"]["marl-render"] == importlib.metadata.version("marl-render")

    summary = report["summary"]
    assert "llvmpipe" in summary["gl"]["renderer"]
    assert summary["tests"] == {"tests": 1, "failures": 0, "errors": 0, "skipped": 0, "failed": []}
    # The gpu-marked test is skipped here (no CUDA), the fake-backed one runs.
    assert summary["interop_tests"] == {"tests": 2, "failures": 0, "errors": 0, "skipped": 1, "failed": []}
    # The GL's debug output was asked for (MARL_RENDER_PRC) and the run went through; llvmpipe logs no 0x502.
    assert "MARL_RENDER_PRC=gl-debug\\ #t" in stages["gl-debug"]["command"]
    assert summary["gl_debug"]["gl_errors_0x502"] == 0
    assert stages["gl-debug"]["result"]["bench"]["results"][0]["worlds"] == 2
    assert set(summary["env"]) == {"cartpole", "spread:4"}
    for task, agents in (("cartpole", 1), ("spread:4", 4)):
        row = summary["env"][task]["4"]
        assert row["device"] == "cpu" and row["env_steps_per_s"] > 0
        assert row["agent_frames_per_s"] == pytest.approx(row["env_steps_per_s"] * agents)
    (rows,) = [stages["env-spread:4-4"]["result"]["results"]]
    # On the CPU the two readbacks of one call are the host's: the direct read and the one through the PBO.
    assert [(r["env"], r["worlds"], r["agents"], r["resolution"], r["device"], r["readback"]) for r in rows] == \
        [("spread", 4, 4, 64, "cpu", "host"), ("spread", 4, 4, 64, "cpu", "pbo")]
    for readback in ("host", "pbo"):
        row = summary["env_by_readback"][readback]["spread:4"]["4"]
        assert set(row["render_ms"]) == {"pack", "cull", "draw", "read", "copy"}
        assert 0 < row["readback_share"] < 1
    assert summary["render"]["views"] == 4 and summary["render"]["speedup"] > 0
    # num_processes=2 against one process with the same 3 worlds (split 2 + 1), in one call
    processes = summary["processes"]
    assert (processes["env"], processes["device"], processes["worlds"]) == ("cartpole", "cpu", 3)
    assert set(processes["by_processes"]) == {"2"} and processes["single_env_steps_per_s"] > 0
    assert processes["by_processes"]["2"]["ratio_to_single"] == pytest.approx(
        processes["by_processes"]["2"]["env_steps_per_s"] / processes["single_env_steps_per_s"])
    assert summary["stages"] == {"skipped": 5, "ok": 9, "failed": 2}


def test_the_dry_run_keeps_to_its_budget(tmp_path):
    # 25 s leave less than a stage's minimum once the report's 20 s are kept: every stage is skipped,
    # whatever the machine's speed, and the JSON is still written.
    report = check(tmp_path, "--sizes", "4", "--budget", "25")
    ran = [stage for stage in report["stages"] if stage.get("reason") != "no time left in the 25s budget"]
    assert [stage["name"] for stage in ran] == ["gl-libraries", "install", "nvidia-smi", "gpu", "pybatchrender"]
    assert report["budget_seconds"] == 25 and report["summary"]["stages"] == {"skipped": len(report["stages"])}


def test_the_report_reads_the_gpu_and_pybatchrenders_figures_and_compares_them():
    """The stages the dry run cannot run here, from their output as nvidia-smi and PyBatchRender's
    CartPole script print it."""
    env_row = {"env": "cartpole", "agents": 1, "worlds": 1024, "env_steps_per_s": 400_000.0,
               "agent_frames_per_s": 400_000.0, "ms_per_step": 2.56, "device": "cuda:0"}
    host_row = {**env_row, "readback": "host", "env_steps_per_s": 100_000.0, "ms_per_step": 10.24,
                "render_ms": {"pack": 0.1, "cull": 0.0, "draw": 2.0, "read": 5.0, "copy": 0.12}}
    gpu_row = {**env_row, "readback": "gpu", "render_ms": {"pack": 0.1, "cull": 0.0, "draw": 2.0, "read": 0.1,
                                                          "copy": 0.156}}
    gpu_path = ("[pbr_run] cuda.cudart: alias of cuda.bindings.runtime, cuda-bindings 13.0.3\nGPU_AVAILABLE: True\n"
                "cuda_gl_interop: True\nFrame grabber initialized: <pybatchrender.renderer.frame_grabber."
                "GPUFrameGrabber object at 0x7fa7400e8080>\n")
    results = "Results:\n  Steps: 100\n  Total frames: 102,400\n  Time: 0.51s\n  FPS: 200,000\n"
    stages = [{"name": "gpu", "status": "ok", "stdout_tail": "NVIDIA H100 80GB HBM3, 81559 MiB, 580.159.04\n"},
              {"name": "pybatchrender-cartpole-1024", "status": "ok", "stdout_tail": gpu_path + results},
              {"name": "env-cartpole-1024", "status": "ok",
               "stdout_tail": json.dumps({"results": [gpu_row, host_row]})},
              {"name": "pybatchrender-cartpole-4096", "status": "timeout", "stdout_tail": ""}]
    for stage in stages:
        report.parse_result(stage, Path("."))
    assert stages[1]["result"] == {"FPS": 200_000.0, "Total frames": 102_400.0, "Time": 0.51, "gpu_available": True,
                                   "grabber": "GPUFrameGrabber",
                                   "cudart": "cuda.cudart: alias of cuda.bindings.runtime, cuda-bindings 13.0.3"}
    summary = report.summary(stages)
    assert summary["gpu"] == [{"name": "NVIDIA H100 80GB HBM3", "memory": "81559 MiB", "driver": "580.159.04"}]
    assert summary["pybatchrender_cartpole_fps"] == {"1024": 200_000.0}  # the timed-out size is left out
    assert summary["cartpole_ratio_to_pybatchrender"] == {"1024": 2.0}  # this project with interop: gpu rows
    assert summary["interop_to_host"] == {"cartpole": {"1024": 4.0}}
    assert summary["env_by_readback"]["gpu"]["cartpole"]["1024"]["readback_share"] == pytest.approx(0.1)
    assert summary["env"]["cartpole"]["1024"]["env_steps_per_s"] == 400_000.0  # the call's first readback
    assert summary["stages"] == {"ok": 3, "timeout": 1}


# What PyBatchRender printed on the H200 without its GPU path (docs/bench/gpu/h200_check_*.json), and variants.
HOST_PATH = ("Error importing CUDA/CuPy/OpenGL: cannot import name 'cudart' from 'cuda'\n"
             "GPU_AVAILABLE: False\ncuda_gl_interop: True\n"
             "Frame grabber initialized: <pybatchrender.renderer.frame_grabber.CPUFrameGrabber object at 0x7fa7>\n")


@pytest.mark.parametrize("output, reason", [
    (HOST_PATH, "its output does not say GPU_AVAILABLE: True (GPU_AVAILABLE: False)"),
    (HOST_PATH.replace("GPU_AVAILABLE: False", "GPU_AVAILABLE: True"), "its frame grabber is not a GPU one "
                                                                        "(CPUFrameGrabber)"),
    ("GPU_AVAILABLE: True\n", "its frame grabber is not a GPU one (None)"),
    ("Frame grabber initialized: <x.GPUFrameGrabber object at 0x1>\n", "its output does not say GPU_AVAILABLE: "
                                                                        "True (GPU_AVAILABLE: None)"),
])
def test_the_report_refuses_pybatchrender_figures_without_its_gpu_path(output, reason):
    env_row = {"env": "cartpole", "agents": 1, "worlds": 1024, "env_steps_per_s": 400_000.0, "readback": "gpu",
               "agent_frames_per_s": 400_000.0, "ms_per_step": 2.56, "device": "cuda:0", "render_ms": {}}
    stages = [{"name": "pybatchrender-cartpole-1024", "status": "ok",
               "stdout_tail": output + "Results:\n  FPS: 18,496\n"},
              {"name": "env-cartpole-1024", "status": "ok", "stdout_tail": json.dumps({"results": [env_row]})}]
    for stage in stages:
        report.parse_result(stage, Path("."))
    summary = report.summary(stages)
    assert "pybatchrender_cartpole_fps" not in summary and "cartpole_ratio_to_pybatchrender" not in summary
    assert summary["pybatchrender_refused"] == {"1024": reason}


def test_the_report_counts_the_gl_errors_of_the_gl_debug_run(tmp_path):
    err = (":display:gsg:glgsg(error): GL error 0x502 : invalid operation\n"
           "progress line\n"
           ":display:gsg:glgsg(error): GL_INVALID_OPERATION error generated. Buffer is mapped.\n"
           ":display:gsg:glgsg(error): GL error 0x502 : invalid operation\n")
    (tmp_path / "12-gl-debug.err").write_text(err)
    stage = {"name": "gl-debug", "status": "ok", "stdout_tail": json.dumps({"results": []}), "stderr_tail": ""}
    report.parse_result(stage, tmp_path)
    assert stage["result"]["gl_errors_0x502"] == 2
    assert stage["result"]["lines"] == [
        ":display:gsg:glgsg(error): GL error 0x502 : invalid operation",
        ":display:gsg:glgsg(error): GL_INVALID_OPERATION error generated. Buffer is mapped."]
    assert report.summary([stage])["gl_debug"] == {"gl_errors_0x502": 2, "lines": stage["result"]["lines"]}


# ---------------------------------------------------------------------- the slimmed Panda3D
PANDA3D_NAMES = [
    "panda3d/__init__.py", "panda3d/core.cpython-312-x86_64-linux-gnu.so", "panda3d/libpanda.so.1.10",
    "panda3d/libp3headlessgl.so", "panda3d/libpandagl.so", "panda3d/libp3tinydisplay.so", "panda3d/libp3assimp.so",
    "panda3d/libp3ptloader.so", "panda3d/bullet.cpython-312-x86_64-linux-gnu.so", "panda3d/etc/Config.prc",
    "panda3d/models/box.egg.pz", "panda3d/models/teapot.egg.pz", "direct/showbase/ShowBase.py",
    "direct/showbase/__pycache__/ShowBase.cpython-312.pyc", "panda3d_tools/pview", "pandac/PandaModules.py",
    "deploy_libs/libz.so.1", "panda3d-1.10.16.dist-info/METADATA", "panda3d-1.10.16.dist-info/RECORD",
    "panda3d-1.10.16.dist-info/entry_points.txt",
]


def test_slim_members_keeps_what_headless_rendering_loads():
    assert build.slim_members(PANDA3D_NAMES) == [
        "panda3d/__init__.py", "panda3d/core.cpython-312-x86_64-linux-gnu.so", "panda3d/libpanda.so.1.10",
        "panda3d/libp3headlessgl.so", "panda3d/libp3ptloader.so", "panda3d/etc/Config.prc",
        "panda3d/models/box.egg.pz", "direct/showbase/ShowBase.py", "panda3d-1.10.16.dist-info/METADATA"]


def test_slim_prc_drops_the_lines_of_libraries_left_out_and_fails_on_a_changed_file():
    config = "load-display pandagl\naux-display p3headlessgl\naudio-library-name p3openal_audio\nwin-size 800 600\n"
    assert build.slim_prc("panda3d/etc/Config.prc", config) == \
        "load-display p3headlessgl\naudio-library-name null\nwin-size 800 600\n"
    with pytest.raises(SystemExit, match=r"panda3d/etc/Config.prc: expected the line 'load-display pandagl' once, "
                                         r"found it 0 times"):
        build.slim_prc("panda3d/etc/Config.prc", "load-display p3tinydisplay\n")
    assert build.slim_prc("panda3d/etc/other.prc", config) == config


def fake_panda3d_wheel(folder: Path) -> Path:
    wheel = folder / "panda3d-1.10.16-cp312-cp312-manylinux2014_x86_64.whl"
    confauto = "load-file-type egg pandaegg\nload-file-type p3assimp\nload-audio-type * p3ffmpeg\n" \
               "load-video-type * p3ffmpeg\nload-file-type p3ptloader\n"
    config = "load-display pandagl\naux-display p3headlessgl\naudio-library-name p3openal_audio\n"
    members = {"panda3d/__init__.py": "VERSION = 'fake'\n", "panda3d/libpanda.so.1.10": "library",
               "panda3d/libp3assimp.so": "assimp", "panda3d/etc/Confauto.prc": confauto,
               "panda3d/etc/Config.prc": config, "panda3d_tools/pview": "tool",
               "panda3d-1.10.16.dist-info/METADATA": "Metadata-Version: 2.1\nName: Panda3D\nVersion: 1.10.16\n",
               "panda3d-1.10.16.dist-info/WHEEL": "Wheel-Version: 1.0\nRoot-Is-Purelib: false\n"
                                                  "Tag: cp312-cp312-manylinux2014_x86_64\n",
               "panda3d-1.10.16.dist-info/top_level.txt": "panda3d\npanda3d_tools\n",
               "panda3d-1.10.16.dist-info/entry_points.txt": "[console_scripts]\npview = panda3d_tools:pview\n",
               "panda3d-1.10.16.dist-info/RECORD": "stale\n"}
    with zipfile.ZipFile(wheel, "w") as archive:
        for name, text in members.items():
            archive.writestr(name, text)
    return wheel


def test_the_slimmed_wheel_is_a_valid_wheel_of_version_headless(tmp_path):
    (tmp_path / "out").mkdir()
    slim = build.slim_panda3d(fake_panda3d_wheel(tmp_path), tmp_path / "out")
    wheel = tmp_path / "out" / "panda3d-1.10.16+headless-cp312-cp312-manylinux2014_x86_64.whl"
    assert slim["wheel"] == wheel.name and slim["kept_members"] == 7 and slim["dropped_members"] == 4
    info = "panda3d-1.10.16+headless.dist-info"
    with zipfile.ZipFile(wheel) as archive:
        contents = {name: archive.read(name) for name in archive.namelist()}
    assert sorted(contents) == sorted(["panda3d/__init__.py", "panda3d/libpanda.so.1.10", "panda3d/etc/Confauto.prc",
                                       "panda3d/etc/Config.prc", f"{info}/METADATA", f"{info}/WHEEL",
                                       f"{info}/top_level.txt", f"{info}/RECORD"])
    assert b"Version: 1.10.16+headless\n" in contents[f"{info}/METADATA"]
    assert contents["panda3d/etc/Confauto.prc"] == b"load-file-type egg pandaegg\nload-file-type p3ptloader\n"
    assert contents["panda3d/etc/Config.prc"] == b"load-display p3headlessgl\naudio-library-name null\n"
    record = list(csv.reader(io.StringIO(contents[f"{info}/RECORD"].decode())))
    for name, digest, size in record[:-1]:
        expected = base64.urlsafe_b64encode(hashlib.sha256(contents[name]).digest()).rstrip(b"=").decode()
        assert digest == f"sha256={expected}" and int(size) == len(contents[name]), name
    assert record[-1] == [f"{info}/RECORD", "", ""] and len(record) == len(contents)
    # pip takes it (tags aside: a target folder, no dependencies) and reads its version
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-index", "--no-compile",
                    "--disable-pip-version-check", "--platform", "manylinux2014_x86_64", "--python-version", "3.12",
                    "--only-binary=:all:", "--implementation", "cp", "--target", str(target), str(wheel)],
                   check=True, capture_output=True, timeout=120)
    (installed,) = importlib.metadata.distributions(path=[str(target)])
    assert installed.version == "1.10.16+headless"
    assert (target / "panda3d" / "libpanda.so.1.10").read_text() == "library"


SLIM_RENDER = """
    import json
    import torch
    import marl_render as mr
    import panda3d
    from marl_render.envs import make_env

    pixels = {}
    for name, agents in (("cartpole", 1), ("spread", 3)):
        env = make_env(name, num_worlds=2, resolution=8, seed=0)
        env.reset(seed=0)
        pixels[name] = list(env.step(env.random_actions())[0]["pixels"].shape)
        env.close()
    {picture}
    with open("tri.egg", "w") as f:
        f.write("<CoordinateSystem> { Z-up }\\n<VertexPool> v { <Vertex> 0 { 0 0 0 } <Vertex> 1 { 1 0 0 } "
                "<Vertex> 2 { 0 1 0 } }\\n<Polygon> { <VertexRef> { 0 1 2 <Ref> { v } } }\\n")
    triangles = mr.load_model("tri.egg").triangles.shape[0]
    libraries = sorted({line.split()[-1] for line in open("/proc/self/maps") if ".so" in line.split()[-1]})
    print(json.dumps({"panda3d": panda3d.__file__, "pixels": pixels, "centre": rgb[8, 8].tolist(),
                      "corner": rgb[0, 0].tolist(), "triangles": triangles, "libraries": libraries}))
"""


def test_the_slimmed_panda3d_layout_renders_here(tmp_path):
    """The files the slim build keeps, taken from the installed Panda3D (the same files under this
    Python's names), alone in a throwaway venv: every kept library loads, tasks step, pixels are
    right and .egg files load; no library of the full install is mapped into the process."""
    full = Path(importlib.util.find_spec("panda3d").origin).parent
    files = {str(f): f.locate() for f in importlib.metadata.files("panda3d")}
    venv = throwaway_venv(tmp_path / "venv")
    site = venv.site
    kept = build.slim_members(sorted(files))
    for name in kept:
        (site / name).parent.mkdir(parents=True, exist_ok=True)
        if name in build.PRC_EDITS:
            (site / name).write_text(build.slim_prc(name, Path(files[name]).read_text()))
        else:
            shutil.copy2(files[name], site / name)
    assert not (site / "panda3d" / "libp3assimp.so").exists() and (site / "panda3d" / "libp3headlessgl.so").exists()
    # marl-render from this checkout's editable install, if that is how it is installed here
    for editable in Path(sysconfig.get_path("purelib")).glob("__editable__*marl_render*.pth"):
        shutil.copy2(editable, site / f"b_{editable.name}")
    code = textwrap.dedent(SLIM_RENDER).replace("{picture}", RED_BOX_PICTURE)
    done = subprocess.run([venv.python, "-I", "-c", code], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert Path(result["panda3d"]).parent == site / "panda3d"
    assert result["pixels"] == {"cartpole": [2, 1, 8, 8, 3], "spread": [2, 3, 8, 8, 3]}
    assert result["centre"] == [255, 0, 0] and result["corner"] == [0, 0, 255] and result["triangles"] == 1
    panda_libraries = [path for path in result["libraries"] if "/panda3d/" in path]
    assert panda_libraries and all(Path(path).parent == site / "panda3d" for path in panda_libraries)
    assert not [path for path in result["libraries"] if Path(path).is_relative_to(full)]


def test_pbr_run_gives_pybatchrender_a_cuda_cudart_aliasing_cuda_bindings_runtime(tmp_path):
    # A stand-in for cuda-bindings 13: a namespace package `cuda` with bindings/runtime.py and no cudart.
    runtime = tmp_path / "site" / "cuda" / "bindings"
    runtime.mkdir(parents=True)
    (runtime / "runtime.py").write_text("cudaGraphicsGLRegisterImage = 'the runtime bindings'\n")
    script = tmp_path / "script.py"
    script.write_text("import sys\nfrom cuda import cudart\nprint(cudart.cudaGraphicsGLRegisterImage, sys.argv[1:])\n")
    done = subprocess.run([sys.executable, str(KIT / "pbr_run.py"), str(script), "--num-scenes", "4"],
                          capture_output=True, text=True, timeout=60, env={"PYTHONPATH": str(tmp_path / "site")})
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["[pbr_run] cuda.cudart: alias of cuda.bindings.runtime, cuda-bindings unknown",
                                        "the runtime bindings ['--num-scenes', '4']"]
    parsed = report.pybatchrender_path(done.stdout)
    assert parsed["cudart"] == "cuda.cudart: alias of cuda.bindings.runtime, cuda-bindings unknown"
