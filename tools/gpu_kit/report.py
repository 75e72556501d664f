"""The GPU kit's helper for check.sh (standard library and packaging only, so that it runs before
anything is known to work):

    python report.py requirements                 # what is installed and whether it fits together (JSON)
    python report.py compose WORK JSON [--mode M] # check.sh's stages in WORK -> one JSON file

A stage in WORK is NN-NAME.{cmd,out,err,rc,time,limit} (or NN-NAME.skipped with the reason).
"""
from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import json
import platform
import re
import sys
import time
import warnings
import xml.etree.ElementTree as ElementTree
from pathlib import Path

from packaging.requirements import Requirement

DISTRIBUTIONS = ("marl-render", "panda3d", "torch", "numpy", "torchrl", "tensordict", "pettingzoo", "gymnasium")
CHECKED = ("marl-render", "torchrl", "tensordict", "pettingzoo", "gymnasium")  # whose requirements must hold
MODULES = ("marl_render", "marl_render.envs", "torchrl", "tensordict", "pettingzoo", "gymnasium")
TAIL = 4000  # characters of a stage's output kept in the JSON


def requirements() -> int:
    versions, unmet = {}, []
    for name in DISTRIBUTIONS:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    for name in CHECKED:
        if versions.get(name) is None:
            unmet.append(f"{name} is not installed")
            continue
        for text in importlib.metadata.requires(name) or []:
            requirement = Requirement(text)
            if requirement.marker is not None and not requirement.marker.evaluate({"extra": ""}):
                continue
            try:
                installed = importlib.metadata.version(requirement.name)
            except importlib.metadata.PackageNotFoundError:
                unmet.append(f"{name} needs {requirement}: not installed")
                continue
            if not requirement.specifier.contains(installed, prereleases=True):
                unmet.append(f"{name} needs {requirement}: {installed} is installed")
    imports = {}
    for module in MODULES:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                importlib.import_module(module)
                imports[module] = {"ok": True}
            except Exception as error:  # the report says what broke, whatever it is
                imports[module] = {"ok": False, "error": f"{type(error).__name__}: {error}"}
        imports[module]["warnings"] = sorted({str(w.message)[:300] for w in caught})
    print(json.dumps({"python": platform.python_version(), "versions": versions, "unmet": unmet,
                      "imports": imports}))
    return 0 if not unmet and all(entry["ok"] for entry in imports.values()) else 1


def read_stage(base: Path) -> dict:
    name = base.name.split("-", 1)[1]
    stage = {"name": name, "command": _text(base.with_suffix(".cmd")).strip()}
    if base.with_suffix(".skipped").exists():
        return {**stage, "status": "skipped", "reason": _text(base.with_suffix(".skipped")).strip()}
    rc = int(_text(base.with_suffix(".rc")) or -1)
    started, ended = (float(x) for x in _text(base.with_suffix(".time")).split())
    stage.update(status={0: "ok", 124: "timeout", 137: "timeout"}.get(rc, "failed"), exit_status=rc,
                 seconds=round(ended - started, 3), limit_seconds=int(_text(base.with_suffix(".limit"))),
                 stdout_tail=_text(base.with_suffix(".out"))[-TAIL:],
                 stderr_tail=_text(base.with_suffix(".err"))[-TAIL:])
    return stage


def _text(path: Path) -> str:
    return path.read_text(errors="replace") if path.exists() else ""


def last_json(text: str):
    for line in reversed(text.strip().splitlines()):
        try:
            return json.loads(line)
        except json.JSONDecodeError:
            continue
    return None


