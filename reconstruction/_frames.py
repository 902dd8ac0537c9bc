"""Reading a video or an image folder, and choosing the frames worth giving to structure from motion."""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from reconstruction._types import FrameSelectionOptions
from reconstruction.errors import InputError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
MIN_FRAMES = 3
MAX_IMAGE_PIXELS = 50_000_000  # an 8K frame is 33 Mpx
MAX_DECODED_BYTES = 2 << 30  # decoded frames held at once: ~340 1080p frames, ~85 4K frames


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


# FFmpeg's own console messages off (an unreadable file then gives the caller's one error line, not FFmpeg's
# "moov atom not found" before it), unless the user set the level. OpenCV reads it once, at its first FFmpeg
# capture in the process: setting it around each open, as before, silenced only a process's first video (the
# CLI test of an unreadable clip printed FFmpeg's line when its worker had opened a good video earlier).
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET


def open_video(path: Path) -> cv2.VideoCapture:
    """`cv2.VideoCapture` of a video file (FFmpeg's console messages off: see `OPENCV_FFMPEG_LOGLEVEL` above)."""
    return cv2.VideoCapture(str(path))


def check_source(source: Path) -> None:
    """Fails fast, before any work is shown, on a source `read_frames` cannot read at all.

    Raises:
        InputError: the source is missing, a folder without images, or a file no video decoder opens.
    """
    if is_video(source):
        opened_video(source).release()
    else:
        _check_path(source)


def _check_path(source: Path) -> None:
    if not source.exists():
        raise InputError(f"{source} does not exist; pass a video file or a folder of images")
    if not (source.is_dir() or source.is_file()):
        raise InputError(f"{source} is neither a video file nor a folder of images; pass one of those")
    if source.is_dir() and not any(p.suffix.lower() in IMAGE_SUFFIXES for p in source.iterdir()):
        raise InputError(f"{source} holds no images ({', '.join(IMAGE_SUFFIXES)}); pass a video or an image folder")


def opened_video(source: Path) -> cv2.VideoCapture:
    """The open capture of a video file; the caller releases it."""
    capture = open_video(source)
    if not capture.isOpened():
        capture.release()
        raise InputError(
            f"{source} is not a readable video (not a video file, or one cut short); pass an .mp4/.mov/.avi file or "
            "a folder of images"
        )
    return capture


