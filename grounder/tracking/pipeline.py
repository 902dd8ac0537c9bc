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

import json
import logging
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from grounder.core.json_files import read_json_file
from grounder.core.trajectory import Trajectory, save_trajectory
from grounder.errors import GrounderError
from grounder.tracking.markers import (
    ObjectMarker,
    aligned_grid_px,
    check_markers,
    combined_markers,
    marker_agreement,
    marker_grid_m,
    marker_object_poses,
    marker_template,
    measure_markers,
    place_markers,
    placement_json,
    scene_markers,
)
from grounder.tracking.render import (
    FeatureModel,
    PinholeCamera,
    PoseRenderer,
    RenderedView,
    ScanFrame,
    backproject,
    build_feature_models,
    merged_feature_models,
    scan_feature_models,
)
from grounder.tracking.smooth import (
    SmoothingOptions,
    free_body_velocities,
    matrix_from_quat,
    pose_matrix,
    quat_from_matrix,
    rotation_angle_deg,
)
from grounder.tracking.support import (
    StaticGeometry,
    SupportFit,
    apply_support_scale,
    collision_points_body,
    fit_support_scale,
    snap_resting_depth,
)
from image2sim_common.progress import ProgressFn
from reconstruction import SIZE_RANGE_M, opened_video
from reconstruction.errors import InputError

log = logging.getLogger(__name__)

GRAVITY_M_S2 = 9.81

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


# ---------------------------------------------------------------- input


def read_clip(clip: Path, max_frames: int | None = None, start_frame: int = 0) -> tuple[list[np.ndarray], float]:
    """Frames (BGR uint8) of a video, or of a folder of images in natural name order (then 30 fps is assumed), and
    the frame rate.

    Reads frames start_frame, start_frame + 1, ... (at most max_frames of them). Every frame of the span is held in
    memory (they are the data): a span that would take more than `MAX_DECODED_BYTES` is refused before decoding.
    """
    from reconstruction import (
        MAX_DECODED_BYTES,
        check_decoded_all,
        check_frame_pixels,
        image_paths,
        image_size,
        read_image,
    )
    from reconstruction.errors import InputError

    clip = Path(clip)
    if not clip.exists():
        raise TrackError(f"clip {clip} does not exist; pass a video file or a folder of images")

    def check_span(count: int, width: float, height: float) -> None:
        span = max(0, count - start_frame) if max_frames is None else min(max(0, count - start_frame), max_frames)
        if span * width * height * 3 > MAX_DECODED_BYTES:
            raise TrackError(
                f"{clip}: {span} frames of {width:.0f}x{height:.0f} px would take "
                f"{span * width * height * 3 / 1e9:.1f} GB decoded; track a part of it with --max-frames "
                "(and --start-frame)"
            )

    frames: list[np.ndarray] = []
    try:
        if clip.is_dir():
            files = image_paths(clip)
            if start_frame < len(files):  # the span's size from the first image's header, before decoding any
                check_span(len(files), *image_size(files[start_frame]))
            stop = None if max_frames is None else start_frame + max_frames
            frames = [read_image(path) for path in files[start_frame:stop]]
            fps = 30.0
            count = len(files)
        else:
            capture = opened_video(clip)  # an unreadable file: said so, not "read 0 frames"
            try:
                fps = float(capture.get(cv2.CAP_PROP_FPS) or 0.0)
                count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
                width, height = capture.get(cv2.CAP_PROP_FRAME_WIDTH), capture.get(cv2.CAP_PROP_FRAME_HEIGHT)
                check_frame_pixels(clip, width, height, "the clip")
                check_span(count, width, height)
                index, stated = 0, count
                while max_frames is None or len(frames) < max_frames:
                    if not capture.grab():
                        check_decoded_all(clip, index, stated)  # the end of the file, or a break in it
                        break
                    if index >= start_frame:  # the frames before the span are decoded, not copied out
                        ok, image = capture.retrieve()
                        if not ok:
                            check_decoded_all(clip, index, stated)
                            break
                        frames.append(image)
                    index += 1
                count = max(count, index)
            finally:
                capture.release()
    except InputError as exc:  # an unreadable or truncated image or video, or a frame over the pixel limit
        raise TrackError(str(exc)) from exc
    if len(frames) < 2:
        where = f" from frame {start_frame} on (the clip has {count})" if start_frame else ""
        raise TrackError(f"{clip}: read {len(frames)} frame(s){where}; a clip needs at least 2 readable frames")
    if not fps > 0:
        raise TrackError(f"{clip}: the video does not state its frame rate; re-encode it with one")
    shapes = {f.shape for f in frames}
    if len(shapes) != 1:
        raise TrackError(f"{clip}: frames differ in size ({sorted(shapes)}); use frames of one size")
    return frames, fps


def distortion_folds(k1: float, k2: float, image_radius: float) -> bool:
    """Whether OpenCV's radial distortion r_d = r (1 + k1 r^2 + k2 r^4) stops increasing before the distorted radius
    reaches ``image_radius`` (normalised image coordinates): two scene directions would then land on one pixel, and
    no undistortion can tell them apart."""
    radius = np.linspace(0.0, 50.0 * max(image_radius, 1e-6), 200_001)
    slope = 1.0 + 3.0 * k1 * radius**2 + 5.0 * k2 * radius**4
    reached = radius * (1.0 + k1 * radius**2 + k2 * radius**4) >= image_radius
    if not reached.any():  # that radius is never reached: the mapping folds (or shrinks) first
        return True
    return bool((slope[: int(np.argmax(reached)) + 1] <= 0.0).any())