def parse_result(stage: dict, work: Path) -> None:
    """The stage's own figures, read from its output, as stage["result"]."""
    name, out = stage["name"], stage.get("stdout_tail", "")
    if name in ("requirements", "gl-info", "processes") or name.startswith(("env-", "render")):
        stage["result"] = last_json(out)
    elif name == "gl-debug":  # the whole of its stderr: the tail may have lost the first errors
        err = "".join(_text(path) for path in sorted(work.glob("[0-9][0-9]-gl-debug.err")))
        stage["result"] = {"bench": last_json(out), **gl_debug_lines(err or stage.get("stderr_tail", ""))}
    elif name in ("tests", "interop-tests") and (work / f"{name}.xml").exists():
        suite = ElementTree.parse(work / f"{name}.xml").getroot()
        suite = suite.find("testsuite") if suite.tag == "testsuites" else suite
        failed = [f"{case.get('classname')}::{case.get('name')}" for case in suite.iter("testcase")
                  if case.find("failure") is not None or case.find("error") is not None]
        stage["result"] = {key: int(suite.get(key, 0)) for key in ("tests", "failures", "errors", "skipped")}
        stage["result"]["failed"] = failed
    elif name == "gpu":
        stage["result"] = [dict(zip(("name", "memory", "driver"), (field.strip() for field in line.split(",")),
                                    strict=False)) for line in out.strip().splitlines()]
    elif name.startswith("pybatchrender-"):
        numbers = {key: re.search(rf"{key}:\s*([\d,.]+)", out) for key in ("FPS", "Total frames", "Time")}
        stage["result"] = {key: float(match[1].replace(",", "")) for key, match in numbers.items() if match}
        stage["result"].update(pybatchrender_path(out))


def pybatchrender_path(out: str) -> dict:
    """What PyBatchRender says of its GPU path: GPU_AVAILABLE, the frame grabber it made (a class
    name), and the launcher's cuda.cudart line (pbr_run.py)."""
    available = re.search(r"^GPU_AVAILABLE:\s*(True|False)\s*$", out, re.M)
    grabber = re.search(r"Frame grabber initialized: <(?:[\w.]*\.)?(\w+) object", out)
    cudart = re.search(r"^\[pbr_run\] (cuda\.cudart: .*)$", out, re.M)
    return {"gpu_available": None if available is None else available[1] == "True",
            "grabber": None if grabber is None else grabber[1], "cudart": None if cudart is None else cudart[1]}


def pybatchrender_refusal(result: dict) -> str | None:
    """Why a PyBatchRender figure must not be recorded (None: it ran its GPU path): its output must
    say `GPU_AVAILABLE: True` and name a GPU frame grabber."""
    if result.get("gpu_available") is not True:
        return f"its output does not say GPU_AVAILABLE: True (GPU_AVAILABLE: {result.get('gpu_available')})"
    grabber = result.get("grabber")
    if not grabber or not grabber.startswith("GPU"):
        return f"its frame grabber is not a GPU one ({grabber})"
    return None


GL_DEBUG_PATTERN = re.compile(r"GL error|0x0*502|GL_INVALID_OPERATION|invalid operation|debug|glgsg", re.I)


def gl_debug_lines(err: str) -> dict:
    """The GL's debug output in a gl-debug run: how many GL errors 0x502 were logged, and the distinct
    lines about GL errors and debug messages (at most 40), where the call behind them is named."""
    lines = [line.strip() for line in err.splitlines() if GL_DEBUG_PATTERN.search(line)]
    return {"gl_errors_0x502": sum("0x502" in line for line in lines), "lines": list(dict.fromkeys(lines))[:40]}


