"""`reconstruct`: frames -> pycolmap SfM -> metric, gravity-aligned world frame -> files other tools can read."""

from __future__ import annotations

import json
import logging
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from image2sim_common.outdir import staged_output_dir, write_image
from image2sim_common.progress import ProgressFn, no_progress
from reconstruction import _frames, _sfm, _world
from reconstruction._colmap import pycolmap
from reconstruction._preview import write_preview
from reconstruction._types import (
    CameraIntrinsics,
    ReconstructionResult,
    ReconstructOptions,
    RegisteredFrame,
    ScaleSource,
    WorldFrame,
)
from reconstruction.errors import InputError, RegistrationError, WorldFrameError

log = logging.getLogger(__name__)

MIN_REGISTRATION_RATE = 0.5
MAX_SEED = 2**31 - 1
SIZE_RANGE_M = (0.005, 5.0)
"""A marker's side or an object's extent as a user gives it, metres: millimetres typed as metres fall outside."""
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])

ProgressFn = ProgressFn  # (stage, done, total)


def _validate(options: ReconstructOptions) -> None:
    if options.aruco_size_m is not None and options.known_extent_m is not None:
        raise InputError("give either --aruco-size or --known-extent, not both")
    for name, value in (("--aruco-size", options.aruco_size_m), ("--known-extent", options.known_extent_m)):
        if value is not None and not (SIZE_RANGE_M[0] <= value <= SIZE_RANGE_M[1]):
            raise InputError(
                f"{name} is {value} m but must be between {SIZE_RANGE_M[0]:g} and {SIZE_RANGE_M[1]:g} m (metres, not "
                "millimetres)"
            )
    if not 0 <= options.sfm.seed <= MAX_SEED:  # COLMAP keeps its seed in a C int
        raise InputError(f"--seed is {options.sfm.seed} but must be between 0 and {MAX_SEED}")
    if options.frames.max_frames < _frames.MIN_FRAMES:
        raise InputError(f"--max-frames is {options.frames.max_frames} but must be at least {_frames.MIN_FRAMES}")


def intrinsics_of(camera: pycolmap.Camera) -> CameraIntrinsics:
    """Pinhole part and radial terms of a COLMAP camera, whatever its model."""
    model = camera.model.name
    params = np.asarray(camera.params, float)
    k1 = k2 = 0.0
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        f, cx, cy = params[:3]
        fx = fy = f
        k1 = float(params[3]) if len(params) > 3 else 0.0
        k2 = float(params[4]) if len(params) > 4 else 0.0
    else:  # PINHOLE, OPENCV, FULL_OPENCV, ...: fx, fy, cx, cy first
        fx, fy, cx, cy = params[:4]
        if len(params) > 4:
            k1, k2 = float(params[4]), float(params[5])
    return CameraIntrinsics(
        width_px=int(camera.width),
        height_px=int(camera.height),
        fx_px=float(fx),
        fy_px=float(fy),
        cx_px=float(cx),
        cy_px=float(cy),
        k1=k1,
        k2=k2,
        colmap_model=model,
    )


def _apply_world(rec: pycolmap.Reconstruction, world_from_sfm: np.ndarray) -> None:
    scale = float(np.cbrt(np.linalg.det(world_from_sfm[:3, :3])))
    rotation = pycolmap.Rotation3d(world_from_sfm[:3, :3] / scale)
    rec.transform(pycolmap.Sim3d(scale, rotation, world_from_sfm[:3, 3]))