def check_decoded_all(source: Path, decoded: int, stated: int) -> None:
    """Refuses a video whose decoding stopped before the frame count its container states (a file cut short, or
    damaged): the frames after the break would be missing without a word. A container that only estimates its
    count from duration x frame rate may be off by a frame or two, hence the margin.

    Raises:
        InputError: naming how many of the stated frames decoded.
    """
    if stated > 0 and decoded < stated - max(2, stated // 100):
        raise InputError(
            f"{source} stops decoding after {decoded} of the {stated} frames it states (the file is truncated or "
            f"damaged); copy or export it again, or cut it to the frames that decode "
            f"(ffmpeg -i {source.name} -frames:v {decoded} -c copy cut{source.suffix})"
        )


def image_paths(folder: Path) -> list[Path]:
    """The images of a folder (`IMAGE_SUFFIXES`), in natural name order (`2.png` before `10.png`)."""
    return sorted(
        (p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES),
        key=lambda p: [int(t) if t.isdigit() else t for t in _split_digits(p.name)],
    )


def check_frame_pixels(where: Path, width: float, height: float, what: str = "the images") -> None:
    """Refuses a frame larger than `MAX_IMAGE_PIXELS`, from its stated size, before anything is decoded.

    Raises:
        InputError: naming `where`, its size and the limit.
    """
    if width * height > MAX_IMAGE_PIXELS:
        raise InputError(
            f"{where} is {width:.0f}x{height:.0f} px, more than the {MAX_IMAGE_PIXELS / 1e6:.0f} Mpx a frame may "
            f"have; downscale {what}"
        )


def image_size(path: Path, *, check_whole: bool = False) -> tuple[int, int]:
    """(width, height) of an image from its header, without decoding it; checked by `check_frame_pixels`, and with
    ``check_whole`` also checked not to be cut short (`_check_whole`), in the same opening of the file.

    Raises:
        InputError: the image is unreadable, larger than `MAX_IMAGE_PIXELS` or (``check_whole``) truncated.
    """
    from PIL import UnidentifiedImageError

    try:
        with _pillow_open(path) as header:
            width, height = header.size
            check_frame_pixels(path, width, height)  # before a JPEG's wholeness check decodes any of it
            if check_whole:
                _check_whole(path, header)
    except (OSError, UnidentifiedImageError, ValueError) as exc:
        raise InputError(f"{path} is not a readable image; remove it or convert it to PNG/JPEG") from exc
    return width, height


@contextlib.contextmanager
def _pillow_open(path: Path) -> Iterator[Any]:
    """`PIL.Image.open`, with Pillow's own image-bomb check turned into this module's: its warning (from 89 Mpx)
    is not printed, and its error (from 179 Mpx) becomes the `MAX_IMAGE_PIXELS` refusal, which is stricter."""
    from PIL import Image

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        try:
            image = Image.open(path)
        except Image.DecompressionBombError as exc:
            raise InputError(
                f"{path} is larger than the {MAX_IMAGE_PIXELS / 1e6:.0f} Mpx a frame may have (its header states "
                f"over {2 * (Image.MAX_IMAGE_PIXELS or 0) / 1e6:.0f} Mpx); downscale the images"
            ) from exc
    with image:
        yield image


def _check_whole(path: Path, header: Any) -> None:
    """Refuses a JPEG or PNG (``header``: it, opened by Pillow) whose data ends before its image does (a copy cut
    short): OpenCV would decode such a JPEG with the missing rows grey, and only a "Premature end of JPEG file" on
    the console. A JPEG is checked by a decode at 1/8 scale (the decoder's own DCT scaling: the whole stream is read
    at a fraction of a full decode's cost), a PNG by Pillow's chunk checksums, without decompressing it."""
    try:
        if header.format == "JPEG":
            width, height = header.size
            header.draft("RGB", (max(1, width // 8), max(1, height // 8)))
            header.load()
        elif header.format == "PNG":
            header.verify()
    except (OSError, ValueError, SyntaxError) as exc:  # Pillow's PNG reader raises SyntaxError
        raise InputError(f"{path} is truncated or damaged ({exc}); copy it again from the camera or remove it") from exc


def read_image(path: Path) -> np.ndarray:
    """One image (H, W, 3) uint8 BGR, its size read from the header first (`image_size`): a small file that would
    decode to a huge image (an image bomb) is refused before it is decoded, and so is a truncated JPEG or PNG.

    Raises:
        InputError: the image is unreadable, truncated or larger than `MAX_IMAGE_PIXELS`.
    """
    image_size(path, check_whole=True)
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise InputError(f"{path} is not a readable image; remove it or convert it to PNG/JPEG")
    return np.asarray(image)


def read_frames(
    source: Path, progress: Callable[[int, int], None] | None = None, *, max_bytes: int = MAX_DECODED_BYTES
) -> list[Frame]:
    """As `read_frames_counted`, without the count of frames in the source."""
    return read_frames_counted(source, progress, max_bytes=max_bytes)[0]


def read_frames_counted(
    source: Path, progress: Callable[[int, int], None] | None = None, *, max_bytes: int = MAX_DECODED_BYTES
) -> tuple[list[Frame], int]:
    """Decodes the frames of a video file, or the images of a folder in natural name order.

    Decoded frames are kept within `max_bytes`: a long or high-resolution video keeps every 2nd, 4th, ... frame,
    evenly over its length (each frame keeps its index in the source), so memory does not grow with the video.
    `progress(done, total)` is called as frames are read (total 0 when a video does not state its length).

    Returns:
        The frames kept and how many frames the source has.

    Raises:
        InputError: the source is missing, unreadable, has frames of different sizes or too few frames.
    """
    source = Path(source)
    report = progress or (lambda _d, _t: None)
    kept: list[Frame] = []
    kept_bytes, stride = 0, 1

    def keep(frame: Frame) -> None:
        nonlocal kept, kept_bytes, stride
        kept.append(frame)
        kept_bytes += frame.image_bgr.nbytes
        if len(kept) > MIN_FRAMES and kept_bytes > max_bytes:
            kept, stride = kept[::2], stride * 2  # what is kept stays evenly spread: indices 0, 2 * stride, ...
            kept_bytes = sum(f.image_bgr.nbytes for f in kept)

    if not is_video(source):
        _check_path(source)
        paths = image_paths(source)
        for i, path in enumerate(paths):
            if i % stride == 0:
                keep(Frame(index=i, name=path.name, image_bgr=read_image(path)))
            report(i + 1, len(paths))
        count = len(paths)
    else:
        capture = opened_video(source)
        total = max(0, int(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0))
        try:
            check_frame_pixels(
                source, capture.get(cv2.CAP_PROP_FRAME_WIDTH), capture.get(cv2.CAP_PROP_FRAME_HEIGHT), "the video"
            )
            i = 0
            while capture.grab():  # decodes; the pixels are copied out only for the frames kept
                if i % stride == 0:
                    ok, image = capture.retrieve()
                    if not ok:
                        break
                    keep(Frame(index=i, name=f"frame_{i:05d}.png", image_bgr=image))
                i += 1
                report(i, total)
        finally:
            capture.release()
        count = i
        check_decoded_all(source, count, total)
        if not kept:
            raise InputError(f"{source} decoded to no frames; check that it is a video file and not truncated")
    shapes = {f.image_bgr.shape for f in kept}
    if len(shapes) > 1:
        raise InputError(f"{source}: images have different sizes {sorted(shapes)}; one camera needs one image size")
    if len(kept) < MIN_FRAMES:
        raise InputError(f"{source} has {len(kept)} frame(s) but at least {MIN_FRAMES} are needed; film a longer orbit")
    return kept, count


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


def select_frames(
    frames: list[Frame],
    options: FrameSelectionOptions,
    num_source_frames: int | None = None,
    *,
    ordered: bool = True,
) -> FrameSelection:
    """Drops blurred frames (relative to their neighbours) and near-duplicates, then caps the count.

    ``ordered`` False (a folder of photos): the frames are stills in no particular order, so neither test applies.
    A still's neighbours by file name are not the views beside it, and two photos that look alike are views worth
    matching, not a camera standing still; every photo goes to structure from motion, as COLMAP would take it.

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
    for i in range(len(frames) if ordered else 0):
        window = sharp[max(0, i - half) : i + half + 1]
        if sharp[i] < options.blur_ratio * np.median(window):
            blurred.append(frames[i].index)
    duplicate = []
    kept_positions: list[int] = []
    for i in range(len(frames)):
        if frames[i].index in blurred:
            continue
        if (
            ordered
            and kept_positions
            and _median_motion_px(grays[kept_positions[-1]], grays[i]) < options.min_motion_px
        ):
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
        num_source_frames=len(frames) if num_source_frames is None else num_source_frames,
        sharpness=tuple(float(s) for s in sharp),
    )
