"""The report of `python -m marl_render.bench accuracy`: recommendations, tables and plot.

Everything here reads only the result dict that the sweeps of marl_render.bench.accuracy
produce (the content of accuracy.json): recommendations phrased from the numbers,
accuracy.md (one markdown table per sweep) and accuracy.png (error against time, Pareto
fronts circled).
"""
from __future__ import annotations

import math
import os

import numpy as np
from tabulate import tabulate

from .common import write_report
from .figures import pyplot

# Display names of the integrators (point labels, progress and recommendations).
SHORT = {"semi_implicit_euler": "SIE", "velocity_verlet": "Verlet", "rk4": "RK4"}
# Thresholds the recommendations are phrased against (the answers come from the data).
SPREAD_TARGETS_M = (1e-2, 1e-3)
CARTPOLE_TARGETS = (1e-3, 1e-6)


def observed_order(points: list, floor: float = 1e-12):
    """Least-squares slope of -log(error) against log(substeps) (errors above `floor`)."""
    pairs = [(math.log(p["substeps"]), math.log(p["error"])) for p in points if p["error"] > floor]
    if len({x for x, _ in pairs}) < 2:
        return None
    xs, ys = zip(*pairs, strict=True)
    return -float(np.polyfit(xs, ys, 1)[0])


# ============================================================================ recommendations
def _fmt_cost(seconds: float) -> str:
    return f"{seconds * 1e6:,.1f} µs" if seconds < 1e-3 else f"{seconds * 1e3:,.2f} ms"


