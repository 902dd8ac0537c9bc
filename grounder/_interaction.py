"""`ground SCAN --interaction CLIP`: a calibrated scene from video alone.

1. **Ground** the scan (`grounder.ground`: reconstruct, segment, mesh, texture, hulls; the property prior when
   `GroundOptions` asks for it).
2. **Track** every grounded object through the interaction clip (`grounder._track.track`); frames where an object
   is lost or hidden are flagged and cut out: only segments in which every object is tracked become trajectories.
3. **Calibrate** (`grounder._calibrate.calibrate`, when present) the objects' contact parameters on those tracked
   segments only, cut into overlapping windows (open-loop rollouts from a tracked state drift; short windows keep
   the loss informative, and give the calibration a validation split). Windows in which nothing moves carry no
   information about friction or restitution and are dropped.
4. **Report** what was calibrated and how well the scene now matches the clip: `interaction.json` and
   `interaction.md` in the output folder.

Output folder (written in a temporary sibling and moved into place at the end):

- `scene.xml`, `assets/`, `scene.json`, `calibration.json`, `report.html`: the calibrated scene (the grounded one,
  unchanged, if nothing could be calibrated);
- `grounded/`: the scene as grounded from the scan, before calibration (with `reconstruction/`);
- `interaction/tracks/`: the tracked trajectories and `track.json` (per-frame valid mask, scores);
- `interaction/windows/`: the windows the calibration was fitted and validated on;
- `interaction.json`, `interaction.md`: the report.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from grounder._ground import GroundOptions, ground
from grounder._track import TrackOptions, TrackResult, track
from grounder._trajectory import Trajectory, save_trajectories
from grounder.errors import GrounderError

log = logging.getLogger(__name__)

ProgressFn = Callable[[str, int, int], None]


@dataclass(frozen=True, kw_only=True)
class InteractionOptions:
    """Settings of `ground_with_interaction`.

    Attributes:
        ground: how the scan is grounded.
        track: how the clip is tracked; its `aruco_size_m` defaults to the scan's (`ground.reconstruct.aruco_size_m`).
        calibrate_params: parameters to fit (calibration's names); None: per object its sliding friction and its
            contact damping ratio (MuJoCo's restitution knob, `solref` dampratio).
        calibrate_settings: extra `CalibrateOptions` fields (e.g. {"generations": 10}).
        window_s: length of the calibration windows cut from the tracked segments (None: whole segments).
        window_stride_s: start-to-start distance of the windows.
        min_motion_m_s: windows where no object moves faster than this are dropped.
    """

    ground: GroundOptions = field(default_factory=GroundOptions)
    track: TrackOptions = field(default_factory=TrackOptions)
    calibrate_params: tuple[str, ...] | None = None
    calibrate_settings: dict[str, Any] = field(default_factory=dict)
    window_s: float | None = 1.0
    window_stride_s: float = 0.5
    min_motion_m_s: float = 0.05

    def __post_init__(self) -> None:
        if self.window_s is not None and not self.window_s > 0:
            raise GrounderError(f"window_s={self.window_s} but expected a positive length in seconds, or None")
        if not self.window_stride_s > 0:
            raise GrounderError(f"window_stride_s={self.window_stride_s} but expected > 0")


@dataclass(frozen=True, kw_only=True)
class InteractionResult:
    """What `ground_with_interaction` wrote.

    Attributes:
        out_dir: the output folder; `scene_xml` is the calibrated scene (the grounded one if not calibrated).
        calibrated: whether a calibration ran.
        track: the tracking result (poses, valid mask, segments).
        report: the content of `interaction.json`.
    """

    out_dir: Path
    scene_xml: Path
    calibrated: bool
    track: TrackResult
    report: dict[str, Any]


def calibration_available() -> bool:
    return importlib.util.find_spec("grounder._calibrate") is not None


def windows(
    trajs: Sequence[Trajectory], window_s: float | None, stride_s: float, min_motion_m_s: float
) -> list[Trajectory]:
    """Cuts trajectories into overlapping windows (each at least 3 samples); drops windows where nothing moves."""
    out: list[Trajectory] = []
    for traj in trajs:
        spans: list[tuple[int, int]] = []
        if window_s is None:
            spans = [(0, len(traj.time_s))]
        else:
            t0 = float(traj.time_s[0])
            start = 0.0
            while True:
                rows = np.nonzero((traj.time_s >= t0 + start - 1e-9) & (traj.time_s <= t0 + start + window_s + 1e-9))[0]
                if len(rows) >= 3:
                    spans.append((int(rows[0]), int(rows[-1]) + 1))
                if t0 + start + window_s >= traj.time_s[-1] - 1e-9:
                    break
                start += stride_s
        for k, (a, b) in enumerate(spans):
            qvel = traj.qvel[a:b]
            speeds = [np.linalg.norm(qvel[:, d : d + 3], axis=1).max() for d in range(0, qvel.shape[1] - 5, 6)]
            if max(speeds, default=0.0) < min_motion_m_s:
                continue
            out.append(
                Trajectory(
                    time_s=traj.time_s[a:b],
                    qpos=traj.qpos[a:b],
                    qvel=traj.qvel[a:b],
                    ctrl=None if traj.ctrl is None else traj.ctrl[a:b],
                    name=f"{traj.name}_w{k:02d}" if len(spans) > 1 else traj.name,
                )
            )
    return out


def default_params(object_names: Sequence[str]) -> tuple[str, ...]:
    return tuple(p for name in object_names for p in (f"{name}.friction.sliding", f"{name}.solref.dampratio"))


def _clip_match(scene_xml: Path, trajs: Sequence[Trajectory]) -> dict[str, dict[str, float]]:
    """Per object, open-loop rollout of each tracked segment from its first state: mean / max position error (mm)
    and mean rotation error (deg) against the tracked poses, over all segments."""
    import mujoco

    from grounder._simulate import free_body_errors, simulate

    model = mujoco.MjModel.from_xml_path(str(scene_xml))
    predicted = simulate(model, list(trajs))
    assert isinstance(predicted, list)
    per_body: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for pred, real in zip(predicted, trajs, strict=True):
        assert isinstance(pred, Trajectory)
        for body, (pos, rot) in free_body_errors(model, pred, real).items():
            per_body.setdefault(body, []).append((pos, rot))
    return {
        body: {
            "mean_position_error_mm": round(1e3 * float(np.mean(np.concatenate([p for p, _ in errs]))), 2),
            "max_position_error_mm": round(1e3 * float(np.max(np.concatenate([p for p, _ in errs]))), 2),
            "mean_rotation_error_deg": round(float(np.rad2deg(np.mean(np.concatenate([r for _, r in errs])))), 2),
        }
        for body, errs in per_body.items()
    }


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
    report = progress or (lambda stage, done, total: None)
    track_options = options.track
    if track_options.aruco_size_m is None:
        track_options = replace(track_options, aruco_size_m=options.ground.reconstruct.aruco_size_m)
    seconds: dict[str, float] = {}
    with staged_output_dir(Path(out), overwrite=overwrite) as stage:
        tick = time.perf_counter()
        grounded = stage / "grounded"
        if grounded_scene is not None:
            if not (Path(grounded_scene) / "scene.xml").is_file():
                raise GrounderError(f"{grounded_scene} has no scene.xml; pass a folder written by `image2sim ground`")
            shutil.copytree(grounded_scene, grounded)
        else:
            ground(Path(scan), grounded, options.ground, progress=report)
        seconds["ground"] = time.perf_counter() - tick

        tick = time.perf_counter()
        tracks_dir = stage / "interaction" / "tracks"
        tracked = track(Path(clip), grounded, tracks_dir, track_options, progress=report)
        seconds["track"] = time.perf_counter() - tick
        segments = list(tracked.trajectories)
        fit_trajs = windows(segments, options.window_s, options.window_stride_s, options.min_motion_m_s)

        names = tracked.object_names
        payload: dict[str, Any] = {
            "format": "image2sim.interaction/1",
            "scan": str(scan),
            "clip": str(clip),
            "tracking": {
                "frames": len(tracked.time_s),
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
                "note": "calibration uses only frames in which every object is tracked (the segments)",
            },
            "windows": [t.name for t in fit_trajs],
        }
        payload["match_before"] = _clip_match(grounded / "scene.xml", segments)
        calibrated = False
        if not calibration_available():
            payload["calibration"] = {"status": "skipped: grounder._calibrate is not installed"}
        elif not fit_trajs:
            payload["calibration"] = {"status": "skipped: no tracked window shows motion"}
        else:
            from grounder._calibrate import CalibrateOptions, calibrate

            save_trajectories(fit_trajs, stage / "interaction" / "windows")
            params = options.calibrate_params or default_params(names)
            settings = {"validation_fraction": 0.3 if len(fit_trajs) >= 3 else 0.0, **options.calibrate_settings}
            cal_options = CalibrateOptions(params=tuple(params), **settings)
            tick = time.perf_counter()
            result = calibrate(grounded, fit_trajs, options=cal_options, out=stage / "calibrated", progress=report)
            seconds["calibrate"] = time.perf_counter() - tick
            calibrated = True
            payload["calibration"] = {
                "status": "calibrated",
                "parameters": {
                    p.name: {
                        "nominal": p.nominal,
                        "value": p.value,
                        "interval": [p.interval_low, p.interval_high],
                        "bounds": [p.lower, p.upper],
                        "unit": p.unit,
                    }
                    for p in result.parameters
                },
                "train": list(result.train_names),
                "validation": list(result.validation_names),
                "before": {k: v.as_dict() for k, v in result.before.items()},
                "after": {k: v.as_dict() for k, v in result.after.items()},
            }
            for child in (stage / "calibrated").iterdir():
                shutil.move(str(child), stage / child.name)
            (stage / "calibrated").rmdir()
            payload["match_after"] = _clip_match(stage / "scene.xml", segments)
        if not calibrated:
            for child in grounded.iterdir():
                if child.name != "reconstruction":
                    target = stage / child.name
                    if child.is_dir():
                        shutil.copytree(child, target)
                    else:
                        shutil.copy2(child, target)
        payload["stage_seconds"] = {k: round(v, 1) for k, v in seconds.items()}
        (stage / "interaction.json").write_text(json.dumps(payload, indent=1) + "\n")
        (stage / "interaction.md").write_text(_markdown(payload))
    return InteractionResult(
        out_dir=Path(out),
        scene_xml=Path(out) / "scene.xml",
        calibrated=calibrated,
        track=tracked,
        report=payload,
    )


def _markdown(payload: dict[str, Any]) -> str:
    lines = ["# Interaction report", "", f"Scan `{payload['scan']}`, clip `{payload['clip']}`.", "", "## Tracking", ""]
    for name, info in payload["tracking"]["objects"].items():
        lost = info["lost_frames"]
        lost_text = f"lost in frames {lost}" if lost else "never lost"
        lines.append(f"- {name}: tracked in {100 * info['tracked_fraction']:.0f}% of the frames, {lost_text}")
    spans = ", ".join(f"{s['first_frame']}-{s['last_frame']}" for s in payload["tracking"]["segments"])
    lines += ["", f"Segments with every object tracked (the only frames calibration sees): {spans}.", ""]
    lines += ["## Calibration", "", f"Status: {payload['calibration']['status']}.", ""]
    params = payload["calibration"].get("parameters", {})
    if params:
        lines += ["| parameter | before | after | interval |", "|---|---|---|---|"]
        for name, p in params.items():
            lines.append(
                f"| {name} | {p['nominal']:.4g} | {p['value']:.4g} | {p['interval'][0]:.4g} .. {p['interval'][1]:.4g} |"
            )
        lines.append("")
    lines += [
        "## Match with the clip",
        "",
        "Open-loop rollout of each tracked segment from its first tracked state:",
        "",
    ]
    lines += ["| object | mean position error before (mm) | after (mm) | mean rotation error before (deg) | after |"]
    lines += ["|---|---|---|---|---|"]
    after = payload.get("match_after", {})
    for name, before in payload["match_before"].items():
        a = after.get(name, {})
        lines.append(
            f"| {name} | {before['mean_position_error_mm']} | {a.get('mean_position_error_mm', '-')} | "
            f"{before['mean_rotation_error_deg']} | {a.get('mean_rotation_error_deg', '-')} |"
        )
    return "\n".join(lines) + "\n"
