"""`ground SCAN --interaction CLIP`: a calibrated scene from video alone.

1. **Ground** the scan (`grounder.ground`: reconstruct, segment, mesh, texture, hulls; the property prior when
   `GroundOptions` asks for it).
2. **Track** every grounded object through the interaction clip (`grounder.tracking.pipeline.track`); frames where an
   object is lost or hidden are flagged and cut out: only segments in which every object is tracked become
   trajectories.
3. **Calibrate** (`grounder.calibration.fit.calibrate`, when present) the objects' contact parameters on tracked frames
   only. By default (`calibration` "impacts", `grounder.interaction.impacts`) each object's contact values come
   from the contacts that follow its free flights: each is rolled out from the state a fit of the whole flight
   gives, not from a few tracked frames, and what no flight's landing resolves is calibrated on windows as follows
   (a windowed value that rests on the start states' accuracy keeps the prior there). The windowed calibration
   (`calibration` "windows"): objects that never touch each other (`separable_bodies`) are calibrated one at a
   time, each in a scene of its own with the table (`calibrate_per_body`), on short windows (0.3 s) of its own
   tracked runs (`own_runs`;
   without the frames the backward pass extrapolated), rolled out open loop from states that tracking measures well
   (`reliable_starts`: in a free flight, or away from impacts); windows keep a bounce's chaos out of the loss.
   First a screen (`screen_parameters`) asks, per parameter, whether moving it by 20% changes its object's
   rollouts by more than tracking resolves (1 mm / 0.75 deg, root mean square over the frames, about the median
   tracking error): an object that never slides says nothing about its friction, one that lands without bouncing
   little about its damping ratio. Only constrained parameters are calibrated; the others
   keep the prior and are reported as unconstrained (interval = bounds), not as a number the clip never measured.
   The same ±20% rule is applied again where the fit lands (the screen looked at its grid best): a value that fails
   there keeps the prior too (reported with its `unresolved_fit`), and the rest is fitted again.
   Each calibrated value also gets its resolution range (`indistinguishable_range`). Contact parameters are
   calibrated as the contact's values (the object's geoms get top priority). The loss counts position errors
   along the camera's viewing rays a quarter (`along_view_weight`: tracked depth is 4-6 times noisier than the
   position across the image). Optionally (`start_rounds`, off by default), each window's start state is then
   refitted to the window's own tracked motion with the calibrated values (`grounder.interaction.starts`: a fresh
   detection's pose and a velocity from a few frames are what the tracking measures worst) and the screen and
   calibration run again.
4. **Report** what was calibrated and how well the scene now matches the clip: `interaction.json` and
   `interaction.md` in the output folder.

Output folder (written in a temporary sibling and moved into place at the end):

- `scene.xml`, `assets/`, `scene.json`, `calibration.json`, `report.html`: the calibrated scene (the grounded one,
  unchanged, if nothing could be calibrated);
- `grounded/`: the scene as grounded from the scan, before calibration (with `reconstruction/`);
- `interaction/tracks/`: the tracked trajectories and `track.json` (per-frame valid mask, scores);
- `interaction/windows/`: the windows the calibration was fitted and validated on, with their tracked starts (how
  far the refits moved each start is in the report's `start_refinement`);
- `interaction/impacts.png`: with the impacts calibration, each object's chi-square over friction x restitution and its
  tracked height after each flight against the rollout at the best values;
- `interaction.json`, `interaction.md`: the report.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import shutil
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from grounder.core.trajectory import Trajectory, save_trajectories
from grounder.errors import GrounderError
from grounder.grounding.pipeline import ground
from grounder.interaction.impacts import impacts_figure
from grounder.interaction.options import InteractionOptions, InteractionResult, default_params
from grounder.interaction.per_object import calibrate_per_body, separable_bodies
from grounder.interaction.report import clip_match, markdown_report, scene_restitution
from grounder.interaction.tracks import SavedTracks, saved_tracks, tracked_states
from grounder.interaction.windows import calibrate_constrained, windows
from grounder.tracking.inputs import read_clip
from grounder.tracking.options import TrackOptions, TrackResult
from grounder.tracking.pipeline import track
from image2sim_common.progress import ProgressFn, no_progress
from reconstruction.errors import InputError

log = logging.getLogger(__name__)


def calibration_available() -> bool:
    return importlib.util.find_spec("grounder.calibration.fit") is not None


# Below this frame rate a bounce or a slide lasts a few frames, and contact values rest on a handful of window starts:
# the same toss calibrated 22 of 24 resolved values within 20% at 30 fps (12 unresolved) and 23 of 24 at 60 fps
# (6 unresolved), over the same scans (docs/interaction_history.md, "Frame rate").
MIN_ADVISED_FPS = 50.0


def frame_rate_advice(fps: float | None) -> str | None:
    """The warning for an interaction clip filmed slower than `MIN_ADVISED_FPS`, or None."""
    if fps is None or fps >= MIN_ADVISED_FPS:
        return None
    return (
        f"the interaction clip has {fps:g} frames per second: a bounce or a slide then spans only a few frames, and "
        "friction and restitution are often unresolved or rest on one or two window starts; film at 60 fps or more "
        "if the camera can"
    )


def ground_with_interaction(
    scan: Path,
    clip: Path,
    out: Path,
    options: InteractionOptions | None = None,
    *,
    grounded_scene: Path | None = None,
    overwrite: bool = False,
    progress: ProgressFn | None = None,
) -> InteractionResult:
    """A calibrated scene from a scan video and an interaction clip (module docstring).

    Args:
        scan: video (or image folder) of the still tabletop.
        clip: video in which the scan's objects move (pushed, tossed, dropped), filmed with the same camera.
        out: output folder (new or empty unless `overwrite`).
        options: settings of each stage.
        grounded_scene: an existing `ground` output of `scan` to reuse instead of grounding again (copied).
        overwrite: replace a non-empty `out` once the result is complete.
        progress: called as progress(stage, done, total).

    Returns:
        Where the scene is, whether it was calibrated, the tracking result and the report.

    Raises:
        GrounderError, ReconstructionError, SceneExportError: bad input, nothing grounded or nothing tracked.
    """
    from reconstruction import staged_output_dir

    options = options or InteractionOptions()
    report = progress or no_progress
    track_options = _track_options(options)
    seconds: dict[str, float] = {}
    _check_inputs(scan, clip, grounded_scene, track_options)
    with staged_output_dir(
        Path(out), overwrite=overwrite, inputs=(scan, clip, grounded_scene), error=InputError
    ) as stage:
        tick = time.perf_counter()
        grounded = stage / "grounded"
        _ground_scan(scan, grounded, grounded_scene, options, report)
        seconds["ground"] = time.perf_counter() - tick

        tick = time.perf_counter()
        tracks_dir = stage / "interaction" / "tracks"
        # track.json names the grounded scene where it will be, not in the staging folder.
        tracked = track(
            Path(clip),
            grounded,
            tracks_dir,
            track_options,
            progress=report,
            scene_recorded_as=Path(out) / "grounded" / "scene.xml",
        )
        seconds["track"] = time.perf_counter() - tick
        # Calibrate from the tracks as written, not as held in memory: they reproduce this scene (`saved_tracks`).
        saved = saved_tracks(tracks_dir, track_options)
        segments = saved.segments
        per_body = _calibrates_per_object(grounded / "scene.xml", segments, tracked, options)
        fit_trajs = (
            [] if per_body else windows(segments, options.window_s, options.window_stride_s, options.min_motion_m_s)
        )

        names = tracked.object_names
        payload = _new_report(scan, clip, tracked, fit_trajs, options)
        advice = frame_rate_advice(payload["tracking"]["fps"])
        if advice:
            log.warning("%s", advice)
        payload["calibration_method"] = options.calibration
        payload["match_before"] = clip_match(grounded / "scene.xml", segments)
        _calibrate(stage, segments, fit_trajs, per_body, names, saved, options, payload, seconds, report)
        calibrated = _install_scene(stage, segments, names, payload)
        payload["stage_seconds"] = {k: round(v, 1) for k, v in seconds.items()}
        if impacts_figure(payload["calibration"].get("per_object", {}), stage / "interaction" / "impacts.png"):
            payload["impacts_figure"] = "interaction/impacts.png"
        (stage / "interaction.json").write_text(json.dumps(payload, indent=1) + "\n")
        (stage / "interaction.md").write_text(markdown_report(payload))
    return InteractionResult(
        out_dir=Path(out),
        scene_xml=Path(out) / "scene.xml",
        calibrated=calibrated,
        track=tracked,
        report=payload,
    )


def _track_options(options: InteractionOptions) -> TrackOptions:
    """How the clip is tracked: `options.track`, with the scan's ArUco marker size where it gives none."""
    track_options = options.track
    if track_options.aruco_size_m is None:
        track_options = replace(track_options, aruco_size_m=options.ground.reconstruct.aruco_size_m)
    return track_options


