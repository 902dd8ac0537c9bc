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
    if result.distribution is not None and free:
        sections.append(_distribution_section(result, list(trajs)))
    return write_html_report(path, "Calibration report", sections)


_FAN_SAMPLES = 16
_MAX_SCORED = 200


def _distribution_section(result: CalibrationResult, trajs: list[Trajectory]) -> Section:
    """``--distribution``: the fitted marginals, sample fans against the recordings, and the reliability curve of
    sampled rollouts (as ``rollout --samples`` draws them) on the report's trajectories (the validation split)."""
    import matplotlib.pyplot as plt

    from grounder.sim.sample_scores import score_samples, summarise
    from grounder.sim.sampled import rollout_samples
    from grounder.sim.start_noise import perturbed_starts

    dist = result.distribution
    model = result.model
    params = dist.parameters(model)
    rows = dist.summary(params)
    table: list[list[object]] = [["parameter", "calibrated", "mean", "std", "5%", "95%", "unit"]]
    table += [
        [r["name"], _fmt(r["value"]), _fmt(r["mean"]), _fmt(r["std"]), _fmt(r["p05"]), _fmt(r["p95"]), r["unit"]]
        for r in rows
    ]
    rng = np.random.default_rng(0)
    scored = trajs[:_MAX_SCORED]
    models = dist.draw_models(model, _FAN_SAMPLES, rng)
    starts = [perturbed_starts(model, t.qpos[0], t.qvel[0], dist.start_noise, _FAN_SAMPLES, rng) for t in scored]
    fans = rollout_samples(models, scored, starts)
    scores = summarise([score_samples(model, t, q, v) for t, (q, v) in zip(scored, fans, strict=True)])
    figs = []
    values = dist.draw_values(params, 4000, np.random.default_rng(1))
    cols = min(4, len(params))
    nrows = -(-len(params) // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(3.4 * cols, 2.6 * nrows), squeeze=False)
    for i, p in enumerate(params):
        ax = axes[i // cols, i % cols]
        ax.hist(values[:, i], bins=40, color="tab:green", alpha=0.8)
        ax.axvline(float(p.from_unit(dist.point[i])), color="k")
        ax.set_title(f"{p.name} ({p.unit})", fontsize=8)
    for j in range(len(params), nrows * cols):
        axes[j // cols, j % cols].axis("off")
    fig.tight_layout()
    figs.append(fig)
    fj = sim.free_joints(model)[0]
    shown = list(range(min(_MAX_PLOTTED, len(scored))))
    if shown:
        fig, axes = plt.subplots(2, len(shown), figsize=(3.6 * len(shown), 5), squeeze=False)
        for col, b in enumerate(shown):
            traj, (qpos, _) = scored[b], fans[b]
            t = traj.time_s - traj.time_s[0]
            first = np.broadcast_to(traj.qpos[0, fj.quat], traj.qpos[:, fj.quat].shape)
            for k in range(len(qpos)):
                axes[0, col].plot(t, qpos[k, :, fj.pos][:, 2], color="tab:blue", alpha=0.25, lw=0.8)
                turn = np.degrees(sim.quat_angle_rad(qpos[k, :, fj.quat], first))
                axes[1, col].plot(t, turn, color="tab:blue", alpha=0.25, lw=0.8)
            axes[0, col].plot(t, traj.qpos[:, fj.pos][:, 2], "k", lw=1.5)
            axes[1, col].plot(t, np.degrees(sim.quat_angle_rad(traj.qpos[:, fj.quat], first)), "k", lw=1.5)
            axes[0, col].set_title(f"{traj.name}: height (m)", fontsize=9)
            axes[1, col].set_title("turn from the first frame (deg)", fontsize=9)
            axes[1, col].set_xlabel("time, s")
        fig.tight_layout()
        figs.append(fig)
    fig, ax = plt.subplots(figsize=(4.5, 4))
    ax.plot(scores["reliability_levels"], scores["reliability_position"], marker="o", label="position")
    ax.plot(scores["reliability_levels"], scores["reliability_rotation"], marker="o", label="rotation")
    ax.plot([0, 1], [0, 1], "k--", lw=0.8)
    ax.set_xlabel("central band level")
    ax.set_ylabel("share of recorded steps inside")
    ax.legend()
    fig.tight_layout()
    figs.append(fig)
    fit = dist.fit
    text = (
        f"Fitted by {dist.method} ({fit.get('iterations')} iterations x {fit.get('samples_per_iteration')} draws on "
        f"{fit.get('trajectories')} trajectories); centred on the calibrated values unless fitted (distribution.json "
        f"holds the Gaussian in search coordinates). Sampled rollouts ({_FAN_SAMPLES} per trajectory, starts "
        f"perturbed by the measured start noise) of {len(scored)} trajectories: 50% bands cover "
        f"{scores['coverage50_position']:.2f} (position) / {scores['coverage50_rotation']:.2f} (rotation) of the "
        f"recorded steps, 90% bands {scores['coverage90_position']:.2f} / {scores['coverage90_rotation']:.2f}; "
        f"energy score {scores['energy']:.4f}; best of {_FAN_SAMPLES}: {scores['best_position_pct']:.1f}% of size / "
        f"{scores['best_rotation_deg']:.1f} deg. Figures: the marginals (black: calibrated), fans (blue) against the "
        "recordings (black), reliability (a calibrated fan lies on the diagonal)."
    )
    return Section(title="Parameter distribution", text=text, table=table, figures=tuple(figs))


def _repeats_note(groups: list[list[str]]) -> str:
    """The copies of one motion the split kept together (`grounder.core.repeats`), or nothing when there were none."""
    return f" {describe_repeats(groups)}; each kept on one side of the split." if groups else ""
