"""The noise floor of the gap: the short-horizon gap a perfect model would still show at the recording's noise level.

Recording noise is estimated from the data itself, per coordinate kind:

- positions (free-joint translations, hinge and slide angles): third differences of the samples cancel any motion
  with constant acceleration and leave 20 sigma^2 of white noise; a robust spread (MAD) ignores the rare impacts;
- orientations: the same on the integrated body-frame rotation increments;
- velocities: third differences of the recorded velocities, the same way (a velocity that was smoothed when it was
  recorded shows less noise than it has, so the floor is then a lower bound). For tracked video (`image2sim track`
  writes velocities as a Savitzky-Golay derivative of the positions over ``w`` frames) the velocity noise is at
  least what that derivative makes of the position noise: ``sigma_p / (dt sqrt(sum k^2))``, k = -(w-1)/2 .. (w-1)/2.

The floor is then measured by simulation: the model's own open-loop trajectories from the recorded initial states,
given noise of those sizes, are scored against the same model with the same short-horizon windows.
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

from grounder.core.trajectory import Trajectory

_FREE = int(mujoco.mjtJoint.mjJNT_FREE)
_BALL = int(mujoco.mjtJoint.mjJNT_BALL)
_MAD = 1.4826


def _robust_std(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    if x.size == 0:
        return 0.0
    return float(_MAD * np.median(np.abs(x - np.median(x))))


def _rotvec_increments(quat_wxyz: np.ndarray) -> np.ndarray:
    """Body-frame rotation vectors from each sample to the next, (T-1, 3)."""
    out = np.empty((len(quat_wxyz) - 1, 3))
    for t in range(len(quat_wxyz) - 1):
        mujoco.mju_subQuat(out[t], quat_wxyz[t + 1], quat_wxyz[t])
    return out


def derivative_noise_gain(window_frames: int, dt_s: float) -> float:
    """Noise of a Savitzky-Golay first derivative (polynomial order 1 or 2, ``window_frames`` odd) per unit of white
    noise on the positions, 1/s: the fit's slope is sum(k x_k) / (dt sum(k^2))."""
    half = (window_frames - 1) // 2
    return 1.0 / (dt_s * float(np.sqrt(sum(k * k for k in range(-half, half + 1)))))


def estimate_noise(
    model: mujoco.MjModel, trajs: Sequence[Trajectory], velocity_smoothing_frames: int | None = None
) -> dict[str, float]:
    """Noise standard deviations per kind: ``position_m``, ``angle_rad`` (joints), ``rotation_rad``, ``velocity_m_s``,
    ``angular_velocity_rad_s``, ``joint_velocity_rad_s``.

    Args:
        velocity_smoothing_frames: the recorded velocities are a Savitzky-Golay derivative of the positions over
            this many frames (tracked video): velocity noise is then at least the position noise through it.
    """
    pos3, rot3, jnt3, vel, angvel, jvel = [], [], [], [], [], []
    for traj in trajs:
        if traj.num_steps < 5:
            continue
        for j in range(model.njnt):
            a, d = int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j])
            jtype = int(model.jnt_type[j])
            if jtype == _FREE:
                p = traj.qpos[:, a : a + 3]
                pos3.append(np.diff(p, n=3, axis=0).ravel())
                vel.append(np.diff(traj.qvel[:, d : d + 3], n=3, axis=0).ravel())
                inc = _rotvec_increments(traj.qpos[:, a + 3 : a + 7])
                rot3.append(np.diff(inc, n=2, axis=0).ravel())
                angvel.append(np.diff(traj.qvel[:, d + 3 : d + 6], n=3, axis=0).ravel())
            elif jtype == _BALL:
                inc = _rotvec_increments(traj.qpos[:, a : a + 4])
                rot3.append(np.diff(inc, n=2, axis=0).ravel())
            else:
                q = traj.qpos[:, a]
                jnt3.append(np.diff(q, n=3))
                jvel.append(np.diff(traj.qvel[:, d], n=3))
    pos_sigma = [_robust_std(np.concatenate(x)) / np.sqrt(20) if x else 0.0 for x in (pos3, rot3, jnt3)]
    vel_sigma = [_robust_std(np.concatenate(x)) / np.sqrt(20) if x else 0.0 for x in (vel, angvel, jvel)]
    sigma_p, sigma_r, sigma_j = pos_sigma
    if velocity_smoothing_frames and velocity_smoothing_frames >= 3 and trajs:
        dt = float(np.median(np.concatenate([np.diff(t.time_s) for t in trajs if t.num_steps > 1])))
        gain = derivative_noise_gain(velocity_smoothing_frames, dt)
        vel_sigma = [max(v, p * gain) for v, p in zip(vel_sigma, pos_sigma, strict=True)]
    return {
        "position_m": sigma_p,
        "rotation_rad": sigma_r,
        "angle_rad": sigma_j,
        "velocity_m_s": vel_sigma[0],
        "angular_velocity_rad_s": vel_sigma[1],
        "joint_velocity_rad_s": vel_sigma[2],
    }


def add_noise(model: mujoco.MjModel, traj: Trajectory, noise: dict[str, float], rng: np.random.Generator) -> Trajectory:
    """A copy of ``traj`` with white noise of the given sizes on every coordinate."""
    qpos, qvel = traj.qpos.copy(), traj.qvel.copy()
    n = traj.num_steps
    for j in range(model.njnt):
        a, d = int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j])
        jtype = int(model.jnt_type[j])
        if jtype in (_FREE, _BALL):
            qa = a + 3 if jtype == _FREE else a
            if jtype == _FREE:
                qpos[:, a : a + 3] += rng.normal(0, noise["position_m"], (n, 3))
                qvel[:, d : d + 3] += rng.normal(0, noise["velocity_m_s"], (n, 3))
                qvel[:, d + 3 : d + 6] += rng.normal(0, noise["angular_velocity_rad_s"], (n, 3))
            delta = rng.normal(0, noise["rotation_rad"], (n, 3))
            for t in range(n):
                q = qpos[t, qa : qa + 4].copy()
                mujoco.mju_quatIntegrate(q, delta[t], 1.0)
                qpos[t, qa : qa + 4] = q / np.linalg.norm(q)
        else:
            qpos[:, a] += rng.normal(0, noise["angle_rad"], n)
            qvel[:, d] += rng.normal(0, noise["joint_velocity_rad_s"], n)
    return Trajectory(time_s=traj.time_s, qpos=qpos, qvel=qvel, ctrl=traj.ctrl, name=traj.name)