def _check_inputs(scan: Path, clip: Path, grounded_scene: Path | None, track_options: TrackOptions) -> None:
    """Fails now, not after the grounding, on what would fail later: a video that cannot be read, no marker size for
    tracking, or a clip too short to make a trajectory (a few of its frames are decoded here)."""
    from reconstruction import check_source

    if grounded_scene is None:  # the videos that will be read fail now, not after the grounding
        check_source(Path(scan))
    check_source(Path(clip))
    if track_options.aruco_size_m is None:  # found now, not after the grounding
        raise GrounderError(
            "tracking the interaction clip finds the camera from the ArUco marker on the table, so it needs the "
            "marker's size: pass --aruco-size M (--known-extent cannot stand in for it)"
        )
    needed = track_options.min_segment_frames  # a few frames decoded now: a clip too short to track fails here
    first, _ = read_clip(Path(clip), needed, track_options.start_frame)
    if len(first) < needed:
        raise GrounderError(
            f"{clip}: {len(first)} frames; tracking needs at least {needed} to make a trajectory: film a longer "
            "interaction clip"
        )


def _ground_scan(
    scan: Path, grounded: Path, grounded_scene: Path | None, options: InteractionOptions, report: ProgressFn
) -> None:
    """Writes the grounded scene to `grounded`: a copy of `grounded_scene` where given, else the scan grounded."""
    if grounded_scene is not None:
        if not (Path(grounded_scene) / "scene.xml").is_file():
            raise GrounderError(f"{grounded_scene} has no scene.xml; pass a folder written by `image2sim ground`")
        shutil.copytree(grounded_scene, grounded)
    else:
        ground(Path(scan), grounded, options.ground, progress=report)


