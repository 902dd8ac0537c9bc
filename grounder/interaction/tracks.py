"""The tracks calibration reads: an `image2sim track` output folder as written (`saved_tracks`: the segments'
trajectories, each object's own runs and the camera centre from `track.json`), the camera poses and centre
(`camera_poses_of`, `view_point_of`), and the tracked poses as one whole-scene trajectory (`tracked_states`).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from grounder.core.trajectory import Trajectory, load_trajectories
from grounder.errors import GrounderError
from grounder.tracking.options import TrackOptions, TrackResult
from grounder.tracking.output import track_payload_trajectories
from image2sim_common.rotations import quat_from_matrix


@dataclass(frozen=True)
class SavedTracks:
    """What calibration reads of an `image2sim track` output folder.

    Attributes:
        segments: the trajectories of the tracked segments (every object tracked), in name order.
        object_tracks: per object its own tracked runs (`object_trajectories` of `track.json`).
        view_point_m: the camera centre (world, metres) from `track.json`'s camera poses; None if never known.
    """

    segments: list[Trajectory]
    object_tracks: dict[str, list[Trajectory]]
    view_point_m: tuple[float, float, float] | None


def saved_tracks(tracks_dir: Path, track_options: TrackOptions | None = None) -> SavedTracks:
    """The tracks of a `track` output folder as written: the segments' trajectory files, and each object's runs
    and the camera from `track.json` (poses rounded to 0.1 um there).

    `ground --interaction` calibrates from these rather than from the tracks it holds in memory, so that calibrating
    its saved tracks again (`benchmarks/track.py --calibrate --tracks`, which reads them here too) gives the same
    scene: a tumbling object's landings on its convex hulls are chaotic at the scale of that rounding, and on
    `samples/toss` the can's fit differed between the two (docs/results/interaction.md).
    """
    options = track_options or TrackOptions()
    track_json = Path(tracks_dir) / "track.json"
    try:
        payload = json.loads(track_json.read_text())
    except (OSError, ValueError) as exc:
        raise GrounderError(f"cannot read {track_json} ({exc}); pass a folder written by `image2sim track`") from exc
    segments = load_trajectories(tracks_dir) if any(Path(tracks_dir).glob("*.npz")) else []
    return SavedTracks(
        segments=segments,
        object_tracks=track_payload_trajectories(payload, options.smoothing, options.min_segment_frames),
        view_point_m=view_point_of(camera_poses_of(payload["world_from_cam"])),
    )


def camera_poses_of(rows: Sequence[Any]) -> np.ndarray:
    """(F, 4, 4) camera poses from `track.json`'s `world_from_cam` rows, NaN where a row is null (a moving camera
    in a frame without the marker)."""
    poses = np.full((len(rows), 4, 4), np.nan)
    for f, row in enumerate(rows):
        if row is not None:
            poses[f] = np.asarray(row, dtype=np.float64).reshape(4, 4)
    return poses


def view_point_of(world_from_cam: np.ndarray) -> tuple[float, float, float] | None:
    """The camera centre (world, metres) of a clip's (F, 4, 4) or (4, 4) camera poses, for weighing tracked depth:
    the mean over the frames where the camera is known (a moving camera's rays are then approximate); None if it is
    never known."""
    poses = np.asarray(world_from_cam, np.float64).reshape(-1, 4, 4)
    centres = poses[:, :3, 3]
    known = np.all(np.isfinite(centres), axis=1)
    if not known.any():
        return None
    x, y, z = (float(v) for v in centres[known].mean(axis=0))
    return (x, y, z)


def tracked_states(model: Any, tracked: TrackResult) -> list[Trajectory]:
    """Every frame in which at least two objects are tracked, as one whole-scene trajectory (zero velocities), with
    the untracked objects parked far from the table and from each other: what `separable_bodies` checks when no
    segment has every object tracked at once."""
    from grounder.sim.rollout import free_joints

    joints = free_joints(model)
    rows = np.nonzero(tracked.valid.sum(axis=1) >= 2)[0]
    if not len(rows):
        return []
    qpos = np.tile(model.qpos0, (len(rows), 1))
    for i, fj in enumerate(joints):
        qpos[:, fj.pos] = [1000.0 + 10.0 * i, 1000.0, 1000.0]
        qpos[:, fj.quat] = [1.0, 0.0, 0.0, 0.0]
        for k, f in enumerate(rows):
            if tracked.valid[f, i]:
                qpos[k, fj.pos] = tracked.world_from_objects[f, i, :3, 3]
                qpos[k, fj.quat] = quat_from_matrix(tracked.world_from_objects[f, i, :3, :3])
    return [Trajectory(time_s=tracked.time_s[rows], qpos=qpos, qvel=np.zeros((len(rows), model.nv)), name="tracked")]
