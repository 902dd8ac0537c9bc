"""Typed stage boundaries of the reconstruction stage.

Conventions (stated once, here):
- `world_from_cam` is a 4x4 rigid transform taking OpenCV/COLMAP camera coordinates (x right, y down, z forward)
  to world coordinates, in metres when the scale is known.
- The world frame is metric and gravity-aligned: z up along the support plane's normal, table top at z = 0.
  With an ArUco marker, world = marker frame (origin at its centre, x to the marker's right, y to its top).
- Pixel coordinates follow COLMAP: the centre of the upper-left pixel is (0.5, 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Literal

import numpy as np


class ScaleSource(StrEnum):
    """Where the metric scale of the world frame came from."""

    ARUCO = "aruco"
    KNOWN_EXTENT = "known_extent"
    UNKNOWN = "unknown"


@dataclass(frozen=True, kw_only=True)
class FrameSelectionOptions:
    """Which video frames go into structure from motion.

    Attributes:
        max_frames: keep at most this many frames (evenly spread over the video) after dropping bad ones.
        blur_ratio: a frame is blurred when its sharpness (variance of the Laplacian) is below this fraction of
            the median sharpness of its neighbourhood.
        min_motion_px: a frame is a near-duplicate when the median feature motion since the last kept frame is
            below this many pixels (at the working resolution).
        work_size_px: longest image side used for the selection measures.
    """

    max_frames: int = 150
    blur_ratio: float = 0.45
    min_motion_px: float = 2.0
    work_size_px: int = 480


@dataclass(frozen=True, kw_only=True)
class SfmOptions:
    """pycolmap structure-from-motion settings tuned for short tabletop videos on a CPU.

    Attributes:
        camera_model: COLMAP camera model shared by every frame.
        max_image_size_px: longest side at which SIFT runs (COLMAP rescales keypoints to full resolution).
        max_num_features: SIFT features per image.
        upsample_below_px: SIFT's first octave works on the frame doubled in size (COLMAP's ``first_octave`` -1, its
            default) when the frames' longest side, after ``max_image_size_px``, is below this; larger frames start
            at their own size (``first_octave`` 0). Small frames need the doubled octave: without it the 640 x 480
            tabletop sample is reconstructed in 21 s instead of 45 s with its cameras as close to the truth (2.4
            against 2.8 mm median), but from 42% fewer keypoints, and the bowl's mesh comes out 5.6 mm from the true
            one (Chamfer) instead of 2.7 mm, over the 3 mm target (2026-11-28); on the real apple video (1296 x 720,
            SIFT at 1024 px) doubling cost 2.5x the extraction, 1.4x the matching and 1.5x the mapping time for
            the same registration (46 of 46 frames, 0.56 against 0.63 px reprojection error, the mesh's IoU with
            the hand-drawn mask 0.77 against 0.78 without it; 2026-11-28). Decided once per video or folder, by
            its smallest frame.
        sequential_overlap: each frame is matched to this many following frames (video input).
        exhaustive_max_images: image folders with at most this many images are matched exhaustively.
        loop_detection: match frames that look alike far apart in time through a vocabulary tree built from
            this video's own descriptors (no download).
        num_threads: CPU threads for COLMAP's matching and mapping. One by default: with all cores (-1) the
            bundle adjustments are reproducible only to about 1e-11, and the meshing downstream turns that into a
            different bowl (0.1% of its volume) and a different tracking result on `samples/toss` (1.20 against
            1.38 mm median). Single-threaded, the same video gives a bit-identical model every run, in the same
            time on the tabletop's 2 cores. -1: all, for long videos on many cores. Matching alone on 2 threads
            is no exception (2026-11-27, the sample's database matched again three times: 384 instead of 385 pairs
            kept, 3-7 of them different each run, in 11-12 s against 13-14 s on one thread); `matching_workers`
            gets that speed without the difference.
        extraction_threads: CPU threads for SIFT extraction. One by default: pycolmap's multi-threaded extraction
            is not reproducible (the tabletop sample twice, same seed: 4669 and 4665 points, cameras up to 1 mm
            apart, the bowl's Chamfer error anywhere in 2.64-3.11 mm), single-threaded it is (to 1e-11), at about
            6 s more on the tabletop's 2 cores. -1: all, when speed matters more than the same scene every run.
        extraction_workers: with ``extraction_threads`` 1, the frames are split into this many contiguous shares,
            each extracted single-threaded in its own thread into its own database, and the databases merged in
            frame order: every table row for row and byte for byte as one thread writes it, in about half the
            time on 2 cores (`tests/reconstruction/test_reconstruct.py`). 0: one per CPU core this process may use.
            Shares that cannot be merged (frames of different sizes) are extracted again on one thread.
        matching_workers: with ``num_threads`` 1, the image pairs to match are split into this many shares, each
            matched and verified single-threaded in a worker process of its own, and the matches merged: the tables
            one thread writes, in about 70-80% of its time on 2 cores (`reconstruction._sfm.match_features`;
            processes, because pycolmap's matching run in several threads of one process gives other matches now
            and then). 0: one per CPU core this process may use.
        seed: random seed for RANSAC, the mapper and the loop-detection index (deterministic results).
        sift: which SIFT finds the features COLMAP matches and maps: "colmap" (pycolmap's own extraction; then
            ``extraction_threads`` and the shares below apply) or "opencv" (`reconstruction._opencv_sift`: 4.5x faster
            on 2 cores, cameras closer to the truth on the tabletop sample, 2.19 against 2.60 mm, the same meshes
            there; but on scene-family test seed 101 the toy figure's mesh then topples in the settle test, and the
            held-out family scenes 1054 and 1055 gained an extra body each: not the default until those are
            understood; docs/results/speed.md, 2026-12-07).
    """

    camera_model: str = "SIMPLE_RADIAL"
    sift: Literal["colmap", "opencv"] = "colmap"
    max_image_size_px: int = 1024
    max_num_features: int = 3000
    upsample_below_px: int = 1000
    sequential_overlap: int = 8
    exhaustive_max_images: int = 40
    loop_detection: bool = True
    num_threads: int = 1
    extraction_threads: int = 1
    extraction_workers: int = 0
    matching_workers: int = 0
    seed: int = 0
    photo_max_image_size_px: int = 2048
    photo_max_num_features: int = 8192

    def for_photos(self) -> SfmOptions:
        """The settings for a folder of stills: ``photo_max_image_size_px`` and ``photo_max_num_features`` (COLMAP's
        feature count) where they are larger. Family photo set 3 (26 photos, 1200 x 900) at the video settings kept
        13 sparse points above the table, too few to find a 6 cm ball."""
        from dataclasses import replace

        return replace(
            self,
            max_image_size_px=max(self.max_image_size_px, self.photo_max_image_size_px),
            max_num_features=max(self.max_num_features, self.photo_max_num_features),
        )


@dataclass(frozen=True, kw_only=True)
class ReconstructOptions:
    """Everything `reconstruct` needs besides its input and output paths; doubles as the CLI section.

    Attributes:
        aruco_size_m: side of the ArUco marker's black square (DICT_4X4_50, id 0) lying on the table.
        known_extent_m: longest extent of the largest object on the table, for videos without a marker.
        frames: frame selection settings; `frames.max_frames` is the CLI's `--max-frames`.
        sfm: structure-from-motion settings.
        aruco_dictionary: OpenCV ArUco dictionary name.
        aruco_id: id of the marker that defines the world frame.
        extent_on_meshes: with `known_extent_m`, when no cluster of sparse points stands above the table (a plain
            object), give a provisional scale (`WorldFrame.scale_provisional`) instead of refusing: for a caller
            that measures the known extent on the objects' meshes (`ground` does; `reconstruct` alone refuses).
    """

    aruco_size_m: float | None = None
    known_extent_m: float | None = None
    frames: FrameSelectionOptions = field(default_factory=FrameSelectionOptions)
    sfm: SfmOptions = field(default_factory=SfmOptions)
    aruco_dictionary: str = "DICT_4X4_50"
    aruco_id: int = 0
    extent_on_meshes: bool = False


@dataclass(frozen=True, kw_only=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels (COLMAP pixel convention) plus the radial distortion COLMAP estimated."""

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    k1: float = 0.0
    k2: float = 0.0
    colmap_model: str = "PINHOLE"

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) calibration matrix K for COLMAP pixel coordinates."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    @property
    def fovy_deg(self) -> float:
        return float(np.rad2deg(2 * np.arctan(0.5 * self.height_px / self.fy_px)))


