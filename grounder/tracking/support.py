"""Depth along the viewing ray from the table: an object at rest on the table touches it.

Model-based tracking fixes an object's image position and its apparent size well, but its distance from the camera
only through that size: a grounded mesh 1% too large is placed 1% too far, which at 0.8 m lifts it 5 mm off the
table or sinks it into it. Where the object rests on the table (still for a few frames, its lowest collision point
within `max_gap_m` of z = 0), the table fixes that distance: moving the pose along the camera ray by a factor k,
``world_from_object.t = cam + k (t - cam)``, puts the lowest point on z = 0. The median k over the resting frames is
applied to every frame of that object (the size error it corrects is the same in flight), so the image position
is kept and the height comes right. Then each frame in which the object lies still on the table gets its own
factor (`snap_resting_depth`): what is left is the depth's jitter from frame to frame, and a velocity fit reads
it as motion.

The same geometry also rules poses out (`StaticGeometry`): an object cannot sit inside the table. A wrong detection
(a printed texture repeats across a box's faces) can match the frame well enough and yet put the box 3-6 cm into
the table; the tracker flags such a pose lost.

Conventions: poses are (4, 4) world-from-body matrices in the gravity-aligned world frame with the table top at
z = 0; `world_from_cam` uses OpenCV axes (only its translation, the camera centre, is used here).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import mujoco


@dataclass(frozen=True, kw_only=True)
class SupportFit:
    """The depth correction of one object.

    Attributes:
        scale: the factor k along the camera ray (1.0: no correction).
        rest_frames: how many frames it was measured on.
        gap_m: median height of the lowest collision point above the table in those frames, before correcting
            (negative: inside the table); NaN where the object never rested on the table.
        applied: whether `scale` was applied (the object rested on the table long enough).
        snapped_frames: frames then moved onto the table one by one (`snap_resting_depth`).
    """

    scale: float
    rest_frames: int
    gap_m: float
    applied: bool
    snapped_frames: int = 0


def resting_frames(
    poses: np.ndarray, valid: np.ndarray, *, still_m: float = 0.002, still_deg: float = 2.0, min_run: int = 5
) -> np.ndarray:
    """(F,) mask of one object's frames inside runs of at least `min_run` frames in which it moves less than
    `still_m` and `still_deg` from one frame to the next.

    Both are loose: a nearly symmetric object (a bowl, a can) is tracked with up to 1.5 deg of jitter about its
    axis while it rests, and a can's depth jitters by 1-2 mm from frame to frame; at 1 mm / 0.5 deg a scan of
    `samples/tabletop` got no resting frames for either on `samples/toss`, so no depth correction (the bowl was
    tracked 4.2 mm off, median). Looser is safe here: 5 frames in flight move far more (gravity alone: 1.6 m/s
    over 5 frames at 30 fps), and the correction also checks that the object touches the table.

    Args:
        poses: (F, 4, 4) world-from-body poses of one object (NaN where lost).
        valid: (F,) tracked mask.
    """
    num = len(poses)
    step_still = np.zeros(max(num - 1, 0), bool)
    for f in range(num - 1):
        if not (valid[f] and valid[f + 1]):
            continue
        move_m = float(np.linalg.norm(poses[f + 1, :3, 3] - poses[f, :3, 3]))
        cos = (np.trace(poses[f, :3, :3].T @ poses[f + 1, :3, :3]) - 1.0) / 2.0
        turn_deg = float(np.rad2deg(np.arccos(np.clip(cos, -1.0, 1.0))))
        step_still[f] = move_m < still_m and turn_deg < still_deg
    out = np.zeros(num, bool)
    f = 0
    while f < num - 1:
        if not step_still[f]:
            f += 1
            continue
        g = f
        while g < num - 1 and step_still[g]:
            g += 1
        if g - f + 1 >= min_run:  # frames f .. g
            out[f : g + 1] = True
        f = g + 1
    return out


def _onto_table(
    pose: np.ndarray, centre: np.ndarray, points_body_m: np.ndarray, max_gap_m: float
) -> tuple[float, float] | None:
    """(k, gap_m): the factor along the camera ray from `centre` that puts the pose's lowest collision point on
    z = 0, and that point's height before; None when the gap exceeds `max_gap_m` (resting on something else), the
    camera is not above the object, or its centre is unknown."""
    if not np.all(np.isfinite(centre)):
        return None
    gap = float((points_body_m @ pose[:3, :3].T + pose[:3, 3])[:, 2].min())
    height_over_cam = float(pose[2, 3] - centre[2])
    if abs(gap) > max_gap_m or height_over_cam > -1e-3:
        return None
    return 1.0 - gap / height_over_cam, gap


def fit_support_scale(
    poses: np.ndarray,
    valid: np.ndarray,
    world_from_cam: np.ndarray,
    points_body_m: np.ndarray,
    *,
    max_gap_m: float = 0.015,
    min_run: int = 5,
) -> SupportFit:
    """The depth factor that puts one object's lowest collision point on the table where it rests.

    Args:
        poses: (F, 4, 4) world-from-body poses of the object (NaN where lost).
        valid: (F,) tracked mask.
        world_from_cam: (F, 4, 4) camera poses (NaN where unknown).
        points_body_m: (P, 3) the object's collision points in its body frame.
        max_gap_m: resting frames whose lowest point is farther than this from the table are not on the table (on
            another object, say): no correction from them.
        min_run: frames an object must stay still to count as resting.
    """
    rest = resting_frames(poses, valid, min_run=min_run)
    scales, gaps = [], []
    for f in np.nonzero(rest)[0]:
        onto = _onto_table(poses[f], world_from_cam[f, :3, 3], points_body_m, max_gap_m)
        if onto is not None:
            scales.append(onto[0])
            gaps.append(onto[1])
    if len(scales) < min_run:
        return SupportFit(scale=1.0, rest_frames=len(scales), gap_m=float("nan"), applied=False)
    return SupportFit(
        scale=float(np.median(scales)), rest_frames=len(scales), gap_m=float(np.median(gaps)), applied=True
    )


def apply_support_scale(poses: np.ndarray, valid: np.ndarray, world_from_cam: np.ndarray, scale: float) -> np.ndarray:
    """(F, 4, 4) poses of one object moved along the camera ray by `scale` (`cam + scale (t - cam)`) where valid."""
    out = np.array(poses, dtype=np.float64, copy=True)
    for f in np.nonzero(valid)[0]:
        centre = world_from_cam[f, :3, 3]
        if np.all(np.isfinite(centre)):
            out[f, :3, 3] = centre + scale * (out[f, :3, 3] - centre)
    return out


def still_on_table_frames(
    poses: np.ndarray,
    valid: np.ndarray,
    world_from_cam: np.ndarray,
    dt_s: float,
    *,
    half_window_s: float = 0.1,
    spread_m: float = 0.002,
    spread_deg: float = 2.0,
) -> np.ndarray:
    """(F,) mask of one object's frames in which it lies still, judged across the camera ray.

    Frame f counts when every frame within `half_window_s` of it is tracked and lies within `spread_m` of its
    position *across* the ray through it and within `spread_deg` of its orientation. Motion along the ray is left
    out: that is the tracker's least certain direction (depth from apparent size), and at rest a can's tracked depth
    jumps by up to 3 mm in single frames (`samples/toss`), which a frame-to-frame test (`resting_frames`) reads as
    motion. The test spans a time, not a count of frames, so it means the same at 30 and at 60 fps: over 0.2 s an
    object sliding at 1 cm/s already moves 2 mm, and a hop or a bounce far more.

    Args:
        poses: (F, 4, 4) world-from-body poses of one object (NaN where lost).
        valid: (F,) tracked mask.
        world_from_cam: (F, 4, 4) camera poses (NaN where unknown).
        dt_s: frame interval, seconds.
    """
    num = len(poses)
    half = max(2, round(half_window_s / dt_s))
    out = np.zeros(num, bool)
    cos_limit = np.cos(np.deg2rad(spread_deg))
    for f in range(half, num - half):
        span = slice(f - half, f + half + 1)
        centre = world_from_cam[f, :3, 3]
        if not (valid[span].all() and np.all(np.isfinite(centre))):
            continue
        ray = poses[f, :3, 3] - centre
        ray /= np.linalg.norm(ray)
        moves = poses[span, :3, 3] - poses[f, :3, 3]
        across = moves - np.outer(moves @ ray, ray)
        # cos of the angle between orientations: (trace(R_f^T R_g) - 1) / 2
        cos = (np.einsum("ij,gij->g", poses[f, :3, :3], poses[span, :3, :3]) - 1.0) / 2.0
        out[f] = bool(np.linalg.norm(across, axis=1).max() < spread_m and cos.min() > cos_limit)
    return out


def snap_resting_depth(
    poses: np.ndarray,
    valid: np.ndarray,
    world_from_cam: np.ndarray,
    points_body_m: np.ndarray,
    dt_s: float,
    *,
    max_gap_m: float = 0.015,
) -> tuple[np.ndarray, int]:
    """One object's poses, each frame in which it lies still on the table moved along its camera ray onto it.

    The clip-wide factor of `fit_support_scale` removes a size error but not the depth's jitter from frame to frame.
    A can resting on `samples/toss` is tracked up to 3 mm off along the ray in single frames; at 60 fps the velocity
    fit turned that into 0.1-0.3 m/s where it lay still, windows started there, and the calibration fitted contact
    damping to bounces that never happened (the can's damping ratio +25% on two scans; +7% and +18% with this). In
    every frame of `still_on_table_frames` whose lowest collision point is within `max_gap_m` of the table, the
    pose is moved along its own ray so that point lies on z = 0 (image position and orientation kept).

    Returns:
        (F, 4, 4) poses and the number of frames moved.
    """
    out = np.array(poses, dtype=np.float64, copy=True)
    moved = 0
    for f in np.nonzero(still_on_table_frames(poses, valid, world_from_cam, dt_s))[0]:
        centre = world_from_cam[f, :3, 3]
        onto = _onto_table(out[f], centre, points_body_m, max_gap_m)
        if onto is not None:
            out[f, :3, 3] = centre + onto[0] * (out[f, :3, 3] - centre)
            moved += 1
    return out, moved


class StaticGeometry:
    """The scene's static geometry (colliding geoms welded to the world: the table, a floor), to tell how deep an
    object's collision geometry at a given pose lies inside it.

    Depths are MuJoCo's signed geom distances (`mujoco.mj_geomDistance`: exact for primitives, the convex hull for a
    mesh), for every object geom and static geom that may collide (contype / conaffinity). Holds its own `MjData`,
    so the caller's state is never touched.

    Args:
        model: the scene (objects on free joints).
    """

    def __init__(self, model: mujoco.MjModel) -> None:
        import mujoco

        self._model = model
        self._data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, self._data)  # the static geoms' poses, once
        static = [g for g in range(model.ngeom) if model.body_weldid[model.geom_bodyid[g]] == 0 and _collides(model, g)]
        self._pairs: dict[int, list[tuple[int, int]]] = {}
        self._qpos_address: dict[int, int] = {}
        for body in range(1, model.nbody):
            joint = int(model.body_jntadr[body])
            if joint < 0 or model.jnt_type[joint] != mujoco.mjtJoint.mjJNT_FREE:
                continue
            self._qpos_address[body] = int(model.jnt_qposadr[joint])
            own = [g for g in range(model.ngeom) if model.geom_bodyid[g] == body and _collides(model, g)]
            self._pairs[body] = [(g, s) for g in own for s in static if _may_touch(model, g, s)]

    def penetration_m(self, body_name: str, world_from_body: np.ndarray) -> float:
        """How deep (metres, 0 where clear of it) the body at `world_from_body` (4, 4) lies inside the static geometry;
        0 for a body without a free joint."""
        import mujoco

        body = int(self._model.body(body_name).id)
        pairs = self._pairs.get(body, [])
        if not pairs:
            return 0.0
        address = self._qpos_address[body]
        quat_wxyz = np.zeros(4)
        mujoco.mju_mat2Quat(quat_wxyz, np.ascontiguousarray(world_from_body[:3, :3], dtype=np.float64).ravel())
        self._data.qpos[address : address + 3] = world_from_body[:3, 3]
        self._data.qpos[address + 3 : address + 7] = quat_wxyz
        mujoco.mj_kinematics(self._model, self._data)
        # distmax 0: a pair apart reports 0 (MuJoCo stops at their bounding boxes), an overlap minus its depth.
        depth = min(mujoco.mj_geomDistance(self._model, self._data, g, s, 0.0, None) for g, s in pairs)
        return max(0.0, -float(depth))


def _collides(model: mujoco.MjModel, geom: int) -> bool:
    return bool(model.geom_contype[geom] or model.geom_conaffinity[geom])


def _may_touch(model: mujoco.MjModel, geom_a: int, geom_b: int) -> bool:
    """MuJoCo's contype / conaffinity filter (either direction)."""
    contype, conaffinity = model.geom_contype, model.geom_conaffinity
    return bool((contype[geom_a] & conaffinity[geom_b]) or (contype[geom_b] & conaffinity[geom_a]))


def collision_points_body(model: object, body_name: str) -> np.ndarray:
    """(P, 3) vertices of a body's colliding geoms (meshes; boxes by their corners) in the body frame, metres."""
    import mujoco

    assert isinstance(model, mujoco.MjModel)
    body_id = model.body(body_name).id
    points = []
    for g in range(model.ngeom):
        if model.geom_bodyid[g] != body_id or not (model.geom_contype[g] or model.geom_conaffinity[g]):
            continue
        rotation = np.zeros(9)
        mujoco.mju_quat2Mat(rotation, model.geom_quat[g])
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
            mesh = model.geom_dataid[g]
            start, count = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
            local = np.asarray(model.mesh_vert[start : start + count], np.float64)
        elif model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
            half = model.geom_size[g]
            local = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
        else:
            continue
        points.append(local @ rotation.reshape(3, 3).T + model.geom_pos[g])
    if not points:
        return np.zeros((0, 3))
    return np.concatenate(points)
