"""Start states of tracked windows as nuisance parameters: fitted to each window's own tracked motion.

A calibration window is rolled out open loop from its first tracked state, so an error in that state (the pose of
a fresh detection, the velocity fitted over a few noisy frames) is read as an error of the physics: on
`samples/toss` start velocities 0.1 m/s off turned into friction 29% off. The frames after the start say where the
object must have started and how fast: `refine_window_starts` fits each window's start pose and velocity (6 + 6
numbers per free body) to the window's tracked poses by least squares, with the scene's current parameters. The
interaction calibration can alternate the two (`grounder.interaction.windows.calibrate_constrained`, `start_rounds`;
off by default): calibrate the parameters on the windows, refit the starts with the calibrated values, calibrate
again; the joint estimate of start states and parameters that multiple-shooting system identification makes, done
in blocks. Where a parameter's loss is nearly flat the starts absorb what decides it (docs/interaction_history.md).

The fit is a maximum a posteriori estimate: the calibration's loss terms over the window's samples (position in
percent of the object's size, about the tracking error, with the along-ray part weighted as in
`grounder.sim.rollout.along_view_weighted`, and `rotation_weight` percent per degree), squared and summed, plus the
start's change over its expected size (`START_SIGMA`), squared: the prior stands for the first sample, the tracked
start, with the error a tracked start really has. Without that prior a start in contact is not determined: a box
sliding on the table fitted its next samples from a start tilted by 4 deg and spinning at 12 rad/s, which the
contact stopped in the first step. The window's first sample is replaced by the fitted start; its other samples are
untouched.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import mujoco
import numpy as np

import grounder.sim.rollout as sim
from grounder.calibration.parameters import body_size_m
from grounder.core.trajectory import Trajectory
from grounder.errors import GrounderError

# Expected error of a tracked start (one standard deviation): position, rotation, linear and angular velocity. On
# `samples/toss` the first frames' poses were 4-8 mm off and velocities fitted over 3-4 frames up to 0.1 m/s.
START_SIGMA = {"position_m": 0.005, "rotation_deg": 3.0, "velocity_m_s": 0.1, "angular_velocity_rad_s": 3.0}


@dataclass(frozen=True, kw_only=True)
class StartFit:
    """How one window's start state moved (largest over its free bodies) and the fit's loss before and after.

    Attributes:
        name: the window.
        position_change_mm, rotation_change_deg: of the start pose.
        velocity_change_m_s, angular_velocity_change_rad_s: of the start velocity.
        cost_before, cost_after: the fit's cost (squared residual terms over the samples, plus the prior's).
        accepted: False when the fit did not lower the cost (the tracked start is kept).
    """

    name: str
    position_change_mm: float
    rotation_change_deg: float
    velocity_change_m_s: float
    angular_velocity_change_rad_s: float
    cost_before: float
    cost_after: float
    accepted: bool

    def as_dict(self) -> dict[str, float | str | bool]:
        return {
            "name": self.name,
            "position_change_mm": round(self.position_change_mm, 2),
            "rotation_change_deg": round(self.rotation_change_deg, 2),
            "velocity_change_m_s": round(self.velocity_change_m_s, 4),
            "angular_velocity_change_rad_s": round(self.angular_velocity_change_rad_s, 3),
            "cost_before": round(self.cost_before, 3),
            "cost_after": round(self.cost_after, 3),
            "accepted": self.accepted,
        }


class _WindowFit:
    """Residuals of one window as a function of its start correction x = per free body (dpos 3, drot 3, dv 3, dw 3),
    many corrections per `mujoco.rollout` call."""

    def __init__(
        self,
        model: mujoco.MjModel,
        traj: Trajectory,
        *,
        rotation_weight: float,
        view_point_m: np.ndarray | None,
        along_view_weight: float,
        nthread: int,
    ) -> None:
        self.model = model
        self.traj = traj
        self.rotation_weight = rotation_weight
        self.view_point_m = view_point_m
        self.along_view_weight = along_view_weight
        self.free = sim.free_joints(model)
        self.dofs = [int(model.jnt_dofadr[model.body(fj.body).jntadr[0]]) for fj in self.free]
        self.sizes_m = [body_size_m(model, model.body(fj.body).id) for fj in self.free]
        self.batch = sim.prepare(model, [traj])  # the window's controls and sample steps, for `mujoco.rollout`
        self.nthread = nthread
        self.qpos_at, _ = sim._offsets(model)
        self.data = mujoco.MjData(model)
        sigma = np.array(
            [START_SIGMA["position_m"]] * 3
            + [np.radians(START_SIGMA["rotation_deg"])] * 3
            + [START_SIGMA["velocity_m_s"]] * 3
            + [START_SIGMA["angular_velocity_rad_s"]] * 3
        )
        self.sigma = np.tile(sigma, len(self.free))

    @property
    def size(self) -> int:
        return 12 * len(self.free)

    def start(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(qpos, qvel) of the start corrected by x."""
        qpos = self.traj.qpos[0].astype(np.float64, copy=True)
        qvel = self.traj.qvel[0].astype(np.float64, copy=True)
        dq = np.zeros(self.model.nv)
        for k, dof in enumerate(self.dofs):
            dq[dof : dof + 6] = x[12 * k : 12 * k + 6]
            qvel[dof : dof + 6] += x[12 * k + 6 : 12 * k + 12]
        mujoco.mj_integratePos(self.model, qpos, dq, 1.0)
        return qpos, qvel

    def residuals(self, xs: np.ndarray) -> np.ndarray:
        """(K, R) residuals of K corrections: per sample after the first and free body,
        the weighted position error in percent of the body's size (3) and the rotation error times
        `rotation_weight` (3, degrees); then the corrections over `START_SIGMA` (12 per body)."""
        starts = replace(
            self.batch,
            states0=np.stack([sim.initial_state(self.model, *self.start(x), self.data) for x in xs]),
            controls=np.repeat(self.batch.controls, len(xs), axis=0),
            sample_steps=self.batch.sample_steps * len(xs),
        )
        full = sim.rollout_states([self.model], starts, nthread=self.nthread)[0]
        # The first sample is the start itself: the prior stands for it, with the error a tracked start really has.
        qpos = full[:, self.batch.sample_steps[0][1:], self.qpos_at : self.qpos_at + self.model.nq]
        seen = self.traj.qpos[1:]
        num = len(seen)
        out = []
        for fj, size_m in zip(self.free, self.sizes_m, strict=True):
            seen_m = seen[None, :, fj.pos]
            dpos = sim.along_view_weighted(
                qpos[:, :, fj.pos] - seen_m, seen_m, self.view_point_m, self.along_view_weight
            )
            drot = np.zeros((len(xs), num, 3))
            for k in range(len(xs)):
                for t in range(num):
                    mujoco.mju_subQuat(drot[k, t], qpos[k, t, fj.quat], seen[t, fj.quat])
            out += [100.0 * dpos / size_m, self.rotation_weight * np.degrees(drot)]
        res = np.concatenate([r.reshape(len(xs), -1) for r in out] + [xs / self.sigma], axis=1)
        res[~np.isfinite(res)] = 1e3
        return res


