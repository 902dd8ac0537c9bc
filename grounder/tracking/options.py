"""What `track` takes and gives: its settings (`TrackOptions`, which double as the CLI section), its error
(`TrackError`), each frame's and object's support (`FrameScore`), what it measured (`TrackResult`), and the name of
the `track.json` it writes beside the trajectories.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from grounder.core.trajectory import Trajectory
from grounder.errors import GrounderError
from grounder.tracking.markers import ObjectMarker
from grounder.tracking.smooth import SmoothingOptions
from grounder.tracking.support import SupportFit
from reconstruction import SIZE_RANGE_M

TRACK_JSON = "track.json"


class TrackError(GrounderError):
    """The clip or the scene cannot be tracked (unreadable clip, no marker, no intrinsics, nothing found)."""


@dataclass(frozen=True, kw_only=True)
class TrackOptions:
    """Settings of `track`; doubles as the CLI section.

    Attributes:
        aruco_size_m: side of the marker's black square (DICT_4X4_50 unless `aruco_dictionary`), which gives the
            camera pose in the scene's world (= marker) frame.
        aruco_dictionary: OpenCV ArUco dictionary name.
        aruco_id: marker id.
        static_camera: True / False, or None to decide from the marker's motion (median corner motion < 1 px).
        intrinsics_colmap: (fx, fy, cx, cy) in pixels, COLMAP convention, or None for the scene's.
        start_frame: first frame of the clip to track (frame times stay the clip's: frame / fps).
        max_frames: track at most this many frames from `start_frame` (None: all).
        max_iterations: render-and-compare iterations per frame.
        converge_m, converge_deg: stop iterating once an update is smaller than both.
        max_features: Lucas-Kanade features per object and iteration.
        lk_window_px, lk_levels: Lucas-Kanade window and pyramid levels (levels catch fast motion).
        search_px: before the first iteration, the rendered object is matched (masked ZNCC) within this many
            pixels of its predicted place, which catches impacts and the first frames' unknown velocity.
        min_inliers, min_inlier_ratio: a pose needs this many agreeing features, and this fraction of those followed.
        min_ncc: least zero-mean normalised cross-correlation between rendering and frame inside the silhouette.
        relative_inliers, relative_ncc: a pose also needs these fractions of the object's own median inlier count
            and NCC over its last accepted frames (a partly hidden object falls below them).
        min_in_frame: least fraction of the object's mesh vertices inside the image.
        min_area_px: least visible silhouette area in pixels.
        max_jump_m: largest accepted distance from the constant-velocity prediction, however fast the object moves.
        max_jump_at_rest_m: largest accepted distance from it for an object at rest. A moving one may also deviate by
            twice its last frame's displacement (an impact can at most reverse the velocity) and by g dt^2 (gravity
            over one frame), up to `max_jump_m`. Applies to every pose with a prediction (the object tracked in the
            frame before): followed, re-detected after a failed step, or tracked backwards. The toss samples'
            correct poses lie at most 5.9 mm off the prediction at rest (moving camera; 5.0 static) and 1.5x the
            displacement at impacts; a resting object that is struck is lost for the frame it is struck in, then
            found again by detection.
        max_penetration_m: largest accepted depth of the object's collision geometry inside the scene's static
            geometry (the table; `grounder.tracking.support.StaticGeometry`). Correct poses of the toss samples reach
            6.3 mm on a grounded scene (its meshes' size error moves the depth; the support correction removes it
            later), 3.2 mm on the true one; wrong detections that matched the frame sat 18-65 mm inside the table.
        max_edge_deviation_m: a tracked run's first / last frame next to a gap (often partly hidden) must lie this
            close to the extrapolation of the run's motion, or it is flagged too.
        detect_min_inliers: PnP inliers needed to accept a detection.
        detect_views: rendered directions in each object's feature model.
        scan_features: also build each object's feature model from the scan's own frames (the scene folder's
            `reconstruction/`; only when the clip is filmed with the scan's camera, i.e. no `intrinsics_colmap`).
            Off by default: it finds objects sooner and tracks the toss a little better (1.32 -> 1.26 mm), but the
            calibration of four scans' tosses came out worse with it (11 of 18 values within 20%, against 14 of
            17): the windows it adds start in flight, where tracking is least certain (docs/results/tracking.md).
        scan_feature_frames: at most this many scan frames, evenly spread over the scan.
        min_segment_frames: shorter tracked runs are not written as trajectories (still in track.json).
        smoothing: the velocity fit.
        support_correction: scale each object's depth along the camera ray so that it rests on the table
            (`grounder.tracking.support`); support_max_gap_m: the largest gap it corrects.
        rest_snap: with `support_correction`, also move each frame in which an object lies still on the table onto
            it, one by one (`grounder.tracking.support.snap_resting_depth`): no depth jitter where it rests.
        object_markers: ArUco markers stuck on objects (`grounder.tracking.markers`; `--object-markers FILE`).
        scene_markers: also use the object markers `ground` measured in the scan (`scene.json`); a marker in
            `object_markers` overrides the scan's entry of the same id.
        marker_use: where an object's marker is seen, "pose" takes the pose from the marker, "rotation" only its
            orientation (the position stays the model-based track's). Where the model-based track lost the object,
            the marker's pose is taken either way.
        marker_ambiguity_ratio: with no model-based orientation to choose between a marker's two planar poses, the
            other must reproject this many times worse.
        marker_max_rms_px: a marker pose whose aligned grid reprojects worse than this (RMS) is not used.
        marker_max_spread_m: a marker without a place in the layout goes to the object it moves with; in 90% of the
            frames its pose in that object's frame must lie this close to its placement.
    """

    aruco_size_m: float | None = None
    aruco_dictionary: str = "DICT_4X4_50"
    aruco_id: int = 0
    static_camera: bool | None = None
    intrinsics_colmap: tuple[float, float, float, float] | None = None
    start_frame: int = 0
    max_frames: int | None = None
    max_iterations: int = 5
    converge_m: float = 1e-4
    converge_deg: float = 0.05
    max_features: int = 400
    lk_window_px: int = 25
    lk_levels: int = 2
    search_px: int = 120
    min_inliers: int = 12
    min_inlier_ratio: float = 0.5
    min_ncc: float = 0.4
    relative_inliers: float = 0.5
    relative_ncc: float = 0.8
    min_in_frame: float = 0.5
    min_area_px: int = 300
    max_jump_m: float = 0.08
    max_jump_at_rest_m: float = 0.015
    max_penetration_m: float = 0.01
    max_edge_deviation_m: float = 0.008
    detect_min_inliers: int = 15
    detect_views: int = 26
    scan_features: bool = False
    scan_feature_frames: int = 16
    min_segment_frames: int = 5
    smoothing: SmoothingOptions = field(default_factory=SmoothingOptions)
    support_correction: bool = True
    support_max_gap_m: float = 0.015
    rest_snap: bool = True
    object_markers: tuple[ObjectMarker, ...] = ()
    scene_markers: bool = True
    marker_use: str = "pose"
    marker_ambiguity_ratio: float = 3.0
    marker_max_rms_px: float = 0.5
    marker_max_spread_m: float = 0.01

    def __post_init__(self) -> None:
        low, high = SIZE_RANGE_M  # as reconstruct's
        if self.aruco_size_m is not None and not low <= self.aruco_size_m <= high:
            raise TrackError(
                f"aruco_size_m={self.aruco_size_m} but expected the square's side in metres, between {low:g} and "
                f"{high:g}, e.g. 0.12"
            )
        if self.start_frame < 0:
            raise TrackError(f"start_frame={self.start_frame} but expected >= 0")
        if self.max_frames is not None and self.max_frames < 2:
            raise TrackError(f"max_frames={self.max_frames} but expected at least 2")
        if self.min_segment_frames < 3:
            raise TrackError(f"min_segment_frames={self.min_segment_frames} but expected >= 3 (velocities need 3)")
        if self.marker_use not in ("pose", "rotation"):
            raise TrackError(f"marker_use={self.marker_use!r} but expected 'pose' or 'rotation'")


@dataclass(frozen=True, kw_only=True)
class FrameScore:
    """How well one object's pose in one frame is supported (NaN where not measured)."""

    inliers: int = 0
    inlier_ratio: float = float("nan")
    ncc: float = float("nan")
    in_frame: float = float("nan")
    source: str = "lost"  # "track", "detect", "track_backwards", "marker" or "lost"
    reason: str = ""
    marker_rms_px: float = float("nan")


@dataclass(frozen=True, kw_only=True)
class TrackResult:
    """What `track` measured and wrote.

    Attributes:
        object_names: body names of the tracked objects, in the scene's joint order.
        frame_index: (F,) index of each tracked frame in the clip.
        time_s: (F,) frame times (frame index / fps).
        world_from_objects: (F, N, 4, 4) poses; NaN where lost.
        valid: (F, N) True where the object is tracked.
        scores: per frame, per object.
        world_from_cam: (F, 4, 4) camera poses (OpenCV axes); NaN where unknown.
        static_camera: whether one camera pose was used for the whole clip.
        segments: (first, last) inclusive of each written trajectory, as indices into the tracked frames (add
            `frame_index[0]` for clip frames).
        trajectories: one per segment, in the scene's joint order.
        out_dir: where they were written (None if not written).
        seconds: wall time per stage.
        support: per object, the depth correction from the table where it rests (`grounder.tracking.support`);
            empty when `support_correction` is off.
        object_markers: per object marker, where it was placed and from how many frames (`placement_json`).
    """

    object_names: tuple[str, ...]
    frame_index: np.ndarray
    time_s: np.ndarray
    world_from_objects: np.ndarray
    valid: np.ndarray
    scores: list[list[FrameScore]]
    world_from_cam: np.ndarray
    static_camera: bool
    segments: tuple[tuple[int, int], ...]
    trajectories: tuple[Trajectory, ...]
    out_dir: Path | None
    seconds: dict[str, float]
    support: tuple[SupportFit, ...] = ()
    object_markers: tuple[dict[str, object], ...] = ()
