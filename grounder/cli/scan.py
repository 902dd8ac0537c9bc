"""CLI commands ``reconstruct`` and ``ground``: the scan side of the pipeline (registered by ``grounder.cli.entry``)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer

from grounder.cli.common import fail, require, setup_logging, stage_progress, user_errors_exit_2

EXIT_BAD_INPUT = 2

# Options that `reconstruct` and `ground` share (the scan side of both commands).
ArucoSizeOption = Annotated[
    float | None,
    typer.Option(help="Side of the ArUco marker's black square in metres (DICT_4X4_50, id 0, on the table)."),
]
KnownExtentOption = Annotated[
    float | None,
    typer.Option(
        help="Longest extent (length, width or height) in metres of the longest object on the table (no marker)."
    ),
]
MaxFramesOption = Annotated[int, typer.Option(help="Use at most this many frames.")]
SfmSeedOption = Annotated[int, typer.Option(help="Random seed (RANSAC, mapper).")]
VerboseOption = Annotated[bool, typer.Option("--verbose", "-v", help="Log each step.")]


def register(app: typer.Typer) -> None:
    """Adds the ``reconstruct`` and ``ground`` commands to the ``image2sim`` app."""
    app.command()(reconstruct)
    app.command()(ground)


def reconstruct(
    source: Annotated[Path, typer.Argument(help="A video file or a folder of images.")],
    out: Annotated[Path, typer.Option("-o", "--out", help="Output folder (created; must be new or empty).")],
    aruco_size: ArucoSizeOption = None,
    known_extent: KnownExtentOption = None,
    max_frames: MaxFramesOption = 150,
    overwrite: Annotated[
        bool, typer.Option(help="Replace a non-empty output folder once the result is ready.")
    ] = False,
    seed: SfmSeedOption = 0,
    verbose: VerboseOption = False,
) -> None:
    """Cameras in a metric, gravity-aligned world frame: COLMAP model, transforms.json, reconstruct.json."""
    setup_logging(verbose)
    with user_errors_exit_2():
        from reconstruction import ReconstructOptions
        from reconstruction import reconstruct as run_reconstruct

        defaults = ReconstructOptions()
        options = ReconstructOptions(
            aruco_size_m=aruco_size,
            known_extent_m=known_extent,
            frames=replace(defaults.frames, max_frames=max_frames),
            sfm=replace(defaults.sfm, seed=seed),
        )
        with stage_progress() as progress:
            result = run_reconstruct(source, out, options, overwrite=overwrite, progress=progress)
    scale = result.world.scale_source
    typer.echo(
        f"registered {len(result.frames)}/{len(result.selected_frame_indices)} frames "
        f"(reprojection {result.mean_reprojection_error_px:.2f} px, scale from {scale}); wrote {out}"
    )


def ground(
    source: Annotated[Path, typer.Argument(help="A video file or a folder of images of the tabletop.")],
    out: Annotated[Path, typer.Option("-o", "--out", help="Output scene folder (created; must be new or empty).")],
    aruco_size: ArucoSizeOption = None,
    known_extent: KnownExtentOption = None,
    max_frames: MaxFramesOption = 150,
    face_budget: Annotated[int, typer.Option(help="Faces per object mesh after decimation.")] = 4000,
    max_hulls: Annotated[int, typer.Option(help="Convex hulls per object (CoACD).")] = 16,
    density: Annotated[
        float, typer.Option(help="Density (kg/m^3) given to every object when the property model is off.")
    ] = 600.0,
    property_model: Annotated[
        bool,
        typer.Option(help="Predict density, friction and contact per object with the learned property model."),
    ] = True,
    overwrite: Annotated[bool, typer.Option(help="Replace a non-empty output folder once the scene is ready.")] = False,
    seed: SfmSeedOption = 0,
    interaction: Annotated[
        Path | None,
        typer.Option(
            help="A clip of the same objects moving (pushed, dropped, tossed): track it and calibrate the scene to it."
        ),
    ] = None,
    object_markers: Annotated[
        Path | None,
        typer.Option(help="With --interaction: JSON layout of ArUco markers stuck on the objects (see `track`)."),
    ] = None,
    calibration: Annotated[
        str,
        typer.Option(
            help="With --interaction: 'impacts' (each contact after a tracked free flight, rolled out from the fit "
            "of the whole flight; what no landing resolves, e.g. an object that only slides, is calibrated on "
            "windows), 'windows' (short windows rolled out from tracked states) or 'shooting' (multiple shooting "
            "over each object's whole tracked run: slower, does not rest on the tracked states)."
        ),
    ] = "impacts",
    verbose: VerboseOption = False,
) -> None:
    """Film a tabletop, get a MuJoCo scene: scene.xml, assets/, scene.json, preview.png.

    With --interaction CLIP: also track the objects in the clip and calibrate their friction and contact to it.
    """
    setup_logging(verbose)
    require(
        # kg/m^3: from foams to osmium (22590), the densest element; 1e300 gave a scene of 4e298 kg objects
        ("--density", density, 1.0 <= density <= 25_000.0, "between 1 and 25000 (kg/m^3)"),
        ("--face-budget", face_budget, 100 <= face_budget <= 200_000, "between 100 and 200000"),
        ("--max-hulls", max_hulls, max_hulls >= 1, ">= 1"),
    )
    with user_errors_exit_2():
        from grounder.grounding.pipeline import GroundOptions
        from grounder.grounding.pipeline import ground as run_ground
        from reconstruction import ReconstructOptions

        defaults = GroundOptions()
        recon = ReconstructOptions(
            aruco_size_m=aruco_size,
            known_extent_m=known_extent,
            frames=replace(defaults.reconstruct.frames, max_frames=max_frames),
            sfm=replace(defaults.reconstruct.sfm, seed=seed),
        )
        options = replace(
            defaults,
            reconstruct=recon,
            objects=replace(defaults.objects, mesh=replace(defaults.objects.mesh, face_budget=face_budget)),
            collision=replace(defaults.collision, max_hulls=max_hulls),
            default_density_kg_m3=density,
            property_model=property_model,
        )
        if object_markers is not None and interaction is None:
            fail("--object-markers needs --interaction CLIP: the markers are tracked in the interaction clip")
        if calibration != "impacts" and interaction is None:
            fail("--calibration needs --interaction CLIP: it is how the scene is calibrated to the clip")
        if interaction is not None:
            from grounder.interaction.options import CALIBRATION_METHODS, InteractionOptions
            from grounder.interaction.pipeline import ground_with_interaction
            from grounder.tracking.markers import load_object_markers
            from grounder.tracking.options import TrackOptions

            if not interaction.exists():
                fail(f"interaction clip {interaction} does not exist; give the path of a video of the objects moving")
            if calibration not in CALIBRATION_METHODS:
                fail(f"--calibration {calibration!r} is not a method; use one of {', '.join(CALIBRATION_METHODS)}")
            markers = () if object_markers is None else load_object_markers(object_markers)
            interaction_options = InteractionOptions(
                ground=options, track=TrackOptions(object_markers=markers), calibration=calibration
            )
            with stage_progress() as progress:
                calibrated = ground_with_interaction(
                    source, interaction, out, interaction_options, overwrite=overwrite, progress=progress
                )
            typer.echo(f"calibrated scene: {calibrated.scene_xml}")
            return
        with stage_progress() as progress:
            result = run_ground(source, out, options, overwrite=overwrite, progress=progress)
    worst = max((d for d, _ in result.settle.values()), default=0.0)
    typer.echo(
        f"{len(result.object_names)} object(s), scale from {result.scale_source}, "
        f"max drift after {defaults.settle_seconds:.0f} s: {worst * 1000:.1f} mm"
    )
    typer.echo(f"MJCF: {result.scene_xml}")