def recommendations(result: dict) -> list:
    sweeps = result["sweeps"]
    out = []
    image = [p for p in sweeps["image"]["points"] if not p["reference"]]
    if image:
        front = sorted((p for p in image if p["pareto"]), key=lambda p: p["cost_s"])
        out.append("Images, all resolutions and anti-aliasing modes (time per view vs MAE against the 8x8 reference "
                   "at the same resolution): the Pareto front, cheapest first, is "
                   + ", ".join(f"{p['resolution']}x{p['resolution']} {p['aa']}" for p in front) + ".")
        halving = {}
        for resolution in sorted({p["resolution"] for p in image}):
            same = [p for p in image if p["resolution"] == resolution]
            none = next((p for p in same if p["aa"] == "none"), None)
            if none is None:
                continue
            good = sorted((p for p in same if p["aa"] != "none" and p["error"] <= none["error"] / 2),
                          key=lambda p: p["cost_s"])
            if good:
                p = good[0]
                halving.setdefault(p["aa"], []).append(resolution)
                out.append(f"At {resolution}x{resolution} the cheapest mode that at least halves the no-AA error is "
                           f"{p['aa']}: MAE {none['error']:.2f} -> {p['error']:.2f} for "
                           f"{p['cost_s'] / none['cost_s']:.1f}x the time per view.")
            else:
                out.append(f"At {resolution}x{resolution} no anti-aliasing mode halves the no-AA error "
                           f"(MAE {none['error']:.2f}).")
        concentrated = [p for p in image if p["aa"] == "none" and p["worst_row_share"] >= 0.25]
        if concentrated:
            out.append("Without AA, one image row holds much of the error at "
                       + ", ".join(f"{p['resolution']} px (row {p['worst_row']}: {p['worst_row_share']:.0%})"
                                   for p in concentrated)
                       + ": a horizontal edge at the same height in every view, so the no-AA error depends on where "
                         "that edge falls inside a pixel row and is not monotonic in resolution.")
        if halving:
            best = max(halving, key=lambda k: len(halving[k]))
            out.append(f"Overall: {best} is the cheapest way to halve aliasing error at "
                       f"{len(halving[best])} of {len({p['resolution'] for p in image})} resolutions.")
    references = [p for p in sweeps["image"]["points"] if p["reference"]]
    differing = [p for p in references if p["max_abs"] > 0]
    if references and not differing:
        out.append("A second renderer reproduced the 8x8 reference bit for bit at every resolution.")
    for p in differing:
        out.append(f"A second renderer did not reproduce the 8x8 reference exactly at {p['resolution']} px: "
                   f"{p['pixels_changed']:.4%} of pixels differ, by up to {p['max_abs']:.0f} level(s) (renders of "
                   "one state by two renderers are not always bit-identical).")
    for aa in dict.fromkeys(k["aa"] for k in sweeps["image"]["skipped"]):
        skips = [k for k in sweeps["image"]["skipped"] if k["aa"] == aa]
        out.append(f"{aa} not measured at {', '.join(str(k['resolution']) for k in skips)} px: {skips[0]['reason']}.")
    effects = sweeps["effects"]["points"]
    none_aa = [p for p in effects if p["aa"] == "none"]
    if none_aa:
        base = next((p for p in none_aa if p["effects"] == "none"), None)
        parts = [f"{p['effects']} {p['cost_vs_no_effect']:+.0%} time, MAE {p['error']:.2f}" for p in none_aa
                 if p is not base and p["cost_vs_no_effect"] is not None]
        if base is not None:
            out.append(f"Effects at {base['resolution']}px without AA (no effect: MAE {base['error']:.2f}): "
                       + "; ".join(parts) + ".")
        worst = max(none_aa, key=lambda p: p["error"])
        fixes = sorted((p for p in effects if p["effects"] == worst["effects"] and p["aa"] != "none"),
                       key=lambda p: p["error"])
        if fixes:
            out.append(f"The effect set with the most aliasing is {worst['effects']} (MAE {worst['error']:.2f}); "
                       f"{fixes[0]['aa']} brings it to {fixes[0]['error']:.2f} at "
                       f"{fixes[0]['cost_s'] / worst['cost_s']:.1f}x the time.")
    precision = sweeps["precision"]["points"]
    if precision:
        f64 = [p for p in precision if p["positions"] == "float64"]
        f32 = sorted((p for p in precision if p["positions"] == "float32"), key=lambda p: p["offset_m"])
        worst64 = max(f64, key=lambda p: p["error"])
        first_bad = next((p for p in f32 if p["pixels_changed"] > 1e-3), None)
        far = f32[-1]
        text = (f"Precision: with float64 positions the worst error up to {max(p['offset_m'] for p in f64):.0e} m is "
                f"MAE {worst64['error']:.3f} ({worst64['pixels_changed']:.2%} of pixels changed); positions cast "
                f"to float32 first reach MAE {far['error']:.1f} at {far['offset_m']:.0e} m "
                f"({far['pixels_changed']:.0%} of pixels changed, float32 spacing {far['float32_spacing_m']:g} m)")
        text += (f"; float32 already changes {first_bad['pixels_changed']:.1%} of pixels at "
                 f"{first_bad['offset_m']:.0e} m "
                 f"(MAE {first_bad['error']:.2f}, worst pixel off by {first_bad['max_abs']:.0f})" if first_bad else "")
        out.append(text + ". Keep world positions in float64 up to BatchRenderer.update (it recentres and splits "
                          "them); never cast them to float32 before.")
    for key, targets, unit, what in (("spread_physics", SPREAD_TARGETS_M, "m", "position"),
                                     ("cartpole_physics", CARTPOLE_TARGETS, "(m, rad)", "(x, θ)"),
                                     ("cartpole_energy", None, "J", "energy drift")):
        sweep = sweeps[key]
        points = sweep["points"]
        if not points:
            continue
        name = key.replace("_", " ")
        orders = {i: observed_order([p for p in points if p["integrator"] == i])
                  for i in dict.fromkeys(p["integrator"] for p in points)}
        out.append(f"{name}: observed convergence order in substeps "
                   + ", ".join(f"{SHORT[i]} {o:.1f}" for i, o in orders.items() if o is not None) + ".")
        first = next(iter(orders))
        ratios = []
        for integrator in list(orders)[1:]:  # error ratio to the first integrator at equal substeps
            pairs = [(p["error"], q["error"]) for p in points for q in points if p["integrator"] == integrator
                     and q["integrator"] == first and p["substeps"] == q["substeps"] and q["error"] > 0]
            if pairs:
                low, high = min(a / b for a, b in pairs), max(a / b for a, b in pairs)
                ratios.append(f"{SHORT[integrator]} {low:.2g}-{high:.2g}x")
        if ratios:
            out.append(f"{name}: error relative to {SHORT[first]} at the same substeps: " + ", ".join(ratios) + ".")
        default = next((p for p in points if p.get("default")), None)
        if default is not None:
            dominated = [p for p in points if p is not default and p["cost_s"] <= default["cost_s"]
                         and p["error"] < default["error"]]
            text = (f"{name}: the env's setting ({SHORT[default['integrator']]} x{default['substeps']}) has "
                    f"{what} error {default['error']:.2e} {unit} at {_fmt_cost(default['cost_s'])} per world-step")
            text += ("; it is on the Pareto front" if default["pareto"] else
                     f"; it is dominated by {', '.join(p['label'] for p in dominated) or 'another point'}")
            out.append(text + ".")
        for target in targets or ():
            fit = sorted((p for p in points if p["error"] <= target), key=lambda p: p["cost_s"])
            if fit:
                out.append(f"{name}: cheapest setting with {what} error <= {target:g} {unit}: {fit[0]['label']} "
                           f"({fit[0]['error']:.2e}, {fit[0]['world_steps_per_s']:,.0f} world-steps/s).")
            else:
                out.append(f"{name}: no tested setting reaches {what} error <= {target:g} {unit}.")
        front = sorted((p for p in points if p["pareto"]), key=lambda p: p["cost_s"])
        out.append(f"{name}: Pareto front, cheapest first: " + ", ".join(p["label"] for p in front) + ".")
        if sweep["skipped"]:
            out.append(f"{name}: " + ", ".join(f"{SHORT[k['integrator']]} x{k['substeps']}" for k in sweep["skipped"])
                       + f" not run: {sweep['skipped'][0]['reason']}.")
    return out