def _least_squares(problem: _WindowFit, z0: np.ndarray, free: np.ndarray, budget: int) -> np.ndarray:
    """Levenberg-Marquardt over the `free` start corrections (in units of the prior's sigma: metres, radians and m/s
    differ by orders of magnitude), the others held at `z0`. Forward differences of 0.02 sigma (0.1 mm, 0.06 deg,
    2 mm/s, 0.06 rad/s), one batch of rollouts per Jacobian."""
    from scipy.optimize import least_squares

    step = 0.02
    sigma = problem.sigma

    def full(z_free: np.ndarray) -> np.ndarray:
        z = z0.copy()
        z[free] = z_free
        return z

    def fun(z_free: np.ndarray) -> np.ndarray:
        return problem.residuals((full(z_free) * sigma)[None])[0]

    def jac(z_free: np.ndarray) -> np.ndarray:
        z = full(z_free)
        zs = np.concatenate([z[None], z[None] + step * np.eye(len(z))[free]])
        res = problem.residuals(zs * sigma)
        return ((res[1:] - res[0]) / step).T

    result = least_squares(fun, z0[free], jac=jac, method="lm", x_scale=1.0, max_nfev=budget)
    return full(result.x)


def refine_window_starts(
    model: mujoco.MjModel,
    windows: Sequence[Trajectory],
    *,
    rotation_weight: float,
    view_point_m: Sequence[float] | None = None,
    along_view_weight: float = 1.0,
    max_iterations: int = 20,
    nthread: int | None = None,
) -> tuple[list[Trajectory], list[StartFit]]:
    """Fits each window's start pose and velocity to its tracked motion under `model` (module docstring).

    Levenberg-Marquardt (SciPy) on forward-difference Jacobians, each one batch of 1 + 12 x bodies rollouts. A fit
    that does not lower the cost keeps the tracked start.

    Returns:
        The windows with their first sample replaced by the fitted start, and what each fit changed.
    """
    view = None if view_point_m is None else np.asarray(view_point_m, np.float64)
    threads = nthread or sim.default_nthread()
    out: list[Trajectory] = []
    fits: list[StartFit] = []
    if not sim.free_joints(model):
        raise GrounderError("start refinement needs free bodies (objects); the model has none")
    for traj in windows:
        problem = _WindowFit(
            model,
            traj,
            rotation_weight=rotation_weight,
            view_point_m=view,
            along_view_weight=along_view_weight,
            nthread=threads,
        )
        z0 = np.zeros(problem.size)
        r0 = problem.residuals(z0[None])[0]
        cost_before = float(r0 @ r0)
        # First the position and linear velocity alone, then all twelve numbers from there: in contact a start's
        # tilt and spin are barely seen (the contact undoes them in a step), and one fit of all twelve from a start
        # 0.15 m/s off traded them against the velocity. The cost stays rough (a landing's timing moves with a
        # millimetre of height): on a skidding ball this stops at cost 5.8 against 2.9 at the true start (within
        # 1 mm and 3 cm/s of it). A global search finds the true start (differential evolution, 6000 rollouts a
        # window) but made the clip's calibration ten times slower.
        linear = np.tile(np.array([True] * 3 + [False] * 3 + [True] * 3 + [False] * 3), len(problem.free))
        z = _least_squares(problem, z0, linear, max_iterations)
        z = _least_squares(problem, z, np.ones(problem.size, bool), max_iterations)
        result_cost = problem.residuals((z * problem.sigma)[None])[0]
        cost_after = float(result_cost @ result_cost)
        accepted = bool(np.isfinite(cost_after) and cost_after < cost_before)
        x = z * problem.sigma if accepted else z0
        qpos0, qvel0 = problem.start(x)
        qpos, qvel = traj.qpos.astype(np.float64, copy=True), traj.qvel.astype(np.float64, copy=True)
        qpos[0], qvel[0] = qpos0, qvel0
        out.append(Trajectory(time_s=traj.time_s, qpos=qpos, qvel=qvel, ctrl=traj.ctrl, name=traj.name))
        per_body = x.reshape(-1, 12)
        fits.append(
            StartFit(
                name=traj.name,
                position_change_mm=1e3 * float(np.linalg.norm(per_body[:, 0:3], axis=1).max()),
                rotation_change_deg=float(np.degrees(np.linalg.norm(per_body[:, 3:6], axis=1).max())),
                velocity_change_m_s=float(np.linalg.norm(per_body[:, 6:9], axis=1).max()),
                angular_velocity_change_rad_s=float(np.linalg.norm(per_body[:, 9:12], axis=1).max()),
                cost_before=cost_before,
                cost_after=cost_after if accepted else cost_before,
                accepted=accepted,
            )
        )
    return out, fits
