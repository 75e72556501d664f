"""The reproducible training mode: golden hashes of a tiny run, its refusals, and what result.json records."""
import json
import os
import subprocess
import sys
import warnings

import pytest
import torch

from marl_render.baselines import golden, reproducible, run
from marl_render.baselines.settings import task_hyperparameters
from marl_render.baselines.training import train

TINY = ["--env-steps", "24", "--checkpoint-every", "0", "--worlds", "2", "--resolution", "12", "--episodes", "2",
        "--rollout", "4"]


def tiny_run() -> dict:
    """python -m marl_render.baselines.golden (it restarts itself in the mode's environment) in a fresh process."""
    out = subprocess.run([sys.executable, "-m", "marl_render.baselines.golden"], capture_output=True, text=True,
                         check=True, env={k: v for k, v in os.environ.items() if k not in reproducible.ENVIRONMENT})
    return json.loads(out.stdout)


def test_a_tiny_reproducible_run_gives_its_cpu_s_golden_hashes():
    """The tiny run gives the hashes recorded for this machine's CPU and torch: if not, the reproducible mode
    does not hold on this CPU, and the message names the primitives that differ. A CPU without a record
    (the bits differ across CPUs, docs/training.md) must at least train the same bits twice."""
    records = golden.recorded()
    found = tiny_run()
    assert found["run"] == records["run"] == golden.TINY
    assert found["cpu"]["torch_cpu_capability"] == "DEFAULT"
    here = f"{reproducible.describe(found['cpu'])}, torch {found['torch']}"
    expected = golden.record_for(found, records)
    if expected is None:
        again = tiny_run()
        assert (again["actor_sha256"], again["losses_sha256"], again["primitives"]) == (
            found["actor_sha256"], found["losses_sha256"], found["primitives"]), f"two runs differ on {here}"
        warnings.warn(f"no golden hashes are recorded for this CPU, {here}: only run-to-run identity was checked "
                      f"(`python -m marl_render.baselines.golden --write` records them)", stacklevel=1)
        return
    assert found["primitives"] == expected["primitives"], (
        f"kernels gave other bits on {here} than when its record was made: "
        f"{golden.differing_primitives(found, expected)}")
    assert (found["actor_sha256"], found["losses_sha256"]) == (expected["actor_sha256"], expected["losses_sha256"]), (
        f"the reproducible mode gave other bits on {here} than when its record was made: first critic loss "
        f"{found['first_loss_critic']!r} against {expected['first_loss_critic']!r}")


def test_the_records_are_one_per_cpu_and_differ_across_cpus():
    """What docs/training.md says of the records: one per CPU and torch, each of the tiny run, and the two
    CPUs measured (an AMD EPYC and an Intel Xeon with AMX) trained other bits from the first update."""
    records = golden.recorded()
    keys = [(reproducible.describe(m["cpu"]), m["torch"]) for m in records["machines"]]
    assert len(keys) == len(set(keys)) >= 2
    by_model = {m["cpu"]["model"]: m for m in records["machines"]}
    epyc, xeon = by_model["AMD EPYC"], by_model["Intel(R) Xeon(R) Processor"]
    assert "amx_bf16" in xeon["cpu"]["flags"] and "amx_bf16" not in epyc["cpu"]["flags"]
    assert epyc["first_loss_critic"] != xeon["first_loss_critic"]
    assert epyc["actor_sha256"] != xeon["actor_sha256"]


def test_a_record_replaces_its_cpu_s_and_keeps_the_others():
    records = golden.recorded()
    first = records["machines"][0]
    remade = {**first, "run": golden.TINY, "actor_sha256": "0" * 64}
    updated = golden.with_record(remade, records)
    assert len(updated["machines"]) == len(records["machines"])
    assert golden.record_for(remade, updated)["actor_sha256"] == "0" * 64
    other_cpu = {**remade, "cpu": {**first["cpu"], "model": "Some Other CPU"}}
    assert len(golden.with_record(other_cpu, records)["machines"]) == len(records["machines"]) + 1
    with pytest.raises(ValueError, match="only the reproducible mode's tiny run"):
        golden.with_record({**remade, "run": {**golden.TINY, "mode": "default"}}, records)
    a, b = {"primitives": {"exp": "1", "gemm": "2"}}, {"primitives": {"exp": "1", "gemm": "3", "sin": "4"}}
    assert golden.differing_primitives(a, b) == ["gemm"]
    assert golden.differing_primitives(a, {"primitives": None}) == []


def test_the_hashes_see_every_parameter_and_every_loss():
    state = {"a": torch.zeros(2), "b": torch.ones(3)}
    one_ulp = {**state, "b": torch.ones(3).nextafter(torch.full((3,), 2.0))}
    renamed = {"a": torch.zeros(2), "c": torch.ones(3)}
    assert golden.tensors_sha256(state) == golden.tensors_sha256(dict(reversed(list(state.items()))))
    assert len({golden.tensors_sha256(s) for s in (state, one_ulp, renamed)}) == 3
    curve = [dict.fromkeys(golden.LOSS_TERMS, 0.5) for _ in range(2)]
    nudged = [curve[0], {**curve[1], "entropy": 0.5 + 2 ** -40}]
    assert golden.losses_sha256(curve) != golden.losses_sha256(nudged)