def reconstruct(
    source: Path,
    out_dir: Path,
    options: ReconstructOptions | None = None,
    *,
    overwrite: bool = False,
    progress: ProgressFn | None = None,
    on_mapping: Callable[[], None] | None = None,
) -> ReconstructionResult:
    """Cameras in a metric, gravity-aligned world frame from a video or an image folder.

    Writes to `out_dir` (atomically): `sparse/` (COLMAP model in the world frame), `images/` (the frames used),
    `transforms.json` (nerfstudio convention: camera-to-world, OpenGL camera axes), `reconstruct.json` and
    `preview.png` (points and cameras from above and from the side).

    Args:
        source: a video file or a folder of images.
        out_dir: output folder; must not exist or be empty unless `overwrite`.
        options: settings; the world frame comes from `aruco_size_m`, else `known_extent_m`, else unknown scale.
        overwrite: replace a non-empty `out_dir` once the new result is complete.
        progress: called as progress(stage, done, total) while work goes on.
        on_mapping: called once when incremental mapping starts, the input having been read and matched. With
            `options.sfm.num_threads` 1 (the default) mapping keeps one core busy for the rest of the stage, so a
            caller can start other work then (`grounder.ground` loads its later stages' libraries).

    Raises:
        InputError, RegistrationError, WorldFrameError: with a message that says what to change.
    """
    options = options or ReconstructOptions()
    _validate(options)
    source = Path(source)
    report = progress or no_progress
    seconds: dict[str, float] = {}
    _sfm._quiet_colmap()
    _frames.check_source(source)

    with staged_output_dir(Path(out_dir), overwrite=overwrite, inputs=(source,), error=InputError) as stage_dir:
        tick = time.perf_counter()
        report("reading frames", 0, 1)
        frames, num_source_frames = _frames.read_frames_counted(
            source, lambda done, total: report("reading frames", done, max(total, done))
        )
        selection = _frames.select_frames(frames, options.frames, num_source_frames, ordered=_frames.is_video(source))
        del frames
        image_dir = stage_dir / "images"
        image_dir.mkdir()
        names = []
        for frame in selection.kept:
            name = f"frame_{frame.index:05d}.jpg"
            write_image(image_dir / name, frame.image_bgr, [cv2.IMWRITE_JPEG_QUALITY, 95], error=InputError)
            names.append(name)
        index_of = {n: f.index for n, f in zip(names, selection.kept, strict=True)}
        # Find the marker before the expensive work, so a missing marker fails in seconds.
        observations = _detect_marker(selection.kept, names, options) if options.aruco_size_m is not None else []
        seconds["frames"] = time.perf_counter() - tick

        tick = time.perf_counter()
        work = stage_dir / "colmap"
        work.mkdir()
        database = work / "database.db"
        report("extracting SIFT features", 0, len(names))
        # A few stills carry each object in few views: COLMAP's own feature budget (8192 at up to 2048 px, not
        # a video's 3000 at 1024) is what puts sparse points on the objects, not only on the table.
        sfm = options.sfm if _frames.is_video(source) else options.sfm.for_photos()
        _sfm.extract_features(
            database, image_dir, names, sfm, lambda done: report("extracting SIFT features", done, len(names))
        )
        seconds["features"] = time.perf_counter() - tick
        tick = time.perf_counter()
        report("matching", 0, 1)  # image pairs: counted once listed
        sequential = _frames.is_video(source) or len(names) > options.sfm.exhaustive_max_images
        _sfm.match_features(
            database,
            len(names),
            sequential=sequential,
            options=options.sfm,
            work_dir=work,
            progress=lambda done, pairs: report("matching", done, pairs),
        )
        seconds["matching"] = time.perf_counter() - tick
        tick = time.perf_counter()
        if on_mapping is not None:
            on_mapping()
        registered = [0]

        def on_image() -> None:
            registered[0] += 1
            report("registering frames", registered[0], len(names))

        rec = _sfm.map_incremental(database, image_dir, work / "mapper", options.sfm, on_image)
        rate = rec.num_reg_images() / len(names)
        if rate < MIN_REGISTRATION_RATE:
            raise RegistrationError(
                f"structure from motion registered {rec.num_reg_images()} of {len(names)} frames "
                f"({rate:.0%}, need {MIN_REGISTRATION_RATE:.0%}); film more slowly, with more overlap and texture"
            )
        seconds["mapping"] = time.perf_counter() - tick

        tick = time.perf_counter()
        report("world frame", 0, 1)
        world = _establish_world(rec, observations, options)
        marker_names = {o.image_name for o in observations}
        _apply_world(rec, world.world_from_sfm)
        seconds["world_frame"] = time.perf_counter() - tick

        tick = time.perf_counter()
        sparse_dir = stage_dir / "sparse"
        sparse_dir.mkdir()
        rec.write(sparse_dir)
        # Keep the database (features and matches, for dense stereo later) but not the mapper's scratch copy.
        shutil.rmtree(work / "mapper", ignore_errors=True)
        (work / "vocab_tree.bin").unlink(missing_ok=True)
        camera = next(iter(rec.cameras.values()))
        intrinsics = intrinsics_of(camera)
        registered_frames = tuple(
            RegisteredFrame(
                frame_index=index_of[image.name],
                image_name=image.name,
                world_from_cam=_world_from_cam(image),
                sees_marker=image.name in marker_names,
            )
            for image in sorted(rec.images.values(), key=lambda im: im.name)
            if image.has_pose
        )
        points = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
        colors = np.array([p.color for p in rec.points3D.values()], np.uint8).reshape(-1, 3)
        result = ReconstructionResult(
            out_dir=Path(out_dir),
            source=source,
            num_source_frames=selection.num_source_frames,
            selected_frame_indices=tuple(f.index for f in selection.kept),
            dropped_blurred=selection.blurred,
            dropped_duplicate=selection.duplicate,
            intrinsics=intrinsics,
            frames=registered_frames,
            world=world,
            points_world_m=points,
            points_rgb=colors,
            mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()),
            stage_seconds=seconds,
        )
        write_transforms_json(stage_dir / "transforms.json", result)
        write_preview(stage_dir / "preview.png", result)
        seconds["write"] = time.perf_counter() - tick
        write_report(stage_dir / "reconstruct.json", result)
    return result


