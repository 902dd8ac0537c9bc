"""Batched evaluation of calibration candidates: `Evaluator` turns (K, P) parameter vectors into models and their
per-trajectory losses on a fixed set of trajectories (the loss of the `grounder.calibration.fit` module docstring,
step 2), each batch one `mujoco.rollout` call; and `pseudo_huber_residuals`, the robust residuals of
``CalibrateOptions.robust_scale``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

import grounder.sim.rollout as sim
from grounder.calibration.parameters import Parameter, apply_to_model, body_size_m
from grounder.calibration.result import ErrorSummary
from grounder.core.trajectory import Trajectory
from grounder.errors import GrounderError


@dataclass(frozen=True, kw_only=True)
class _JointError:
    qpos_index: int
    scale: float  # error units per "percent": hinge 0.01 rad, slide 0.001 m


def scalar_joint_errors(model: mujoco.MjModel) -> list[_JointError]:
    """The hinge and slide joints' errors and their scales (hinge 0.01 rad, slide 1 mm per "percent")."""
    out = []
    for j in range(model.njnt):
        jtype = int(model.jnt_type[j])
        if jtype == mujoco.mjtJoint.mjJNT_HINGE:
            out.append(_JointError(qpos_index=int(model.jnt_qposadr[j]), scale=0.01))
        elif jtype == mujoco.mjtJoint.mjJNT_SLIDE:
            out.append(_JointError(qpos_index=int(model.jnt_qposadr[j]), scale=0.001))
    return out


def pseudo_huber_residuals(res: np.ndarray, scale: float) -> np.ndarray:
    """Residuals whose squares are the pseudo-Huber function of `res` with this scale: quadratic below it, linear
    above, so least squares (and sums of squares) over them are robust to a few large residuals."""
    return scale * np.sqrt(2.0 * (np.sqrt(1.0 + (res / scale) ** 2) - 1.0))


class Evaluator:
    """Losses of many candidate parameter vectors on a fixed set of trajectories, each batch one `mujoco.rollout`.

    Trajectories are grouped by length so that short ones are not simulated to the length of the longest.
    """

    def __init__(
        self,
        base: mujoco.MjModel,
        params: Sequence[Parameter],
        trajs: Sequence[Trajectory],
        *,
        rotation_weight: float,
        view_point_m: Sequence[float] | None = None,
        along_view_weight: float = 1.0,
        nthread: int | None = None,
        max_batch_mb: float = 256.0,
        group_size: int = 16,
    ) -> None:
        if not trajs:
            raise GrounderError("no trajectories to evaluate")
        self.base = base
        self.params = list(params)
        self.trajs = list(trajs)
        self.rotation_weight = rotation_weight
        self.view_point_m = None if view_point_m is None else np.asarray(view_point_m, np.float64)
        self.along_view_weight = along_view_weight
        self.nthread = nthread or sim.default_nthread()
        self.max_batch_bytes = max_batch_mb * 2**20
        self._data = mujoco.MjData(base)
        self.qpos_at, _ = sim._offsets(base)
        self.free = sim.free_joints(base)
        self.sizes = [body_size_m(base, mujoco.mj_name2id(base, mujoco.mjtObj.mjOBJ_BODY, fj.body)) for fj in self.free]
        self.scalar = scalar_joint_errors(base)
        order = sorted(range(len(self.trajs)), key=lambda i: self.trajs[i].num_steps)
        self.groups = [order[i : i + group_size] for i in range(0, len(order), group_size)]
        self.batches = [sim.prepare(base, [self.trajs[i] for i in g]) for g in self.groups]
        self.rollouts = 0
        self.steps = 0
        self.rollout_seconds = 0.0
        self.eval_seconds = 0.0

    def absorb_counts(self, other: Evaluator) -> None:
        """Adds another evaluator's rollout counts and times to this one's (a search that used both)."""
        self.rollouts += other.rollouts
        self.steps += other.steps
        self.rollout_seconds += other.rollout_seconds
        self.eval_seconds += other.eval_seconds

    def models(self, values: np.ndarray) -> list[mujoco.MjModel]:
        """Models for (K, P) physical parameter vectors."""
        return [apply_to_model(self.base, self.params, row, data=self._data) for row in np.atleast_2d(values)]

    def errors(self, models: Sequence[mujoco.MjModel]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per (model, trajectory): position % of size, rotation degrees, loss; each (K, B)."""
        tick = time.perf_counter()
        k_count, b_count = len(models), len(self.trajs)
        pos = np.zeros((k_count, b_count))
        rot = np.zeros((k_count, b_count))
        joint = np.zeros((k_count, b_count))
        nstate = mujoco.mj_stateSize(self.base, sim.FULLPHYSICS)
        for group, batch in zip(self.groups, self.batches, strict=True):
            per_model_bytes = len(group) * (batch.nstep + 1) * nstate * 8 * 2
            chunk = max(1, int(self.max_batch_bytes // max(per_model_bytes, 1)))
            for start in range(0, k_count, chunk):
                sub = list(models[start : start + chunk])
                t0 = time.perf_counter()
                states = sim.rollout_states(sub, batch, nthread=self.nthread)
                self.rollout_seconds += time.perf_counter() - t0
                self.rollouts += len(sub) * len(group)
                self.steps += len(sub) * len(group) * batch.nstep
                for col, b in enumerate(group):
                    traj = self.trajs[b]
                    rows = states[:, col, batch.sample_steps[col], self.qpos_at : self.qpos_at + self.base.nq]
                    p_err = np.zeros(len(sub))
                    r_err = np.zeros(len(sub))
                    for fj, size in zip(self.free, self.sizes, strict=True):
                        seen_m = traj.qpos[None, :, fj.pos]
                        dpos = np.linalg.norm(
                            sim.along_view_weighted(
                                rows[:, :, fj.pos] - seen_m, seen_m, self.view_point_m, self.along_view_weight
                            ),
                            axis=2,
                        )
                        p_err += 100.0 * dpos.mean(axis=1) / size
                        ang = sim.quat_angle_rad(
                            rows[:, :, fj.quat], np.broadcast_to(traj.qpos[:, fj.quat], rows[:, :, fj.quat].shape)
                        )
                        r_err += np.degrees(ang.mean(axis=1))
                    if self.free:
                        p_err /= len(self.free)
                        r_err /= len(self.free)
                    j_err = np.zeros(len(sub))
                    for je in self.scalar:
                        j_err += (
                            np.abs(rows[:, :, je.qpos_index] - traj.qpos[None, :, je.qpos_index]).mean(1) / je.scale
                        )
                    pos[start : start + len(sub), b] = p_err
                    rot[start : start + len(sub), b] = r_err
                    joint[start : start + len(sub), b] = j_err
        loss = pos + self.rotation_weight * rot + joint
        loss[~np.isfinite(loss)] = 1e6
        self.eval_seconds += time.perf_counter() - tick
        return pos, rot, loss

    def loss_of_values(self, values: np.ndarray) -> np.ndarray:
        """Per (candidate, trajectory) loss (K, B) for (K, P) physical values."""
        _, _, loss = self.errors(self.models(values))
        return loss

    def summary(self, model: mujoco.MjModel) -> ErrorSummary:
        pos, rot, loss = self.errors([model])
        return ErrorSummary(
            names=tuple(t.name for t in self.trajs), position_pct=pos[0], rotation_deg=rot[0], loss=loss[0]
        )