def test_the_mode_refuses_a_process_that_loaded_torch_unpinned():
    """This test process imported torch without ATEN_CPU_CAPABILITY=default: the mode says what is missing and
    changes nothing."""
    assert torch.backends.cpu.get_cpu_capability() != "DEFAULT" or "ATEN_CPU_CAPABILITY" in os.environ
    onednn, deterministic = torch.backends.mkldnn.enabled, torch.are_deterministic_algorithms_enabled()
    with pytest.raises(ValueError, match="ATEN_CPU_CAPABILITY") as error, reproducible.mode():
        pass
    assert "needs its environment set before torch is imported" in str(error.value)
    assert (torch.backends.mkldnn.enabled, torch.are_deterministic_algorithms_enabled()) == (onednn, deterministic)


@pytest.mark.parametrize("override, message", [
    ({"precision": "bfloat16"}, "precision must be 'float32' in reproducible mode"),
    ({"torch_threads": 2}, "torch_threads must be 1 in reproducible mode"),
])
def test_train_refuses_settings_that_depend_on_the_cpu(override, message, monkeypatch):
    def no_trainer(*args, **kwargs):
        raise AssertionError("a trainer was built before the settings were checked")
    monkeypatch.setattr("marl_render.baselines.training.MAPPO", no_trainer)
    hp = task_hyperparameters("spread", **{"precision": "float32", **override})
    with pytest.raises(ValueError, match=message):
        train("spread", updates=1, hyperparameters=hp, reproducible=True)


@pytest.mark.parametrize("args, message", [
    (["--precision", "bfloat16"], "--precision must be float32 with --reproducible"),
    (["--torch-threads", "2"], "--torch-threads must be 1 with --reproducible"),
    (["--torch-threads", "0"], "--torch-threads must be 1 with --reproducible"),
])
def test_the_command_refuses_settings_that_depend_on_the_cpu(args, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        run.parse_args(["--env", "spread", "--reproducible", *args])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_reproducible_takes_float32_by_default_and_default_mode_keeps_the_tasks_precision():
    assert run.parse_args(["--env", "spread", "--reproducible"]).precision == "float32"
    assert run.parse_args(["--env", "spread"]).precision is None  # the task's (bfloat16), as before


def test_the_command_called_from_python_refuses_an_unpinned_process(tmp_path, capsys, monkeypatch):
    def no_work(*args, **kwargs):
        raise AssertionError("worked in a process that is not pinned")
    monkeypatch.setattr(run, "evaluate", no_work)
    assert run.main(["--env", "spread", "--reproducible", "--out", str(tmp_path / "run"), *TINY]) == 2
    err = capsys.readouterr().err
    assert "--reproducible needs a process started with its environment" in err and "MKL_CBWR" in err
    assert not (tmp_path / "run").exists()


def test_cpu_names_the_model_its_flags_and_torchs_kernels():
    record = reproducible.cpu()
    with open("/proc/cpuinfo") as info:
        lines = info.read().splitlines()
    model = next(line.split(":", 1)[1].strip() for line in lines if line.startswith("model name"))
    flags = set(next(line.split(":", 1)[1] for line in lines if line.startswith("flags")).split())
    assert record == {"model": model, "flags": [f for f in reproducible.RELEVANT_FLAGS if f in flags],
                      "torch_cpu_capability": torch.backends.cpu.get_cpu_capability()}
    assert "avx2" in record["flags"]  # every machine of the project has it
    assert reproducible.describe(record).startswith(f"{model} (flags ")


def test_a_reproducible_command_records_its_mode_cpu_and_versions(tmp_path):
    """The command line restarts itself pinned: result.json says so, with the CPU, the arithmetic and every
    library's version."""
    out = tmp_path / "run"
    subprocess.run([sys.executable, "-m", "marl_render.baselines", "--env", "spread", "--reproducible", "--out",
                    str(out), *TINY], check=True, capture_output=True,
                   env={k: v for k, v in os.environ.items() if k not in reproducible.ENVIRONMENT})
    result = json.loads((out / "result.json").read_text())
    assert result["mode"] == "reproducible" and result["hyperparameters"]["precision"] == "float32"
    assert result["arithmetic"] == {"environment": reproducible.ENVIRONMENT, "onednn": False,
                                    "deterministic_algorithms": True, "torch_threads": 1}
    assert result["machine"]["cpu"] == {**reproducible.cpu(), "torch_cpu_capability": "DEFAULT"}
    assert set(result["versions"]) == {"marl_render", "torch", "torchrl", "tensordict", "numpy", "panda3d", "python"}
    assert "not installed" not in result["versions"].values()
    assert result["command"] == ("python -m marl_render.baselines --env spread --reproducible --out "
                                 + str(out) + " " + " ".join(TINY))
