"""`image2sim track CLIP --scene SCENE_DIR -o TRAJ_DIR`: object trajectories from a clip, by model-based tracking."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
import typer


def register(app: typer.Typer) -> None:
    """Adds the `track` command to the image2sim CLI."""
    from grounder.cli.common import fail, require, setup_logging, stage_progress, user_errors_exit_2

    @app.command()
    def track(
        clip: Annotated[Path, typer.Argument(help="Video (or folder of images) in which the scene's objects move.")],
        scene: Annotated[Path, typer.Option("--scene", help="Scene folder written by `image2sim ground`.")],
        out: Annotated[
            Path, typer.Option("-o", "--out", help="Trajectory folder to write (created; must be new or empty).")
        ],
        aruco_size: Annotated[
            float,
            typer.Option(help="Side of the ArUco marker's black square in metres (DICT_4X4_50, id 0, on the table)."),
        ] = 0.12,
        intrinsics: Annotated[
            tuple[float, float, float, float] | None,
            typer.Option(help="FX FY CX CY of the clip's camera in pixels (default: the scan's camera)."),
        ] = None,
        static_camera: Annotated[
            bool | None,
            typer.Option("--static-camera/--moving-camera", help="Default: decided from the marker's motion."),
        ] = None,
        max_frames: Annotated[int | None, typer.Option(help="Track at most this many frames.")] = None,
        start_frame: Annotated[int, typer.Option(help="First frame of the clip to track (0-based).")] = 0,
        min_segment_frames: Annotated[
            int, typer.Option(help="Shortest run of fully tracked frames written as a trajectory.")
        ] = 5,
        object_markers: Annotated[
            Path | None,
            typer.Option(
                help="JSON layout of ArUco markers stuck on objects: ids, sizes, optionally objects and places "
                "(see docs/cli.md). Where seen, a marker gives its object's pose."
            ),
        ] = None,
        marker_use: Annotated[
            str, typer.Option(help="Where a marker is seen, take its 'pose', or only its 'rotation'.")
        ] = "pose",
        scan_features: Annotated[
            bool,
            typer.Option(
                help="Also learn each object's appearance from the scan's frames (finds weakly textured objects "
                "sooner; off by default, see docs/cli.md)."
            ),
        ] = False,
        overwrite: Annotated[bool, typer.Option(help="Replace a non-empty output folder once done.")] = False,
        verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log each step.")] = False,
    ) -> None:
        """6-DoF pose of every grounded object in every frame; lost frames flagged; trajectories per tracked run."""
        setup_logging(verbose)
        from reconstruction import SIZE_RANGE_M

        low, high = SIZE_RANGE_M
        require(
            ("--aruco-size", aruco_size, low <= aruco_size <= high, f"between {low:g} and {high:g} (metres)"),
            ("--min-segment-frames", min_segment_frames, min_segment_frames >= 3, ">= 3"),
            (
                "--max-frames",
                max_frames,
                max_frames is None or max_frames >= min_segment_frames,
                f">= --min-segment-frames ({min_segment_frames}): a shorter span can hold no trajectory",
            ),
            ("--start-frame", start_frame, start_frame >= 0, ">= 0"),
        )
        if marker_use not in ("pose", "rotation"):
            fail(f"--marker-use {marker_use}: expected pose or rotation")
        with user_errors_exit_2():
            from grounder.tracking.markers import load_object_markers
            from grounder.tracking.options import TrackOptions
            from grounder.tracking.pipeline import track as run_track

            markers = () if object_markers is None else load_object_markers(object_markers)
            options = TrackOptions(
                aruco_size_m=aruco_size,
                intrinsics_colmap=intrinsics,
                static_camera=static_camera,
                max_frames=max_frames,
                start_frame=start_frame,
                min_segment_frames=min_segment_frames,
                object_markers=markers,
                marker_use=marker_use,
                scan_features=scan_features,
            )
            with stage_progress() as progress:
                result = run_track(clip, scene, out, options, overwrite=overwrite, progress=progress)
        if result.static_camera:
            typer.echo("camera: static (one pose from the table's marker)")
        else:
            placed = int(np.isfinite(result.world_from_cam).all(axis=(1, 2)).sum())
            total = len(result.world_from_cam)
            typer.echo(f"camera: moving, placed from the table's marker in {placed}/{total} frames")
        for i, name in enumerate(result.object_names):
            lost = int((~result.valid[:, i]).sum())
            typer.echo(f"{name}: tracked {len(result.valid) - lost}/{len(result.valid)} frames")
        for record in result.object_markers:
            where = record["object"] or f"no object ({record.get('note', '')})"
            typer.echo(f"object marker {record['id']}: on {where}")
        if result.trajectories:
            spans = ", ".join(f"{a}-{b}" for a, b in result.segments)
            typer.echo(f"{len(result.trajectories)} trajectory file(s) (frames {spans}) and track.json in {out}")
        else:
            typer.echo(
                f"no run of {min_segment_frames} frames has every object tracked at once: no trajectory file; each "
                f"object's own tracked frames are in {out / 'track.json'}"
            )