def rescale_written(result: ReconstructionResult, factor: float, note: str) -> ReconstructionResult:
    """The reconstruction with its world scaled by `factor` about the origin, and its output folder rewritten to
    match: the sparse model, `transforms.json`, `reconstruct.json` (scale, `world_from_sfm`, `note` added) and the
    preview. For a later, better scale estimate (`image2sim ground` refines a known extent on the segmented mesh):
    the folder then stays in the same metres as the scene built from it.
    """
    from dataclasses import replace

    sparse_dir = result.out_dir / "sparse"
    scaling = np.diag([factor, factor, factor, 1.0])
    model = pycolmap.Reconstruction(sparse_dir)
    _apply_world(model, scaling)
    model.write(sparse_dir)
    world_from_sfm = scaling @ result.world.world_from_sfm  # world = factor * (s R sfm + t)
    frames = []
    for frame in result.frames:
        pose = frame.world_from_cam.copy()
        pose[:3, 3] *= factor
        frames.append(replace(frame, world_from_cam=pose))
    world = replace(
        result.world,
        world_from_sfm=world_from_sfm,
        scale=result.world.scale * factor,
        notes=(*result.world.notes, note),
    )
    rescaled = replace(result, world=world, frames=tuple(frames), points_world_m=result.points_world_m * factor)
    write_transforms_json(result.out_dir / "transforms.json", rescaled)
    write_preview(result.out_dir / "preview.png", rescaled)
    write_report(result.out_dir / "reconstruct.json", rescaled)
    return rescaled


def _world_from_cam(image: pycolmap.Image) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :] = image.cam_from_world().inverse().matrix()
    return pose


def _detect_marker(
    kept: tuple[_frames.Frame, ...], names: list[str], options: ReconstructOptions
) -> list[_world.MarkerObservation]:
    detector = _world.aruco_detector(options.aruco_dictionary)
    observations = []
    for frame, name in zip(kept, names, strict=True):
        corners = _world.detect_marker_corners_px(frame.image_bgr, detector, options.aruco_id)
        if corners is not None:
            observations.append(_world.MarkerObservation(image_name=name, corners_px=corners))
    if not observations:
        raise WorldFrameError(
            f"--aruco-size was given but no ArUco marker {options.aruco_dictionary} id {options.aruco_id} "
            "was found in any frame; check the marker is in view with its white margin, or use --known-extent"
        )
    return observations