@dataclass(frozen=True, kw_only=True)
class RegisteredFrame:
    """One video frame that structure from motion registered, with its pose in the world frame."""

    frame_index: int  # index in the source video (or sorted image folder)
    image_name: str
    world_from_cam: np.ndarray  # (4, 4), OpenCV camera axes
    sees_marker: bool = False

    @property
    def centre_world_m(self) -> np.ndarray:
        return self.world_from_cam[:3, 3]


@dataclass(frozen=True, kw_only=True)
class WorldFrame:
    """How SfM coordinates became the metric gravity-aligned world: world = scale * R @ sfm + t."""

    world_from_sfm: np.ndarray  # (4, 4) similarity transform (the scale is inside the rotation block)
    scale_source: ScaleSource
    scale: float  # metres per SfM unit (1.0 when unknown)
    plane_inlier_ratio: float  # fraction of sparse points on the support plane
    marker_views: int = 0  # frames in which the marker was detected and used
    marker_corner_rms_px: float = float("nan")  # reprojection RMS of the triangulated marker corners
    notes: tuple[str, ...] = ()
    # known extent with no cluster of sparse points above the table: a stand-in scale (the cameras at
    # `_world.NOMINAL_CAMERA_DISTANCE_M`) until the caller measures the known extent on the meshes (`ground`)
    scale_provisional: bool = False


