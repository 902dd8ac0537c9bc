"""Velocities of tracked free bodies from a smoothing fit (Savitzky-Golay), and the rotation helpers tracking uses.

Conventions (MuJoCo's, as in the trajectory format): quaternions are w-first; a free joint's qvel is the world linear
velocity, then the body-frame angular velocity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from grounder.errors import GrounderError


def quat_from_matrix(rotation: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (4,) unit quaternion w-first with w >= 0."""
    import mujoco

    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(rotation, dtype=np.float64).reshape(-1))
    quat /= np.linalg.norm(quat)
    return quat if quat[0] >= 0 else -quat


def matrix_from_quat(quat_wxyz: np.ndarray) -> np.ndarray:
    """(4,) quaternion w-first (any norm) -> (3, 3) rotation."""
    import mujoco

    quat = np.asarray(quat_wxyz, np.float64) / np.linalg.norm(quat_wxyz)
    out = np.zeros(9)
    mujoco.mju_quat2Mat(out, quat)
    return out.reshape(3, 3)


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of w-first quaternions, broadcasting over leading axes."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, np.float64), -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conj(q: np.ndarray) -> np.ndarray:
    return np.asarray(q, np.float64) * np.array([1.0, -1.0, -1.0, -1.0])


def sign_continuous(quats_wxyz: np.ndarray) -> np.ndarray:
    """(T, 4) quaternions with signs flipped so consecutive ones are in the same hemisphere (q and -q agree)."""
    out = np.array(quats_wxyz, np.float64)
    for k in range(1, len(out)):
        if np.dot(out[k], out[k - 1]) < 0:
            out[k] = -out[k]
    return out


def rotation_angle_deg(rot_a: np.ndarray, rot_b: np.ndarray) -> float:
    """Angle of rot_a^T rot_b in degrees."""
    cos = (np.trace(rot_a.T @ rot_b) - 1.0) / 2.0
    return float(np.rad2deg(np.arccos(np.clip(cos, -1.0, 1.0))))


@dataclass(frozen=True, kw_only=True)
class SmoothingOptions:
    """Savitzky-Golay fit used for velocities (and, if `smooth_poses`, for the poses themselves).

    Attributes:
        window_frames: odd window length in frames; shortened (to the largest odd length that fits) in short segments.
        polyorder: polynomial order of the local fit (2 = constant acceleration, exact on free flight).
        smooth_poses: replace measured poses by the fitted ones (less jitter, rounder impacts).
    """

    window_frames: int = 7
    polyorder: int = 2
    smooth_poses: bool = False

    def __post_init__(self) -> None:
        if self.window_frames < 3 or self.window_frames % 2 == 0:
            raise GrounderError(f"{self.window_frames=} but expected an odd number >= 3")
        if not 1 <= self.polyorder < self.window_frames:
            raise GrounderError(f"{self.polyorder=} but expected 1 <= polyorder < window_frames")


def _window(num: int, options: SmoothingOptions) -> tuple[int, int]:
    window = min(options.window_frames, num if num % 2 else num - 1)
    return window, min(options.polyorder, window - 1)


def free_body_velocities(
    time_s: np.ndarray, pos_m: np.ndarray, quat_wxyz: np.ndarray, options: SmoothingOptions | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Velocities of one free body over one uniformly sampled segment, from a Savitzky-Golay fit.

    The quaternion is fitted component-wise after making its sign continuous; the body angular velocity is
    ``2 * vec(conj(q) * dq/dt)`` of the fitted, normalised quaternion.

    Args:
        time_s: (T,) sample times, uniform spacing, T >= 3.
        pos_m: (T, 3) world positions.
        quat_wxyz: (T, 4) orientations.
        options: smoothing window and order.

    Returns:
        (pos_m (T, 3), quat_wxyz (T, 4), linvel_world_m_s (T, 3), angvel_body_rad_s (T, 3)); the poses are the
        fitted ones if `options.smooth_poses`, else the inputs (quaternions sign-normalised).
    """
    from scipy.signal import savgol_filter

    options = options or SmoothingOptions()
    time_s = np.asarray(time_s, np.float64)
    num = len(time_s)
    if num < 3:
        raise GrounderError(f"a segment needs at least 3 samples for velocities, got {num}")
    dt_s = float(np.median(np.diff(time_s)))
    window, order = _window(num, options)
    quats = sign_continuous(quat_wxyz)
    kwargs = {"window_length": window, "polyorder": order, "axis": 0, "mode": "interp"}
    pos_fit = savgol_filter(pos_m, deriv=0, **kwargs)
    linvel = savgol_filter(pos_m, deriv=1, delta=dt_s, **kwargs)
    quat_fit = savgol_filter(quats, deriv=0, **kwargs)
    quat_dot = savgol_filter(quats, deriv=1, delta=dt_s, **kwargs)
    norm = np.linalg.norm(quat_fit, axis=1, keepdims=True)
    unit = quat_fit / norm
    # d(q/|q|)/dt = (dq - q (q.dq)/|q|^2) / |q|: keep only the part tangent to the unit sphere.
    unit_dot = (quat_dot - unit * np.sum(unit * quat_dot, axis=1, keepdims=True)) / norm
    angvel_body = 2.0 * quat_mul(quat_conj(unit), unit_dot)[:, 1:]
    if options.smooth_poses:
        return pos_fit, unit, linvel, angvel_body
    return (
        np.asarray(pos_m, np.float64).copy(),
        quats / np.linalg.norm(quats, axis=1, keepdims=True),
        linvel,
        angvel_body,
    )