def _calibrates_per_object(
    scene_xml: Path, segments: list[Trajectory], tracked: TrackResult, options: InteractionOptions
) -> bool:
    """Whether the objects are calibrated one at a time (`options.per_object`): where they never touch each other in
    the segments, or, with no segment, in the frames where two or more are tracked (with `options.own_runs`)."""
    if segments:
        return options.per_object and separable_bodies(scene_xml, segments)
    # No frame has every object: each object's own runs, if the objects never touch where tracked together.
    import mujoco

    model = mujoco.MjModel.from_xml_path(str(scene_xml))
    return options.per_object and options.own_runs and separable_bodies(scene_xml, tracked_states(model, tracked))


def _new_report(
    scan: Path, clip: Path, tracked: TrackResult, fit_trajs: list[Trajectory], options: InteractionOptions
) -> dict[str, Any]:
    """The report's (`interaction.json`) first entries: the inputs, what was tracked, the windows and the start
    errors the calibrated values are profiled under."""
    names = tracked.object_names
    return {
        "format": "image2sim.interaction/1",
        "scan": str(scan),
        "clip": str(clip),
        "tracking": {
            "frames": len(tracked.time_s),
            "fps": round(1.0 / float(np.median(np.diff(tracked.time_s))), 3) if len(tracked.time_s) > 1 else None,
            "objects": {
                n: {
                    "tracked_fraction": round(float(tracked.valid[:, i].mean()), 4),
                    "lost_frames": [int(tracked.frame_index[f]) for f in np.nonzero(~tracked.valid[:, i])[0]],
                }
                for i, n in enumerate(names)
            },
            "segments": [
                {
                    "name": t.name,
                    "first_frame": int(tracked.frame_index[a]),
                    "last_frame": int(tracked.frame_index[b]),
                }
                for t, (a, b) in zip(tracked.trajectories, tracked.segments, strict=True)
            ],
            "note": (
                "calibration uses only tracked frames: the segments (every object tracked), or with "
                "InteractionOptions.own_runs, per object its own tracked runs"
            ),
        },
        "windows": [t.name for t in fit_trajs],  # per-object calibration replaces this with its own
        "start_speed_error_m_s": options.start_speed_error_m_s,
        "start_state_errors": {
            "draws": options.start_state_draws,
            "position_m": options.start_position_error_m,
            "rotation_deg": options.start_rotation_error_deg,
            "speed_m_s": options.start_speed_error_m_s,
            "spin_rad_s": options.start_spin_error_rad_s,
        },
    }