@dataclass(frozen=True, kw_only=True)
class ReconstructionResult:
    """What `reconstruct` returns and writes to its output folder."""

    out_dir: Path
    source: Path
    num_source_frames: int
    selected_frame_indices: tuple[int, ...]
    dropped_blurred: tuple[int, ...]
    dropped_duplicate: tuple[int, ...]
    intrinsics: CameraIntrinsics
    frames: tuple[RegisteredFrame, ...]
    world: WorldFrame
    points_world_m: np.ndarray  # (N, 3) sparse points in the world frame
    points_rgb: np.ndarray  # (N, 3) uint8
    mean_reprojection_error_px: float
    stage_seconds: dict[str, float]

    @property
    def registration_rate(self) -> float:
        return len(self.frames) / max(1, len(self.selected_frame_indices))


@dataclass(frozen=True, kw_only=True)
class TexturedMesh:
    """A triangle mesh with an optional colour texture (MuJoCo shows textures, not vertex colours).

    Attributes:
        vertices_m: (V, 3) float64 vertex positions, metres, in the frame stated by the owner.
        faces: (F, 3) int64 vertex indices, counter-clockwise seen from outside.
        uv: (V, 2) float64 texture coordinates in [0, 1], OBJ convention (v = 0 is the image's bottom row),
            or None when untextured. Vertices on a UV seam are duplicated, so uv is per vertex.
        texture_rgb: (H, W, 3) uint8 texture image (row 0 is the top), or None.
    """

    vertices_m: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None
    texture_rgb: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.vertices_m.ndim != 2 or self.vertices_m.shape[1] != 3:
            raise ValueError(f"{self.vertices_m.shape=} but expected (V, 3)")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"{self.faces.shape=} but expected (F, 3)")
        if self.uv is not None and self.uv.shape != (len(self.vertices_m), 2):
            raise ValueError(f"{self.uv.shape=} but expected ({len(self.vertices_m)}, 2)")
        if (self.uv is None) != (self.texture_rgb is None):
            raise ValueError("uv and texture_rgb must be given together")


@dataclass(frozen=True, kw_only=True)
class ObjectInstance:
    """One segmented object of the scene, meshed in its own frame.

    Attributes:
        name: unique, a valid MJCF/file name (`object_0`, ...).
        mesh: watertight mesh in the object frame (origin at its bounding-box centre, axes parallel to world).
        world_from_object: (4, 4) pose of the object frame in the world frame, metres.
        num_views: frames in which the object is visible.
        closed_bottom: the unseen underside was closed with a flat cap on the table plane (an assumption).
        warnings: problems noticed (partly out of view, possibly several touching objects, ...).
        mesh_quality: "full" (meshed from its fused surface), "fallback" (that failed: the convex hull of its
            points, `reconstruction._objects.fallback_mesh`) or "silhouette" (no fused surface: the visual hull of
            its outlines against the table, `reconstruction._silhouette`; a cavity is closed).
        mesh_reason: why the full mesh failed, for a fallback.
        at_region_edge: its fused points reach a side of the region that was fused: it may go on past it, and its
            mesh be cut short there.
    """

    name: str
    mesh: TexturedMesh
    world_from_object: np.ndarray
    num_views: int = 0
    closed_bottom: bool = True
    warnings: tuple[str, ...] = ()
    mesh_quality: str = "full"
    mesh_reason: str | None = None
    at_region_edge: bool = False
