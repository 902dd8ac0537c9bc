"""`track`: 6-DoF poses of a grounded scene's objects in every frame of a clip, by model-based tracking.

Pipeline, per clip:

1. **Camera.** Intrinsics are the scan's (`reconstruction/reconstruct.json` of the scene folder: the same camera
   films the scan and the clip; frames are undistorted with its k1, k2) unless given. The camera pose comes from the
   ArUco marker on the table (the scene's world frame is the marker frame): the marker is detected, then its whole
   image is aligned by an ECC homography (the four corners alone gave 4 mm / 0.25 deg on the toss sample, the
   aligned image 2 mm / 0.1 deg), and PnP runs on an 8 x 8 grid of marker-plane points. A static camera (decided
   from the marker's motion unless told) uses the median grid over up to 30 frames; a moving camera gets one pose
   per frame, and frames without the marker are lost for every object.
2. **Detection** (first frame, and whenever an object is not tracked): SIFT features of the frame (upsampled 2x:
   tabletop objects are small) are matched to a feature model of each object (SIFT of its textured mesh rendered
   from 26 directions, each feature with its 3D point from the rendered depth); PnP + RANSAC, repeated without the
   previous inliers (printed textures repeat across faces), gives up to 4 candidates; each is refined (step 3) and
   the one whose rendering best matches the frame (NCC) is kept.
3. **Tracking.** The pose is predicted at constant velocity from the two previous frames, then refined by
   render-and-compare: all tracked objects are rendered at their current poses (MuJoCo, colour + depth +
   segmentation, so objects occlude each other); the rendered object is first matched to the frame by masked
   ZNCC within +-120 px (impacts and the first frames break the prediction), then features of the rendering
   inside each object's eroded silhouette are followed into the frame by pyramidal Lucas-Kanade on locally
   contrast-normalised images (the rendering's lighting is not the clip's), back-projected with the rendered
   depth, and PnP (RANSAC, then Levenberg-Marquardt on the inliers) updates the pose. Repeated until the update is
   below 0.1 mm / 0.05 deg. After the forward pass, every track is extended backwards into the frames before it.
4. **Lost frames are flagged, never invented.** A frame's pose is rejected when too few features agree (inlier
   count or ratio, absolute and relative to the object's own recent values), when the rendering and the frame
   disagree (zero-mean normalised cross-correlation, absolute and relative), when less than half of the object is
   inside the image, when it puts the object into the table (or other static geometry) deeper than a tracked
   depth's error, when it lies farther from the constant-velocity prediction than the object's own speed allows
   (tracked, detected or tracked backwards alike), or, for the first / last frame of a run next to a gap (typically
   partly hidden), when it is off the run's motion.
5. **Output.** The trajectory format has no mask, so the clip is cut into *segments*: maximal runs of frames in
   which every object is tracked (at least `min_segment_frames`). Each segment is one trajectory file in the
   scene's joint order; velocities come from a Savitzky-Golay fit over the segment (window 7, order 2: exact in
   free flight; impacts are smoothed over the window). `track.json` beside them holds the per-frame, per-object
   `valid` mask, scores and reasons, poses (null where lost), the segments' frame ranges and the camera.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from grounder.tracking.camera import clip_camera, marker_camera_poses, undistorter
from grounder.tracking.inputs import load_scan, read_clip
from grounder.tracking.markers import (
    ObjectMarker,
    check_markers,
    combined_markers,
    marker_agreement,
    marker_object_poses,
    measure_markers,
    place_markers,
    placement_json,
    scene_markers,
)
from grounder.tracking.options import FrameScore, TrackError, TrackOptions, TrackResult
from grounder.tracking.output import iter_valid_runs, scene_trajectories, tracked_segments, write_track_output
from grounder.tracking.render import PinholeCamera, PoseRenderer
from grounder.tracking.support import (
    SupportFit,
    apply_support_scale,
    collision_points_body,
    fit_support_scale,
    snap_resting_depth,
)
from grounder.tracking.tracker import track_frames
from image2sim_common.progress import ProgressFn
from reconstruction.errors import InputError

if TYPE_CHECKING:
    import mujoco

log = logging.getLogger(__name__)


def apply_object_markers(
    grays: Sequence[np.ndarray],
    camera: PinholeCamera,
    world_from_cam: np.ndarray,
    names: Sequence[str],
    poses: np.ndarray,
    valid: np.ndarray,
    scores: list[list[FrameScore]],
    markers: Sequence[ObjectMarker],
    options: TrackOptions,
    *,
    progress: ProgressFn | None = None,
) -> tuple[dict[str, object], ...]:
    """Puts the object markers' poses into the model-based track (`options.marker_use`). In place.

    Markers without a place (from the scan or the layout) are placed from the model-based track
    (`place_markers`). This runs before the support correction, so the table also fixes the depth of the marker
    poses where the object rests. Where the track lost an object (hidden texture, blur, a first frame it was not
    found in) and its marker is seen, the marker's pose fills the frame. A marker whose poses lie more than
    `marker_max_spread_m` across the camera ray from the model-based track, or more than 5 deg off it (medians),
    is still used, but a warning says so: its place is likely wrong (moved after the scan). Returns each marker's
    `placement_json`.
    """
    views = measure_markers(grays, camera, world_from_cam, markers, options.aruco_dictionary, progress=progress)
    model_based = valid & np.array([[s.source in ("track", "detect") for s in row] for row in scores], bool)
    placed, placements = place_markers(
        views,
        markers,
        names,
        poses,
        model_based,
        ambiguity_ratio=options.marker_ambiguity_ratio,
        max_spread_m=options.marker_max_spread_m,
    )
    reference = np.where(valid[:, :, None, None], poses, np.nan)
    measured = marker_object_poses(
        views,
        placed,
        names,
        reference=reference,
        ambiguity_ratio=options.marker_ambiguity_ratio,
        max_rms_px=options.marker_max_rms_px,
    )
    agreement = marker_agreement(measured, poses, model_based, world_from_cam)
    for f, i in zip(*np.nonzero(measured.seen), strict=True):
        old = scores[f][i]
        pose = measured.world_from_objects[f, i].copy()
        if options.marker_use == "rotation" and model_based[f, i]:
            pose[:3, 3] = poses[f, i, :3, 3]
        poses[f, i] = pose
        valid[f, i] = True
        scores[f][i] = replace(old, source="marker", reason="", marker_rms_px=float(measured.rms_px[f, i]))
    records = []
    for marker, placement in zip(placed, placements, strict=True):
        if placement.object_name is None:
            records.append(placement_json(marker, placement))
            continue
        i = list(names).index(placement.object_name)
        frames, off_mm, off_deg = agreement[i]
        log.info(
            "object marker %d on %s: seen in %d of %d frames",
            marker.marker_id,
            placement.object_name,
            int(measured.seen[:, i].sum()),
            len(grays),
        )
        if frames and (off_mm > 1e3 * options.marker_max_spread_m or off_deg > 5.0):
            log.warning(
                "object marker %d on %s: its poses lie %.0f mm across the view / %.0f deg from the model-based track "
                "(median of %d frames); was it moved after the scan? Give its place again (--object-markers) or "
                "scan again",
                marker.marker_id,
                placement.object_name,
                off_mm,
                off_deg,
                frames,
            )
        records.append(placement_json(marker, placement, agreement[i]))
    return tuple(records)


# ---------------------------------------------------------------- track


def track(
    clip: Path,
    scene: Path,
    out_dir: Path | None,
    options: TrackOptions | None = None,
    *,
    overwrite: bool = False,
    progress: ProgressFn | None = None,
    scene_recorded_as: Path | None = None,
) -> TrackResult:
    """Tracks every object of a grounded scene through a clip; writes trajectories and `track.json` to `out_dir`.

    Args:
        clip: video file (or folder of images) in which the scene's objects move.
        scene: scene folder written by `ground` (or its scene.xml).
        out_dir: trajectory folder to write (new or empty unless `overwrite`), or None to only return the result.
        options: tracking settings; `aruco_size_m` is required (the camera pose comes from the marker).
        overwrite: replace a non-empty `out_dir` once the result is complete.
        progress: called as progress(stage, done, total).
        scene_recorded_as: the scene.xml path `track.json` names, where `scene` is a copy that will move (a staging
            folder); default: `scene`'s scene.xml.

    Returns:
        The poses, valid mask, scores, segments and their trajectories.

    Raises:
        TrackError: unreadable clip or scene, no marker, or no object tracked for `min_segment_frames` frames.
        GrounderError: no scene at `scene` (neither an MJCF file nor a folder with scene.xml).
    """
    from grounder.sim.scene_files import scene_xml_path

    options = options or TrackOptions()
    seconds: dict[str, float] = {}
    tick = time.perf_counter()
    scene_xml = scene_xml_path(Path(scene))
    if out_dir is not None:  # before the long work, not only when writing
        from reconstruction import check_output_dir

        check_output_dir(out_dir, overwrite=overwrite, inputs=(clip, scene_xml.parent), error=InputError)
    frames, fps = read_clip(Path(clip), options.max_frames, options.start_frame)
    _check_frame_count(clip, len(frames), options)
    height_px, width_px = frames[0].shape[:2]
    camera, dist = clip_camera(scene_xml, width_px, height_px, options)
    undistort = undistorter(camera, dist, width_px, height_px)
    frames = [undistort(f) for f in frames]
    grays = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in frames]
    world_from_cam, static = marker_camera_poses(grays, camera, options)
    seconds["read_and_camera"] = time.perf_counter() - tick

    tick = time.perf_counter()
    tracked = _track_scene(
        scene_xml, frames, fps, camera, world_from_cam, options, undistort, (height_px, width_px), progress=progress
    )
    model, names, markers = tracked.model, tracked.names, tracked.markers
    poses, valid, scores = tracked.poses, tracked.valid, tracked.scores
    seconds["tracking"] = time.perf_counter() - tick
    marker_records: tuple[dict[str, object], ...] = ()
    if markers:
        tick = time.perf_counter()
        marker_records = apply_object_markers(
            grays, camera, world_from_cam, names, poses, valid, scores, markers, options, progress=progress
        )
        seconds["object_markers"] = time.perf_counter() - tick

    support: list[SupportFit] = []
    if options.support_correction:
        support = _correct_support(model, names, poses, valid, world_from_cam, 1.0 / fps, options)
    time_s = (options.start_frame + np.arange(len(frames))) / fps
    segments = tracked_segments(valid, options.min_segment_frames)
    trajectories = scene_trajectories(model, scene_xml, Path(clip).stem, time_s, poses, segments, options.smoothing)
    for name, frac in zip(names, valid.mean(axis=0), strict=True):
        log.info("%s tracked in %.0f%% of the frames", name, 100 * frac)
    result = TrackResult(
        object_names=names,
        frame_index=options.start_frame + np.arange(len(frames)),
        time_s=time_s,
        world_from_objects=poses,
        valid=valid,
        scores=scores,
        world_from_cam=world_from_cam,
        static_camera=static,
        segments=tuple(segments),
        trajectories=trajectories,
        out_dir=None if out_dir is None else Path(out_dir),
        seconds=seconds,
        support=tuple(support),
        object_markers=marker_records,
    )
    if out_dir is not None:
        _check_tracked_runs(result, options.min_segment_frames)
        _write_result(
            result,
            Path(out_dir),
            frames,
            clip=Path(clip),
            scene_xml=scene_xml,
            recorded_as=scene_recorded_as or scene_xml,
            camera=camera,
            fps=fps,
            options=options,
            overwrite=overwrite,
        )
    return result


def _check_frame_count(clip: Path, count: int, options: TrackOptions) -> None:
    """Refuses a span of `count` frames shorter than a trajectory (`min_segment_frames`) before tracking it."""
    if options.min_segment_frames > count:  # not after tracking the whole clip
        lower = (
            f"or pass --min-segment-frames {count}"
            if count >= 3  # the fewest a trajectory may have (TrackOptions)
            else "a trajectory needs at least 3"
        )
        raise TrackError(
            f"{clip}: {count} frames to track, fewer than a trajectory's {options.min_segment_frames} "
            f"(--min-segment-frames); track a longer clip (or span: --start-frame, --max-frames) {lower}"
        )


@dataclass(frozen=True, kw_only=True)
class _SceneTrack:
    """The model-based track of a clip (`_track_scene`): the scene's model and object names, the object markers to
    put in, and the poses (F, N, 4, 4), valid mask (F, N) and scores of `track_frames`."""

    model: mujoco.MjModel
    names: tuple[str, ...]
    markers: tuple[ObjectMarker, ...]
    poses: np.ndarray
    valid: np.ndarray
    scores: list[list[FrameScore]]


def _track_scene(
    scene_xml: Path,
    frames: list[np.ndarray],
    fps: float,
    camera: PinholeCamera,
    world_from_cam: np.ndarray,
    options: TrackOptions,
    undistort: Callable[[np.ndarray], np.ndarray],
    size_px: tuple[int, int],
    *,
    progress: ProgressFn | None,
) -> _SceneTrack:
    """Tracks the scene's objects through the undistorted `frames` (`track_frames`) with the scene rendered at the
    clip's camera. The object markers (`options.object_markers`, with the scan's where `options.scene_markers`) are
    checked against the scene first, and with `options.scan_features` the scan's frames (`load_scan`, undistorted
    by `undistort`; `size_px`: the clip's height, width) join the feature models."""
    height_px, width_px = size_px
    with PoseRenderer(scene_xml, camera) as renderer:
        markers = options.object_markers
        if options.scene_markers:
            markers = combined_markers(markers, scene_markers(scene_xml.parent / "scene.json"))
        check_markers(markers, renderer.names, options.aruco_dictionary, options.aruco_id)
        scan = (
            load_scan(scene_xml, renderer.names, options, undistort, (height_px, width_px))
            if options.scan_features
            else None
        )
        poses, valid, scores = track_frames(
            frames, fps, renderer, world_from_cam, options, scan=scan, progress=progress
        )
        model: mujoco.MjModel = renderer.model
        names = renderer.names
    return _SceneTrack(model=model, names=names, markers=markers, poses=poses, valid=valid, scores=scores)


