"""`python -m marl_render.bench accuracy --quick`: files, sweeps, and errors that behave.

Speed is never asserted (benchmarks measure it); only that costs are positive and finite,
and that the errors order the way numerics says they must.
"""
from __future__ import annotations

import json
import math
import warnings

import pytest
import torch

from marl_render.bench import __main__ as bench
from marl_render.bench import accuracy, accuracy_report

warnings.filterwarnings("ignore", message="The given NumPy array is not writable")

SWEEPS = ("image", "effects", "precision", "spread_physics", "cartpole_physics", "cartpole_energy")


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("accuracy")
    assert bench.main(["accuracy", "--quick", "--json", "--out", str(out)]) == 0
    with open(out / "accuracy.json") as f:
        return out, json.load(f)  # strict JSON: written with allow_nan=False


def _finite_numbers(value, path="result"):
    """Every number in the JSON is finite (None stands for an infinite PSNR)."""
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _finite_numbers(item, f"{path}.{key}")
    elif isinstance(value, list):
        for index, item in enumerate(value):
            yield from _finite_numbers(item, f"{path}[{index}]")
    elif isinstance(value, float) and not math.isfinite(value):
        yield path


def _point(points, **match):
    found = [p for p in points if all(p[k] == v for k, v in match.items())]
    assert len(found) == 1, (match, found)
    return found[0]


