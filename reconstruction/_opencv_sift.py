"""SIFT by OpenCV, written into a COLMAP database for COLMAP's matcher and mapper (`SfmOptions.sift` "opencv").

OpenCV's SIFT finds the same kind of features as COLMAP's CPU SIFT about 4.5x faster on this project's 2-core
machine (the tabletop sample's 66 frames: 3.3 s on one thread against 14.8 s; 2026-12-07). What COLMAP's extraction
does is done the same way here: one shared camera from COLMAP's own image reader (`pycolmap.import_images`), frames
scaled down to ``max_image_size_px`` with keypoints given at the frame's own size, COLMAP's pixel convention (the
top-left pixel's centre is (0.5, 0.5), OpenCV's (0, 0)), RootSIFT descriptors (L1-normalised, square-rooted) stored
as COLMAP stores its own (x 512, rounded, capped at 255), at most ``max_num_features`` per frame, the strongest.

Settings matched to COLMAP's: OpenCV's contrast threshold 0.02 is COLMAP's peak threshold 0.02 / 3 octave layers;
the first octave works on the frame doubled with OpenCV's precise upscaling (its default upscaling shifts keypoints
by a fraction of a pixel: on the tabletop sample 0.91 mm median camera error after a similarity, against 0.63 mm
precise and 0.71 mm for COLMAP's SIFT); for ``first_octave`` 0 the frame is halved first, as OpenCV always doubles.

Each frame's features are a function of its pixels alone (sorted by strength, then position: OpenCV's own order
depends on its threads), computed by a few threads at once and written in frame order: the database is the same
every run.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from reconstruction._colmap import pycolmap
from reconstruction._parallel import ordered_ahead, usable_cores
from reconstruction._types import SfmOptions
from reconstruction.errors import InputError

CONTRAST_THRESHOLD = 0.02  # COLMAP's SIFT peak threshold (0.02 / 3 layers) in OpenCV's terms (it divides by 3 too)


def frame_features(path: Path, options: SfmOptions, first_octave: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4) float32 keypoints (x, y in COLMAP pixels of the frame, scale, orientation in radians) and (N, 128)
    uint8 descriptors of one frame, strongest first, at most ``options.max_num_features``."""
    gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if gray is None:
        raise InputError(f"{path}: OpenCV cannot read this image; use JPEG or PNG frames")
    height, width = gray.shape
    longest = max(height, width)
    if longest > options.max_image_size_px:
        factor = options.max_image_size_px / longest
        size = (max(1, round(width * factor)), max(1, round(height * factor)))
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
    if first_octave >= 0:  # OpenCV always starts on the frame doubled: halve it first to start at its own size
        gray = cv2.resize(gray, (max(1, gray.shape[1] // 2), max(1, gray.shape[0] // 2)), interpolation=cv2.INTER_AREA)
    sift = cv2.SIFT.create(
        nfeatures=0,
        nOctaveLayers=3,
        contrastThreshold=CONTRAST_THRESHOLD,
        edgeThreshold=10,
        sigma=1.6,
        descriptorType=cv2.CV_32F,
        enable_precise_upscale=True,
    )
    keypoints, descriptors = sift.detectAndCompute(gray, None)
    if not keypoints:
        return np.zeros((0, 4), np.float32), np.zeros((0, 128), np.uint8)
    found = np.array([(k.pt[0], k.pt[1], k.size, k.angle, k.response) for k in keypoints], np.float64)
    order = np.lexsort((found[:, 3], found[:, 2], found[:, 1], found[:, 0], -found[:, 4]))
    order = order[: options.max_num_features]
    found, raw = found[order], np.asarray(descriptors, np.float32)[order]
    scale_x, scale_y = width / gray.shape[1], height / gray.shape[0]
    points = np.column_stack(
        [
            (found[:, 0] + 0.5) * scale_x,
            (found[:, 1] + 0.5) * scale_y,
            0.5 * found[:, 2] * scale_x,
            np.deg2rad(found[:, 3]),
        ]
    ).astype(np.float32)
    root = np.sqrt(raw / np.maximum(raw.sum(axis=1, keepdims=True), 1e-12))
    return points, np.minimum(255.0, np.round(512.0 * root)).astype(np.uint8)


def extract(
    database_path: Path,
    image_dir: Path,
    image_names: Sequence[str],
    options: SfmOptions,
    first_octave: int,
    progress: Callable[[int], None] | None = None,
) -> None:
    """Every frame's features into a new database at ``database_path``, frames in the order given, one camera.

    ``progress(frames_done)`` is called in the calling thread as frames are written; Ctrl-C waits for the frames
    being worked on only (a fraction of a second each).
    """
    pycolmap.Database.open(database_path).close()  # the tables, for COLMAP's image reader to fill
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = options.camera_model
    pycolmap.import_images(
        database_path, image_dir, camera_mode=pycolmap.CameraMode.SINGLE, image_names=list(image_names), options=reader
    )
    workers = min(len(image_names), options.extraction_workers if options.extraction_workers > 0 else usable_cores())
    pool = ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="sift")
    try:
        features = ordered_ahead(
            pool, lambda name: frame_features(image_dir / name, options, first_octave), image_names, 2 * workers
        )
        with contextlib.closing(pycolmap.Database.open(database_path)) as db:
            image_id = {image.name: image.image_id for image in db.read_all_images()}
            missing = [name for name in image_names if name not in image_id]
            if missing:
                raise InputError(
                    f"{image_dir / missing[0]}: COLMAP's image reader did not take this frame (one camera: every "
                    "frame the same size, JPEG or PNG)"
                )
            for done, (name, (points, descriptors)) in enumerate(zip(image_names, features, strict=True), 1):
                db.write_keypoints(image_id[name], points)
                db.write_descriptors(
                    image_id[name], pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, descriptors)
                )
                if progress is not None:
                    progress(done)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
