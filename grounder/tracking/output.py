"""What `track` writes, and reading it back: the segments (maximal runs of frames in which every object is
tracked) and their whole-scene trajectories, each object's own tracked runs as single-body trajectories
(`object_trajectories`, also from a written `track.json`: `load_object_trajectories`, `track_payload_trajectories`),
and the output folder itself (`write_track_output`: trajectories, `track.json`, `overview.png`).
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from grounder.core.trajectory import Trajectory, save_trajectory
from grounder.tracking.options import TRACK_JSON, FrameScore, TrackError, TrackOptions, TrackResult
from grounder.tracking.render import PinholeCamera
from grounder.tracking.smooth import SmoothingOptions, free_body_velocities
from image2sim_common.rotations import matrix_from_quat, quat_from_matrix
from reconstruction.errors import InputError

if TYPE_CHECKING:
    import mujoco


# ---------------------------------------------------------------- segments and trajectories


def tracked_segments(valid: np.ndarray, min_frames: int) -> list[tuple[int, int]]:
    """Maximal runs (first, last), inclusive, of frames in which every object is valid, at least min_frames long."""
    runs = iter_valid_runs(np.all(np.asarray(valid, bool), axis=1, keepdims=False).reshape(-1))
    return [(a, b) for a, b in runs if b - a + 1 >= min_frames]


def segment_trajectory(
    renderer_model_nq: int,
    renderer_model_nv: int,
    joints: list,
    time_s: np.ndarray,
    poses: np.ndarray,
    segment: tuple[int, int],
    smoothing: SmoothingOptions,
    name: str,
) -> Trajectory:
    """One segment's trajectory: qpos from the tracked poses, qvel from the smoothing fit."""
    first, last = segment
    frames = slice(first, last + 1)
    count = last - first + 1
    qpos = np.zeros((count, renderer_model_nq))
    qvel = np.zeros((count, renderer_model_nv))
    for i, fj in enumerate(joints):
        pos = poses[frames, i, :3, 3]
        quat = np.stack([quat_from_matrix(p[:3, :3]) for p in poses[frames, i]])
        pos, quat, linvel, angvel = free_body_velocities(time_s[frames], pos, quat, smoothing)
        qpos[:, fj.pos] = pos
        qpos[:, fj.quat] = quat
        dof = fj.dof
        qvel[:, dof : dof + 3] = linvel
        qvel[:, dof + 3 : dof + 6] = angvel
    return Trajectory(time_s=time_s[frames], qpos=qpos, qvel=qvel, name=name)


def scene_trajectories(
    model: mujoco.MjModel,
    scene_xml: Path,
    stem: str,
    time_s: np.ndarray,
    poses: np.ndarray,
    segments: Sequence[tuple[int, int]],
    smoothing: SmoothingOptions,
) -> tuple[Trajectory, ...]:
    """One whole-scene trajectory per segment, in the scene's joint order, named `{stem}_{k:02d}` (`segment_trajectory`
    over every free joint of `model`; a scene with other joints is refused)."""
    from grounder.sim.rollout import free_joints

    joints = [
        _JointAddress(pos=fj.pos, quat=fj.quat, dof=int(model.jnt_dofadr[model.body(fj.body).jntadr[0]]))
        for fj in free_joints(model)
    ]
    if len(joints) != model.njnt:
        raise TrackError(
            f"{scene_xml} has {model.njnt} joints but only {len(joints)} free ones; tracking writes free bodies only"
        )
    return tuple(
        segment_trajectory(model.nq, model.nv, joints, time_s, poses, seg, smoothing, f"{stem}_{k:02d}")
        for k, seg in enumerate(segments)
    )