def test_writes_the_three_files(report):
    out, result = report
    for name in ("accuracy.md", "accuracy.json", "accuracy.png"):
        assert (out / name).stat().st_size > 0, name
    assert (out / "accuracy.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    markdown = (out / "accuracy.md").read_text()
    assert "## Recommendations" in markdown and "Pareto front" in markdown
    for recommendation in result["recommendations"]:
        assert recommendation in markdown


def test_json_has_every_sweep_with_finite_numbers(report):
    _, result = report
    assert set(SWEEPS) <= set(result["sweeps"])
    assert list(_finite_numbers(result)) == []
    for name in SWEEPS:
        points = result["sweeps"][name]["points"]
        assert points, name
        for p in points:
            assert p["cost_s"] > 0 and p["error"] >= 0, (name, p)
    settings = result["settings"]
    image = result["sweeps"]["image"]
    measured = {(p["resolution"], p["aa"]) for p in image["points"]}
    skipped = {(k["resolution"], k["aa"]) for k in image["skipped"]}
    assert measured | skipped == {(r, aa) for r in settings["resolutions"] for aa in settings["image_aa"]}
    assert not measured & skipped
    assert {(r, aa) for r in settings["resolutions"] for aa in ("none", "ss2x2", "ss4x4", "msaa4", "ss8x8")} <= measured
    effects = {p["effects"] for p in result["sweeps"]["effects"]["points"]}
    assert effects == {"+".join(e) or "none" for e in accuracy.EFFECT_SETS}


def test_reference_against_itself_is_exact(report):
    """A second renderer at 8x8 supersampling reproduces the reference bit for bit: zero error,
    infinite PSNR (the renderer draws its groups in a fixed order, so depth-test ties between
    touching surfaces resolve the same way in every renderer)."""
    _, result = report
    for p in result["sweeps"]["image"]["points"]:
        if p["aa"] == accuracy.REFERENCE_AA:
            assert p["reference"] and not p["pareto"]
            assert p["psnr_db"] is None and p["mae"] == 0 and p["max_abs"] == 0 and p["pixels_changed"] == 0, p
        else:
            assert not p["reference"] and p["psnr_db"] is not None and p["psnr_db"] > 0
    image = torch.full((1, 1, 4, 4, 3), 7, dtype=torch.uint8)
    identical = accuracy.image_error(image, image.clone())
    assert identical["psnr_db"] is None and identical["mae"] == 0


def test_supersampling_lowers_the_error(report):
    _, result = report
    points = result["sweeps"]["image"]["points"]
    for resolution in result["settings"]["resolutions"]:
        none = _point(points, resolution=resolution, aa="none")
        assert none["mae"] > 0
        assert _point(points, resolution=resolution, aa="ss4x4")["mae"] < none["mae"]
        assert _point(points, resolution=resolution, aa="msaa4")["mae"] < none["mae"]
    for p in result["sweeps"]["effects"]["points"]:
        if p["aa"] == "ss2x2":
            assert p["mae"] < _point(result["sweeps"]["effects"]["points"], effects=p["effects"], aa="none")["mae"]


def test_more_substeps_lower_the_state_error(report):
    _, result = report
    spread = result["sweeps"]["spread_physics"]
    # spread's config refuses 1 substep (no-tunnelling bound): reported, not measured
    assert {(k["integrator"], k["substeps"]) for k in spread["skipped"]} == {
        (i, 1) for i in accuracy.SPREAD_INTEGRATORS}
    for name, integrators in (("spread_physics", accuracy.SPREAD_INTEGRATORS),
                              ("cartpole_physics", accuracy.CARTPOLE_INTEGRATORS),
                              ("cartpole_energy", accuracy.CARTPOLE_INTEGRATORS)):
        points = result["sweeps"][name]["points"]
        for integrator in integrators:
            series = sorted((p for p in points if p["integrator"] == integrator), key=lambda p: p["substeps"])
            fewest, most = series[0], series[-1]
            assert most["substeps"] == 16 and fewest["substeps"] < most["substeps"]
            assert most["error"] < fewest["error"] / 4, (name, integrator, fewest, most)
    cartpole = result["sweeps"]["cartpole_physics"]["points"]
    orders = {i: accuracy_report.observed_order([p for p in cartpole if p["integrator"] == i])
              for i in accuracy.CARTPOLE_INTEGRATORS}
    assert orders["semi_implicit_euler"] == pytest.approx(1, abs=0.3)
    assert orders["velocity_verlet"] == pytest.approx(2, abs=0.3)
    assert orders["rk4"] == pytest.approx(4, abs=0.5)


def test_float64_survives_far_from_the_origin_and_float32_does_not(report):
    _, result = report
    points = result["sweeps"]["precision"]["points"]
    far = max(p["offset_m"] for p in points)
    assert far >= 1e7
    for p in points:
        if p["positions"] == "float64":
            assert p["mae"] < 0.01 and p["pixels_changed"] < 1e-3, p
    f32 = _point(points, offset_m=far, positions="float32")
    assert f32["float32_spacing_m"] >= 1.0
    assert f32["mae"] > 1.0 and f32["pixels_changed"] > 0.02


def test_pareto_front_is_consistent(report):
    _, result = report
    for name in SWEEPS:
        sweep = result["sweeps"][name]
        if name == "precision":
            continue
        group = sweep.get("group")
        points = [p for p in sweep["points"] if not p.get("reference")]
        assert any(p["pareto"] for p in points), name
        for p in points:
            rivals = [q for q in points if q is not p and (group is None or q[group] == p[group])]
            dominated = any(q["cost_s"] <= p["cost_s"] and q["error"] <= p["error"]
                            and (q["cost_s"] < p["cost_s"] or q["error"] < p["error"]) for q in rivals)
            assert p["pareto"] == (not dominated), (name, p["label"])
        # the cheapest and the most accurate points are always on the front
        if group is None:
            assert min(points, key=lambda p: (p["cost_s"], p["error"]))["pareto"]
            assert min(points, key=lambda p: (p["error"], p["cost_s"]))["pareto"]


def test_pareto_flags_and_observed_order_helpers():
    points = [{"cost_s": 1, "error": 5}, {"cost_s": 2, "error": 1}, {"cost_s": 3, "error": 1},
              {"cost_s": 1, "error": 6}, {"cost_s": 9, "error": 0, "reference": True}]
    accuracy.pareto_flags(points)
    assert [p["pareto"] for p in points] == [True, True, False, False, False]
    series = [{"substeps": s, "error": 3.0 * s ** -2} for s in (1, 2, 4, 8)]
    assert accuracy_report.observed_order(series) == pytest.approx(2.0)


def test_shadow_sweep_covers_every_map_and_finer_maps_err_less(report):
    _, result = report
    settings, points = result["settings"], result["sweeps"]["shadows"]["points"]
    assert {(p["shadow_map"], p["pcf"]) for p in points} == {(None, False)} | {
        (m, pcf) for m in settings["shadow_maps"] for pcf in (False, True)}
    for p in points:
        assert p["cost_s"] > 0 and p["error"] >= 0, p
    coarse, fine = min(settings["shadow_maps"]), max(settings["shadow_maps"])
    for pcf in (False, True):
        assert _point(points, shadow_map=fine, pcf=pcf)["mae"] < _point(points, shadow_map=coarse, pcf=pcf)["mae"]
