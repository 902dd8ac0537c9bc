"""``report.html`` of a diagnosis: one self-contained page, matplotlib figures embedded as base64 PNG."""

from __future__ import annotations

import base64
import html
import io
from typing import TYPE_CHECKING, Any

import numpy as np

from image2sim_common.rotations import quat_angle_rad

if TYPE_CHECKING:
    from grounder.diagnosis.result import Diagnosis


def _png(fig: Any) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return f'<img src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}"/>'


def _bars(ax: Any, before: dict[str, float], after: dict[str, float], title: str) -> None:
    keys = list(before)
    x = np.arange(len(keys))
    ax.bar(x - 0.2, [before[k] for k in keys], 0.4, label="nominal")
    ax.bar(x + 0.2, [after.get(k, np.nan) for k in keys], 0.4, label="with selected effects")
    ax.set_xticks(x, keys, rotation=30, ha="right")
    ax.set_title(title)
    ax.set_ylabel("gap (robust normalised RMS)")
    ax.legend(fontsize=8)


def render_report(diag: Diagnosis) -> str:
    """The HTML report: gap by body, coordinate, phase and time; real vs simulated; the effect ranking."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    gap, after = diag.gap, diag.gap["after_selected"]["short_horizon"]
    figs = []
    pairs = {k: v["gap"] for k, v in gap.get("by_pair", {}).items()}
    pairs_after = {k: v["gap"] for k, v in after.get("by_pair", {}).items()}
    fig, axes = plt.subplots(1, 4 if pairs else 3, figsize=(20 if pairs else 15, 3.8))
    _bars(axes[0], gap["by_body"], after["by_body"], "gap by body (short horizon)")
    _bars(axes[1], gap["by_coordinate"], after["by_coordinate"], "gap by coordinate")
    _bars(axes[2], gap["by_phase"], after["by_phase"], "gap by phase")
    if pairs:
        _bars(axes[3], pairs, pairs_after, "gap by contact pair (while touching)")
    figs.append(_png(fig))

    fig, ax = plt.subplots(figsize=(7, 3.5))
    for label, entry in (("short horizon, nominal", gap), ("short horizon, diagnosed", after)):
        ax.plot([p["t_s"] for p in entry["by_time"]], [p["gap"] for p in entry["by_time"]], "o-", label=label)
    for label, entry in (
        ("open loop, nominal", gap["open_loop"]),
        ("open loop, diagnosed", diag.gap["after_selected"]["open_loop"]),
    ):
        ax.plot([p["t_s"] for p in entry["by_time"]], [p["gap"] for p in entry["by_time"]], "--", label=label)
    ax.set_xlabel("time since start of trajectory (s)")
    ax.set_ylabel("gap")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    ax.set_title("gap over time")
    figs.append(_png(fig))

    effects = diag.effects
    if effects:
        fig, ax = plt.subplots(figsize=(7, 0.35 * len(effects) + 1))
        y = np.arange(len(effects))[::-1]
        red = np.array([e.heldout_reduction for e in effects])
        lo = np.array([e.ci[0] for e in effects])
        hi = np.array([e.ci[1] for e in effects])
        colors = ["tab:green" if e.key in diag.selected else "tab:gray" for e in effects]
        ax.barh(y, red, color=colors)
        ax.errorbar(red, y, xerr=[red - lo, hi - red], fmt="none", ecolor="black", capsize=3)
        ax.set_yticks(y, [f"{e.key} ({e.kind})" for e in effects])
        ax.axvline(0, color="black", lw=0.8)
        ax.set_xlabel("held-out gap reduction, alone (95% bootstrap interval); green = selected")
        ax.set_title("effect ranking")
        figs.append(_png(fig))

    for item in diag.figures.get("trajectories", []):
        groups = diag.figures["groups"]
        fig, axes = plt.subplots(1, len(groups), figsize=(4.5 * len(groups), 3.2), squeeze=False)
        for ax, g in zip(axes[0], groups, strict=False):
            if g.kind == "rotation":
                # Orientation: the geodesic angle between simulated and real (q and -q are the same rotation).
                for key, style, label in (("before", "r-", "nominal"), ("after", "g-", "diagnosed")):
                    angle = quat_angle_rad(item[key][:, g.index], item["real"][:, g.index])
                    ax.plot(item["time_s"], np.rad2deg(angle), style, lw=1, label=label)
                ax.set_ylabel("rotation error (deg)")
            for k, col in enumerate(g.index if g.kind != "rotation" else []):
                ax.plot(item["time_s"], item["real"][:, col], "k.", ms=2, label="real" if k == 0 else None)
                ax.plot(item["time_s"], item["before"][:, col], "r-", lw=1, label="nominal" if k == 0 else None)
                ax.plot(item["time_s"], item["after"][:, col], "g-", lw=1, label="diagnosed" if k == 0 else None)
            ax.set_title(f"{item['name']}: {g.label}")
            ax.set_xlabel("s")
            ax.legend(fontsize=7)
        figs.append(_png(fig))

    rows = "".join(
        f"<tr><td>{html.escape(e.key)}</td><td>{html.escape(e.kind)}</td>"
        f"<td>{html.escape(', '.join(f'{k}={v:.4g}' for k, v in e.params.items()))}</td>"
        f"<td>{e.heldout_gap_before:.4f}</td><td>{e.heldout_gap_after:.4f}</td>"
        f"<td>{e.heldout_reduction:.1%}</td><td>[{e.ci[0]:.1%}, {e.ci[1]:.1%}]</td></tr>"
        for e in effects
    )
    held = diag.heldout
    summary = diag.to_json()["finding"]
    by_body = "".join(
        f"<tr><td>{html.escape(str(step['effect']))}</td><td>{html.escape(body)}</td><td>{v['before']:.4f}</td>"
        f"<td>{v['after']:.4f}</td><td>{v['reduction']:.1%}</td></tr>"
        for step in diag.steps
        for body, v in step.get("heldout_by_body", {}).items()
    )
    per_body = (
        "<h2>Reduction per body (held-out, each selected effect)</h2><table><tr><th>effect</th><th>body</th>"
        f"<th>before</th><th>after</th><th>reduction</th></tr>{by_body}</table>"
        if by_body and len(diag.gap["by_body"]) > 1
        else ""
    )
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>Gap diagnosis</title>
<style>body{{font-family:sans-serif;max-width:1400px;margin:auto}}td,th{{padding:2px 8px;text-align:right}}</style>
</head><body>
<h1>Sim-to-real gap diagnosis</h1>
<p><b>{html.escape(summary)}</b></p>
<p>Selected (in order): {html.escape(", ".join(diag.selected) or "none")}. Held-out gap {held["gap_before"]:.4f} &rarr;
{held["gap_after"]:.4f} (reduction {held["reduction"]:.1%}); unexplained fraction {diag.unexplained_fraction:.1%}.</p>
<p>Metric: {html.escape(diag.gap_metric)}.</p>
<h2>Where</h2>{figs[0]}{figs[1]}
<h2>Which</h2>{figs[2] if len(figs) > 2 else ""}
<table><tr><th>effect</th><th>kind</th><th>params</th><th>before</th><th>after</th><th>reduction</th>
<th>95% CI</th></tr>
{rows}</table>
{per_body}
<h2>Real vs simulated (held-out, open loop)</h2>{"".join(figs[3:])}
</body></html>"""