# ============================================================================ accuracy.md
def _table(headers: list, rows: list, floatfmt: list, missingval="∞") -> list:
    """Markdown table lines; numbers formatted per column, None shown as `missingval` (by default
    ∞: the PSNR of identical images)."""
    return tabulate(rows, headers, tablefmt="pipe", floatfmt=floatfmt, missingval=missingval).splitlines()


def _pareto(point: dict) -> str:
    return "**yes**" if point.get("pareto") else ""


def write(out: str, result: dict) -> None:
    """accuracy.md, accuracy.json and accuracy.png into `out`."""
    s, m, settings = result["sweeps"], result["machine"], result["settings"]
    lines = ["# Accuracy against cost", "",
             f"{m['gl_renderer']}, torch {m['torch']} ({m['cpu_threads']} thread), seed {result['seed']}, "
             f"{'quick' if result['quick'] else 'full'} run of {result['seconds']:.0f} s. Costs are measured in the "
             f"same run as the errors: renders as the fastest of {settings['rounds']} round-robin passes "
             "over the settings (each the median frame time), physics as the fastest of "
             f"{settings['physics_rounds']} round-robin passes of identical rollouts "
             f"({settings['energy_rounds']} for energy drift). The machine is shared: compare within a "
             "table. PSNR ∞ = identical images.", "",
             "## Recommendations (derived from the numbers below)", ""]
    lines += [f"- {r}" for r in result["recommendations"]]

    lines += ["", "## Resolution x anti-aliasing", "", s["image"]["what"] + ".", ""]
    lines += _table(["resolution", "AA", "views/s", "µs/view", "MAE", "PSNR dB", "max abs", "px changed",
                     "worst row (share)", "Pareto", "front at res"],
                    [[p["resolution"], p["aa"] + (" (reference)" if p["reference"] else ""), p["views_per_s"],
                      p["cost_s"] * 1e6, p["mae"], p["psnr_db"], p["max_abs"], p["pixels_changed"],
                      f"{p['worst_row']} ({p['worst_row_share']:.0%})", _pareto(p),
                      "yes" if p["pareto_at_resolution"] else ""] for p in s["image"]["points"]],
                    ["", "", ",.0f", ",.1f", ".3f", ".2f", ".0f", ".1%", "", "", ""])
    for aa in dict.fromkeys(k["aa"] for k in s["image"]["skipped"]):
        skips = [k for k in s["image"]["skipped"] if k["aa"] == aa]
        resolutions = ", ".join(str(k["resolution"]) for k in skips)
        lines += ["", f"Not measured: {aa} at {resolutions} px ({skips[0]['reason']})."]

    lines += ["", "## Effects", "", s["effects"]["what"] + ". Pareto front within each effect set.", ""]
    lines += _table(["effects", "AA", "views/s", "µs/view", "time vs no effect", "MAE", "PSNR dB", "px changed",
                     "Pareto"],
                    [[p["effects"], p["aa"], p["views_per_s"], p["cost_s"] * 1e6, p["cost_vs_no_effect"], p["mae"],
                      p["psnr_db"], p["pixels_changed"], _pareto(p)] for p in s["effects"]["points"]],
                    ["", "", ",.0f", ",.1f", "+.0%", ".3f", ".2f", ".1%", ""], ["", "", "", "", "", "", "∞", "", ""])

    lines += ["", "## Far from the origin: float64 vs float32 positions", "", s["precision"]["what"] + ".", ""]
    lines += _table(["offset (m)", "positions", "float32 spacing (m)", "views/s", "MAE", "PSNR dB", "max abs",
                     "px changed"],
                    [[p["offset_m"], p["positions"], p["float32_spacing_m"], p["views_per_s"], p["mae"], p["psnr_db"],
                      p["max_abs"], p["pixels_changed"]] for p in s["precision"]["points"]],
                    [".0e", "", "g", ",.0f", ".3f", ".2f", ".0f", ".2%"])

    if "shadows" in s:
        lines += ["", "## Shadows: shadow-map resolution", "", s["shadows"]["what"] + ".", ""]
        lines += _table(["shadow map (per world)", "PCF", "views/s", "µs/view", "time vs no shadows", "MAE",
                         "PSNR dB", "px changed"],
                        [["none" if p["shadow_map"] is None else f"{p['shadow_map']}x{p['shadow_map']}",
                          "" if p["shadow_map"] is None else "on" if p["pcf"] else "off", p["views_per_s"],
                          p["cost_s"] * 1e6, p["cost_vs_no_shadows"], p["mae"], p["psnr_db"], p["pixels_changed"]]
                         for p in s["shadows"]["points"]],
                        ["", "", ",.0f", ",.1f", "+.0%", ".3f", ".2f", ".1%"])

    sp = s["spread_physics"]
    lines += ["", "## Spread physics: substeps x integrator", "", sp["what"] + ".", ""]
    lines += _table(["integrator", "substeps", "world-steps/s", "µs/world-step", "pos RMS (m)", "pos max (m)",
                     "vel RMS (m/s)", "pos RMS vs own x64 (m)", "Pareto"],
                    [[p["integrator"] + (" (env default)" if p["default"] else ""), p["substeps"],
                      p["world_steps_per_s"], p["cost_s"] * 1e6, p["pos_rms_m"], p["pos_max_m"], p["vel_rms_m_s"],
                      p["pos_rms_vs_own_64_m"], _pareto(p)] for p in sp["points"]],
                    ["", "", ",.0f", ",.2f", ".2e", ".2e", ".2e", ".2e", ""])
    if sp["skipped"]:
        lines += ["", "Not run: " + "; ".join(f"{k['integrator']} x{k['substeps']}" for k in sp["skipped"])
                  + f" ({sp['skipped'][0]['reason']})."]

    cp = s["cartpole_physics"]
    lines += ["", "## Cart-pole physics: substeps x integrator", "", cp["what"] + ".", ""]
    lines += _table(["integrator", "substeps", "world-steps/s", "µs/world-step", "(x, θ) RMS", "(x, θ) max",
                     "state RMS", "Pareto"],
                    [[p["integrator"] + (" (env default)" if p["default"] else ""), p["substeps"],
                      p["world_steps_per_s"], p["cost_s"] * 1e6, p["q_rms"], p["q_max"], p["state_rms"], _pareto(p)]
                     for p in cp["points"]],
                    ["", "", ",.0f", ",.2f", ".2e", ".2e", ".2e", ""])

    ce = s["cartpole_energy"]
    lines += ["", "## Cart-pole energy drift (frictionless)", "", ce["what"] + ".", ""]
    lines += _table(["integrator", "substeps", "world-steps/s", "µs/world-step", "drift mean (J)", "drift max (J)",
                     "Pareto"],
                    [[p["integrator"], p["substeps"], p["world_steps_per_s"], p["cost_s"] * 1e6, p["drift_mean_j"],
                      p["drift_max_j"], _pareto(p)] for p in ce["points"]],
                    ["", "", ",.0f", ",.2f", ".2e", ".2e", ""])
    lines += ["", "![error against time](accuracy.png)", ""]
    write_report(out, "accuracy", result, lines, allow_nan=False)
    _plot(os.path.join(out, "accuracy.png"), result)


