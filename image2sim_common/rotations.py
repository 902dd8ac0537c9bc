"""Rotations and frames, written once for every package: quaternions (w first, as MuJoCo and the trajectory format
store them), rotation matrices, rotation vectors and camera look-at frames.

Conventions: ``world_from_body`` rotations map body coordinates to world ones; a quaternion ``q`` and ``-q`` are the
same rotation. Batched functions take any leading axes. MuJoCo is imported only by the functions that call it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def quat_to_mat(quat_wxyz: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions -> (..., 3, 3) rotation matrices (body -> world)."""
    w, x, y, z = np.moveaxis(quat_wxyz, -1, 0)
    out = np.empty((*quat_wxyz.shape[:-1], 3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - w * z)
    out[..., 0, 2] = 2 * (x * z + w * y)
    out[..., 1, 0] = 2 * (x * y + w * z)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - w * x)
    out[..., 2, 0] = 2 * (x * z - w * y)
    out[..., 2, 1] = 2 * (y * z + w * x)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def rotvec_to_quat(rotvec: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors (radians) -> (..., 4) unit quaternions."""
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(a/2)/a -> 1/2 as a -> 0; the series keeps full precision for tiny corrections.
    small = angle < 1e-6
    scale = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / np.where(small, 1.0, angle))
    return np.concatenate([np.cos(half), rotvec * scale], axis=-1)


def quat_to_rotvec(quat_wxyz: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions -> (..., 3) rotation vectors, angle in [0, pi] (q and -q give the same)."""
    q = np.where(quat_wxyz[..., :1] < 0, -quat_wxyz, quat_wxyz)
    sin_half = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sin_half, q[..., :1])
    small = sin_half < 1e-9
    scale = np.where(small, 2.0, angle / np.where(small, 1.0, sin_half))
    return q[..., 1:] * scale


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


def pose_matrix(pos_m: Sequence[float] | np.ndarray, quat_wxyz: Sequence[float] | np.ndarray) -> np.ndarray:
    """(4, 4) rigid transform from a position and a quaternion w-first (as scene.json and layouts store poses)."""
    out = np.eye(4)
    out[:3, :3] = matrix_from_quat(np.asarray(quat_wxyz, np.float64))
    out[:3, 3] = np.asarray(pos_m, np.float64)
    return out


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


def quat_angle_rad(quat_wxyz_a: np.ndarray, quat_wxyz_b: np.ndarray) -> np.ndarray:
    """Geodesic angle between rotations (..., 4) -> (...,), radians in [0, pi]; q and -q are the same rotation."""
    a = quat_wxyz_a / np.linalg.norm(quat_wxyz_a, axis=-1, keepdims=True)
    b = quat_wxyz_b / np.linalg.norm(quat_wxyz_b, axis=-1, keepdims=True)
    dot = np.abs(np.sum(a * b, axis=-1))
    return 2.0 * np.arccos(np.clip(dot, 0.0, 1.0))


def look_at_world_from_cam(eye_m: np.ndarray, target_m: np.ndarray) -> np.ndarray:
    """(4, 4) world_from_cam of a camera at `eye_m` looking at `target_m`, world z up, OpenCV/COLMAP camera axes
    (x right, y down, z forward)."""
    forward = np.asarray(target_m, np.float64) - np.asarray(eye_m, np.float64)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([right, down, forward])
    pose[:3, 3] = eye_m
    return pose