def summary(stages: list) -> dict:
    """The headline figures: env-steps/s per task and size (the first readback of each call) and per
    readback, the draw/read/copy split and readback's share of a step, PyBatchRender's FPS (only from
    runs of its GPU path) and the ratio of this project with interop to it, the tests, the gl-debug run."""
    env, by_readback, pybatchrender, refused, out = {}, {}, {}, {}, {"stages": {}}
    for stage in stages:
        out["stages"][stage["status"]] = out["stages"].get(stage["status"], 0) + 1
        result = stage.get("result")
        if not result or stage["status"] != "ok":
            continue
        if stage["name"].startswith("env-"):
            for row in result.get("results", []):
                task = row["env"] if row["agents"] == 1 else f"{row['env']}:{row['agents']}"
                figures = {key: row[key] for key in ("env_steps_per_s", "agent_frames_per_s", "ms_per_step", "device")}
                env.setdefault(task, {}).setdefault(str(row["worlds"]), figures)
                readback = row.get("readback", "host")
                split = row.get("render_ms", {})
                by_readback.setdefault(readback, {}).setdefault(task, {})[str(row["worlds"])] = {
                    **figures, "render_ms": split,
                    "readback_share": (split.get("read", 0.0) + split.get("copy", 0.0)) / row["ms_per_step"]}
        elif stage["name"].startswith("pybatchrender-") and "FPS" in result:
            size = stage["name"].rsplit("-", 1)[1]
            reason = pybatchrender_refusal(result)
            if reason is None:
                pybatchrender[size] = result["FPS"]
            else:
                refused[size] = reason
        elif stage["name"] == "processes":
            out["processes"] = processes_figures(result)
        elif stage["name"] == "render":
            out["render"] = {key: result.get(key) for key in ("views", "batched", "plain_panda3d", "speedup")}
        elif stage["name"] == "gl-info":
            out["gl"] = result
        elif stage["name"] == "gpu":
            out["gpu"] = result
        elif stage["name"] in ("tests", "interop-tests"):
            out[stage["name"].replace("-", "_")] = result
        elif stage["name"] == "gl-debug":
            out["gl_debug"] = {key: result[key] for key in ("gl_errors_0x502", "lines")}
    out["env_steps_per_s"] = {task: {size: row["env_steps_per_s"] for size, row in sizes.items()}
                              for task, sizes in env.items()}
    out["env"] = env
    out["env_by_readback"] = by_readback
    if "gpu" in by_readback and "host" in by_readback:  # the same call's two readbacks
        host = by_readback["host"]
        out["interop_to_host"] = {task: {size: row["env_steps_per_s"] / host[task][size]["env_steps_per_s"]
                                         for size, row in sizes.items() if size in host.get(task, {})}
                                  for task, sizes in by_readback["gpu"].items()}
    if refused:
        out["pybatchrender_refused"] = refused
    if pybatchrender:
        out["pybatchrender_cartpole_fps"] = pybatchrender
        cartpole = by_readback.get("gpu", {}).get("cartpole", {})  # this project with interop against it
        out["cartpole_ratio_to_pybatchrender"] = {size: cartpole[size]["env_steps_per_s"] / fps
                                                  for size, fps in pybatchrender.items() if size in cartpole}
    return out


def processes_figures(result: dict) -> dict:
    """bench parallel's single and processes rows: env-steps/s with all the worlds in one process and
    over each count of worker processes (num_processes=), with the ratio to the single process."""
    rows = result.get("results", [])
    single = next((row for row in rows if row["kind"] == "single"), None)
    return {"env": result.get("env"), "device": result.get("device"), "resolution": result.get("resolution"),
            "worlds": None if not rows else rows[0]["worlds"],
            "single_env_steps_per_s": None if single is None else single["env_steps_per_s"],
            "by_processes": {str(row["workers"]): {"env_steps_per_s": row["env_steps_per_s"],
                                                   "ratio_to_single": row.get("ratio_to_single"),
                                                   "setup_s": row["setup_s"]}
                             for row in rows if row["kind"] == "processes"}}


def compose(work: Path, target: Path, mode: str, budget: int, started: float) -> int:
    bases = sorted({path.with_suffix("") for path in work.glob("[0-9][0-9]-*.*")})
    stages = [read_stage(base) for base in bases]
    for stage in stages:
        if "stdout_tail" in stage:
            parse_result(stage, work)
    report = {"kit_check": 1, "mode": mode, "budget_seconds": budget,
              "seconds": round(time.time() - started, 1), "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
              "machine": {"python": platform.python_version(), "platform": platform.platform()},
              "ok": all(stage["status"] in ("ok", "skipped") for stage in stages),
              "summary": summary(stages), "stages": stages}
    manifest = Path(__file__).resolve().parent / "MANIFEST.json"
    if manifest.exists():
        about = json.loads(manifest.read_text())
        report["kit"] = {key: value for key, value in about.items() if key != "files"}
    target.write_text(json.dumps(report, indent=1) + "\n")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("requirements")
    composing = sub.add_parser("compose")
    composing.add_argument("work", type=Path)
    composing.add_argument("json", type=Path)
    composing.add_argument("--mode", default="gpu")
    composing.add_argument("--budget", type=int, default=0)
    composing.add_argument("--started", type=float, default=time.time())
    args = parser.parse_args(argv)
    if args.command == "requirements":
        return requirements()
    return compose(args.work, args.json, args.mode, args.budget, args.started)


if __name__ == "__main__":
    sys.exit(main())