def _establish_world(
    rec: pycolmap.Reconstruction, observations: list[_world.MarkerObservation], options: ReconstructOptions
) -> WorldFrame:
    registered = [im for im in rec.images.values() if im.has_pose]
    cam_centres = np.array([im.projection_center() for im in registered])
    points = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    plane = _world.fit_support_plane(points, cam_centres, seed=options.sfm.seed)
    if options.aruco_size_m is not None:
        return _world.world_from_marker(rec, plane, observations, options.aruco_size_m)
    if options.known_extent_m is not None:
        return _world.world_from_extent(
            rec, plane, points, cam_centres, options.known_extent_m, provisional_ok=options.extent_on_meshes
        )
    log.warning(
        "SCALE UNKNOWN: no --aruco-size or --known-extent given; the world frame is gravity-aligned with the "
        "table at z = 0, but its units are arbitrary, not metres"
    )
    return _world.world_unknown_scale(rec, plane, points)


def write_transforms_json(path: Path, result: ReconstructionResult) -> None:
    """nerfstudio's transforms.json: camera-to-world `transform_matrix` with OpenGL camera axes."""
    k = result.intrinsics
    payload = {
        "camera_model": "OPENCV",
        "w": k.width_px,
        "h": k.height_px,
        "fl_x": k.fx_px,
        "fl_y": k.fy_px,
        "cx": k.cx_px,
        "cy": k.cy_px,
        "k1": k.k1,
        "k2": k.k2,
        "p1": 0.0,
        "p2": 0.0,
        "scale_source": str(result.world.scale_source),
        "frames": [
            {
                "file_path": f"images/{frame.image_name}",
                "transform_matrix": (frame.world_from_cam @ OPENGL_FROM_OPENCV).tolist(),
                "frame_index": frame.frame_index,
            }
            for frame in result.frames
        ],
    }
    path.write_text(json.dumps(payload, indent=1) + "\n")


def write_report(path: Path, result: ReconstructionResult) -> None:
    import importlib.metadata as md

    def version(pkg: str) -> str:
        try:
            return md.version(pkg)
        except md.PackageNotFoundError:
            return "unknown"

    world = result.world
    payload = {
        "source": str(result.source),
        "frames_in_source": result.num_source_frames,
        "frames_selected": len(result.selected_frame_indices),
        "frames_registered": len(result.frames),
        "registration_rate": result.registration_rate,
        "dropped_blurred": list(result.dropped_blurred),
        "dropped_duplicate": list(result.dropped_duplicate),
        "mean_reprojection_error_px": result.mean_reprojection_error_px,
        "num_points3d": len(result.points_world_m),
        "scale": {
            "source": str(world.scale_source),
            "metres_per_sfm_unit": world.scale if world.scale_source != ScaleSource.UNKNOWN else None,
            "marker_views": world.marker_views,
            "marker_corner_rms_px": None if np.isnan(world.marker_corner_rms_px) else world.marker_corner_rms_px,
        },
        "support_plane_inlier_ratio": world.plane_inlier_ratio,
        "world_from_sfm": world.world_from_sfm.tolist(),
        "intrinsics": {
            "model": result.intrinsics.colmap_model,
            "width_px": result.intrinsics.width_px,
            "height_px": result.intrinsics.height_px,
            "fx_px": result.intrinsics.fx_px,
            "fy_px": result.intrinsics.fy_px,
            "cx_px": result.intrinsics.cx_px,
            "cy_px": result.intrinsics.cy_px,
            "k1": result.intrinsics.k1,
            "k2": result.intrinsics.k2,
        },
        "notes": list(world.notes),
        "stage_seconds": {k: round(v, 3) for k, v in result.stage_seconds.items()},
        "versions": {p: version(p) for p in ("image2sim", "pycolmap", "opencv-contrib-python-headless", "numpy")},
    }
    path.write_text(json.dumps(payload, indent=1) + "\n")