def object_trajectories(
    time_s: np.ndarray,
    world_from_objects: np.ndarray,
    valid: np.ndarray,
    names: Sequence[str],
    smoothing: SmoothingOptions,
    min_frames: int,
    stem: str,
    *,
    sources: np.ndarray | None = None,
) -> dict[str, list[Trajectory]]:
    """Per object, its own tracked motion: one single-body trajectory (qpos 7, qvel 6, the object's free joint alone)
    per maximal run of frames in which *it* is tracked, at least `min_frames` long, velocities from the smoothing
    fit. Where objects never touch, each can be calibrated on these: an object hidden for a while costs the others
    nothing (the segments, runs in which every object is tracked, would cut all of them).

    Frames the backward pass recovered (`sources` "track_backwards") are left out. They are extrapolated from a later
    detection, and on `samples/toss` the box's two such frames at the start (in flight) were 8.6 and 12.2 mm off,
    against 0.4 mm at the detection after them. A window started there missed by 14 mm at the rendered values, and
    the box's friction came out +126%; without them, -7%.

    Args:
        time_s: (F,) frame times, seconds.
        world_from_objects: (F, N, 4, 4) tracked poses (anything where not valid).
        valid: (F, N) tracked mask.
        names: the N object names.
        sources: (F, N) each frame's `FrameScore.source`, or None to use every valid frame.
    """
    joint = _JointAddress(pos=slice(0, 3), quat=slice(3, 7), dof=0)
    usable = np.asarray(valid, bool) if sources is None else np.asarray(valid, bool) & (sources != "track_backwards")
    out: dict[str, list[Trajectory]] = {}
    for i, name in enumerate(names):
        runs = [(a, b) for a, b in iter_valid_runs(usable[:, i]) if b - a + 1 >= min_frames]
        out[name] = [
            segment_trajectory(
                7, 6, [joint], time_s, world_from_objects[:, i : i + 1], run, smoothing, f"{stem}_{name}_{k:02d}"
            )
            for k, run in enumerate(runs)
        ]
    return out


def load_object_trajectories(
    track_json: Path, smoothing: SmoothingOptions | None = None, min_frames: int | None = None
) -> dict[str, list[Trajectory]]:
    """`object_trajectories` of a `track.json` written by `track` (its poses, valid mask and frame times)."""
    return track_payload_trajectories(json.loads(Path(track_json).read_text()), smoothing, min_frames)


def track_payload_trajectories(
    payload: Mapping[str, Any], smoothing: SmoothingOptions | None = None, min_frames: int | None = None
) -> dict[str, list[Trajectory]]:
    """`load_object_trajectories` of a `track.json` already read."""
    names = list(payload["object_names"])
    valid = np.array([payload["objects"][n]["valid"] for n in names], dtype=bool).T
    poses = np.tile(np.eye(4), (len(valid), len(names), 1, 1))
    for i, name in enumerate(names):
        for f, row in enumerate(payload["objects"][name]["qpos"]):
            if row is not None:
                poses[f, i, :3, 3] = row[:3]
                poses[f, i, :3, :3] = matrix_from_quat(np.asarray(row[3:7], float))
    sources = np.array([[s["source"] for s in payload["objects"][n]["scores"]] for n in names]).T
    time_s = (int(payload["first_frame"]) + np.arange(len(valid))) / float(payload["fps"])
    options = TrackOptions()
    return object_trajectories(
        time_s,
        poses,
        valid,
        names,
        smoothing or options.smoothing,
        min_frames or options.min_segment_frames,
        Path(payload["clip"]).stem,
        sources=sources,
    )


@dataclass(frozen=True, kw_only=True)
class _JointAddress:
    pos: slice
    quat: slice
    dof: int


def iter_valid_runs(valid: np.ndarray) -> Iterator[tuple[int, int]]:
    """Every maximal run (first, last), inclusive, of True in a (F,) mask."""
    flags: list[bool] = [bool(v) for v in np.asarray(valid, bool)]
    start: int | None = None
    for f, ok in enumerate([*flags, False]):
        if ok and start is None:
            start = f
        elif not ok and start is not None:
            yield start, f - 1
            start = None


# ---------------------------------------------------------------- the output folder


