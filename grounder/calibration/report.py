"""The calibration's HTML report: parameters with intervals, errors before/after per split, real vs simulated."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import mujoco
import numpy as np

import grounder.sim.rollout as sim
from grounder.core.html_report import Section, write_html_report
from grounder.core.repeats import describe_repeats
from grounder.core.trajectory import Trajectory

if TYPE_CHECKING:
    from grounder.calibration.result import CalibrationResult

_MAX_PLOTTED = 4


def _fmt(v: float) -> str:
    return f"{v:.4g}"


def write_report(path: Path, result: CalibrationResult, base: mujoco.MjModel, trajs: Sequence[Trajectory]) -> Path:
    """Writes ``report.html`` for a calibration; ``trajs`` are plotted (the first few validation trajectories)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sections: list[Section] = []
    table: list[list[object]] = [["parameter", "nominal", "calibrated", "interval", "bounds", "unit"]]
    for p in result.parameters:
        table.append(
            [
                p.name,
                _fmt(p.nominal),
                _fmt(p.value),
                f"[{_fmt(p.interval_low)}, {_fmt(p.interval_high)}]",
                f"[{_fmt(p.lower)}, {_fmt(p.upper)}]",
                p.unit,
            ]
        )
    sections.append(
        Section(
            title="Parameters",
            text=(
                f"Mode {result.mode}; {result.evaluations} rollouts in {result.seconds:.1f} s, "
                f"{result.steps_per_second:,.0f} model steps/s inside mujoco.rollout. Intervals: Gauss-Newton "
                "approximation at the optimum; a parameter the data does not constrain shows its whole bounds."
            ),
            table=table,
        )
    )

    err_table: list[list[object]] = [
        ["split", "trajectories", "position % of size, before", "after", "rotation deg, before", "after"]
    ]
    for split, before in result.before.items():
        after = result.after[split]
        err_table.append(
            [
                split,
                len(before.names),
                f"{before.position_pct.mean():.1f} ± {before.position_pct.std():.1f}",
                f"{after.position_pct.mean():.1f} ± {after.position_pct.std():.1f}",
                f"{before.rotation_deg.mean():.1f} ± {before.rotation_deg.std():.1f}",
                f"{after.rotation_deg.mean():.1f} ± {after.rotation_deg.std():.1f}",
            ]
        )
    figs = []
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
    for ax, key, label in (
        (axes[0], "position_pct", "position error, % of size"),
        (axes[1], "rotation_deg", "rotation error, deg"),
    ):
        for split, before in result.before.items():
            after = result.after[split]
            ax.scatter(getattr(before, key), getattr(after, key), s=10, label=split)
        hi = max(
            [float(np.max(getattr(s, key), initial=1.0)) for s in (*result.before.values(), *result.after.values())]
        )
        ax.plot([0, hi], [0, hi], "k--", lw=0.8)
        ax.set_xlabel(f"before: {label}")
        ax.set_ylabel("after")
        ax.legend()
    fig.tight_layout()
    figs.append(fig)
    if len(result.history) > 1:
        fig, ax = plt.subplots(figsize=(6, 3))
        ax.plot(result.history, marker=".")
        ax.set_xlabel("search step (DE generations, then least-squares iterations)")
        ax.set_ylabel("training loss")
        fig.tight_layout()
        figs.append(fig)
    sections.append(
        Section(
            title="Errors",
            text="Open-loop from each trajectory's first recorded state; time-average per trajectory, mean ± std."
            + _repeats_note(result.extra.get("repeated_trajectories", [])),
            table=err_table,
            figures=tuple(figs),
        )
    )

    shown = list(trajs)[:_MAX_PLOTTED]
    free = sim.free_joints(base)
    if shown:
        pred_before: list[Trajectory] = sim.simulate(base, shown)  # type: ignore[assignment]
        pred_after: list[Trajectory] = sim.simulate(result.model, shown)  # type: ignore[assignment]
        figs = []
        for k, traj in enumerate(shown):
            fig, axes = plt.subplots(1, 2, figsize=(11, 3.2))
            t = traj.time_s - traj.time_s[0]
            if free:
                fj = free[0]
                for axis_i, c in zip(range(3), "rgb", strict=True):
                    axes[0].plot(t, traj.qpos[:, fj.pos][:, axis_i], c, lw=2, alpha=0.4)
                    axes[0].plot(t, pred_before[k].qpos[:, fj.pos][:, axis_i], c + ":", lw=1)
                    axes[0].plot(t, pred_after[k].qpos[:, fj.pos][:, axis_i], c + "-", lw=1)
                axes[0].set_ylabel(f"{fj.body} x/y/z, m")
                axes[0].set_title(f"{traj.name}: real (thick), before (dotted), after (thin)")
                axes[1].plot(
                    t,
                    np.degrees(sim.quat_angle_rad(pred_before[k].qpos[:, fj.quat], traj.qpos[:, fj.quat])),
                    ":",
                    label="before",
                )
                axes[1].plot(
                    t,
                    np.degrees(sim.quat_angle_rad(pred_after[k].qpos[:, fj.quat], traj.qpos[:, fj.quat])),
                    label="after",
                )
                axes[1].set_ylabel("rotation error, deg")
                axes[1].legend()
            else:
                axes[0].plot(t, traj.qpos, lw=2, alpha=0.4)
                axes[0].plot(t, pred_before[k].qpos, ":")
                axes[0].plot(t, pred_after[k].qpos, "-")
                axes[0].set_ylabel("qpos")
                axes[1].plot(t, np.abs(pred_after[k].qpos - traj.qpos))
                axes[1].set_ylabel("|error| after")
            for ax in axes:
                ax.set_xlabel("time, s")
            fig.tight_layout()
            figs.append(fig)
        sections.append(Section(title="Real vs simulated", figures=tuple(figs)))
    return write_html_report(path, "Calibration report", sections)


def _repeats_note(groups: list[list[str]]) -> str:
    """The copies of one motion the split kept together (`grounder.core.repeats`), or nothing when there were none."""
    return f" {describe_repeats(groups)}; each kept on one side of the split." if groups else ""
