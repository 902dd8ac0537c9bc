"""The residual's HTML report: what the gain check chose and why, held-out rollouts with and without the residual,
and where its safety gate lets it act.

``train_residual`` writes it into the residual scene folder as ``report.html`` (one self-contained file).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from grounder.core.html_report import Section, write_html_report
from grounder.core.trajectory import Trajectory
from grounder.residual.free_body import free_bodies
from grounder.residual.joint import joint_error, joint_space
from grounder.sim.rollout import free_body_errors, free_joints
from image2sim_common.rotations import quat_angle_rad

_MAX_PLOTTED = 4


@dataclass(frozen=True, kw_only=True)
class RolloutErrors:
    """Per trajectory time-averaged open-loop errors of one model, each averaged over the scene's free bodies.

    Attributes:
        position_pct: (N,) position error in % of the body size (a cube's width); free bodies, else empty.
        rotation_deg: (N,) rotation error in degrees; free bodies, else empty.
        joint_error: (N,) mean joint error (rad for hinges, m for slides); scenes without free bodies, else empty.
    """

    position_pct: np.ndarray
    rotation_deg: np.ndarray
    joint_error: np.ndarray

    def scores(self) -> np.ndarray:
        """(N,) the gain check's score per trajectory: position / body size + rotation / 100 deg, or joint error."""
        if self.joint_error.size:
            return self.joint_error
        return self.position_pct / 100.0 + self.rotation_deg / 100.0


def rollout_errors(model: mujoco.MjModel, preds: Sequence[Trajectory], real: Sequence[Trajectory]) -> RolloutErrors:
    """Time-averaged errors of ``preds`` against ``real``, per trajectory (see :class:`RolloutErrors`).

    Body size: twice the largest distance of a collision point from the body origin, scaled by 1/sqrt(3) (a
    cube's edge; for the cube tosses exactly the cube width).
    """
    pairs = list(zip(preds, real, strict=True))
    if not free_joints(model):
        space = joint_space(model)
        errors = [float(np.mean(np.abs(joint_error(p.qpos, r.qpos, space)))) for p, r in pairs]
        return RolloutErrors(position_pct=np.empty(0), rotation_deg=np.empty(0), joint_error=np.array(errors))
    size_m = {b.name: 2.0 * b.radius_m / np.sqrt(3.0) for b in free_bodies(model)}
    pos_pct = np.zeros((len(pairs), len(size_m)))
    rot_deg = np.zeros((len(pairs), len(size_m)))
    for i, (pred, rec) in enumerate(pairs):
        for b, (body, (dist_m, angle_rad)) in enumerate(free_body_errors(model, pred, rec).items()):
            pos_pct[i, b] = 100.0 * np.mean(dist_m) / size_m[body]
            rot_deg[i, b] = np.degrees(np.mean(angle_rad))
    return RolloutErrors(position_pct=pos_pct.mean(axis=1), rotation_deg=rot_deg.mean(axis=1), joint_error=np.empty(0))


@dataclass(frozen=True, kw_only=True)
class ResidualReport:
    """What the report shows (gathered by ``train_residual``).

    Attributes:
        model: The scene's model (MuJoCo alone).
        space: ``free`` or ``joint``.
        num_fit: Trajectories the network was fitted on.
        held_out: The trajectories the gain was chosen on (never fitted).
        num_samples: Training samples in the last round.
        seconds: Training wall time.
        period_steps: Model steps per residual period.
        gain: The chosen output gain.
        preds_by_gain: Held-out rollouts per candidate gain (gain 0 = MuJoCo alone).
        errors_by_gain: Their errors, as the gain check scored them.
        one_step_rms: Rows of (label, train before, train after, held-out before, held-out after) at gain 1.
        output_names: Names of the correction's components.
        output_bound: (B, O) caps of each component (99.5% quantile of the training corrections by default).
        held_out_gate: Gate in [0, 1] at every held-out recorded state and body (the gain not included).
    """

    model: mujoco.MjModel
    space: str
    num_fit: int
    held_out: Sequence[Trajectory]
    num_samples: int
    seconds: float
    period_steps: int
    gain: float
    preds_by_gain: Mapping[float, Sequence[Trajectory]]
    errors_by_gain: Mapping[float, RolloutErrors]
    one_step_rms: Sequence[tuple[str, float, float, float, float]]
    output_names: Sequence[str]
    output_bound: np.ndarray
    held_out_gate: np.ndarray


def _mean_std(values: np.ndarray) -> str:
    return f"{values.mean():.2f} ± {values.std():.2f}" if values.size else "-"


def write_residual_report(path: Path, rep: ResidualReport) -> Path:
    """Writes the residual's ``report.html``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    free = rep.space == "free"
    period_s = rep.period_steps * float(rep.model.opt.timestep)
    if not rep.preds_by_gain:
        verdict = (
            f"No gain check: too few trajectories to hold any out, so the residual is saved at gain {rep.gain:g} "
            "without a check on multi-step rollouts. Train on at least 5 trajectories for one."
        )
    elif rep.gain == 0.0:
        verdict = (
            "The gain check chose gain 0: at no gain did the residual improve multi-step rollouts of the held-out "
            "trajectories, so this scene steps as MuJoCo alone. The sections below show what the residual would do."
        )
    else:
        verdict = f"The gain check chose gain {rep.gain:g}: the residual improved the held-out multi-step rollouts."
    sections = [
        Section(
            title="Summary",
            text=(
                f"{verdict}\n\nA state correction after each period of {rep.period_steps} model steps "
                f"({period_s * 1000:.2f} ms), {'per free body' if free else 'in joint space'}. Fitted on "
                f"{rep.num_fit} trajectories ({rep.num_samples} samples in the last round) in {rep.seconds:.1f} s"
                + (
                    f"; the gain chosen on {len(rep.held_out)} held-out trajectories, never fitted."
                    if rep.held_out
                    else "."
                )
            ),
        )
    ]

    sections.append(
        Section(
            title="One-step error (RMS)",
            text=(
                "From each recorded state one period ahead, against the next recorded state: MuJoCo alone, and with "
                "the residual at gain 1. A lower one-step error does not mean better rollouts: the gain is chosen on "
                "multi-step rollouts below."
            ),
            table=[
                ["component", "training: MuJoCo", "with residual", "held out: MuJoCo", "with residual"],
                *[[label, *(f"{v:.4g}" for v in values)] for label, *values in rep.one_step_rms],
            ],
        )
    )

    gains = sorted(rep.errors_by_gain)
    errors = rep.errors_by_gain
    if gains:
        scores = {g: float(errors[g].scores().mean()) for g in gains}
        fig, ax = plt.subplots(figsize=(5, 3))
        ax.plot(gains, [scores[g] for g in gains], marker="o")
        ax.plot([rep.gain], [scores[rep.gain]], "r*", ms=14, label=f"chosen: {rep.gain:g}")
        ax.set_xlabel("output gain (0 = MuJoCo alone)")
        ax.set_ylabel("held-out score" if free else "held-out joint error")
        ax.legend()
        fig.tight_layout()
        if free:
            head = ["gain", "score", "position, % of size", "rotation, deg"]
            rows = [
                [f"{g:g}", f"{scores[g]:.4f}", _mean_std(errors[g].position_pct), _mean_std(errors[g].rotation_deg)]
                for g in gains
            ]
        else:
            head = ["gain", "joint error (rad or m), mean ± std"]
            rows = [[f"{g:g}", _mean_std(errors[g].joint_error)] for g in gains]
        sections.append(
            Section(
                title="Gain on held-out multi-step rollouts",
                text=(
                    "Each held-out trajectory rolled out open loop from its first recorded state over its whole "
                    "length, per candidate gain. Score: time-averaged position error / body size + rotation error / "
                    "100 deg (jointed scenes: joint error), mean over trajectories; the lowest wins, ties to the "
                    "smaller gain."
                ),
                table=[head, *rows],
                figures=(fig,),
            )
        )
        sections.append(_rollout_section(rep, errors, plt))
    sections.append(_safety_section(rep, plt))
    return write_html_report(path, "Residual report", sections)


def _rollout_section(rep: ResidualReport, errors: Mapping[float, RolloutErrors], plt: Any) -> Section:
    """Per held-out trajectory: MuJoCo alone against the residual at the chosen gain (and at 1 if 0 was chosen)."""
    shown_gain = rep.gain if rep.gain != 0.0 else max(rep.preds_by_gain)
    alone = rep.preds_by_gain.get(0.0)
    figs = []
    if alone is not None and shown_gain != 0.0:
        fig, ax = plt.subplots(figsize=(4.5, 4))
        a, r = errors[0.0].scores(), errors[shown_gain].scores()
        ax.scatter(a, r, s=12)
        hi = float(max(a.max(), r.max(), 1e-9))
        ax.plot([0, hi], [0, hi], "k--", lw=0.8)
        ax.set_xlabel("MuJoCo alone: score per trajectory")
        ax.set_ylabel(f"with residual, gain {shown_gain:g}")
        fig.tight_layout()
        figs.append(fig)
    preds = rep.preds_by_gain[shown_gain]
    bodies = free_bodies(rep.model) if rep.space == "free" else []
    for k, traj in enumerate(list(rep.held_out)[:_MAX_PLOTTED]):
        fig, axes = plt.subplots(1, 2, figsize=(11, 3.2))
        t = traj.time_s - traj.time_s[0]
        if bodies:
            p = bodies[0].qpos_adr
            for i, c in enumerate("rgb"):
                axes[0].plot(t, traj.qpos[:, p + i], c, lw=2, alpha=0.4)
                if alone is not None:
                    axes[0].plot(t, alone[k].qpos[:, p + i], c + ":", lw=1)
                axes[0].plot(t, preds[k].qpos[:, p + i], c + "-", lw=1)
            axes[0].set_ylabel(f"{bodies[0].name} x/y/z, m")
            if alone is not None:
                rot = np.degrees(quat_angle_rad(alone[k].qpos[:, p + 3 : p + 7], traj.qpos[:, p + 3 : p + 7]))
                axes[1].plot(t, rot, ":", label="MuJoCo alone")
            rot = np.degrees(quat_angle_rad(preds[k].qpos[:, p + 3 : p + 7], traj.qpos[:, p + 3 : p + 7]))
            axes[1].plot(t, rot, label=f"residual, gain {shown_gain:g}")
            axes[1].set_ylabel("rotation error, deg")
        else:
            for j in range(traj.qpos.shape[1]):
                colour = f"C{j % 10}"
                axes[0].plot(t, traj.qpos[:, j], color=colour, lw=2, alpha=0.4)
                if alone is not None:
                    axes[0].plot(t, alone[k].qpos[:, j], ":", color=colour, lw=1)
                axes[0].plot(t, preds[k].qpos[:, j], "-", color=colour, lw=1)
            axes[0].set_ylabel("qpos (rad or m)")
            space = joint_space(rep.model)
            if alone is not None:
                axes[1].plot(t, np.abs(joint_error(alone[k].qpos, traj.qpos, space)).mean(axis=1), ":", label="alone")
            err = np.abs(joint_error(preds[k].qpos, traj.qpos, space)).mean(axis=1)
            axes[1].plot(t, err, label=f"residual, gain {shown_gain:g}")
            axes[1].set_ylabel("mean joint error")
        axes[0].set_title(f"{traj.name}: recorded (thick), MuJoCo alone (dotted), residual (thin)")
        axes[1].legend()
        for ax in axes:
            ax.set_xlabel("time, s")
        fig.tight_layout()
        figs.append(fig)
    note = "" if rep.gain != 0.0 else f" Gain 0 was chosen; shown for comparison at gain {shown_gain:g}."
    return Section(
        title="Held-out rollouts",
        text=f"Open loop from each held-out trajectory's first recorded state.{note}",
        figures=tuple(figs),
    )


def _safety_section(rep: ResidualReport, plt: Any) -> Section:
    """The caps of each output component and where the gate lets the residual act on the held-out states."""
    gate = np.asarray(rep.held_out_gate, dtype=np.float64).ravel()
    table: list[list[object]] = [["component", *(f"cap, body {b}" for b in range(rep.output_bound.shape[0]))]]
    for j, name in enumerate(rep.output_names):
        table.append([name, *(f"{rep.output_bound[b, j]:.4g}" for b in range(rep.output_bound.shape[0]))])
    figs = []
    if gate.size:
        closed, open_ = float(np.mean(gate <= 0.0)), float(np.mean(gate >= 1.0))
        text = (
            f"Over the {gate.size} held-out recorded states (per body): the gate is closed (no correction) in "
            f"{100 * closed:.1f}%, fully open in {100 * open_:.1f}%, in between in {100 * (1 - closed - open_):.1f}%. "
            "It closes for a body at rest in contact and fades outside the training states' ranges and coverage. "
            "Each output component is capped (tanh) at the value below."
        )
        fig, ax = plt.subplots(figsize=(5, 3))
        ax.hist(gate, bins=20, range=(0.0, 1.0))
        ax.set_xlabel("gate (0: no correction, 1: full)")
        ax.set_ylabel("held-out states")
        fig.tight_layout()
        figs.append(fig)
    else:
        text = "No held-out trajectories (fewer than 5 given): the gate was not measured. Caps per component below."
    return Section(title="Safety", text=text, table=table, figures=tuple(figs))