def _calibrate(
    stage: Path,
    segments: list[Trajectory],
    fit_trajs: list[Trajectory],
    per_body: bool,
    names: tuple[str, ...],
    saved: SavedTracks,
    options: InteractionOptions,
    payload: dict[str, Any],
    seconds: dict[str, float],
    report: ProgressFn,
) -> None:
    """Calibrates the grounded scene (`stage/grounded`) per object or on the segments' windows, or says why not:
    sets the report's `calibration` entry (and, per object, its `windows`) in `payload` and the time taken in
    `seconds`; a calibrated scene goes to `stage/calibrated`."""
    grounded = stage / "grounded"
    view_point_m = saved.view_point_m
    if not calibration_available():
        payload["calibration"] = {"status": "skipped: grounder.calibration.fit is not installed"}
    elif per_body:
        params = options.calibrate_params or default_params(names)
        tick = time.perf_counter()
        payload["calibration"], payload["windows"] = calibrate_per_body(
            grounded / "scene.xml",
            segments,
            params,
            options,
            view_point_m=view_point_m,
            object_tracks=saved.object_tracks if options.own_runs else None,
            out=stage / "calibrated",
            progress=report,
        )
        seconds["calibrate"] = time.perf_counter() - tick
    elif options.calibration == "shooting":
        payload["calibration"] = {
            "status": "skipped: multiple shooting calibrates one object at a time, and these objects touch where "
            "tracked together (or per-object calibration is off); use calibration 'windows'"
        }
    elif not segments:
        payload["calibration"] = {
            "status": "skipped: no frame has every object tracked, and the objects cannot be calibrated one at a "
            "time (they touch where tracked together, or per-object calibration is off)"
        }
    elif not fit_trajs:
        payload["calibration"] = {"status": "skipped: no tracked window shows motion"}
    else:
        save_trajectories(fit_trajs, stage / "interaction" / "windows")
        params = options.calibrate_params or default_params(names)
        tick = time.perf_counter()
        payload["calibration"] = calibrate_constrained(
            grounded / "scene.xml",
            fit_trajs,
            params,
            options,
            view_point_m=view_point_m,
            out=stage / "calibrated",
            progress=report,
        )
        seconds["calibrate"] = time.perf_counter() - tick


def _install_scene(stage: Path, segments: list[Trajectory], names: tuple[str, ...], payload: dict[str, Any]) -> bool:
    """Puts the output's scene at the top of `stage`: the calibrated one where calibration wrote one (its match with
    the clip in `payload`'s `match_after`), else the grounded one; adds each object's bounce before and after
    (`restitution`). Returns whether the scene is calibrated."""
    grounded = stage / "grounded"
    calibrated = (stage / "calibrated" / "scene.xml").is_file()
    if calibrated:
        for child in (stage / "calibrated").iterdir():
            shutil.move(str(child), stage / child.name)
        (stage / "calibrated").rmdir()
        payload["match_after"] = clip_match(stage / "scene.xml", segments)
    payload["restitution"] = scene_restitution(
        grounded / "scene.xml", stage / "scene.xml" if calibrated else None, names
    )
    if not calibrated:
        for child in grounded.iterdir():
            if child.name != "reconstruction":
                target = stage / child.name
                if child.is_dir():
                    shutil.copytree(child, target)
                else:
                    shutil.copy2(child, target)
    return calibrated