def scene_intrinsics(scene_xml: Path, width_px: int, height_px: int) -> tuple[PinholeCamera, np.ndarray]:
    """The scan's intrinsics, scaled to the clip's size, and OpenCV distortion (k1, k2, 0, 0)."""
    rec_json = scene_xml.parent / "reconstruction" / "reconstruct.json"
    if not rec_json.is_file():
        raise TrackError(
            f"{rec_json} not found: the scene does not say which camera filmed it; pass the clip's intrinsics "
            "(--intrinsics FX FY CX CY)"
        )
    redo = "re-run `image2sim ground` for this scene, or pass the clip's intrinsics (--intrinsics FX FY CX CY)"
    payload = read_json_file(rec_json, redo, TrackError)  # the scene may be someone else's: every value checked
    try:
        intr = payload["intrinsics"]
        keys = ("width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px")
        values = [float(intr[k]) for k in keys] + [float(intr.get(k, 0.0)) for k in ("k1", "k2")]
    except (ValueError, KeyError, TypeError, AttributeError, OverflowError) as exc:
        raise TrackError(f"{rec_json}: no readable camera intrinsics ({type(exc).__name__}: {exc}); {redo}") from exc
    if not (np.isfinite(values).all() and min(values[:4]) > 0):
        raise TrackError(
            f"{rec_json}: camera intrinsics {dict(zip(keys, values, strict=False))} are not positive finite numbers; "
            f"{redo}"
        )
    intr = dict(zip((*keys, "k1", "k2"), values, strict=True))
    corner_radius = np.hypot(
        max(intr["cx_px"], intr["width_px"] - intr["cx_px"]) / intr["fx_px"],
        max(intr["cy_px"], intr["height_px"] - intr["cy_px"]) / intr["fy_px"],
    )
    # A fit may bend the model a little past its data at the very corners; folding halfway out is no lens at all.
    if distortion_folds(intr["k1"], intr["k2"], 0.5 * corner_radius):
        raise TrackError(
            f"{rec_json}: distortion k1={intr['k1']:g}, k2={intr['k2']:g} folds the image over less than halfway to "
            f"its corners (no real lens does; frames could not be undistorted); {redo}"
        )
    sx, sy = width_px / intr["width_px"], height_px / intr["height_px"]
    if abs(sx - sy) > 1e-3:
        raise TrackError(
            f"the clip is {width_px}x{height_px} px but the scan was {intr['width_px']}x{intr['height_px']} (another "
            "aspect ratio); pass the clip's intrinsics (--intrinsics FX FY CX CY)"
        )
    camera = PinholeCamera.from_colmap(
        width_px, height_px, intr["fx_px"] * sx, intr["fy_px"] * sy, intr["cx_px"] * sx, intr["cy_px"] * sy
    )
    dist = np.array([intr.get("k1", 0.0), intr.get("k2", 0.0), 0.0, 0.0])
    return camera, dist


def load_scan(
    scene_xml: Path,
    names: Sequence[str],
    options: TrackOptions,
    undistort: Callable[[np.ndarray], np.ndarray],
    size_px: tuple[int, int],
) -> tuple[list[ScanFrame], list[np.ndarray]] | None:
    """Up to `scan_feature_frames` registered scan frames (undistorted like the clip) and each object's pose during
    the scan, for the feature models; None (logged) where the scene folder lacks them or the clip was filmed with
    another camera or at another size (`size_px`: the clip's height, width)."""
    rec_dir = scene_xml.parent / "reconstruction"
    transforms, manifest = rec_dir / "transforms.json", scene_xml.parent / "scene.json"
    if options.intrinsics_colmap is not None or not (transforms.is_file() and manifest.is_file()):
        log.info("feature models from renders only (no scan frames, or the clip has its own camera)")
        return None
    try:
        rows = read_json_file(transforms, "re-run `image2sim ground`")["frames"]
        if not (isinstance(rows, list) and rows and all(isinstance(r, dict) for r in rows)):
            raise ValueError(f"{transforms}: 'frames' is not a list of frames")
        objects = read_json_file(manifest, "re-run `image2sim ground`")["objects"]
        world_from_objects = [pose_matrix(objects[n]["pos_m"], objects[n]["quat_wxyz"]) for n in names]
        if not all(np.isfinite(pose).all() for pose in world_from_objects):
            raise ValueError(f"{manifest}: an object's pos_m or quat_wxyz is not finite")
    except (GrounderError, ValueError, KeyError, TypeError) as exc:
        log.warning("scan frames not used for the feature models: %s", exc)
        return None
    picks = np.unique(np.linspace(0, len(rows) - 1, min(len(rows), options.scan_feature_frames)).round().astype(int))
    frames = []
    for k in picks:
        image_path = (rec_dir / str(rows[k].get("file_path", ""))).resolve()
        if not image_path.is_relative_to(rec_dir.resolve()):  # an untrusted scene may name any image on disk
            log.warning("scan frames not used for the feature models: %s lies outside %s", image_path, rec_dir)
            return None
        image = cv2.imread(str(image_path))
        if image is None:
            continue
        if image.shape[:2] != tuple(size_px):
            log.info("feature models from renders only: the scan frames are not the clip's size")
            return None
        gray = cv2.cvtColor(undistort(image), cv2.COLOR_BGR2GRAY)
        # transforms.json: nerfstudio's camera-to-world with OpenGL camera axes (y up, z back).
        try:
            transform = np.asarray(rows[k]["transform_matrix"], float)
            if transform.shape != (4, 4) or not np.isfinite(transform).all():  # (2, 4, 4) would broadcast below
                raise ValueError(f"transform_matrix is not a finite 4 x 4 matrix (shape {transform.shape})")
            world_from_cam = transform @ np.diag([1.0, -1.0, -1.0, 1.0])
        except (KeyError, ValueError, TypeError) as exc:
            log.warning("scan frames not used for the feature models: %s frame %d: %s", transforms, k, exc)
            return None
        frames.append(ScanFrame(gray=gray, world_from_cam=world_from_cam))
    if not frames:
        return None
    return frames, world_from_objects


# ---------------------------------------------------------------- camera


