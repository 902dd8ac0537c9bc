"""What `track` reads besides the scene: the clip's frames (`read_clip`: a video, or a folder of images) and,
for the feature models, the scan's own registered frames with each object's pose during the scan (`load_scan`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np

from grounder.core.json_files import read_json_file
from grounder.errors import GrounderError
from grounder.tracking.options import TrackError, TrackOptions
from grounder.tracking.render import ScanFrame
from image2sim_common.rotations import pose_matrix
from reconstruction import opened_video

log = logging.getLogger(__name__)


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