# ============================================================================ accuracy.png
def _plot(path: str, result: dict) -> None:
    plt = pyplot()

    s = result["sweeps"]
    fig, axes = plt.subplots(2, 3, figsize=(16, 9.5))
    panels = [("image", "aa", "resolution x anti-aliasing", "µs per view", 1e6, "MAE vs 8x8 reference (0-255)"),
              ("effects", "effects", "effects x anti-aliasing (front per effect set)", "µs per view", 1e6,
               "MAE vs 8x8 reference (0-255)"),
              ("spread_physics", "integrator", "spread physics: substeps", "µs per world-step", 1e6,
               "RMS position error (m)"),
              ("cartpole_physics", "integrator", "cart-pole physics: substeps", "µs per world-step", 1e6,
               "RMS (x, θ) error"),
              ("cartpole_energy", "integrator", "cart-pole energy drift (frictionless)", "µs per world-step", 1e6,
               "energy drift (J)")]
    # Five panels here; the sixth axis (precision) is drawn below.
    for ax, (key, series, title, xlabel, scale, ylabel) in zip(axes.flat, panels, strict=False):
        points = [p for p in s[key]["points"] if not p.get("reference") and p["error"] > 0]
        names = list(dict.fromkeys(p[series] for p in points))
        for index, name in enumerate(names):
            group = [p for p in points if p[series] == name]
            group.sort(key=lambda p: p["cost_s"] if series == "effects" else p.get("resolution", p.get("substeps", 0)))
            marker = "o" if series != "effects" else "os^vD"[index % 5]
            ax.plot([p["cost_s"] * scale for p in group], [p["error"] for p in group], marker=marker, ms=5,
                    lw=1, label=SHORT.get(name, name), color=f"C{index}")
            for p in group:
                tag = p.get("resolution", p.get("substeps"))
                if series == "effects":
                    tag = p["aa"]
                ax.annotate(str(tag), (p["cost_s"] * scale, p["error"]), fontsize=6, xytext=(3, 3),
                            textcoords="offset points")
        front = [p for p in points if p["pareto"]]
        ax.scatter([p["cost_s"] * scale for p in front], [p["error"] for p in front], s=120, facecolors="none",
                   edgecolors="k", linewidths=1.2, label="Pareto front", zorder=3)
        if s[key].get("group") is None and front:
            front.sort(key=lambda p: p["cost_s"])
            xs = [p["cost_s"] * scale for p in front]
            ys = [p["error"] for p in front]
            ax.step(xs, ys, where="post", color="k", lw=0.8, ls="--", zorder=2)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.25)
        ax.legend(fontsize=7)
    ax = axes.flat[5]
    for index, dtype in enumerate(("float64", "float32")):
        group = sorted((p for p in s["precision"]["points"] if p["positions"] == dtype), key=lambda p: p["offset_m"])
        # zero error cannot sit on a log axis: drawn at 1e-7, labelled so
        ax.plot([p["offset_m"] for p in group], [max(p["error"], 1e-7) for p in group], "o-", color=f"C{index}",
                label=f"{dtype} positions")
    ax.axhline(1e-7, color="grey", lw=0.5, ls=":")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_title("far from the origin (error 0 drawn at 1e-7)", fontsize=10)
    ax.set_xlabel("offset (m)")
    ax.set_ylabel("MAE vs the scene at the origin")
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=7)
    fig.suptitle("error against time (log scales; circled: Pareto front)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