def _correct_support(
    model: mujoco.MjModel,
    names: Sequence[str],
    poses: np.ndarray,
    valid: np.ndarray,
    world_from_cam: np.ndarray,
    dt_s: float,
    options: TrackOptions,
) -> list[SupportFit]:
    """Per object, the depth correction from the table where it rests (`fit_support_scale`, applied where it fits)
    and, with `options.rest_snap`, each resting frame moved onto the table (`snap_resting_depth`; `dt_s`: the frame
    interval). Changes `poses` in place."""
    support: list[SupportFit] = []
    for i, name in enumerate(names):
        points = collision_points_body(model, name)
        fit = fit_support_scale(poses[:, i], valid[:, i], world_from_cam, points, max_gap_m=options.support_max_gap_m)
        if fit.applied:
            poses[:, i] = apply_support_scale(poses[:, i], valid[:, i], world_from_cam, fit.scale)
            log.info(
                "%s: rests %.1f mm %s the table as tracked; depth along the camera ray scaled by %.4f",
                name,
                abs(fit.gap_m) * 1e3,
                "above" if fit.gap_m > 0 else "inside",
                fit.scale,
            )
        if options.rest_snap:
            poses[:, i], snapped = snap_resting_depth(
                poses[:, i],
                valid[:, i],
                world_from_cam,
                points,
                dt_s,
                max_gap_m=options.support_max_gap_m,
            )
            fit = replace(fit, snapped_frames=snapped)
        support.append(fit)
    return support


