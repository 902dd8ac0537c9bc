"""How wrong a recording's first state is, measured from the recordings themselves, and starts drawn to match.

A rollout starts from a trajectory's first recorded state, which carries the tracker's error: a pose a millimetre
or two off and, worse, a velocity taken from differences of noisy poses. A sampled simulation (``image2sim rollout
--samples``, ``calibrate --distribution``) must start from where the object may really have been, not from one
guess of it.

`measure_start_noise` fits, per trajectory, a quadratic in time to its first `WINDOW` samples in the model's
tangent space (each sample's displacement from the first one, `mujoco.mj_differentiatePos`: metres, and radians in
the body frame for a free joint's or ball joint's rotation) and reads the error of the recorded first state against
the fit: the fitted displacement at the first time (pose error, divided by sqrt(1 - h) with h the first sample's
leverage in the fit, since the fit is itself pulled toward that sample's error) and the recorded velocity minus the
fitted slope (velocity error, less the slope's own variance from the pose noise; a free joint's angular velocity
is in the body frame both in qvel and in the tangent space). A
quadratic is exact for free flight (a parabola under gravity, a constant body rate for a body spinning freely about
a principal axis or with isotropic inertia) and a fair local fit of any smooth motion over a few frames. Across
trajectories, each tangent component's error scale is the robust one about zero, 1.4826 x the median absolute
error (so that a trajectory whose first frames hold an impact does not set it). `perturbed_starts` draws starts
``recorded + N(0, scale^2)`` per component, the pose through `mujoco.mj_integratePos`.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from grounder.core.trajectory import Trajectory
from grounder.errors import GrounderError

log = logging.getLogger(__name__)

WINDOW = 8  # samples fitted per trajectory (54 ms at 148 Hz)
MIN_TRAJECTORIES = 3  # fewer: no noise measured (a scale from one or two trajectories means nothing)
MAD_TO_STD = 1.4826


@dataclass(frozen=True, kw_only=True, eq=False)
class StartNoise:
    """Per tangent component (nv of them) of a scene's state, the scale of a recorded first state's error.

    Attributes:
        pose_std: (nv,) pose error scale: metres for positions and slide joints, radians for rotations and hinges.
        velocity_std: (nv,) velocity error scale, the units of qvel.
        trajectories: How many trajectories measured it (0: not measured; the scales are 0).
        window: Samples fitted per trajectory.
    """

    pose_std: np.ndarray
    velocity_std: np.ndarray
    trajectories: int
    window: int = WINDOW

    @staticmethod
    def zero(nv: int) -> StartNoise:
        """No start noise (starts as recorded)."""
        return StartNoise(pose_std=np.zeros(nv), velocity_std=np.zeros(nv), trajectories=0)

    def scaled(self, factor: float) -> StartNoise:
        """The same noise with every scale multiplied by ``factor``."""
        return StartNoise(
            pose_std=self.pose_std * factor,
            velocity_std=self.velocity_std * factor,
            trajectories=self.trajectories,
            window=self.window,
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "method": "quadratic fit of the first samples in tangent space; robust scale about zero",
            "window_samples": self.window,
            "trajectories": self.trajectories,
            "pose_std": [float(v) for v in self.pose_std],
            "velocity_std": [float(v) for v in self.velocity_std],
        }

    @staticmethod
    def from_json(data: Mapping[str, Any], nv: int, where: str) -> StartNoise:
        """Reads `to_json`'s form back, checking every field.

        Raises:
            GrounderError: a field is missing, has the wrong length, or holds a negative or non-finite number.
        """
        out = []
        for key in ("pose_std", "velocity_std"):
            value = data.get(key) if isinstance(data, Mapping) else None
            if not isinstance(value, list) or len(value) != nv:
                raise GrounderError(f"{where}: start_noise.{key} must be a list of {nv} numbers (one per qvel entry)")
            arr = np.asarray([v if isinstance(v, int | float) and not isinstance(v, bool) else np.nan for v in value])
            if not np.all(np.isfinite(arr)) or np.any(arr < 0):
                raise GrounderError(f"{where}: start_noise.{key} must hold finite numbers >= 0")
            out.append(arr.astype(np.float64))
        count = data.get("trajectories", 0)
        window = data.get("window_samples", WINDOW)
        if not isinstance(count, int) or isinstance(count, bool) or count < 0:
            raise GrounderError(f"{where}: start_noise.trajectories must be an integer >= 0")
        if not isinstance(window, int) or isinstance(window, bool) or window < 3:
            raise GrounderError(f"{where}: start_noise.window_samples must be an integer >= 3")
        return StartNoise(pose_std=out[0], velocity_std=out[1], trajectories=count, window=window)


def first_state_errors(
    model: mujoco.MjModel, traj: Trajectory, window: int = WINDOW
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """(pose error (nv,), velocity error (nv,), the fit's slope variance per unit pose variance) of a trajectory's
    first recorded state against a quadratic fitted to its first ``window`` samples in tangent space (module
    docstring); None when it has fewer samples."""
    if traj.num_steps < window or model.nv == 0:
        return None
    time_s = traj.time_s[:window] - traj.time_s[0]
    disp = np.zeros((window, model.nv))
    for k in range(1, window):
        mujoco.mj_differentiatePos(model, disp[k], 1.0, traj.qpos[0], traj.qpos[k])
    design = np.stack([np.ones(window), time_s, time_s**2], axis=1)
    coef, *_ = np.linalg.lstsq(design, disp, rcond=None)
    inverse = np.linalg.inv(design.T @ design)
    leverage = float(design[0] @ inverse @ design[0])
    # recorded (displacement 0) minus fitted; the residual of a fitted sample is (1 - h) times its error on average
    return -coef[0] / np.sqrt(max(1.0 - leverage, 1e-6)), traj.qvel[0] - coef[1], float(inverse[1, 1])


def measure_start_noise(model: mujoco.MjModel, trajs: Sequence[Trajectory], window: int = WINDOW) -> StartNoise:
    """The start-noise scales of the module docstring, over the trajectories with at least ``window`` samples."""
    errors = [e for e in (first_state_errors(model, t, window) for t in trajs) if e is not None]
    if len(errors) < MIN_TRAJECTORIES:
        log.warning(
            "start noise not measured: %d trajectories have %d samples or more (at least %d needed); "
            "sampled rollouts start from the recorded states",
            len(errors),
            window,
            MIN_TRAJECTORIES,
        )
        return StartNoise.zero(model.nv)
    pose = np.stack([e[0] for e in errors])
    vel = np.stack([e[1] for e in errors])
    pose_std = MAD_TO_STD * np.median(np.abs(pose), axis=0)
    # the recorded velocity minus the fitted slope also holds the slope's own error (pose noise through the fit)
    slope_var = pose_std**2 * float(np.median([e[2] for e in errors]))
    vel_var = (MAD_TO_STD * np.median(np.abs(vel), axis=0)) ** 2 - slope_var
    return StartNoise(
        pose_std=pose_std,
        velocity_std=np.sqrt(np.maximum(vel_var, 0.0)),
        trajectories=len(errors),
        window=window,
    )


def perturbed_starts(
    model: mujoco.MjModel,
    qpos0: np.ndarray,
    qvel0: np.ndarray,
    noise: StartNoise,
    count: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """``count`` starts (qpos (count, nq), qvel (count, nv)) around a recorded one, drawn from the noise scales."""
    qpos = np.repeat(np.asarray(qpos0, np.float64)[None], count, axis=0)
    qvel = np.repeat(np.asarray(qvel0, np.float64)[None], count, axis=0)
    if noise.trajectories == 0 or model.nv == 0:
        return qpos, qvel
    dq = rng.normal(size=(count, model.nv)) * noise.pose_std
    dv = rng.normal(size=(count, model.nv)) * noise.velocity_std
    for k in range(count):
        mujoco.mj_integratePos(model, qpos[k], dq[k], 1.0)
    return qpos, qvel + dv