def marker_camera_poses(
    frames_gray: list[np.ndarray], camera: PinholeCamera, options: TrackOptions
) -> tuple[np.ndarray, bool]:
    """Per-frame `world_from_cam` (F, 4, 4) from the ArUco marker (NaN where unseen), and whether it is static.

    The marker is detected, then its whole image is aligned (ECC homography); the pose is PnP on an 8 x 8 grid of
    marker-plane points. A static camera uses the median grid over up to 30 frames.
    """
    from reconstruction import aruco_detector, detect_marker_corners_px

    if options.aruco_size_m is None:
        raise TrackError("the camera pose comes from the ArUco marker on the table: pass its size (--aruco-size M)")
    detector = aruco_detector(options.aruco_dictionary)
    corners: list[np.ndarray | None] = []
    for gray in frames_gray:
        found = detect_marker_corners_px(gray, detector, options.aruco_id)
        corners.append(None if found is None else found - 0.5)  # COLMAP -> OpenCV pixel convention
    seen = [f for f, c in enumerate(corners) if c is not None]
    if not seen:
        raise TrackError(
            f"ArUco marker {options.aruco_dictionary} id {options.aruco_id} not found in any frame of the clip; "
            "keep the marker of the scan in view"
        )
    seen_corners = [c for c in corners if c is not None]
    median = np.median(np.stack(seen_corners), axis=0)
    spread_px = float(np.median([np.abs(c - median).max() for c in seen_corners]))
    size_m = options.aruco_size_m
    static = options.static_camera if options.static_camera is not None else spread_px < 1.0
    template, px_per_m = marker_template(options.aruco_dictionary, options.aruco_id, size_m)
    grid_m = marker_grid_m(size_m)
    object_points = np.concatenate([grid_m, np.zeros((len(grid_m), 1))], axis=1)

    def grid(f: int) -> np.ndarray | None:
        found = corners[f]
        if found is None:
            return None
        return aligned_grid_px(frames_gray[f], found, template, px_per_m, grid_m, size_m)

    def pose(image_points: np.ndarray) -> np.ndarray:
        ok, rvec, tvec = cv2.solvePnP(object_points, image_points, camera.cv_matrix, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            return np.full((4, 4), np.nan)
        rvec, tvec = cv2.solvePnPRefineLM(object_points, image_points, camera.cv_matrix, None, rvec, tvec)
        return np.linalg.inv(_pose_from_rt(rvec, tvec))

    if static:
        picks = seen[:: max(1, len(seen) // 30)]
        grids = [g for g in (grid(f) for f in picks) if g is not None]
        if not grids:
            raise TrackError("the marker was detected but its image could not be aligned; is it sharp and flat?")
        return np.repeat(pose(np.median(np.stack(grids), axis=0))[None], len(frames_gray), axis=0), True
    poses = []
    for f in range(len(frames_gray)):
        g = grid(f)
        poses.append(np.full((4, 4), np.nan) if g is None else pose(g))
    return np.stack(poses), False


# ---------------------------------------------------------------- image helpers


def normalise(gray: np.ndarray, sigma_px: float = 4.0) -> np.ndarray:
    """Local contrast normalisation (subtract the local mean, divide by the local deviation) as uint8 for LK."""
    g = gray.astype(np.float32)
    mean = cv2.GaussianBlur(g, (0, 0), sigma_px)
    centred = g - mean
    std = np.sqrt(cv2.GaussianBlur(centred * centred, (0, 0), sigma_px)) + 4.0
    return np.clip(128.0 + 40.0 * centred / std, 0, 255).astype(np.uint8)


def _zncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a.astype(np.float64) - a.mean()
    b = b.astype(np.float64) - b.mean()
    denom = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / denom) if denom > 0 else 0.0


def _template_shift(rend_norm: np.ndarray, real_norm: np.ndarray, mask: np.ndarray, search_px: int) -> np.ndarray:
    """Image shift (dx, dy) of the rendered object that best matches the frame within +-search_px (masked ZNCC).

    Gives Lucas-Kanade a start when the prediction is far off (first frames, impacts); zero when nothing matches.
    """
    rows, cols = np.nonzero(mask)
    if len(rows) == 0:
        return np.zeros(2)
    y0, y1, x0, x1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    height, width = real_norm.shape
    ry0, ry1 = max(0, y0 - search_px), min(height, y1 + search_px)
    rx0, rx1 = max(0, x0 - search_px), min(width, x1 + search_px)
    template = rend_norm[y0:y1, x0:x1].astype(np.float32) - 128.0
    region = real_norm[ry0:ry1, rx0:rx1].astype(np.float32) - 128.0
    if region.shape[0] < template.shape[0] or region.shape[1] < template.shape[1]:
        return np.zeros(2)
    weights = mask[y0:y1, x0:x1].astype(np.float32)
    score = cv2.matchTemplate(region, template * weights, cv2.TM_CCORR_NORMED, mask=weights)
    score = np.nan_to_num(score, nan=-1.0, posinf=-1.0, neginf=-1.0)
    _, best, _, (bx, by) = cv2.minMaxLoc(score)
    if best < 0.3:
        return np.zeros(2)
    return np.array([rx0 + bx - x0, ry0 + by - y0], np.float64)


def _pose_from_rt(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(rvec)[0]
    pose[:3, 3] = np.asarray(tvec).ravel()
    return pose


def _rt_from_pose(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return cv2.Rodrigues(pose[:3, :3])[0], pose[:3, 3].reshape(3, 1).copy()


# ---------------------------------------------------------------- the tracker


@dataclass
class _Step:
    pose: np.ndarray | None
    inliers: int = 0
    followed: int = 0
    ncc: float = float("nan")
    reason: str = ""

    def score(self, in_frame: float, *, source: str = "lost", reason: str = "") -> FrameScore:
        """This step's support as a frame's score: accepted (`source`) or rejected (`reason`)."""
        return FrameScore(
            inliers=self.inliers,
            inlier_ratio=self.inliers / max(self.followed, 1),
            ncc=self.ncc,
            in_frame=in_frame,
            source=source,
            reason=reason,
        )


class _Tracker:
    """Holds the renderer, the feature models and the per-object geometry for one clip."""

    def __init__(
        self,
        renderer: PoseRenderer,
        options: TrackOptions,
        scan: tuple[list[ScanFrame], list[np.ndarray]] | None = None,
    ) -> None:
        self.renderer = renderer
        self.options = options
        self.scan = scan
        self.camera = renderer.camera
        self.vertices = [self._object_vertices(i) for i in range(len(renderer.names))]
        self.radii = [float(np.linalg.norm(v, axis=1).max()) for v in self.vertices]
        self.static = StaticGeometry(renderer.model)
        self._features: list[FeatureModel] | None = None
        self._sift = cv2.SIFT.create()
        self._matcher = cv2.BFMatcher(cv2.NORM_L2)

    def _object_vertices(self, index: int) -> np.ndarray:
        """Vertices (V, 3) of the object's rendered meshes in its body frame."""
        import mujoco

        model = self.renderer.model
        body = model.body(self.renderer.names[index]).id
        points = []
        for g in range(model.ngeom):
            if model.geom_bodyid[g] != body or model.geom_group[g] > 2:
                continue
            if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
                m = model.geom_dataid[g]
                start, count = model.mesh_vertadr[m], model.mesh_vertnum[m]
                local = model.mesh_vert[start : start + count].astype(np.float64)
            else:
                local = (
                    np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
                    * model.geom_rbound[g]
                )
            rot = matrix_from_quat(model.geom_quat[g])
            points.append(local @ rot.T + model.geom_pos[g])
        if not points:
            raise TrackError(f"object {self.renderer.names[index]!r} has no visible geometry to track")
        return np.concatenate(points)

    @property
    def features(self) -> list[FeatureModel]:
        """Per object: SIFT of its textured mesh rendered from `detect_views` directions, plus (where the scene's
        scan frames are at hand) SIFT of the object in the scan's own frames (`scan_feature_models`)."""
        if self._features is None:
            world_from_cam = self.renderer.world_from_cam.copy()
            features = build_feature_models(self.renderer, self.radii, num_views=self.options.detect_views)
            if self.scan is not None:
                frames, world_from_objects = self.scan
                features = merged_feature_models(
                    features, scan_feature_models(self.renderer, frames, world_from_objects)
                )
                log.info("feature models from %d scan frames: %s", len(frames), [len(f.descriptors) for f in features])
            self.renderer.set_camera(world_from_cam)
            self._features = features
        return self._features

    def in_frame(self, index: int, world_from_object: np.ndarray) -> float:
        cam_from_object = np.linalg.inv(self.renderer.world_from_cam) @ world_from_object
        points = self.vertices[index] @ cam_from_object[:3, :3].T + cam_from_object[:3, 3]
        ahead = points[:, 2] > 1e-3
        if not ahead.any():
            return 0.0
        uv = self.camera.project(points[ahead])
        inside = (
            (uv[:, 0] >= 0) & (uv[:, 0] < self.camera.width_px) & (uv[:, 1] >= 0) & (uv[:, 1] < self.camera.height_px)
        )
        return float(inside.sum()) / len(points)

    def judge(
        self, index: int, step: _Step, typical: _Typical | None = None, expected: _Expected | None = None
    ) -> tuple[bool, str, float]:
        """Whether `step` is a pose of object `index` the frame supports (`_accept`), why not, and its in-image
        fraction."""
        if step.pose is None:
            return False, step.reason, 0.0
        fraction = self.in_frame(index, step.pose)
        depth_m = self.static.penetration_m(self.renderer.names[index], step.pose)
        ok, reason = _accept(step, fraction, self.options, typical, penetration_m=depth_m, expected=expected)
        return ok, reason, fraction

    # ---- render-and-compare

    def _follow(
        self,
        index: int,
        view: RenderedView,
        rend_norm: np.ndarray,
        real_norm: np.ndarray,
        pose: np.ndarray,
        search_px: int = 0,
    ) -> _Step:
        """One update of object `index` from one rendering: LK from rendering to frame, then PnP."""
        opts = self.options
        mask = (view.object_id == index).astype(np.uint8)
        if int(mask.sum()) < opts.min_area_px:
            return _Step(pose=None, reason=f"visible area {int(mask.sum())} px")
        inner = cv2.erode(mask, np.ones((7, 7), np.uint8))
        corners = cv2.goodFeaturesToTrack(rend_norm, opts.max_features, 0.01, 4, mask=inner, blockSize=7)
        if corners is None or len(corners) < opts.min_inliers:
            return _Step(pose=None, reason="too few features on the rendering")
        start = np.rint(corners.reshape(-1, 2)).astype(np.float32)
        shift = _template_shift(rend_norm, real_norm, inner, search_px) if search_px > 0 else np.zeros(2)
        window = (opts.lk_window_px, opts.lk_window_px)
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 40, 0.01)
        guess = (start + shift.astype(np.float32)).astype(np.float32)

        def flow(
            src: np.ndarray, dst: np.ndarray, points: np.ndarray, initial: np.ndarray
        ) -> tuple[np.ndarray, np.ndarray]:
            found, ok, _ = cv2.calcOpticalFlowPyrLK(
                src, dst, points, initial, None, None, window, opts.lk_levels, criteria, cv2.OPTFLOW_USE_INITIAL_FLOW
            )
            return np.asarray(found), np.asarray(ok)

        # Forward from the rendering to the frame, then back: a feature must return to within a pixel of its start.
        moved, status = flow(rend_norm, real_norm, start, guess)
        back, status_back = flow(real_norm, rend_norm, moved, start.copy())
        good = (status.ravel() == 1) & (status_back.ravel() == 1) & (np.linalg.norm(back - start, axis=1) < 1.0)
        followed = int(good.sum())
        if followed < opts.min_inliers:
            return _Step(pose=None, followed=followed, reason=f"{followed} features followed")
        cols, rows = start[good, 0].astype(int), start[good, 1].astype(int)
        depth = view.depth_m[rows, cols].astype(np.float64)
        points_cam = backproject(self.camera, start[good].astype(np.float64), depth)
        cam_from_world = np.linalg.inv(self.renderer.world_from_cam)
        cam_from_object = cam_from_world @ pose
        object_from_cam = np.linalg.inv(cam_from_object)
        points_obj = points_cam @ object_from_cam[:3, :3].T + object_from_cam[:3, 3]
        image_points = moved[good].astype(np.float64)
        rvec, tvec = _rt_from_pose(cam_from_object)
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            points_obj,
            image_points,
            self.camera.cv_matrix,
            None,
            rvec,
            tvec,
            useExtrinsicGuess=True,
            iterationsCount=200,
            reprojectionError=2.0,
            confidence=0.999,
            flags=cv2.SOLVEPNP_ITERATIVE,
        )
        if not ok or inliers is None or len(inliers) < opts.min_inliers:
            count = 0 if inliers is None else len(inliers)
            return _Step(pose=None, followed=followed, inliers=count, reason=f"{count} PnP inliers")
        keep = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(points_obj[keep], image_points[keep], self.camera.cv_matrix, None, rvec, tvec)
        # Appearance check on the rendering that produced this update (the pose moved by at most one update).
        ncc = _zncc(rend_norm[inner > 0], real_norm[inner > 0])
        new_pose = self.renderer.world_from_cam @ _pose_from_rt(rvec, tvec)
        return _Step(pose=new_pose, inliers=len(keep), followed=followed, ncc=ncc)

    def refine(self, poses: list[np.ndarray | None], active: list[int], real_norm: np.ndarray) -> dict[int, _Step]:
        """Render-and-compare iterations for the `active` objects (the others are rendered where `poses` says)."""
        current = list(poses)
        steps: dict[int, _Step] = {}
        pending = [i for i in active if current[i] is not None]
        for iteration in range(self.options.max_iterations):
            if not pending:
                break
            search_px = self.options.search_px if iteration == 0 else 0
            view = self.renderer.render(current)
            rend_norm = normalise(cv2.cvtColor(view.rgb, cv2.COLOR_RGB2GRAY))
            still = []
            for i in pending:
                pose = current[i]
                assert pose is not None
                step = self._follow(i, view, rend_norm, real_norm, pose, search_px)
                steps[i] = step
                if step.pose is None:
                    current[i] = None
                    continue
                moved_m = float(np.linalg.norm(step.pose[:3, 3] - pose[:3, 3]))
                turned = rotation_angle_deg(step.pose[:3, :3], pose[:3, :3])
                current[i] = step.pose
                if moved_m > self.options.converge_m or turned > self.options.converge_deg:
                    still.append(i)
            pending = still
        return steps

    # ---- detection

    def detect(
        self, index: int, frame_features: tuple[np.ndarray, np.ndarray], max_hypotheses: int = 4
    ) -> list[np.ndarray]:
        """Candidate poses of object `index` from SIFT matches against its feature model.

        Textures repeat (a printed box shows the same print on several faces), so one RANSAC consensus can be
        the wrong face: PnP + RANSAC is run up to `max_hypotheses` times, each time without the previous
        inliers, and the caller verifies each candidate by render-and-compare.
        """
        pixels, descriptors = frame_features
        model = self.features[index]
        if len(descriptors) < 2 or len(model.descriptors) < 2:
            return []
        pairs = self._matcher.knnMatch(model.descriptors, descriptors, k=2)
        query, train = [], []
        for pair in pairs:
            if len(pair) == 2 and pair[0].distance < 0.8 * pair[1].distance:
                query.append(pair[0].queryIdx)
                train.append(pair[0].trainIdx)
        object_points = model.points_object_m[query]
        image_points = pixels[train]
        candidates = []
        remaining = np.arange(len(query))
        for _ in range(max_hypotheses):
            if len(remaining) < self.options.detect_min_inliers:
                break
            try:
                ok, rvec, tvec, inliers = cv2.solvePnPRansac(
                    object_points[remaining],
                    image_points[remaining],
                    self.camera.cv_matrix,
                    None,
                    iterationsCount=2000,
                    reprojectionError=3.0,
                    confidence=0.9999,
                    flags=cv2.SOLVEPNP_EPNP,
                )
            except cv2.error:  # degenerate minimal sets (all points nearly coincident)
                break
            if not ok or inliers is None or len(inliers) < self.options.detect_min_inliers:
                break
            keep = remaining[inliers.ravel()]
            rvec, tvec = cv2.solvePnPRefineLM(
                object_points[keep], image_points[keep], self.camera.cv_matrix, None, rvec, tvec
            )
            if float(tvec[2, 0]) > 0:
                candidates.append(self.renderer.world_from_cam @ _pose_from_rt(rvec, tvec))
            remaining = np.setdiff1d(remaining, keep)
        return candidates

    def frame_features(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """SIFT of the frame upsampled 2x (objects are small in a tabletop clip), in frame pixels."""
        big = cv2.resize(gray, None, fx=2.0, fy=2.0, interpolation=cv2.INTER_LINEAR)
        keypoints, descriptors = self._sift.detectAndCompute(big, None)
        if descriptors is None:
            return np.zeros((0, 2)), np.zeros((0, 128), np.float32)
        # Pixel centres: upsampled pixel u covers frame pixels (u - 0.5) / 2 .. (u + 0.5) / 2.
        return (np.array([kp.pt for kp in keypoints], np.float64) - 0.5) / 2.0, descriptors


def _predict(history: list[np.ndarray | None]) -> np.ndarray | None:
    """Constant-velocity prediction from the last two poses (constant pose from one; None without the last)."""
    last = history[-1] if history else None
    if last is None:
        return None
    before = history[-2] if len(history) >= 2 else None
    if before is None:
        return last.copy()
    pred = np.eye(4)
    pred[:3, 3] = 2 * last[:3, 3] - before[:3, 3]
    delta = last[:3, :3] @ before[:3, :3].T  # world-frame rotation over one frame
    rot = delta @ last[:3, :3]
    u, _, vt = np.linalg.svd(rot)
    pred[:3, :3] = u @ vt
    return pred


@dataclass(frozen=True, kw_only=True)
class _Expected:
    """Where an object's own motion puts it in a frame: the constant-velocity prediction and how far off it a pose
    may lie (`TrackOptions.max_jump_m`, `max_jump_at_rest_m`)."""

    pose: np.ndarray
    max_jump_m: float


def _expected(history: list[np.ndarray | None], dt_s: float, options: TrackOptions) -> _Expected | None:
    """The prediction from the last two poses of `history` (oldest first) and its allowed deviation; None without
    the last pose. With one pose the velocity is unknown, and only `max_jump_m` bounds the deviation."""
    prediction = _predict(history)
    if prediction is None:
        return None
    last, before = history[-1], history[-2] if len(history) >= 2 else None
    if last is None or before is None:
        return _Expected(pose=prediction, max_jump_m=options.max_jump_m)
    step_m = float(np.linalg.norm(last[:3, 3] - before[:3, 3]))
    allowed = options.max_jump_at_rest_m + 2.0 * step_m + GRAVITY_M_S2 * dt_s**2
    return _Expected(pose=prediction, max_jump_m=min(options.max_jump_m, allowed))


@dataclass
class _Typical:
    """An object's recent accepted inlier counts and NCCs: a partly hidden object falls well below its own typical
    values (absolute thresholds cannot tell: a rough grounded mesh matches its frames at NCC 0.5, a perfect one at
    0.98)."""

    inliers: list[int] = field(default_factory=list)
    ncc: list[float] = field(default_factory=list)

    def add(self, step: _Step, keep: int = 15) -> None:
        self.inliers = [*self.inliers, step.inliers][-keep:]
        self.ncc = [*self.ncc, step.ncc][-keep:]


def _accept(
    step: _Step,
    in_frame: float,
    options: TrackOptions,
    typical: _Typical | None = None,
    *,
    penetration_m: float = 0.0,
    expected: _Expected | None = None,
) -> tuple[bool, str]:
    """Whether a refined pose is supported: enough agreeing features, the rendering like the frame, in the image, out
    of the table (`penetration_m`: depth inside the static geometry) and, where the object was tracked in the frame
    before (`expected`), near where its motion puts it."""
    if step.pose is None:
        return False, step.reason
    ratio = step.inliers / max(step.followed, 1)
    min_inliers, min_ncc = float(options.min_inliers), options.min_ncc
    if typical is not None and len(typical.ncc) >= 3:
        min_inliers = max(min_inliers, options.relative_inliers * float(np.median(typical.inliers)))
        min_ncc = max(min_ncc, options.relative_ncc * float(np.median(typical.ncc)))
    if step.inliers < min_inliers or ratio < options.min_inlier_ratio:
        return False, f"{step.inliers} of {step.followed} features agree (need {min_inliers:.0f})"
    if not step.ncc >= min_ncc:
        return False, f"appearance NCC {step.ncc:.2f} (need {min_ncc:.2f})"
    if in_frame < options.min_in_frame:
        return False, f"{in_frame:.0%} in the image"
    if penetration_m > options.max_penetration_m:
        return False, f"{1e3 * penetration_m:.0f} mm inside the table or other static geometry"
    if expected is not None:
        jump_m = float(np.linalg.norm(step.pose[:3, 3] - expected.pose[:3, 3]))
        if jump_m > expected.max_jump_m:
            allowed_mm = 1e3 * expected.max_jump_m
            return False, f"{1e3 * jump_m:.0f} mm off the prediction (its motion allows {allowed_mm:.0f})"
    return True, ""


def track_frames(
    frames_bgr: list[np.ndarray],
    fps: float,
    renderer: PoseRenderer,
    world_from_cam: np.ndarray,
    options: TrackOptions,
    *,
    scan: tuple[list[ScanFrame], list[np.ndarray]] | None = None,
    progress: ProgressFn | None = None,
) -> tuple[np.ndarray, np.ndarray, list[list[FrameScore]]]:
    """Tracks every object through undistorted frames; returns poses (F, N, 4, 4) (NaN where lost), valid (F, N)
    and scores. `scan`: the scan's frames and the objects' poses in them, for the feature models (`load_scan`)."""
    report = progress or (lambda stage, done, total: None)
    tracker = _Tracker(renderer, options, scan)
    count, num = len(frames_bgr), len(renderer.names)
    poses = np.full((count, num, 4, 4), np.nan)
    valid = np.zeros((count, num), bool)
    scores: list[list[FrameScore]] = []
    history: list[list[np.ndarray | None]] = [[] for _ in range(num)]
    typical = [_Typical() for _ in range(num)]
    for f, frame in enumerate(frames_bgr):
        report("tracking", f, count)
        row: list[FrameScore] = [FrameScore() for _ in range(num)]
        if not np.isfinite(world_from_cam[f]).all():
            row = [FrameScore(reason="camera pose unknown") for _ in range(num)]
            for i in range(num):
                history[i].append(None)
            scores.append(row)
            continue
        renderer.set_camera(world_from_cam[f])
        gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        real_norm = normalise(gray)
        expected = [_expected(h, 1.0 / fps, options) for h in history]
        predicted = [None if e is None else e.pose for e in expected]
        steps = tracker.refine(predicted, [i for i in range(num) if predicted[i] is not None], real_norm)
        accepted: list[np.ndarray | None] = [None] * num
        for i, step in steps.items():
            ok, reason, fraction = tracker.judge(i, step, typical[i], expected[i])
            if ok:
                accepted[i] = step.pose
                typical[i].add(step)
                row[i] = step.score(fraction, source="track")
            else:
                row[i] = step.score(fraction, reason=reason)
        missing = [i for i in range(num) if accepted[i] is None]
        if missing:
            features = tracker.frame_features(gray)
            for i in missing:
                best: tuple[_Step, float] | None = None
                failure, failure_ncc = "", -np.inf  # why the best-matching rejected candidate was rejected
                for found in tracker.detect(i, features):
                    # Refine each candidate with the accepted objects in place (they may occlude it).
                    others = [accepted[j] if j != i else found for j in range(num)]
                    step = tracker.refine(others, [i], real_norm).get(i, _Step(pose=None, reason="no refinement"))
                    # Where the object was tracked in the frame before (its step failed), its motion bounds the
                    # detection as it bounds a step: else a pose the jump gate refused would come back here.
                    ok, reason, fraction = tracker.judge(i, step, typical[i], expected[i])
                    if not ok:
                        ncc = step.ncc if np.isfinite(step.ncc) else -np.inf
                        if not failure or ncc > failure_ncc:
                            failure, failure_ncc = reason, ncc
                    elif best is None or step.ncc > best[0].ncc:
                        best = (step, fraction)
                if best is None:
                    detected = f"detected, but {failure}" if failure else "not detected"
                    refused = row[i].reason  # the tracked step's, where there was one
                    row[i] = FrameScore(reason=f"{refused}; {detected}" if refused and failure else refused or detected)
                    continue
                step, fraction = best
                accepted[i] = step.pose
                typical[i].add(step)
                row[i] = step.score(fraction, source="detect")
        for i in range(num):
            pose = accepted[i]
            history[i].append(pose)
            if pose is not None:
                poses[f, i] = pose
                valid[f, i] = True
        scores.append(row)
    report("tracking", count, count)
    _track_backwards(tracker, frames_bgr, 1.0 / fps, world_from_cam, poses, valid, scores, typical, progress=report)
    _trim_run_edges(poses, valid, scores, options.max_edge_deviation_m)
    return poses, valid, scores


def _trim_run_edges(
    poses: np.ndarray, valid: np.ndarray, scores: list[list[FrameScore]], max_deviation_m: float
) -> None:
    """Drops a tracked run's first / last frame next to a gap when it disagrees with the run's motion. In place.

    The frames next to a gap are the partly hidden ones, where PnP on the visible part can still agree with
    itself and yet be off (28 mm seen on the occluded sample with 20% of the box covered). Such an edge frame must
    lie within `max_deviation_m` of the constant-acceleration extrapolation from its three inner neighbours
    (exact in free flight and in sliding; constant velocity from two when the run is that short); if not, it is
    flagged lost. One frame per edge at most: an impact right at a gap also breaks the extrapolation, and
    cascading would eat a genuine track.
    """
    count, num = valid.shape
    for i in range(num):
        for first, last in list(iter_valid_runs(valid[:, i])):
            length = last - first + 1
            if length < 3:
                continue
            edges = []
            if first > 0:
                edges.append((first, 1))
            if last < count - 1:
                edges.append((last, -1))
            for edge, step in edges:
                p1, p2 = poses[edge + step, i, :3, 3], poses[edge + 2 * step, i, :3, 3]
                guess = 2 * p1 - p2
                if length >= 4:
                    guess = 3 * p1 - 3 * p2 + poses[edge + 3 * step, i, :3, 3]
                deviation = float(np.linalg.norm(poses[edge, i, :3, 3] - guess))
                if deviation <= max_deviation_m:
                    continue
                valid[edge, i] = False
                poses[edge, i] = np.nan
                old = scores[edge][i]
                scores[edge][i] = FrameScore(
                    inliers=old.inliers,
                    inlier_ratio=old.inlier_ratio,
                    ncc=old.ncc,
                    in_frame=old.in_frame,
                    reason=f"{1e3 * deviation:.0f} mm off the motion of its tracked neighbours, next to a gap",
                )


def _track_backwards(
    tracker: _Tracker,
    frames_bgr: list[np.ndarray],
    dt_s: float,
    world_from_cam: np.ndarray,
    poses: np.ndarray,
    valid: np.ndarray,
    scores: list[list[FrameScore]],
    typical: list[_Typical],
    *,
    progress: ProgressFn,
) -> None:
    """Extends every track backwards into the frames before it, where the forward pass had not found the object yet
    (a wrong first detection, or the end of an occlusion seen only once the object is re-detected). In place."""
    count, num = valid.shape
    todo = [f for f in range(count - 2, -1, -1) if (~valid[f] & valid[f + 1]).any()]
    if not todo:
        return
    for f in range(count - 2, -1, -1):
        lost_here = [i for i in range(num) if not valid[f, i] and valid[f + 1, i]]
        if not lost_here or not np.isfinite(world_from_cam[f]).all():
            continue
        progress("tracking backwards", count - 1 - f, count)
        tracker.renderer.set_camera(world_from_cam[f])
        real_norm = normalise(cv2.cvtColor(frames_bgr[f], cv2.COLOR_BGR2GRAY))
        current: list[np.ndarray | None] = [poses[f, j] if valid[f, j] else None for j in range(num)]
        expected: dict[int, _Expected] = {}
        for i in lost_here:
            later = [poses[f + 2, i] if f + 2 < count and valid[f + 2, i] else None, poses[f + 1, i]]
            guess = _expected(later, dt_s, tracker.options)  # the motion run backwards: later frames first
            assert guess is not None
            expected[i] = guess
            current[i] = guess.pose
        steps = tracker.refine(current, lost_here, real_norm)
        for i in lost_here:
            step = steps.get(i, _Step(pose=None, reason="no refinement"))
            ok, _, fraction = tracker.judge(i, step, typical[i], expected[i])
            if ok and step.pose is not None:
                poses[f, i] = step.pose
                valid[f, i] = True
                scores[f][i] = step.score(fraction, source="track_backwards")


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


def _score_json(score: FrameScore) -> dict[str, object]:
    out = asdict(score)
    for key, value in out.items():
        if isinstance(value, float) and not np.isfinite(value):
            out[key] = None
        elif isinstance(value, float):
            out[key] = round(value, 4)
    return out


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
    import mujoco

    from grounder.sim.rollout import free_joints, scene_xml_path

    options = options or TrackOptions()
    seconds: dict[str, float] = {}
    tick = time.perf_counter()
    scene_xml = scene_xml_path(Path(scene))
    if out_dir is not None:  # before the long work, not only when writing
        from reconstruction import check_output_dir

        check_output_dir(out_dir, overwrite=overwrite, inputs=(clip, scene_xml.parent), error=InputError)
    frames, fps = read_clip(Path(clip), options.max_frames, options.start_frame)
    if options.min_segment_frames > len(frames):  # not after tracking the whole clip
        lower = (
            f"or pass --min-segment-frames {len(frames)}"
            if len(frames) >= 3  # the fewest a trajectory may have (TrackOptions)
            else "a trajectory needs at least 3"
        )
        raise TrackError(
            f"{clip}: {len(frames)} frames to track, fewer than a trajectory's {options.min_segment_frames} "
            f"(--min-segment-frames); track a longer clip (or span: --start-frame, --max-frames) {lower}"
        )
    height_px, width_px = frames[0].shape[:2]
    if options.intrinsics_colmap is not None:
        fx, fy, cx, cy = options.intrinsics_colmap
        # A focal length outside 0.05-50 image widths is not a camera (a 170-degree fisheye to a 1-degree telephoto);
        # 1e300 px made OpenCV's pose solver fail an assertion.
        focal_ok = all(0.05 * width_px <= f <= 50.0 * width_px for f in (fx, fy))
        if not (np.isfinite([fx, fy, cx, cy]).all() and focal_ok and 0 < cx < width_px and 0 < cy < height_px):
            raise TrackError(
                f"intrinsics fx {fx:g}, fy {fy:g}, cx {cx:g}, cy {cy:g} do not fit the {width_px}x{height_px} clip;"
                f" pass focal lengths of {0.05 * width_px:g}-{50 * width_px:g} px and a principal point inside the "
                "image, in pixels (COLMAP's PINHOLE)"
            )
        camera = PinholeCamera.from_colmap(width_px, height_px, fx, fy, cx, cy)
        dist = np.zeros(4)
    else:
        camera, dist = scene_intrinsics(scene_xml, width_px, height_px)
    maps = None
    if np.abs(dist).max() > 0:
        maps = cv2.initUndistortRectifyMap(
            camera.cv_matrix, dist, None, camera.cv_matrix, (width_px, height_px), cv2.CV_32FC1
        )

    def undistort(image: np.ndarray) -> np.ndarray:
        return image if maps is None else cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR)

    frames = [undistort(f) for f in frames]
    grays = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in frames]
    world_from_cam, static = marker_camera_poses(grays, camera, options)
    seconds["read_and_camera"] = time.perf_counter() - tick

    tick = time.perf_counter()
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
        for i, name in enumerate(names):
            points = collision_points_body(model, name)
            fit = fit_support_scale(
                poses[:, i], valid[:, i], world_from_cam, points, max_gap_m=options.support_max_gap_m
            )
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
                    1.0 / fps,
                    max_gap_m=options.support_max_gap_m,
                )
                fit = replace(fit, snapped_frames=snapped)
            support.append(fit)
    time_s = (options.start_frame + np.arange(len(frames))) / fps
    segments = tracked_segments(valid, options.min_segment_frames)
    joints = [
        _JointAddress(pos=fj.pos, quat=fj.quat, dof=int(model.jnt_dofadr[model.body(fj.body).jntadr[0]]))
        for fj in free_joints(model)
    ]
    if len(joints) != model.njnt:
        raise TrackError(
            f"{scene_xml} has {model.njnt} joints but only {len(joints)} free ones; tracking writes free bodies only"
        )
    stem = Path(clip).stem
    trajectories = tuple(
        segment_trajectory(model.nq, model.nv, joints, time_s, poses, seg, options.smoothing, f"{stem}_{k:02d}")
        for k, seg in enumerate(segments)
    )
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
        own_runs = {
            n: [r for r in iter_valid_runs(valid[:, i]) if r[1] - r[0] + 1 >= options.min_segment_frames]
            for i, n in enumerate(names)
        }
        if not any(own_runs.values()):
            raise TrackError(
                f"no object is tracked for {options.min_segment_frames} frames in a row (tracked fractions: "
                + ", ".join(f"{n} {100 * v:.0f}%" for n, v in zip(names, valid.mean(axis=0), strict=True))
                + "); check the marker size, the scene and the clip"
            )
        if not trajectories:
            log.warning(
                "no run of %d frames has every object tracked at once, so no whole-scene trajectory is written; "
                "each object's own tracked runs are in track.json (%s)",
                options.min_segment_frames,
                ", ".join(f"{n}: {len(r)} run(s)" for n, r in own_runs.items()),
            )
        from grounder.tracking.overview import track_overview

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
            Path(out_dir),
            clip=Path(clip),
            scene_xml=scene_recorded_as or scene_xml,
            camera=camera,
            fps=fps,
            options=options,
            overwrite=overwrite,
            overview_bgr=overview,
        )
    return result


@dataclass(frozen=True, kw_only=True)
class _JointAddress:
    pos: slice
    quat: slice
    dof: int


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


def _options_json(options: TrackOptions) -> dict[str, object]:
    out = asdict(options)
    out.pop("object_markers")  # in "object_markers" with their placements
    return json.loads(json.dumps(out, default=str))


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
