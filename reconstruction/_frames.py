"""Reading a video or an image folder, and choosing the frames worth giving to structure from motion."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from reconstruction._types import FrameSelectionOptions
from reconstruction.errors import InputError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
MIN_FRAMES = 3


@dataclass(frozen=True, kw_only=True)
class Frame:
    """One decoded frame: its index in the source and its pixels (H, W, 3) uint8 BGR."""

    index: int
    name: str
    image_bgr: np.ndarray


@dataclass(frozen=True, kw_only=True)
class FrameSelection:
    """Frames kept for SfM and why the others were dropped."""

    kept: tuple[Frame, ...]
    blurred: tuple[int, ...]
    duplicate: tuple[int, ...]
    num_source_frames: int
    sharpness: tuple[float, ...]


def is_video(source: Path) -> bool:
    return source.is_file()


def open_video(path: Path) -> cv2.VideoCapture:
    """`cv2.VideoCapture` of a video file with FFmpeg's own console messages off while it opens (an unreadable file
    then gives the caller's one error line, not FFmpeg's "moov atom not found" before it), unless the user set
    `OPENCV_FFMPEG_LOGLEVEL`."""
    key = "OPENCV_FFMPEG_LOGLEVEL"
    if key in os.environ:
        return cv2.VideoCapture(str(path))
    os.environ[key] = "-8"  # AV_LOG_QUIET
    try:
        return cv2.VideoCapture(str(path))
    finally:
        del os.environ[key]


def check_source(source: Path) -> None:
    """Fails fast, before any work is shown, on a source `read_frames` cannot read at all.

    Raises:
        InputError: the source is missing, a folder without images, or a file no video decoder opens.
    """
    if is_video(source):
        _opened_video(source).release()
    else:
        _check_path(source)


def _check_path(source: Path) -> None:
    if not source.exists():
        raise InputError(f"{source} does not exist; pass a video file or a folder of images")
    if not (source.is_dir() or source.is_file()):
        raise InputError(f"{source} is neither a video file nor a folder of images; pass one of those")
    if source.is_dir() and not any(p.suffix.lower() in IMAGE_SUFFIXES for p in source.iterdir()):
        raise InputError(f"{source} holds no images ({', '.join(IMAGE_SUFFIXES)}); pass a video or an image folder")


def _opened_video(source: Path) -> cv2.VideoCapture:
    """The open capture of a video file; the caller releases it."""
    capture = open_video(source)
    if not capture.isOpened():
        capture.release()
        raise InputError(f"{source} is not a readable video; pass an .mp4/.mov/.avi file or a folder of images")
    return capture


def read_frames(source: Path) -> list[Frame]:
    """Decodes every frame of a video file, or every image of a folder in natural name order.

    Raises:
        InputError: the source is missing, unreadable, has frames of different sizes or too few frames.
    """
    frames: list[Frame] = []
    if not is_video(source):
        _check_path(source)
        paths = sorted(
            (p for p in source.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES),
            key=lambda p: [int(t) if t.isdigit() else t for t in _split_digits(p.name)],
        )
        for i, path in enumerate(paths):
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None:
                raise InputError(f"{path} is not a readable image; remove it or convert it to PNG/JPEG")
            frames.append(Frame(index=i, name=path.name, image_bgr=image))
    else:
        capture = _opened_video(source)
        try:
            while True:
                ok, image = capture.read()
                if not ok:
                    break
                frames.append(Frame(index=len(frames), name=f"frame_{len(frames):05d}.png", image_bgr=image))
        finally:
            capture.release()
        if not frames:
            raise InputError(f"{source} decoded to no frames; check that it is a video file and not truncated")
    shapes = {f.image_bgr.shape for f in frames}
    if len(shapes) > 1:
        raise InputError(f"{source}: images have different sizes {sorted(shapes)}; one camera needs one image size")
    if len(frames) < MIN_FRAMES:
        raise InputError(
            f"{source} has {len(frames)} frame(s) but at least {MIN_FRAMES} are needed; film a longer orbit"
        )
    return frames


def _split_digits(name: str) -> list[str]:
    import re

    return re.findall(r"\d+|\D+", name)


def _gray_small(image_bgr: np.ndarray, work_size_px: int) -> np.ndarray:
    gray = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY)
    scale = work_size_px / max(gray.shape)
    if scale < 1:
        gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return gray


def sharpness(gray: np.ndarray) -> float:
    """Variance of the Laplacian: falls sharply with motion and defocus blur."""
    return float(cv2.Laplacian(gray, cv2.CV_64F).var())


def _median_motion_px(prev: np.ndarray, cur: np.ndarray) -> float:
    """Median displacement of corners tracked by pyramidal Lucas-Kanade (inf when nothing can be tracked)."""
    corners = cv2.goodFeaturesToTrack(prev, maxCorners=300, qualityLevel=0.01, minDistance=8)
    if corners is None or len(corners) < 10:
        return float("inf")
    moved, status, _ = cv2.calcOpticalFlowPyrLK(prev, cur, corners, corners.copy())
    ok = status.ravel() == 1
    if ok.sum() < 10:
        return float("inf")
    return float(np.median(np.linalg.norm((moved - corners)[ok].reshape(-1, 2), axis=1)))


def select_frames(frames: list[Frame], options: FrameSelectionOptions) -> FrameSelection:
    """Drops blurred frames (relative to their neighbours) and near-duplicates, then caps the count.

    Raises:
        InputError: the frames carry no texture to match, or too few frames survive.
    """
    grays = [_gray_small(f.image_bgr, options.work_size_px) for f in frames]
    sharp = np.array([sharpness(g) for g in grays])
    if np.median(sharp) < 1.0:
        raise InputError(
            "the frames are featureless (median Laplacian variance "
            f"{np.median(sharp):.2f}); film a textured scene in focus"
        )
    half = 5
    blurred = []
    for i in range(len(frames)):
        window = sharp[max(0, i - half) : i + half + 1]
        if sharp[i] < options.blur_ratio * np.median(window):
            blurred.append(frames[i].index)
    duplicate = []
    kept_positions: list[int] = []
    for i in range(len(frames)):
        if frames[i].index in blurred:
            continue
        if kept_positions and _median_motion_px(grays[kept_positions[-1]], grays[i]) < options.min_motion_px:
            duplicate.append(frames[i].index)
            continue
        kept_positions.append(i)
    if len(kept_positions) > options.max_frames:
        picks = np.linspace(0, len(kept_positions) - 1, options.max_frames).round().astype(int)
        kept_positions = [kept_positions[p] for p in np.unique(picks)]
    if len(kept_positions) < MIN_FRAMES:
        raise InputError(
            f"only {len(kept_positions)} usable frame(s) after dropping {len(blurred)} blurred and "
            f"{len(duplicate)} near-duplicate ones; film more slowly around the scene"
        )
    return FrameSelection(
        kept=tuple(frames[p] for p in kept_positions),
        blurred=tuple(blurred),
        duplicate=tuple(duplicate),
        num_source_frames=len(frames),
        sharpness=tuple(float(s) for s in sharp),
    )