def write_track_output(
    result: TrackResult,
    out_dir: Path,
    *,
    clip: Path,
    scene_xml: Path,
    camera: PinholeCamera,
    fps: float,
    options: TrackOptions,
    overwrite: bool = False,
    overview_bgr: np.ndarray | None = None,
) -> None:
    """Writes the segment trajectories, `track.json` and (if given) `overview.png` atomically into `out_dir`."""
    from image2sim_common.outdir import write_image
    from reconstruction import staged_output_dir

    with staged_output_dir(out_dir, overwrite=overwrite, error=InputError) as stage:
        if overview_bgr is not None:
            write_image(stage / "overview.png", overview_bgr, error=TrackError)
        for traj in result.trajectories:
            save_trajectory(traj, stage / f"{traj.name}.npz")
        objects = {}
        for i, name in enumerate(result.object_names):
            qpos_rows: list[list[float] | None] = []
            for f in range(len(result.time_s)):
                if result.valid[f, i]:
                    pose = result.world_from_objects[f, i]
                    qpos_rows.append(
                        [*np.round(pose[:3, 3], 7).tolist(), *np.round(quat_from_matrix(pose[:3, :3]), 7).tolist()]
                    )
                else:
                    qpos_rows.append(None)
            support = asdict(result.support[i]) if i < len(result.support) else None
            if support is not None and not np.isfinite(support["gap_m"]):
                support["gap_m"] = None
            objects[name] = {
                "tracked_fraction": round(float(result.valid[:, i].mean()), 4),
                "support": support,
                "valid": result.valid[:, i].astype(bool).tolist(),
                "qpos": qpos_rows,
                "scores": [_score_json(row[i]) for row in result.scores],
            }
        cam_rows = result.world_from_cam[:1] if result.static_camera else result.world_from_cam
        payload = {
            "format": "image2sim.track/1",
            "convention": (
                "valid[f] is False where the object was lost or hidden: its qpos is null there and no trajectory "
                "covers that frame. Trajectories (*.npz) are the segments: maximal runs of frames in which every "
                "object is tracked. Frame f of the clip is at time f / fps; per-frame lists start at first_frame. "
                "qpos = world position (m) then quaternion w-first of the scene's body frame; world_from_cam uses "
                "OpenCV axes; intrinsics in COLMAP pixel convention."
            ),
            "clip": str(clip),
            "scene_xml": str(scene_xml),
            "fps": fps,
            "first_frame": int(result.frame_index[0]),
            "num_frames": len(result.time_s),
            "object_names": list(result.object_names),
            "static_camera": result.static_camera,
            "world_from_cam": [None if not np.isfinite(p).all() else np.round(p, 9).tolist() for p in cam_rows],
            "intrinsics": {
                "width_px": camera.width_px,
                "height_px": camera.height_px,
                "fx_px": float(camera.cv_matrix[0, 0]),
                "fy_px": float(camera.cv_matrix[1, 1]),
                "cx_px": float(camera.cv_matrix[0, 2] + 0.5),
                "cy_px": float(camera.cv_matrix[1, 2] + 0.5),
            },
            "segments": [
                {"name": t.name, "first_frame": int(result.frame_index[a]), "last_frame": int(result.frame_index[b])}
                for t, (a, b) in zip(result.trajectories, result.segments, strict=True)
            ],
            "objects": objects,
            "object_markers": list(result.object_markers),
            "options": _options_json(options),
            "stage_seconds": {k: round(v, 2) for k, v in result.seconds.items()},
        }
        (stage / TRACK_JSON).write_text(json.dumps(payload, indent=1) + "\n")


def _score_json(score: FrameScore) -> dict[str, object]:
    out = asdict(score)
    for key, value in out.items():
        if isinstance(value, float) and not np.isfinite(value):
            out[key] = None
        elif isinstance(value, float):
            out[key] = round(value, 4)
    return out


def _options_json(options: TrackOptions) -> dict[str, object]:
    out = asdict(options)
    out.pop("object_markers")  # in "object_markers" with their placements
    return json.loads(json.dumps(out, default=str))