def _check_tracked_runs(result: TrackResult, min_frames: int) -> None:
    """Refuses a result in which no object is tracked for `min_frames` frames in a row (nothing to write), and warns
    where no whole-scene trajectory is written (each object's own runs are still in `track.json`)."""
    names, valid, trajectories = result.object_names, result.valid, result.trajectories
    own_runs = {
        n: [r for r in iter_valid_runs(valid[:, i]) if r[1] - r[0] + 1 >= min_frames] for i, n in enumerate(names)
    }
    if not any(own_runs.values()):
        raise TrackError(
            f"no object is tracked for {min_frames} frames in a row (tracked fractions: "
            + ", ".join(f"{n} {100 * v:.0f}%" for n, v in zip(names, valid.mean(axis=0), strict=True))
            + "); check the marker size, the scene and the clip"
        )
    if not trajectories:
        log.warning(
            "no run of %d frames has every object tracked at once, so no whole-scene trajectory is written; "
            "each object's own tracked runs are in track.json (%s)",
            min_frames,
            ", ".join(f"{n}: {len(r)} run(s)" for n, r in own_runs.items()),
        )


def _write_result(
    result: TrackResult,
    out_dir: Path,
    frames: list[np.ndarray],
    *,
    clip: Path,
    scene_xml: Path,
    recorded_as: Path,
    camera: PinholeCamera,
    fps: float,
    options: TrackOptions,
    overwrite: bool,
) -> None:
    """Writes `result` into `out_dir` (`write_track_output`) with its `overview.png` (`track_overview` of the
    undistorted `frames`, rendering `scene_xml`); `track.json` names the scene `recorded_as`."""
    from grounder.tracking.overview import track_overview

    names, valid, scores = result.object_names, result.valid, result.scores
    world_from_cam, poses = result.world_from_cam, result.world_from_objects
    overview = track_overview(
        frames,
        scene_xml,
        camera,
        world_from_cam,
        poses,
        valid,
        np.array([[score.source for score in row] for row in scores]),
        names,
        options.start_frame,
    )
    write_track_output(
        result,
        out_dir,
        clip=clip,
        scene_xml=recorded_as,
        camera=camera,
        fps=fps,
        options=options,
        overwrite=overwrite,
        overview_bgr=overview,
    )
